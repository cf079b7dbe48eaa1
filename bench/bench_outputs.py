"""Benchmark of the output writers (issues 10 and 20): `archive render` to Zarr, COG and ENVI against the
I/O floor and GDAL's geolocation warp, on a real flight's shape, in one run.

    python bench/bench_outputs.py [--cubes 8] [--bands 300] [--samples 900] [--lines 1000] [--gsd 0.04]
                                  [--scaling 8x4,16x4,32x4] [--scaling-bands 32] [--scaling-formats hdr,zarr,tif]
                                  [--formats zarr,tif,hdr] [--workdir DIR] [--no-gdal] [--json FILE]

Default flight (issue 20): the paper's cubes (900 samples x 1000 lines x 300 bands) in a lawn-mower
pattern, 2 cubes per pass, so 8 cubes = 4 passes; passes 25 m apart at 40 m above ground with a
47.5 deg field of view: swath 2 x 40 x tan(23.75 deg) = 35.2 m, sidelap 1 - 25 / 35.2 = 29 %
(printed from the simulator's constants). Simulated once into --workdir and reused while its
marker file exists. After reading the input once (warm page cache), one run measures:

1. the I/O floor: read every input .bil once + write the mosaic's float32 byte count once, fsync'ed
   (``bench_render.io_floor``);
2. GDAL's direct method: ``rasterio.warp.reproject`` with geolocation arrays, all bands per call, 2
   threads, per cube (``bench_render.gdal_direct``);
3. per format, ``archive render FLIGHT --out X.{zarr,tif,hdr} ...`` through ``bench/stage_profile.py``
   (the command's own code, ``archive.cli.main``, on a local cluster started exactly as the command
   starts it, with the task stream recorded and stage timers in the workers): wall (process start
   to exit, Python imports and cluster start-up included), then ``sync`` (wall + sync compares with
   the floor's fsync'ed write), peak RSS of the whole process tree (polled every 0.1 s), CPU-seconds
   of the tree, **cores busy** = CPU-s / wall / cores and, from the task stream, task-seconds /
   (graph seconds x worker threads), **CPU-seconds per cube per stage** (GL lookup, band passes or
   CPU gather, DN reads, mosaic, NaN checks, compression, overviews, writes, the command's own
   process), output size; ratios to the floor and to GDAL from this same run;
4. a 512 x 512 window of the COG read with rasterio for 3 bands and for all bands;
5. memory against flight length: ``--scaling`` flights ``NxP`` (N cubes over P passes of the same
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

FORMATS = ("zarr", "tif", "hdr")


def _say(text: str) -> None:
    print(f"{text}   [load {br.load()}]", flush=True)


def render_cli(flight: Path, out: Path, gsd: float, ground: float, extra=(), work: Path | None = None) -> dict:
    """``archive render`` through ``bench/stage_profile.py`` in a subprocess: wall, wall + sync, peak tree
    RSS, CPU of the tree, output bytes, the task stream's summary and CPU-seconds per stage."""
    profile = (work or out.parent) / f"{out.name}.profile.json"
    cmd = [sys.executable, str(Path(__file__).resolve().parent / "stage_profile.py"), str(profile), "--",
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
    files = [out] if out.is_file() else [f for f in out.rglob("*") if f.is_file()]
    if out.suffix == ".hdr":
        files.append(out.with_suffix(""))
    size = sum(f.stat().st_size for f in files)
    prof = json.loads(profile.read_text())
    cpu = prof["cpu"]["client"] + sum(prof["cpu"]["workers"].values())
    task_s = sum(v["task_s"] for v in prof["tasks"].values())
    return {"cmd": "archive render " + " ".join(cmd[4:]), "wall_s": wall, "wall_sync_s": synced,
            "peak_tree_rss": poll.peak_rss, "peak_tree_anon": poll.peak_anon, "out_mb": size / br.MB,
            "command_s": prof["wall_s"], "graph_s": prof["graph_s"], "cpu_s": cpu, "tree_cpu_s": tree,
            "busy_cpu": cpu / wall / prof["cores"], "busy_graph_cpu": cpu / max(prof["graph_s"], 1e-9) / prof["cores"],
            "busy_tasks": task_s / max(prof["graph_s"] * prof["nthreads"], 1e-9),
            "profile": prof, "load": [load0, br.load()]}


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


def scaling_flight(workdir: Path, cubes: int, passes: int, bands: int, samples: int, lines: int) -> Path:
    """``cubes`` paper-size cubes over ``passes`` lawn-mower passes (simulated once, reused)."""
    per_pass = -(-cubes // passes)
    d = workdir / f"scaling_c{cubes}_p{passes}_b{bands}_s{samples}_l{lines}"
    if (d / ".bench-complete").exists():
        return d
    from archive.simulator.command import simulate_flight

    if d.exists():
        shutil.rmtree(d)
    t = time.perf_counter()
    simulate_flight(d, cubes=cubes, bands=bands, samples=samples, lines=lines, cubes_per_pass=per_pass, seed=1,
                    progress=False)
    (d / ".bench-complete").write_text(f"{time.perf_counter() - t:.1f} s\n")
    return d


def sidelap() -> dict:
    """Swath, pass spacing and sidelap of the simulated flights (the simulator's constants)."""
    import math

    from archive.simulator.command import HEIGHT, SPACING

    swath = 2 * HEIGHT * math.tan(math.radians(br.FOV / 2))
    return {"height_m": HEIGHT, "spacing_m": SPACING, "swath_m": swath, "sidelap": 1 - SPACING / swath}


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


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    br.add_flight_arguments(ap, bands=300, workdir="/tmp/archive-bench-outputs", cubes=8)
    ap.add_argument("--scaling", default="8x4,16x4,32x4",
                    help="memory-vs-length flights, CUBESxPASSES ('' to skip; the paper's flight: 40x5)")
    ap.add_argument("--scaling-bands", type=int, default=32)
    ap.add_argument("--scaling-formats", default=",".join(FORMATS))
    ap.add_argument("--formats", default=",".join(FORMATS))
    ap.add_argument("--no-gdal", action="store_true")
    ap.add_argument("--json", metavar="FILE")
    args = ap.parse_args(argv)
    work = Path(args.workdir)
    work.mkdir(parents=True, exist_ok=True)
    formats = [f for f in args.formats.split(",") if f]
    R: dict = {"machine": br.machine(), "args": vars(args), "load_start": br.load(), "sidelap": sidelap()}
    try:
        from archive.render.context import gl_info

        R["gl"] = gl_info()
    except Exception as exc:  # the bench still measures the rest
        R["gl"] = repr(exc)
    _say(f"machine {R['machine']}, GL {R['gl']}")
    sl = R["sidelap"]
    _say(f"passes {sl['spacing_m']:.0f} m apart at {sl['height_m']:.0f} m: swath {sl['swath_m']:.1f} m, "
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
    for fmt in formats:
        out = work / f"mosaic.{fmt}"
        r = render_cli(flight, out, args.gsd, ground, work=work)
        R["render"][fmt] = r
        _say(f"archive render -> .{fmt}: {r['wall_s']:.1f} s (+sync {r['wall_sync_s']:.1f}), "
             f"{r['cpu_s']:.1f} CPU-s, cores busy {100 * r['busy_cpu']:.0f} % (tasks {100 * r['busy_tasks']:.0f} %), "
             f"tree RSS {br.fmt_gb(r['peak_tree_rss'])}, {r['out_mb']:.0f} MB")
        if fmt == "tif":
            R["cog_reads"] = cog_window_reads(out)
            from archive.outputs.cog_check import check_cog

            R["cog_errors"] = check_cog(out)
            _say(f"COG window reads {R['cog_reads']}; layout errors {R['cog_errors']}")
        _remove(out)

    R["scaling"] = {}
    for spec in [v for v in args.scaling.split(",") if v]:
        n, p = (int(x) for x in spec.split("x"))
        small = scaling_flight(work, n, p, args.scaling_bands, args.samples, args.lines)
        br.warm(small)
        for fmt in [f for f in args.scaling_formats.split(",") if f]:
            out = work / f"scaling{n}.{fmt}"
            r = render_cli(small, out, args.gsd, ground, work=work)
            _remove(out)
            r.pop("profile")
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
    print("| path | wall s | wall + sync s | ratio to floor | GDAL / it | CPU-s (tree, start-up incl.) | CPU-s per cube (render) | "
          "cores busy (CPU/wall) | busy in graph (CPU/graph) | threads busy (task stream) | peak RSS GB (tree) | "
          "lines/s | load before -> after |")
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
              f"**{r['wall_sync_s'] / floor:.2f}** | {gdal} | {r['tree_cpu_s']:.1f} | {r['cpu_s'] / R['cubes']:.2f} | "
              f"{100 * r['busy_cpu']:.0f} % | {100 * r['busy_graph_cpu']:.0f} % | {100 * r['busy_tasks']:.0f} % | "
              f"{br.fmt_gb(r['peak_tree_rss'])} | {R['lines'] / r['wall_s']:.0f} | {r['load'][0]} -> {r['load'][1]} |")
    if R["render"]:
        print()
        print("\n".join(stage_table(R)))
        print()
        print("Task stream (task-seconds by kind, count):")
        for fmt, r in R["render"].items():
            tasks = r["profile"]["tasks"]
            print(f"  .{fmt}: " + ", ".join(f"{k} {v['task_s']:.1f} s ({v['count']})" for k, v in
                                            sorted(tasks.items(), key=lambda kv: -kv[1]["task_s"]) if v["task_s"] > 0.05))
    if "cog_reads" in R:
        print()
        for name, v in R["cog_reads"].items():
            print(f"COG 512 x 512 window, {name}: {v['bytes'] / 1e6:.2f} MB read in {v['s'] * 1000:.0f} ms")
    if R["scaling"]:
        print()
        print("| flight | format | wall s | CPU-s (render) | peak RSS (tree) | load |")
        print("|---|---|---|---|---|---|")
        for key, r in R["scaling"].items():
            spec, fmt = key.split(".")
            n, p = spec.split("x")
            print(f"| {n} cubes / {p} passes | .{fmt} | {r['wall_s']:.1f} | {r['cpu_s']:.1f} | "
                  f"{br.fmt_gb(r['peak_tree_rss'])} | {r['load'][1]} |")


if __name__ == "__main__":
    raise SystemExit(main())
