"""Batch jobs against the number of flights (issue 19): per-flight overhead, submission time, peak
tasks in the scheduler, peak client and scheduler RSS.

Builds an archive of N small flights with ``archive simulate --seed K`` (each seed its own start,
hence its own id) and ``archive ingest``, starts a scheduler and one worker (``dask scheduler``,
``dask worker --nthreads 2 --resources GPU=2``, separate processes), and renders the archive as
one batch (``archive render --archive A --query-bbox ... --out DIR --format zarr --scheduler``) in a
child process per N. Per-flight overhead = (batch wall time - N x one flight rendered alone on
the same cluster, the median of 5 after a warm-up) / N. Peak tasks: a scheduler plugin; RSS: the child's ru_maxrss (client) and the
scheduler process's peak, sampled every 50 ms.

    .venv/bin/python bench/bench_batch.py --flights 10,50,100
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

SHAPE = dict(cubes=2, bands=16, samples=128, lines=250, cubes_per_pass=2)


def build_archive(work: Path, n: int) -> Path:
    from archive.ingest.command import ingest
    from archive.simulator.command import simulate_flight

    archive = work / "archive"
    have = len(list((archive / "collections").glob("*.zarr"))) if archive.is_dir() else 0
    for seed in range(have, n):
        d = work / "raw" / f"flight{seed:03d}"
        simulate_flight(d, seed=seed, overwrite=True, **SHAPE)
        ingest([str(d)], archive, 47.5, progress=False)
        shutil.rmtree(d)
    return archive


def child(args) -> None:
    """One batch of the first ``args.n`` flights on ``args.scheduler``; prints a JSON line."""
    import resource

    import archive as api
    from distributed import Client
    from distributed.diagnostics.plugin import SchedulerPlugin

    class Peak(SchedulerPlugin):
        name = "bench-peak-tasks"

        def __init__(self):
            self.peak = 0

        async def start(self, scheduler):
            self.scheduler = scheduler

        def transition(self, key, start, finish, *a, **kw):
            self.peak = max(self.peak, len(self.scheduler.tasks))

    ids = api.open_archive(args.archive).search()[: args.n]
    with Client(args.scheduler) as client:
        client.register_plugin(Peak())
        ones = []
        for k in range(6):   # the first warms the worker up (imports, GL context): the median of the others
            one = api.georectify(ids[:1], Path(args.out) / f"one{k}.zarr", archive=args.archive, gsd=args.gsd,
                                 scheduler=args.scheduler)
            ones.append(one["graph_seconds"]) if k else None
        t = time.perf_counter()
        s = api.georectify(ids, Path(args.out) / "batch", archive=args.archive, gsd=args.gsd, per_flight=True,
                           scheduler=args.scheduler)
        wall = time.perf_counter() - t
        peak = client.run_on_scheduler(lambda dask_scheduler: dask_scheduler.plugins["bench-peak-tasks"].peak)
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    print(json.dumps({"n": args.n, "wall": wall, "one_flight": statistics.median(ones), "submit": s["submit_seconds"],
                      "done": s["done"], "failed": s["failed"], "wave": s["wave"], "peak_tasks": peak,
                      "client_rss": rss}))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--flights", default="10,50,100")
    ap.add_argument("--gsd", type=float, default=0.1)
    ap.add_argument("--workdir", default="/tmp/bench_batch")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--n", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--archive", help=argparse.SUPPRESS)
    ap.add_argument("--scheduler", help=argparse.SUPPRESS)
    ap.add_argument("--out", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        return child(args)
    import psutil

    print(f"load average at start {os.getloadavg()[0]:.2f} (2-core VM shared with other jobs)", flush=True)
    work = Path(args.workdir)
    counts = [int(v) for v in args.flights.split(",")]
    t = time.perf_counter()
    archive = build_archive(work, max(counts))
    print(f"archive of {max(counts)} flights {SHAPE} in {time.perf_counter() - t:.0f} s", flush=True)
    bin_dir = Path(sys.executable).parent
    port = 8786 + os.getpid() % 500
    address = f"tcp://127.0.0.1:{port}"
    rows = []
    for n in counts:
        sched = subprocess.Popen([str(bin_dir / "dask"), "scheduler", "--host", "127.0.0.1", "--port", str(port),
                                  "--dashboard-address", ":0"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        worker = subprocess.Popen([str(bin_dir / "dask"), "worker", address, "--nthreads", "2", "--nworkers", "1",
                                   "--resources", "GPU=2", "--memory-limit", "4GB"],
                                  stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        peak = {"rss": 0}
        stop = threading.Event()

        def sample():
            p = psutil.Process(sched.pid)
            while not stop.is_set():
                try:
                    peak["rss"] = max(peak["rss"], p.memory_info().rss)
                except psutil.Error:
                    return
                time.sleep(0.05)

        sampler = threading.Thread(target=sample, daemon=True)
        sampler.start()
        try:
            time.sleep(4)
            out = work / f"out{n}"
            shutil.rmtree(out, ignore_errors=True)
            done = subprocess.run([sys.executable, __file__, "--child", "--n", str(n), "--archive", str(archive),
                                   "--scheduler", address, "--out", str(out), "--gsd", str(args.gsd)],
                                  capture_output=True, text=True, timeout=3600)
            if done.returncode:
                raise SystemExit(done.stderr[-3000:])
            row = json.loads(done.stdout.strip().splitlines()[-1])
        finally:
            stop.set()
            worker.terminate()
            sched.terminate()
            worker.wait(30)
            sched.wait(30)
        row["scheduler_rss"] = peak["rss"]
        row["load"] = os.getloadavg()[0]   # the VM is shared: say how loaded it was
        row["overhead"] = (row["wall"] - n * row["one_flight"]) / n
        rows.append(row)
        print(json.dumps(row), flush=True)
    print(f"\nload average {os.getloadavg()[0]:.2f}; flights {SHAPE}, gsd {args.gsd} m")
    print("| flights | batch wall | one flight alone | overhead per flight | submission (all) | wave | peak tasks "
          "| client RSS | scheduler RSS | load after |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['n']} | {r['wall']:.1f} s | {r['one_flight']:.2f} s | {r['overhead']:.3f} s | {r['submit']:.1f} s "
              f"| {r['wave']} | {r['peak_tasks']} | {r['client_rss'] / 1e6:.0f} MB | {r['scheduler_rss'] / 1e6:.0f} MB "
              f"| {r['load']:.1f} |")


if __name__ == "__main__":
    main()
