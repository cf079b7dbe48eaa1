"""Rendering from a post-processed trajectory (SBET) against rendering from the recorder's .lcf (issue 46).

One simulated flight of several cubes over overlapping passes (default: 8 cubes of 1000 lines x 300
samples x 32 bands, 2 cubes a pass, 4 passes), its true trajectory written as an SBET beside it; then,
alternated ``--rounds`` times in one run, ``archive render`` (a process each, start to exit) from the
``.lcf`` and with ``--navigation flight.out``, to the same COG format. Prints the medians and their
ratio; ``--results FILE`` appends a section to bench/RESULTS.md.

    .venv/bin/python bench/bench_navigation.py --rounds 3
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cubes", type=int, default=8)
    ap.add_argument("--cubes-per-pass", type=int, default=2)
    ap.add_argument("--lines", type=int, default=1000)
    ap.add_argument("--samples", type=int, default=300)
    ap.add_argument("--bands", type=int, default=32)
    ap.add_argument("--gsd", type=float, default=0.1)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--workdir", default="/tmp/archive-bench-nav")
    ap.add_argument("--results", metavar="FILE")
    args = ap.parse_args()

    from archive.simulator.command import simulate_flight
    from archive.simulator.postprocessed import write_trajectory

    work = Path(args.workdir)
    flight, sbet = work / "flight", work / "flight.out"
    if not sbet.exists():
        work.mkdir(parents=True, exist_ok=True)
        truth = simulate_flight(flight, cubes=args.cubes, cubes_per_pass=args.cubes_per_pass, lines=args.lines,
                                samples=args.samples, bands=args.bands, seed=46, gnss_bias_m=(1.5, -1.1, 0.8),
                                overwrite=True)
        write_trajectory(truth, sbet)
    times: dict[str, list[float]] = {"lcf": [], "sbet": []}
    for _ in range(args.rounds):
        for name in ("lcf", "sbet"):
            out = work / f"{name}.tif"
            cmd = [sys.executable, "-m", "archive", "render", str(flight), "--fov", "47.5", "--gsd", str(args.gsd),
                   "--out", str(out), "--overwrite", "--quiet", *(["--navigation", str(sbet)] if name == "sbet" else [])]
            t0 = time.perf_counter()
            subprocess.run(cmd, check=True, capture_output=True)
            times[name].append(time.perf_counter() - t0)
            print(f"{name}: {times[name][-1]:.2f} s (load {os.getloadavg()[0]:.2f})", flush=True)
    lcf, ppk = statistics.median(times["lcf"]), statistics.median(times["sbet"])
    text = (f"render from the .lcf {lcf:.2f} s, from the SBET {ppk:.2f} s (medians of {args.rounds}, alternated): "
            f"ratio {ppk / lcf:.3f}")
    print(text)
    if args.results:
        with open(args.results, "a") as f:
            f.write(f"\n## Rendering from a post-processed trajectory (issue 46)\n\nMachine: {platform.node()}, "
                    f"{os.cpu_count()} cores; load {os.getloadavg()[0]:.2f} at the end. Command: "
                    f"`.venv/bin/python bench/bench_navigation.py --rounds {args.rounds}` ({args.cubes} cubes x "
                    f"{args.lines} lines x {args.samples} samples x {args.bands} bands, {args.cubes_per_pass} a pass, "
                    f"{args.gsd} m, COG; each a process, start to exit).\n\n{text}.\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
