"""A small render's wall time: in this process (what ``archive render`` does for raw flights of at most
``SMALL_JOB_BYTES`` of DN) against a local cluster of one worker process (``--workers 1``, what it
did before for every size), from one run, alternating the two.

    .venv/bin/python bench/bench_small.py [--rounds 5] [--work DIR]

The command's wall time is measured around the whole ``archive render`` process (interpreter start,
imports, cluster, render, exit), as a user waits for it. The outputs are compared bit for bit.
"""

from __future__ import annotations

import argparse
import hashlib
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ARCHIVE = [sys.executable, "-m", "archive"]


def _render(flight: Path, out: Path, extra: list[str]) -> float:
    t = time.perf_counter()
    subprocess.run([*ARCHIVE, "render", str(flight), "--fov", "47.5", "--gsd", "0.1", "--out", str(out),
                    "--overwrite", "--quiet", *extra], check=True)
    return time.perf_counter() - t


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--work", type=Path, default=None)
    args = parser.parse_args()
    work = args.work or Path(tempfile.mkdtemp(prefix="bench-small-"))
    flight = work / "flight"
    if not flight.exists():
        subprocess.run([*ARCHIVE, "simulate", str(flight), "--cubes", "2", "--bands", "8", "--samples", "128",
                        "--lines", "200", "--quiet"], check=True)
    dn = sum(p.stat().st_size for p in flight.glob("*.bil"))
    times: dict[str, list[float]] = {"in-process": [], "--workers 1": []}
    for _ in range(args.rounds):
        times["in-process"].append(_render(flight, work / "in.tif", []))
        times["--workers 1"].append(_render(flight, work / "proc.tif", ["--workers", "1"]))
    same = hashlib.sha256((work / "in.tif").read_bytes()).digest() == \
        hashlib.sha256((work / "proc.tif").read_bytes()).digest()
    print(f"flight: 2 cubes x 200 lines x 128 samples x 8 bands ({dn / 1e6:.1f} MB of DN); {args.rounds} rounds")
    for name, values in times.items():
        print(f"{name:>12}: median {statistics.median(values):.2f} s, min {min(values):.2f} s, "
              f"max {max(values):.2f} s")
    ratio = statistics.median(times["in-process"]) / statistics.median(times["--workers 1"])
    print(f"ratio in-process / worker process: {ratio:.2f}; outputs identical: {same}")


if __name__ == "__main__":
    main()
