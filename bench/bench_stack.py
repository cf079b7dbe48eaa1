"""Time stacks against the number of flights (issue 32): peak RSS of the whole command (its process
and the local cluster's worker processes, summed, sampled every 50 ms) and seconds per flight.

Builds an archive of N small flights of one field (``simulate_flight(seed=k, scene_seed=0)``, one
hour apart), then runs ``archive render --archive A --query-datetime <first n hours> --stack --gsd G
--out X.zarr --quiet`` in a child process for each n, and checks that the stack holds n time steps.

    .venv/bin/python bench/bench_stack.py --flights 10,100
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import threading
import time
from datetime import UTC, datetime, timedelta
from pathlib import Path

SHAPE = dict(cubes=2, bands=8, samples=64, lines=100, cubes_per_pass=2)
START = datetime(2024, 6, 12, 16, tzinfo=UTC)


def build_archive(work: Path, n: int) -> Path:
    """An archive of ``n`` flights of one field, flight k starting k hours after START."""
    from archive.ingest.command import ingest
    from archive.simulator.command import simulate_flight

    archive = work / "archive"
    have = len(list((archive / "collections").glob("*.zarr"))) if archive.is_dir() else 0
    for k in range(have, n):
        d = work / "raw" / f"flight{k:03d}"
        simulate_flight(d, seed=k, scene_seed=0, start=START + timedelta(hours=k), overwrite=True, **SHAPE)
        ingest([str(d)], archive, 47.5, progress=False)
        shutil.rmtree(d)
    return archive


def tree_rss(pid: int) -> int:
    """Resident bytes of process ``pid`` and all its descendants."""
    import psutil

    try:
        root = psutil.Process(pid)
        procs = [root, *root.children(recursive=True)]
    except psutil.Error:
        return 0
    total = 0
    for p in procs:
        try:
            total += p.memory_info().rss
        except psutil.Error:
            pass
    return total


def run_stack(archive: Path, n: int, out: Path, gsd: str) -> dict:
    """One stack of the first ``n`` flights; its wall time and peak RSS (process tree)."""
    end = START + timedelta(hours=n - 1, minutes=30)
    when = f"{START.isoformat().replace('+00:00', 'Z')}/{end.isoformat().replace('+00:00', 'Z')}"
    cmd = [sys.executable, "-m", "archive", "render", "--archive", str(archive), "--query-datetime", when,
           "--stack", "--gsd", gsd, "--out", str(out), "--quiet"]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    peak = {"rss": 0}
    stop = threading.Event()

    def sample() -> None:
        while not stop.is_set():
            peak["rss"] = max(peak["rss"], tree_rss(proc.pid))
            time.sleep(0.05)

    thread = threading.Thread(target=sample, daemon=True)
    thread.start()
    stdout, stderr = proc.communicate()
    stop.set()
    thread.join()
    seconds = time.perf_counter() - t0
    if proc.returncode:
        raise SystemExit(f"stack of {n} failed: {stderr.strip()}")
    import xarray as xr

    with xr.open_zarr(out) as ds:
        steps = ds.sizes["time"]
        shape = dict(ds.sizes)
    assert steps == n, (steps, n)
    return {"flights": n, "seconds": seconds, "per_flight_s": seconds / n, "peak_rss": peak["rss"],
            "shape": shape, "summary": stdout.strip().splitlines()[-1]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--flights", default="10,100", help="stack sizes (default 10,100)")
    parser.add_argument("--gsd", default="0.1", help="stack GSD, m (default 0.1)")
    parser.add_argument("--work", default="/tmp/bench_stack", help="work folder (the archive is kept there)")
    parser.add_argument("--build-only", type=int, metavar="N", help=argparse.SUPPRESS)
    args = parser.parse_args()
    work = Path(args.work)
    if args.build_only:   # in a child process: the bench's own process holds no catalog handle
        build_archive(work, args.build_only)
        return
    sizes = [int(v) for v in args.flights.split(",")]
    work.mkdir(parents=True, exist_ok=True)
    t = time.perf_counter()
    subprocess.run([sys.executable, __file__, "--work", str(work), "--build-only", str(max(sizes))], check=True)
    archive = work / "archive"
    print(f"archive of {max(sizes)} flights ready in {time.perf_counter() - t:.0f} s", file=sys.stderr)
    rows = []
    for n in sizes:
        out = work / f"stack{n}.zarr"
        shutil.rmtree(out, ignore_errors=True)
        out.with_name(out.name + ".json").unlink(missing_ok=True)
        rows.append(run_stack(archive, n, out, args.gsd))
        print(json.dumps(rows[-1]), flush=True)
    print("\n| flights | stack (time, band, y, x) | wall | per flight | peak RSS (command + worker) |")
    print("|---|---|---|---|---|")
    for r in rows:
        s = r["shape"]
        print(f"| {r['flights']} | ({s['time']}, {s['band']}, {s['y']}, {s['x']}) | {r['seconds']:.1f} s "
              f"| {r['per_flight_s']:.2f} s | {r['peak_rss'] / 1e6:.0f} MB |")


if __name__ == "__main__":
    main()
