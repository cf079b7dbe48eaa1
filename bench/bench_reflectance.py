"""What ``--mode reflectance`` from the sky spectrometer costs over ``--mode radiance`` (issue 34:
at most 5 %).

    python bench/bench_reflectance.py [--cubes 2] [--bands 64] [--samples 300] [--lines 1000]
                                      [--gsd 0.1] [--repeats 3] [--workdir DIR]

A ``simulate --clouds`` flight (simulated once into --workdir, reused), then:

1. in process, per cube, the work a render task does that the mode changes: ``source.radiometry``
   (reflectance: the spectra read, converted, resampled and interpolated on first use, then per cube
   the separable terms) and the CPU band pass (``gather_lookup``) through the cube's lookup; the
   median of --repeats, a fresh source each time (the spectra are read once per process: the first
   run's radiometry, reported apart, is the cold read);
2. ``python -m archive render`` end to end (its own local cluster), radiance and reflectance
   alternating (radiance, reflectance, reflectance, radiance, ...) so that the shared machine's load
   hits both alike; medians of the wall time.
"""

from __future__ import annotations

import argparse
import os
import platform
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path


def machine() -> str:
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return f"{platform.node()} {platform.machine()}, {cpus} cores, load {os.getloadavg()[0]:.1f}"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cubes", type=int, default=2)
    ap.add_argument("--bands", type=int, default=64)
    ap.add_argument("--samples", type=int, default=300)
    ap.add_argument("--lines", type=int, default=1000)
    ap.add_argument("--gsd", type=float, default=0.1)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--workdir", default="/tmp/archive-bench-reflectance")
    args = ap.parse_args(argv)

    import numpy as np

    from archive.graph.plan import cube_meshes
    from archive.grid import Grid
    from archive.params import NavigationParams
    from archive.render.gather import gather_lookup
    from archive.render.renderer import rasterize_lookup
    from archive.simulator.command import simulate_flight
    from archive.sources import RawFlightSource

    work = Path(args.workdir)
    flight = work / f"clouds_{args.cubes}x{args.lines}x{args.samples}x{args.bands}"
    if not (flight / "downwelling.dcp").is_file():
        shutil.rmtree(flight, ignore_errors=True)
        simulate_flight(flight, cubes=args.cubes, bands=args.bands, samples=args.samples, lines=args.lines,
                        cubes_per_pass=args.cubes, clouds=True)
    print(f"machine {machine()}; flight {flight}", flush=True)

    params = NavigationParams()
    source = RawFlightSource(flight, params)
    meshes = cube_meshes(source, 47.5, 80.0)
    bands = list(range(args.bands))
    lookups, dns = [], []
    for k, mesh in enumerate(meshes):
        w, s, e, n = mesh.bounds_utm()
        grid = Grid.from_bounds(mesh.epsg, w, s, e, n, args.gsd)
        lookups.append(rasterize_lookup(mesh, grid, source.cubes[k].samples))
        dns.append(source.read_bands(k, bands))
    task = {}
    for mode in ("radiance", "reflectance") * args.repeats:
        src = RawFlightSource(flight, params)          # a fresh source: spectra read again
        t0 = time.perf_counter()
        rads = [src.radiometry(k, bands, mode) for k in range(len(meshes))]
        t1 = time.perf_counter()
        for lk, dn, rad in zip(lookups, dns, rads, strict=True):
            gather_lookup(lk, dn, rad)
        t2 = time.perf_counter()
        task.setdefault(mode, []).append((t1 - t0, t2 - t1))
    print(f"first reflectance radiometry (spectra read, cold): {1000 * task['reflectance'][0][0]:.1f} ms", flush=True)
    for mode, runs in task.items():
        rad_s = statistics.median(r[0] for r in runs)
        pass_s = statistics.median(r[1] for r in runs)
        print(f"in process {mode:11s}: radiometry {1000 * rad_s:7.1f} ms, band pass {1000 * pass_s:7.1f} ms "
              f"({len(meshes)} cubes x {args.bands} bands)", flush=True)

    wall = {"radiance": [], "reflectance": []}
    order = []
    for i in range(args.repeats):
        order += ["radiance", "reflectance"] if i % 2 == 0 else ["reflectance", "radiance"]
    for mode in order:
        out = work / f"out_{mode}.tif"
        cmd = [sys.executable, "-m", "archive", "render", str(flight), "--fov", "47.5", "--gsd", str(args.gsd),
               "--mode", mode, "--bands", "all", "--out", str(out), "--overwrite", "--quiet"]
        t = time.perf_counter()
        done = subprocess.run(cmd, capture_output=True, text=True)
        wall[mode].append(time.perf_counter() - t)
        if done.returncode:
            raise SystemExit(f"{' '.join(cmd)} failed: {done.stderr[-2000:]}")
    rad, refl = statistics.median(wall["radiance"]), statistics.median(wall["reflectance"])
    print(f"end to end (archive render ... --gsd {args.gsd} --bands all --out X.tif): radiance {rad:.2f} s, "
          f"reflectance {refl:.2f} s (medians of {args.repeats}), ratio {refl / rad:.3f}; "
          f"runs {[round(v, 2) for v in wall['radiance']]} / {[round(v, 2) for v in wall['reflectance']]}")
    print(f"load after: {os.getloadavg()[0]:.1f}; numpy {np.__version__}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
