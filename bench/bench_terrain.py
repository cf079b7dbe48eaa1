"""Benchmark of terrain rendering (issue 11): the same flight rendered flat and over its DEM.

    python bench/bench_terrain.py [--cubes 4] [--bands 60] [--samples 900] [--lines 1000] [--gsd 0.04]
                                  [--repeat 3] [--workdir DIR] [--results FILE]

The flight is ``archive simulate --terrain hills`` (simulated once into --workdir and reused while
its truth exists) with its ``dem.tif`` (0.1 m, UTM, ellipsoidal heights declared). Both renders use
the same GSD and radiance mode; "flat" puts the ground at the mean DEM height under the flight (the
output grid is then about the same size). Measured, alternating flat and DEM, ``--repeat`` times each
(medians reported):

1. end-to-end: ``archive.georectify([FLIGHT], OUT.zarr, ...)`` in a subprocess (Dask local cluster,
   Zarr writer; what ``archive render`` runs), wall time and the peak summed RSS of its process tree
   (polled every 0.1 s);
2. render core, in this process: the plan (``archive.api.plan``: sources, meshes, grid; the DEM's
   cost is here: reading it, tracing every mesh vertex and segment midpoint), pass 1 per cube
   (``rasterize_lookup``), pass 2 per cube and group of 32 bands (read + radiometry +
   ``render_lookup``).

Prints a Markdown section (machine, command, table, ratios) and appends it to --results if given.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_render as br  # noqa: E402  (machine, the flight options)

FOV = 47.5
MODE = "radiance"
GROUP = 32


def machine() -> str:
    m = br.machine()
    return f"{m['cpu']}, {m['cores']} cores, {m['ram_gb']:.1f} GB RAM, Python {m['python']}"


def gl_text() -> str:
    from archive.render.context import gl_info

    info = gl_info()
    return f"{info['renderer']} | {info['version']}"


class MemoryPoll:
    """Peak of the summed RSS of a process and its descendants, polled in a thread (bytes)."""

    def __init__(self, pid: int, interval: float = 0.1):
        import psutil

        self.proc = psutil.Process(pid)
        self.interval = interval
        self.peak = 0
        self._stop = threading.Event()

    def _run(self) -> None:
        import psutil

        while not self._stop.is_set():
            total = 0
            try:
                for p in [self.proc, *self.proc.children(recursive=True)]:
                    try:
                        total += p.memory_info().rss
                    except psutil.Error:
                        pass
            except psutil.Error:
                pass
            self.peak = max(self.peak, total)
            self._stop.wait(self.interval)

    def __enter__(self):
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()


def flight(args) -> Path:
    from archive.simulator.command import simulate_flight

    directory = Path(args.workdir) / f"hills_{args.cubes}x{args.lines}x{args.samples}x{args.bands}"
    if not (directory / "truth" / "truth.json").exists():
        t = time.perf_counter()
        simulate_flight(directory, cubes=args.cubes, bands=args.bands, samples=args.samples, lines=args.lines,
                        seed=11, terrain="hills", overwrite=True, progress=True)
        print(f"simulated {directory} in {time.perf_counter() - t:.1f} s", flush=True)
    return directory


def mean_ground(directory: Path) -> float:
    """The mean DEM height over the flight's footprint (m above the ellipsoid): the flat run's ground."""
    from archive.simulator.truth import load_truth

    truth = load_truth(directory)
    rings = np.concatenate(truth.footprint())
    xx, yy = np.meshgrid(np.linspace(rings[:, 0].min(), rings[:, 0].max(), 300),
                         np.linspace(rings[:, 1].min(), rings[:, 1].max(), 300))
    inside = truth.covered(xx, yy)
    return round(float(np.mean(truth.terrain.height(xx[inside], yy[inside]))), 3)


def ground_keywords(directory: Path, kind: str, ground: float) -> dict:
    return {"dem": str(directory / "dem.tif")} if kind == "dem" else {"ground_height": ground}


def end_to_end(directory: Path, args, kind: str, ground: float) -> dict:
    out = Path(args.workdir) / f"bench_terrain_{kind}.zarr"
    keywords = ground_keywords(directory, kind, ground)
    extra = ", ".join(f"{k}={v!r}" for k, v in keywords.items())
    call = (f"archive.georectify([{str(directory)!r}], {str(out)!r}, gsd={args.gsd!r}, fov={FOV!r}, {extra}, "
            f"mode={MODE!r}, overwrite=True)")
    code = f"import json, archive\nprint(json.dumps({call}))"
    t = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    with MemoryPoll(proc.pid) as poll:
        stdout, stderr = proc.communicate()
    wall = time.perf_counter() - t
    if proc.returncode != 0:
        print(stderr[-4000:], file=sys.stderr)
        raise SystemExit(f"archive.render ({kind}) failed with exit code {proc.returncode}")
    summary = json.loads(stdout.strip().splitlines()[-1])
    return {"wall_s": wall, "peak_rss_mb": poll.peak / 1e6, "width": summary["width"], "height": summary["height"],
            "graph_s": summary["graph_seconds"], "call": call}


def core(directory: Path, args, kind: str, ground: float) -> dict:
    """Plan + pass 1 + pass 2 in this process (module docstring), seconds each."""
    from archive.api import plan
    from archive.render.renderer import rasterize_lookup, render_lookup

    t0 = time.perf_counter()
    planned = plan([str(directory)], gsd=args.gsd, fov=FOV, mode=MODE, **ground_keywords(directory, kind, ground))
    t1 = time.perf_counter()
    source, p = planned.sources[0], planned.plan
    lookups = [rasterize_lookup(job.mesh, job.window, source.cubes[job.cube].samples) for job in p.jobs]
    t2 = time.perf_counter()
    nb = len(p.bands[0])
    for job, lookup in zip(p.jobs, lookups):
        for b0 in range(0, nb, GROUP):
            bands = list(p.bands[0][b0:b0 + GROUP])
            dn = source.read_bands(job.cube, bands)
            render_lookup(lookup, dn, source.radiometry(job.cube, bands, MODE), 8)
    t3 = time.perf_counter()
    meshes = [job.mesh for job in p.jobs]
    return {"plan_s": t1 - t0, "lookup_s": t2 - t1, "bands_s": t3 - t2, "total_s": t3 - t0,
            "vertices_per_row": sorted({m.per_row for m in meshes}),
            "triangles": int(sum(len(m.triangles()) for m in meshes)),
            "covered_px": int(sum(int(lk.covered.sum()) for lk in lookups)),
            "grid": f"{p.grid.width} x {p.grid.height}"}


def median(rows: list[dict], key: str) -> float:
    return statistics.median(r[key] for r in rows)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    br.add_flight_arguments(ap, bands=60, workdir="/tmp/bench_terrain", cubes=4)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--results", help="append the Markdown section to this file")
    args = ap.parse_args()
    Path(args.workdir).mkdir(parents=True, exist_ok=True)
    directory = flight(args)
    ground = mean_ground(directory)
    load_before = os.getloadavg()
    runs: dict[str, dict[str, list]] = {k: {"e2e": [], "core": []} for k in ("flat", "dem")}
    for r in range(args.repeat):
        for kind in ("flat", "dem"):
            runs[kind]["core"].append(core(directory, args, kind, ground))
            runs[kind]["e2e"].append(end_to_end(directory, args, kind, ground))
            c, e = runs[kind]["core"][-1], runs[kind]["e2e"][-1]
            print(f"run {r + 1} {kind}: end-to-end {e['wall_s']:.2f} s (peak {e['peak_rss_mb']:.0f} MB), core "
                  f"{c['total_s']:.2f} s (plan {c['plan_s']:.2f}, pass 1 {c['lookup_s']:.2f}, pass 2 "
                  f"{c['bands_s']:.2f})", flush=True)
    load_after = os.getloadavg()
    flat, dem = runs["flat"], runs["dem"]
    cmd = " ".join(["python", "bench/bench_terrain.py", *sys.argv[1:]])
    lines = [
        f"## Terrain (issue 11): {args.cubes} cubes x {args.lines} lines x {args.samples} samples x {args.bands} "
        f"bands, flat vs DEM at {args.gsd:g} m",
        "",
        f"Command: `{cmd}` (flight: `simulate_flight(..., terrain='hills')`, 12 m of relief ~40 m below the "
        f"camera, DEM 0.1 m UTM; flat run at the mean DEM height under the flight, {ground:g} m; medians of "
        f"{args.repeat} alternating runs).",
        f"Machine: {machine()}; GL: {gl_text()}; load average before {load_before[0]:.2f}, after "
        f"{load_after[0]:.2f}.",
        "",
        "| measure | flat | DEM | DEM / flat |",
        "|---|---|---|---|",
    ]

    def row(name, a, b, unit="s", fmt=".2f"):
        lines.append(f"| {name} | {a:{fmt}} {unit} | {b:{fmt}} {unit} | {b / a:.2f} |")

    row("end-to-end `archive.render` (subprocess, cluster start-up included)", median(flat["e2e"], "wall_s"),
        median(dem["e2e"], "wall_s"))
    row("  of which the render graph", median(flat["e2e"], "graph_s"), median(dem["e2e"], "graph_s"))
    row("peak RSS of the process tree", median(flat["e2e"], "peak_rss_mb"), median(dem["e2e"], "peak_rss_mb"),
        "MB", ".0f")
    row("render core: plan (meshes; DEM read and traced)", median(flat["core"], "plan_s"),
        median(dem["core"], "plan_s"))
    row("render core: pass 1 (lookups)", median(flat["core"], "lookup_s"), median(dem["core"], "lookup_s"))
    row("render core: pass 2 (bands)", median(flat["core"], "bands_s"), median(dem["core"], "bands_s"))
    row("render core: total", median(flat["core"], "total_s"), median(dem["core"], "total_s"))
    c_flat, c_dem = flat["core"][-1], dem["core"][-1]
    lines += [
        "",
        f"Output grid {c_flat['grid']} (flat) and {c_dem['grid']} (DEM); pixels covered by the cubes "
        f"{c_flat['covered_px']} and {c_dem['covered_px']}; mesh vertices per row {c_flat['vertices_per_row']} and "
        f"{c_dem['vertices_per_row']}, triangles {c_flat['triangles']} and {c_dem['triangles']}.",
        f"Calls: `{flat['e2e'][-1]['call']}` and `{dem['e2e'][-1]['call']}`.",
        "",
    ]
    text = "\n".join(lines)
    print(text)
    if args.results:
        with open(args.results, "a", encoding="utf-8") as f:
            f.write("\n" + text)


if __name__ == "__main__":
    main()
