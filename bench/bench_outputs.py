"""Benchmark of the output writers (issue 10): `archive render` to Zarr, COG and ENVI against the I/O
floor and GDAL's geolocation warp, in one run.

    python bench/bench_outputs.py [--cubes 2] [--bands 100] [--samples 900] [--lines 1000] [--gsd 0.04]
                                  [--scaling 8,16] [--workdir DIR] [--no-gdal] [--json FILE]

On one simulated flight (simulated once into --workdir and reused while its marker file exists;
default: 2 paper-shape cubes of 900 samples x 1000 lines, with --bands bands), after reading the
input once (warm page cache), one run measures:

1. the I/O floor: read every input .bil once + write the mosaic's float32 byte count once, fsync'ed
   (``bench_render.io_floor``);
2. GDAL's direct method: ``rasterio.warp.reproject`` with geolocation arrays, all bands per call, 2
   threads, per cube (``bench_render.gdal_direct``);
3. ``python -m archive render FLIGHT --out X.{zarr,tif,hdr} ...`` (its own local cluster) per
   format: wall, then ``sync`` of the written pages (wall + sync is what compares with the floor's
   fsync'ed write), the command's own seconds (its summary line: after Python's start and imports,
   cluster start-up included), peak RSS of the whole process tree (polled every 0.1 s), output size;
4. a 512 x 512 window of the COG read with rasterio for 3 bands and for all bands: bytes the
   process read (``/proc/self/io`` rchar: what GDAL asked the kernel for) and seconds;
5. memory against flight length: the same command for ``--scaling`` flights of small cubes (256
   samples x 500 lines x 16 bands, 2 cubes per pass) to every format: peak process-tree RSS.

The machine is often shared: the load average is printed after each step; compare runs only at a
similar load.
"""

from __future__ import annotations

import argparse
import json
import os
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


def render_cli(flight: Path, out: Path, gsd: float, ground: float, extra=()) -> dict:
    """``python -m archive render`` in a subprocess: wall, wall + sync, peak tree RSS, output bytes."""
    cmd = [sys.executable, "-m", "archive", "render", str(flight), "--fov", str(br.FOV), "--gsd", str(gsd),
           "--ground-height", str(ground), "--mode", br.MODE, "--bands", "all", "--out", str(out),
           "--overwrite", "--quiet", *extra]
    t = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    with br.MemoryPoll(proc.pid) as poll:
        stdout, stderr = proc.communicate()
    wall = time.perf_counter() - t
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({proc.returncode}): {stderr[-3000:]}")
    os.sync()
    synced = time.perf_counter() - t
    files = [out] if out.is_file() else [f for f in out.rglob("*") if f.is_file()]
    if out.suffix == ".hdr":
        files.append(out.with_suffix(""))
    size = sum(f.stat().st_size for f in files)
    import re

    said = re.search(r" in ([0-9.]+) s\.$", stdout.strip())  # the command's own clock, after imports
    return {"cmd": " ".join(cmd[1:]), "wall_s": wall, "wall_sync_s": synced, "peak_tree_rss": poll.peak_rss,
            "peak_tree_anon": poll.peak_anon, "out_mb": size / br.MB, "stdout": stdout.strip(),
            "command_s": float(said.group(1)) if said else None}


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


def scaling_flight(workdir: Path, cubes: int) -> Path:
    ns = argparse.Namespace(cubes=cubes, bands=16, samples=256, lines=500, workdir=str(workdir))
    return br.flight_dir(ns)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    br.add_flight_arguments(ap, bands=100, workdir="/tmp/archive-bench-outputs")
    ap.add_argument("--scaling", default="8,16", help="cube counts of the memory-vs-length flights ('' to skip)")
    ap.add_argument("--formats", default=",".join(FORMATS))
    ap.add_argument("--no-gdal", action="store_true")
    ap.add_argument("--json", metavar="FILE")
    args = ap.parse_args(argv)
    work = Path(args.workdir)
    work.mkdir(parents=True, exist_ok=True)
    formats = [f for f in args.formats.split(",") if f]
    R: dict = {"machine": br.machine(), "args": vars(args), "load_start": br.load()}
    try:
        from archive.render.context import gl_info

        R["gl"] = gl_info()
    except Exception as exc:  # the bench still measures the rest
        R["gl"] = repr(exc)
    _say(f"machine {R['machine']}, GL {R['gl']}")

    flight = br.flight_dir(args)
    R["warm_s"] = br.warm(flight)
    from archive.simulator.command import GROUND_HEIGHT

    ground = GROUND_HEIGHT  # the simulator's flat ground, m
    source, plan, _ = br.make_plan(flight, args.gsd, ground)
    g = plan.grid
    out_bytes = g.width * g.height * plan.nbands * 4
    lines = sum(c.lines for c in source.cubes)
    flight_s = lines / float(source.cubes[0].framerate)
    R["grid"] = {"width": g.width, "height": g.height, "bands": plan.nbands, "mb": out_bytes / br.MB,
                 "input_mb": sum(f.stat().st_size for f in br.bil_files(flight)) / br.MB, "flight_s": flight_s}
    _say(f"grid {g.width} x {g.height} px x {plan.nbands} bands = {out_bytes / br.MB:.0f} MB; "
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
        r = render_cli(flight, out, args.gsd, ground)
        R["render"][fmt] = r
        _say(f"archive render -> .{fmt}: {r['wall_s']:.1f} s (+sync {r['wall_sync_s']:.1f}), "
             f"tree RSS {br.fmt_gb(r['peak_tree_rss'])}, {r['out_mb']:.0f} MB")
        if fmt == "tif":
            R["cog_reads"] = cog_window_reads(out)
            from archive.outputs.tiff import check_cog

            R["cog_errors"] = check_cog(out)
            _say(f"COG window reads {R['cog_reads']}; layout errors {R['cog_errors']}")

    R["scaling"] = {}
    for n in [int(v) for v in args.scaling.split(",") if v]:
        small = scaling_flight(work, n)
        br.warm(small)
        for fmt in formats:
            r = render_cli(small, work / f"scaling{n}.{fmt}", 0.04, ground)
            R["scaling"][f"{n}.{fmt}"] = r
            _say(f"scaling {n} cubes -> .{fmt}: {r['wall_s']:.1f} s, tree RSS {br.fmt_gb(r['peak_tree_rss'])}")
    R["load_end"] = br.load()
    report(R)
    if args.json:
        Path(args.json).write_text(json.dumps(R, indent=1, default=str))
    return 0


def report(R: dict) -> None:
    floor = R["floor"]["wall_s"]
    print()
    print(f"Grid {R['grid']['width']} x {R['grid']['height']} px x {R['grid']['bands']} bands "
          f"({R['grid']['mb']:.0f} MB float32), input {R['grid']['input_mb']:.0f} MB; load {R['load_start']} "
          f"-> {R['load_end']}")
    print()
    print("| path | wall s | wall + sync s | command's own s | peak RSS GB (tree) | output MB | ratio to floor (wall+sync) |")
    print("|---|---|---|---|---|---|---|")
    print(f"| I/O floor (read input + write {R['grid']['mb']:.0f} MB, fsync) | {floor:.1f} | {floor:.1f} | - | - | - | 1.00 |")
    if "gdal" in R:
        gd = R["gdal"]
        print(f"| GDAL geolocation warp (all bands per call, 2 threads) | {gd['wall_s']:.1f} | - | - | "
              f"{br.fmt_gb(gd['peak_rss'])} | - | {gd['wall_s'] / floor:.2f} |")
    for fmt, r in R["render"].items():
        own = "-" if r.get("command_s") is None else f"{r['command_s']:.1f}"
        print(f"| `archive render` -> .{fmt} | {r['wall_s']:.1f} | {r['wall_sync_s']:.1f} | {own} | "
              f"{br.fmt_gb(r['peak_tree_rss'])} | {r['out_mb']:.0f} | {r['wall_sync_s'] / floor:.2f} |")
    if "gdal" in R:
        print()
        for fmt, r in R["render"].items():
            print(f"GDAL warp / render .{fmt}: {R['gdal']['wall_s'] / r['wall_sync_s']:.2f}x")
    if "cog_reads" in R:
        print()
        for name, v in R["cog_reads"].items():
            print(f"COG 512 x 512 window, {name}: {v['bytes'] / 1e6:.2f} MB read in {v['s'] * 1000:.0f} ms")
    if R["scaling"]:
        print()
        print("| flight | format | wall s | peak RSS (tree) |")
        print("|---|---|---|---|")
        for key, r in R["scaling"].items():
            n, fmt = key.split(".")
            print(f"| {n} cubes | .{fmt} | {r['wall_s']:.1f} | {br.fmt_gb(r['peak_tree_rss'])} |")


if __name__ == "__main__":
    raise SystemExit(main())
