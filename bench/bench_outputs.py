"""Benchmark of the output writers (issues 10, 20 and 37): `archive render` to Zarr, COG and ENVI against
the I/O floor and GDAL's geolocation warp, on a real flight's shape, in one run.

    python bench/bench_outputs.py [--shape heldout|sidelap|tilted] [--cubes 8] [--bands 300] [--samples 900]
                                  [--lines 1000] [--gsd 0.04] [--formats hdr,zarr,tif] [--compression NAME]
                                  [--no-stages] [--codec-table] [--scaling 8x4,16x4,32x4] [--scaling-bands 32]
                                  [--scaling-formats hdr,zarr,tif] [--workdir DIR] [--no-gdal] [--json FILE]

Flight (``--shape``, :data:`SHAPES`): the paper's cubes (900 samples x 1000 lines x 300 bands) in a
lawn-mower pattern, 2 cubes per pass, so 8 cubes = 4 passes, 40 m above ground with a 47.5 deg field
of view (swath 35.2 m). ``heldout`` (default since issue 37): passes along grid north 25 m apart
(29 % sidelap), as the held-out flight of issue 37: the grid is the footprint's box, 2897 x 2071 px
at 4 cm (7.2 GB with 300 bands), nearly all covered. ``sidelap``: passes 20 m apart (43 %).
``tilted``: the default before issue 37, passes at 20 deg: the grid is the tilted footprint's box
(3282 x 2795 px, 11.0 GB), a third of it NaN, which ENVI writes in full while Zarr skips and the
COG compresses to nothing: it flattered Zarr and COG against ENVI (and every format against the
floor, whose write counts the NaN bytes). Simulated once into --workdir and reused while its
marker file exists. After reading the input once (warm page cache), one run measures:

1. the I/O floor: read every input .bil once + write the mosaic's float32 byte count once, fsync'ed
   (``bench_render.io_floor``);
2. GDAL's direct method: ``rasterio.warp.reproject`` with geolocation arrays, all bands per call, 2
   threads, per cube (``bench_render.gdal_direct``);
3. per format, ``python -m archive render FLIGHT --out X.{zarr,tif,hdr} ...`` as a user runs it
   (:func:`render_plain`): wall from process start to exit, then ``sync`` (wall + sync compares
   with the floor's fsync'ed write), CPU-seconds of the whole process tree (the command, its
   scheduler, its workers: ``getrusage`` of the reaped children), **cores busy** = that CPU / wall
   / cores, the machine's cores x wall meanwhile split into busy (the tree) / iowait (waiting on the
   disk) / idle / others (other processes, steal) from ``/proc/stat`` (``bench/timeline.py`` splits
   it per phase of the command), peak RSS of the tree (polled every 0.1 s), output size; ratios to the floor and to
   GDAL from this same run. Then (unless ``--no-stages``) the same render again through
   ``bench/stage_profile.py`` (its cluster started apart, the task stream recorded, stage timers in
   the workers): **CPU-seconds per cube per stage** (GL lookup, band passes or CPU gather, DN reads,
   mosaic, NaN checks, compression, overviews, writes, the command's own process) and threads busy;
4. a 512 x 512 window of the COG read with rasterio for 3 bands and for all bands;
5. ``--codec-table``: every Zarr and COG codec of :data:`ZARR_CODECS` / :data:`COG_CODECS` on the
   ENVI render's tiles (:func:`codec_table`): CPU-seconds per cube against bytes on disk;
6. memory against flight length: ``--scaling`` flights ``NxP`` (N cubes over P passes of the same
   paper-size cubes with ``--scaling-bands`` bands: a render holds one band group, as with 300
   bands) rendered to ``--scaling-formats``: peak process-tree RSS. The paper's flight is 40x5.

The machine is often shared: the load average is printed after each step and with every figure;
CPU-seconds move less with the load than wall seconds.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_render as br  # noqa: E402  (the I/O floor, GDAL's warp, memory polling, flights)
import timeline  # noqa: E402  (the machine's CPU split from /proc/stat)
from timeline import machine_jiffies  # noqa: E402

FORMATS = ("zarr", "tif", "hdr")


def _say(text: str) -> None:
    print(f"{text}   [load {br.load()}]", flush=True)


def render_cli(flight: Path, out: Path, gsd: float, ground: float, extra=(), work: Path | None = None) -> dict:
    """``archive render`` through ``bench/stage_profile.py`` in a subprocess: wall, wall + sync, peak tree
    RSS, CPU of the tree, output bytes, the task stream's summary and CPU-seconds per stage."""
    profile = (work or out.parent) / f"{out.name}.profile.json"
    extra, sizing = list(extra), []
    for flag in ("--workers", "--threads"):   # they size stage_profile's own cluster
        if flag in extra:
            i = extra.index(flag)
            sizing += extra[i:i + 2]
            del extra[i:i + 2]
    cmd = [sys.executable, str(Path(__file__).resolve().parent / "stage_profile.py"), str(profile), *sizing, "--",
           str(flight), "--fov", str(br.FOV), "--gsd", str(gsd), "--ground-height", str(ground), "--mode", br.MODE,
           "--bands", "all", "--out", str(out), "--overwrite", *extra]
    load0 = br.load()
    t = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    with br.MemoryPoll(proc.pid) as poll:
        stdout, stderr = proc.communicate()
        tree = poll.cpu_s
    wall = time.perf_counter() - t
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({proc.returncode}): {stderr[-3000:]}")
    os.sync()
    synced = time.perf_counter() - t
    size = output_bytes(out)
    prof = json.loads(profile.read_text())
    cpu = prof["cpu"]["client"] + sum(prof["cpu"]["workers"].values())
    task_s = sum(v["task_s"] for v in prof["tasks"].values())
    return {"cmd": "archive render " + " ".join(cmd[4 + len(sizing):]), "wall_s": wall, "wall_sync_s": synced,
            "peak_tree_rss": poll.peak_rss, "peak_tree_anon": poll.peak_anon, "out_mb": size / br.MB,
            "command_s": prof["wall_s"], "graph_s": prof["graph_s"], "cpu_s": cpu, "tree_cpu_s": tree,
            "busy_cpu": cpu / wall / prof["cores"], "busy_graph_cpu": cpu / max(prof["graph_s"], 1e-9) / prof["cores"],
            "busy_tasks": task_s / max(prof["graph_s"] * prof["nthreads"], 1e-9),
            "profile": prof, "load": [load0, br.load()]}


def core_split(m0: dict, m1: dict, tree_cpu_s: float) -> dict:
    """The machine's cores x wall between two :func:`timeline.machine_jiffies` reads, split into
    the render's tree (``tree_cpu_s``), other processes, waiting on the disk (iowait), idle (what
    the render left idle: its serial phases) and steal; fractions summing to 1."""
    d = {k: (m1[k] - m0[k]) / timeline.HZ for k in m0}
    total = max(sum(d.values()), 1e-9)
    ours = min(tree_cpu_s, d["busy"])
    return {"busy": ours / total, "others": max(d["busy"] - ours, 0.0) / total, "iowait": d["iowait"] / total,
            "idle": d["idle"] / total, "steal": d["steal"] / total}


def split_text(split: dict | None) -> str:
    """'busy 75 / iowait 12 / idle 10 / others 3 %' of :func:`core_split` ('-' without one)."""
    if not split:
        return "-"
    return (f"{100 * split['busy']:.0f} / {100 * split['iowait']:.0f} / {100 * split['idle']:.0f} / "
            f"{100 * (split['others'] + split['steal']):.0f} %")


def output_bytes(out: Path) -> int:
    """Bytes of an output on disk: the file, every file of a store, an ENVI header and its data."""
    files = [out] if out.is_file() else [f for f in out.rglob("*") if f.is_file()]
    if out.suffix == ".hdr":
        files.append(out.with_suffix(""))
    return sum(f.stat().st_size for f in files)


def render_plain(flight: Path, out: Path, gsd: float, ground: float, extra=()) -> dict:
    """``python -m archive render`` as a user runs it, from process start to exit: wall, wall +
    sync, CPU-seconds of the whole process tree (``getrusage(RUSAGE_CHILDREN)`` before and after:
    the command, its scheduler and its worker processes, all reaped), **cores busy** = that CPU /
    wall / cores, its :func:`core_split` (busy / iowait / idle / others), peak tree RSS (polled
    every 0.1 s), output bytes."""
    import resource

    cmd = [sys.executable, "-m", "archive", "render", str(flight), "--fov", str(br.FOV), "--gsd", str(gsd),
           "--ground-height", str(ground), "--mode", br.MODE, "--bands", "all", "--out", str(out), "--overwrite",
           "--quiet", *extra]
    load0 = br.load()
    ru0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    m0 = machine_jiffies()
    t = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    with br.MemoryPoll(proc.pid) as poll:
        stdout, stderr = proc.communicate()
    wall = time.perf_counter() - t
    m1 = machine_jiffies()
    ru1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({proc.returncode}): {stderr[-3000:]}")
    os.sync()
    synced = time.perf_counter() - t
    cpu = (ru1.ru_utime - ru0.ru_utime) + (ru1.ru_stime - ru0.ru_stime)
    return {"cmd": "archive render " + " ".join(cmd[4:]), "wall_s": wall, "wall_sync_s": synced, "tree_cpu_s": cpu,
            "busy_tree": cpu / wall / (os.cpu_count() or 1), "split": core_split(m0, m1, cpu), "peak_tree_rss": poll.peak_rss,
            "peak_tree_anon": poll.peak_anon, "out_mb": output_bytes(out) / br.MB,
            "load": [load0, br.load()]}


def _rchar() -> int:
    for line in Path("/proc/self/io").read_text().splitlines():
        if line.startswith("rchar:"):
            return int(line.split()[1])
    return 0


def cog_window_reads(path: Path) -> dict:
    """Bytes read and seconds for a 512 x 512 window (the tile at the mosaic's centre) of 3 bands and
    of every band, each read from a freshly opened dataset (no GDAL block cache carried over)."""
    import rasterio
    from rasterio.windows import Window

    with rasterio.open(path) as ds:
        nb, h, w = ds.count, ds.height, ds.width
    row, col = (h // 2) // 512 * 512, (w // 2) // 512 * 512
    window = Window(col, row, min(512, w - col), min(512, h - row))
    out = {}
    for name, bands in (("3 bands", [1, nb // 2, nb]), (f"{nb} bands", list(range(1, nb + 1)))):
        with rasterio.Env(GDAL_CACHEMAX=64):
            before, t = _rchar(), time.perf_counter()
            with rasterio.open(path) as ds:
                data = ds.read(bands, window=window)
            out[name] = {"bytes": _rchar() - before, "s": time.perf_counter() - t,
                         "finite": float(np.isfinite(data).mean())}
    return out


def scaling_flight(workdir: Path, cubes: int, passes: int, bands: int, samples: int, lines: int,
                   heading: float, spacing: float) -> Path:
    """``cubes`` paper-size cubes over ``passes`` lawn-mower passes (simulated once, reused)."""
    import types

    args = types.SimpleNamespace(workdir=str(workdir), cubes=cubes, bands=bands, samples=samples, lines=lines,
                                 heading=heading, spacing=spacing, cubes_per_pass=-(-cubes // passes))
    return br.flight_dir(args, prefix=f"scaling_p{passes}_")


#: Flight shapes (``--shape``): grid heading of the passes (degrees) and metres between them. All
#: fly the paper's cubes 40 m above flat ground with a 47.5 deg field of view (swath 35.2 m).
#: ``heldout``: passes along grid north, as the held-out flight of issue 37 (the mosaic's grid is the
#: footprint's box: 2819 x 2100 px at 4 cm for 8 cubes, 7.1 GB with 300 bands, nearly all of it
#: covered); ``sidelap``: the same with passes 20 m apart (43 % sidelap: more renders per output
#: pixel); ``tilted``: the bench's flight before issue 37 (heading 20 deg: the grid is the tilted
#: footprint's box, 11.0 GB of which a third is NaN that Zarr and the COG do not compress).
SHAPES = {"heldout": (0.0, 25.0), "sidelap": (0.0, 20.0), "tilted": (20.0, 25.0)}


def sidelap(spacing: float) -> dict:
    """Swath, pass spacing and sidelap of a simulated flight with passes ``spacing`` m apart."""
    import math

    from archive.simulator.command import HEIGHT

    swath = 2 * HEIGHT * math.tan(math.radians(br.FOV / 2))
    return {"height_m": HEIGHT, "spacing_m": spacing, "swath_m": swath, "sidelap": 1 - spacing / swath}


STAGES = ("GL lookup", "GL band passes", "CPU band gather", "lookup unpack", "lookup decode", "read DN", "radiometry terms",
          "mosaic (last)", "mosaic (nadir)", "NaN checks", "compression (Zarr Blosc)", "compression (COG)",
          "overviews (2x2 mean)", "writes (pwrite)", "writes (Zarr chunk files)", "writes (COG spool)",
          "COG layout in the graph")


def stage_table(R: dict) -> list[str]:
    """Markdown rows: CPU-seconds per cube per stage and format (from the workers' stage timers)."""
    cubes = R["cubes"]
    fmts = list(R["render"])
    rows = [f"| stage (CPU-s per cube) | {' | '.join('.' + f for f in fmts)} |", "|---|" + "---|" * len(fmts)]
    for stage in STAGES:
        vals = [R["render"][f]["profile"]["stages"].get(stage, {}).get("cpu_s") for f in fmts]
        if any(v for v in vals):
            rows.append(f"| {stage} | " + " | ".join("-" if not v else f"{v / cubes:.2f}" for v in vals) + " |")
    for name, get in (
            ("workers, rest (task bodies unlisted above, Dask)", lambda p: sum(p["cpu"]["workers"].values())
             - sum(v["cpu_s"] for v in p["stages"].values())),
            ("command process (plan, meshes, scheduler, COG layout)", lambda p: p["cpu"]["client"]),
            ("**total**", lambda p: p["cpu"]["client"] + sum(p["cpu"]["workers"].values())),
            ("**total outside GL and band passes**", lambda p: p["cpu"]["client"] + sum(p["cpu"]["workers"].values())
             - sum(p["stages"].get(k, {}).get("cpu_s", 0.0) for k in ("GL lookup", "GL band passes", "CPU band gather")))):
        rows.append(f"| {name} | " + " | ".join(f"{get(R['render'][f]['profile']) / cubes:.2f}" for f in fmts) + " |")
    return rows


#: Zarr chunk codecs measured by :func:`codec_table`: (label, Blosc (cname, clevel, shuffle) or None
#: for no compression, chunk edge px).
ZARR_CODECS = [("none", None, 1024),
               ("blosc lz4 1 shuffle", ("lz4", 1, "shuffle"), 1024),
               ("blosc lz4 5 shuffle", ("lz4", 5, "shuffle"), 1024),
               ("blosc lz4 9 shuffle", ("lz4", 9, "shuffle"), 1024),
               ("blosc lz4 5 bitshuffle", ("lz4", 5, "bitshuffle"), 1024),
               ("blosc lz4 5 noshuffle", ("lz4", 5, "noshuffle"), 1024),
               ("blosc lz4hc 5 shuffle", ("lz4hc", 5, "shuffle"), 1024),
               ("blosc blosclz 5 shuffle", ("blosclz", 5, "shuffle"), 1024),
               ("blosc zstd 1 shuffle", ("zstd", 1, "shuffle"), 1024),
               ("blosc zstd 3 shuffle", ("zstd", 3, "shuffle"), 1024),
               ("blosc zstd 1 bitshuffle", ("zstd", 1, "bitshuffle"), 1024),
               ("blosc lz4 5 shuffle, 512 px chunks", ("lz4", 5, "shuffle"), 512)]
#: COG tile codecs: (label, zstd level or None (no compression), predictor 3 or 1 (none)).
COG_CODECS = [("none", None, 1), ("zstd -5 + predictor", -5, 3), ("zstd -3 + predictor", -3, 3),
              ("zstd -1 + predictor", -1, 3), ("zstd 1 + predictor", 1, 3), ("zstd 3 + predictor", 3, 3),
              ("zstd -3, no predictor", -3, 1), ("zstd 1, no predictor", 1, 1)]


def codec_table(envi: Path, cubes: int, bands_full: int = 300, spool: Path | None = None) -> dict:
    """CPU-seconds per cube (scaled to ``bands_full`` bands) and bytes of every codec of
    :data:`ZARR_CODECS` and :data:`COG_CODECS` on the tiles of a rendered ENVI mosaic ``envi`` (.hdr):
    one thread, ``time.thread_time`` around each encode (and, for Zarr, each chunk file's atomic
    write into ``spool``: a temporary file renamed, as :class:`archive.outputs.zarr.ChunkWriter`
    writes it); all-NaN Zarr chunks are skipped as the writer skips them. Overviews: the 2 x 2
    NaN-mean and nearest neighbour over the full resolution (each further level adds a quarter)."""
    import tempfile

    from archive.codecs import numcodecs_blosc
    from archive.files import write_atomic
    from archive.outputs.tiff import TILE, downsample2, encode_tile

    import numcodecs.blosc
    import rasterio

    numcodecs.blosc.use_threads = False   # as in the render's task threads (Blosc's threads only serve the main thread)
    with rasterio.open(envi.with_suffix("")) as ds:
        nb, h, w = ds.count, ds.height, ds.width
    data = np.memmap(envi.with_suffix(""), np.float32, "r", shape=(nb, h, w))
    raw = bands_full * h * w * 4
    bands = range(0, nb, max(1, nb // 10))   # about 10 bands spread over the spectrum
    scale = bands_full / len(bands) / cubes

    def chunks(edge: int):
        buf = np.empty((edge, edge), np.float32)
        for b in bands:
            for r in range(0, h, edge):
                for c in range(0, w, edge):
                    buf[...] = np.nan
                    part = data[b, r:r + edge, c:c + edge]
                    buf[:part.shape[0], :part.shape[1]] = part
                    yield buf

    out: dict = {"raw_mb": raw / br.MB, "bands": len(bands), "cubes": cubes, "zarr": {}, "cog": {}}
    spool = Path(tempfile.mkdtemp(dir=spool))
    try:
        for label, blosc, edge in ZARR_CODECS:
            codec = None if blosc is None else numcodecs_blosc(*blosc)
            enc = wr = 0.0
            size = 0
            for k, buf in enumerate(chunks(edge)):
                if np.isnan(buf).all():
                    continue
                t = time.thread_time()
                encoded = buf.tobytes() if codec is None else codec.encode(buf)
                t1 = time.thread_time()
                write_atomic(str(spool / f"c{k % 64}"), encoded)
                wr += time.thread_time() - t1
                enc += t1 - t
                size += len(encoded)
            out["zarr"][label] = {"encode_s": enc * scale, "write_s": wr * scale, "mb": size * bands_full / len(bands) / br.MB,
                                  "ratio": raw / max(size * bands_full / len(bands), 1)}
        for label, level, predictor in COG_CODECS:
            enc = 0.0
            size = 0
            for buf in chunks(TILE):
                t = time.thread_time()
                if level is None:
                    encoded = buf.tobytes()
                else:
                    encoded = encode_tile(buf, level=level, predictor=predictor)
                enc += time.thread_time() - t
                size += len(encoded)
            out["cog"][label] = {"encode_s": enc * scale, "mb": size * bands_full / len(bands) / br.MB,
                                 "ratio": raw / max(size * bands_full / len(bands), 1)}
        for label, down in (("overviews: 2 x 2 NaN-mean", downsample2), ("overviews: nearest", lambda x: np.array(x[::2, ::2]))):
            spent = 0.0
            for buf in chunks(1024):
                t = time.thread_time()
                down(buf)
                spent += time.thread_time() - t
            out["cog"][label] = {"encode_s": spent * scale * 4 / 3}
    finally:
        shutil.rmtree(spool, ignore_errors=True)
    return out


def codec_rows(T: dict) -> list[str]:
    """Markdown tables of :func:`codec_table`'s result."""
    rows = [f"Zarr chunk codecs ({T['bands']}-band mosaic of {T['cubes']} cubes, scaled to 300 bands; raw float32 "
            f"{T['raw_mb']:.0f} MB):", "",
            "| codec | encode CPU-s per cube | chunk-file write CPU-s per cube | MB on disk | ratio |", "|---|---|---|---|---|"]
    rows += [f"| {k} | {v['encode_s']:.2f} | {v['write_s']:.2f} | {v['mb']:.0f} | {v['ratio']:.2f} |"
             for k, v in T["zarr"].items()]
    rows += ["", "COG tile codecs (512 px tiles, full resolution; overview levels add about a third):", "",
             "| codec | CPU-s per cube | MB on disk (full resolution) | ratio |", "|---|---|---|---|"]
    rows += [f"| {k} | {v['encode_s']:.2f} | {v.get('mb', 0):.0f} | {v.get('ratio', 0):.2f} |" if "mb" in v
             else f"| {k} | {v['encode_s']:.2f} | - | - |" for k, v in T["cog"].items()]
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    br.add_flight_arguments(ap, bands=300, workdir="/tmp/archive-bench-outputs", cubes=8)
    ap.add_argument("--scaling", default="8x4,16x4,32x4",
                    help="memory-vs-length flights, CUBESxPASSES ('' to skip; the paper's flight: 40x5)")
    ap.add_argument("--scaling-bands", type=int, default=32)
    ap.add_argument("--scaling-formats", default=",".join(FORMATS))
    ap.add_argument("--formats", default=",".join(FORMATS))
    ap.add_argument("--shape", choices=sorted(SHAPES), default="heldout",
                    help="flight shape: heldout (default: passes along grid north, 29 %% sidelap), sidelap "
                         "(43 %%), tilted (the pre-issue-37 default: passes at 20 deg, a third of the grid NaN)")
    ap.add_argument("--no-stages", action="store_true",
                    help="skip the second, stage-profiled run of each format (bench/stage_profile.py)")
    ap.add_argument("--codec-table", action="store_true",
                    help="measure every Zarr and COG codec on the ENVI render's tiles (needs hdr in --formats)")
    ap.add_argument("--render-option", action="append", default=[], metavar="ARG",
                    help="one more argument for every archive render (repeat it: --render-option=--threads "
                         "--render-option=3)")
    ap.add_argument("--compression", help="archive render --compression for every format (default: the command's)")
    ap.add_argument("--no-gdal", action="store_true")
    ap.add_argument("--json", metavar="FILE")
    args = ap.parse_args(argv)
    args.heading, args.spacing = SHAPES[args.shape]
    work = Path(args.workdir)
    work.mkdir(parents=True, exist_ok=True)
    formats = [f for f in args.formats.split(",") if f]
    R: dict = {"machine": br.machine(), "args": vars(args), "load_start": br.load(), "sidelap": sidelap(args.spacing)}
    try:
        from archive.render.context import gl_info

        R["gl"] = gl_info()
    except Exception as exc:  # the bench still measures the rest
        R["gl"] = repr(exc)
    _say(f"machine {R['machine']}, GL {R['gl']}")
    sl = R["sidelap"]
    _say(f"shape {args.shape}: heading {args.heading:g} deg, passes {sl['spacing_m']:.0f} m apart at {sl['height_m']:.0f} m: swath {sl['swath_m']:.1f} m, "
         f"sidelap {100 * sl['sidelap']:.0f} %")

    flight = br.flight_dir(args)
    R["warm_s"] = br.warm(flight)
    from archive.simulator.command import GROUND_HEIGHT

    ground = GROUND_HEIGHT  # the simulator's flat ground, m
    source, plan, _ = br.make_plan(flight, args.gsd, ground)
    g = plan.grid
    out_bytes = g.width * g.height * plan.nbands * 4
    lines = sum(c.lines for c in source.cubes)
    flight_s = lines / float(source.cubes[0].framerate)
    R["cubes"] = len(plan.jobs)
    R["lines"] = lines
    R["grid"] = {"width": g.width, "height": g.height, "bands": plan.nbands, "mb": out_bytes / br.MB,
                 "input_mb": sum(f.stat().st_size for f in br.bil_files(flight)) / br.MB, "flight_s": flight_s}
    _say(f"{len(plan.jobs)} cubes, grid {g.width} x {g.height} px x {plan.nbands} bands = {out_bytes / br.MB:.0f} MB; "
         f"flight {flight_s:.1f} s of recording")

    R["floor"] = br.io_floor(flight, out_bytes, work)
    _say(f"I/O floor: {R['floor']['wall_s']:.1f} s (read {R['floor']['read_s']:.1f}, "
         f"write+fsync {R['floor']['write_s']:.1f})")

    if not args.no_gdal:
        R["gdal"] = br.gdal_direct(source, plan, ground, work, group=plan.nbands, threads=2)
        for f in work.glob("gdal_cube*.npy"):
            f.unlink()
        _say(f"GDAL warp: {R['gdal']['wall_s']:.1f} s, peak {br.fmt_gb(R['gdal']['peak_rss'])}")

    R["render"] = {}
    compression = (["--compression", args.compression] if args.compression else []) + list(args.render_option)
    for fmt in formats:
        out = work / f"mosaic.{fmt}"
        r = R["render"][fmt] = render_plain(flight, out, args.gsd, ground, extra=compression)
        _say(f"archive render -> .{fmt}: {r['wall_s']:.1f} s (+sync {r['wall_sync_s']:.1f}), "
             f"{r['tree_cpu_s']:.1f} CPU-s (tree, start to exit), cores busy {100 * r['busy_tree']:.0f} % "
             f"(cores x wall: busy / iowait / idle / others {split_text(r.get('split'))}), "
             f"tree RSS {br.fmt_gb(r['peak_tree_rss'])}, {r['out_mb']:.0f} MB")
        if fmt == "hdr" and args.codec_table:
            R["codecs"] = codec_table(out, len(plan.jobs), plan.nbands, spool=work)
            print("\n".join(codec_rows(R["codecs"])), flush=True)
        if not args.no_stages:   # the same render again, through stage_profile.py: CPU-s per stage
            p = render_cli(flight, out, args.gsd, ground, work=work, extra=compression)
            r["profiled"] = {k: v for k, v in p.items() if k != "profile"}
            r["profile"] = p["profile"]
            _say(f"  profiled: {p['cpu_s']:.1f} CPU-s of the render (cluster start-up excluded), threads busy "
                 f"{100 * p['busy_tasks']:.0f} % (task stream)")
        if fmt == "tif":
            R["cog_reads"] = cog_window_reads(out)
            from archive.outputs.cog_check import check_cog

            R["cog_errors"] = check_cog(out)
            _say(f"COG window reads {R['cog_reads']}; layout errors {R['cog_errors']}")
        _remove(out)

    R["scaling"] = {}
    for spec in [v for v in args.scaling.split(",") if v]:
        n, p = (int(x) for x in spec.split("x"))
        small = scaling_flight(work, n, p, args.scaling_bands, args.samples, args.lines, args.heading, args.spacing)
        br.warm(small)
        for fmt in [f for f in args.scaling_formats.split(",") if f]:
            out = work / f"scaling{n}.{fmt}"
            r = render_plain(small, out, args.gsd, ground, extra=compression)
            _remove(out)
            R["scaling"][f"{n}x{p}.{fmt}"] = r
            _say(f"scaling {n} cubes / {p} passes -> .{fmt}: {r['wall_s']:.1f} s, tree RSS {br.fmt_gb(r['peak_tree_rss'])}")
    R["load_end"] = br.load()
    report(R)
    if args.json:
        Path(args.json).write_text(json.dumps(R, indent=1, default=str))
    return 0


def _remove(out: Path) -> None:
    """Delete a rendered output (they are GBs; the next format needs the disk)."""
    for f in (out, out.with_suffix(""), Path(str(out) + ".json")):
        if f.is_dir():
            shutil.rmtree(f)
        elif f.exists() and f != out.parent:
            f.unlink()


def report(R: dict) -> None:
    floor = R["floor"]["wall_s"]
    print()
    print(f"{R['cubes']} cubes ({R['lines']} lines), grid {R['grid']['width']} x {R['grid']['height']} px x "
          f"{R['grid']['bands']} bands ({R['grid']['mb']:.0f} MB float32), input {R['grid']['input_mb']:.0f} MB; "
          f"load {R['load_start']} -> {R['load_end']}")
    print()
    print("| path | wall s | wall + sync s | ratio to floor | GDAL / it | CPU-s (tree, start to exit) | CPU-s per cube (tree) | "
          "cores busy (tree CPU / wall / cores) | cores x wall: busy / iowait / idle / others | "
          "threads busy (task stream, profiled run) | peak RSS GB (tree) | lines/s | load before -> after |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    print(f"| I/O floor (read input + write {R['grid']['mb']:.0f} MB, fsync) | {floor:.1f} | {floor:.1f} | 1.00 | "
          "- | - | - | - | - | - | - | - | - |")
    if "gdal" in R:
        gd = R["gdal"]
        print(f"| GDAL geolocation warp (all bands per call, 2 threads) | {gd['wall_s']:.1f} | - | "
              f"{gd['wall_s'] / floor:.2f} | 1.00 | - | - | - | - | - | {br.fmt_gb(gd['peak_rss'])} | "
              f"{R['lines'] / gd['wall_s']:.0f} | - |")
    for fmt, r in R["render"].items():
        gdal = f"{R['gdal']['wall_s'] / r['wall_sync_s']:.2f}" if "gdal" in R else "-"
        print(f"| `archive render` -> .{fmt} | {r['wall_s']:.1f} | {r['wall_sync_s']:.1f} | "
              f"**{r['wall_sync_s'] / floor:.2f}** | {gdal} | {r['tree_cpu_s']:.1f} | {r['tree_cpu_s'] / R['cubes']:.2f} | "
              f"**{100 * r['busy_tree']:.0f} %** | {split_text(r.get('split'))} | "
              f"{'-' if 'profiled' not in r else format(100 * r['profiled']['busy_tasks'], '.0f') + ' %'} | "
              f"{br.fmt_gb(r['peak_tree_rss'])} | {R['lines'] / r['wall_s']:.0f} | {r['load'][0]} -> {r['load'][1]} |")
    if any("profile" in r for r in R["render"].values()):
        print()
        print("\n".join(stage_table(R)))
        print()
        print("Task stream (task-seconds by kind, count):")
        for fmt, r in R["render"].items():
            tasks = r.get("profile", {}).get("tasks", {})
            print(f"  .{fmt}: " + ", ".join(f"{k} {v['task_s']:.1f} s ({v['count']})" for k, v in
                                            sorted(tasks.items(), key=lambda kv: -kv[1]["task_s"]) if v["task_s"] > 0.05))
    if "cog_reads" in R:
        print()
        for name, v in R["cog_reads"].items():
            print(f"COG 512 x 512 window, {name}: {v['bytes'] / 1e6:.2f} MB read in {v['s'] * 1000:.0f} ms")
    if R["scaling"]:
        print()
        print("| flight | format | wall s | CPU-s (tree) | peak RSS (tree) | load |")
        print("|---|---|---|---|---|---|")
        for key, r in R["scaling"].items():
            spec, fmt = key.split(".")
            n, p = spec.split("x")
            print(f"| {n} cubes / {p} passes | .{fmt} | {r['wall_s']:.1f} | {r['tree_cpu_s']:.1f} | "
                  f"{br.fmt_gb(r['peak_tree_rss'])} | {r['load'][1]} |")


if __name__ == "__main__":
    raise SystemExit(main())
