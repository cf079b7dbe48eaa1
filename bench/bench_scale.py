"""A batch over an archive of many flights, killed and resumed (issue 45 point 3).

Takes the archive that ``bench/bench_ingest.py many --flights N`` leaves in ``WORKDIR/many/archive``
(N tiny flights, 2 cubes x 100 lines x 64 samples x 4 bands, their clocks a minute apart) and runs
``archive render --archive A --query-bbox -180,-90,180,90 --out DIR --format zarr`` as a user runs it
(a process of its own, a local cluster of ``--workers``), SIGKILLs its whole process group once its
report says ``--kill-at`` flights are done, then runs the same command with ``--resume`` to the end.
Prints: flights done before the kill, the rerun's wall time, how many it skipped and rendered, the
per-flight wall time of both runs, the peak RSS of the command's process (sampled every 0.2 s), and
whether the final report is complete with every flight done.

    python bench/bench_ingest.py many --flights 1000 --workdir /tmp/scale
    python bench/bench_scale.py --workdir /tmp/scale [--kill-at 500] [--workers 2]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

PY = sys.executable


def _report(out: Path) -> dict | None:
    try:
        return json.loads((out / "report.json").read_text())
    except (OSError, ValueError):
        return None


def _run(cmd: list[str], out: Path, kill_at: int | None) -> dict:
    """Run ``cmd`` in its own session; SIGKILL the group once the report counts ``kill_at`` done.
    Returns wall seconds, exit code, peak RSS (MiB) of the command's process and the report."""
    import psutil

    t = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, start_new_session=True)
    peak, stop = [0], threading.Event()

    def sample() -> None:
        p = psutil.Process(proc.pid)
        while not stop.wait(0.2):
            try:
                peak[0] = max(peak[0], p.memory_info().rss)
            except psutil.Error:
                return

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    killed = False
    while proc.poll() is None:
        time.sleep(0.2)
        doc = _report(out) if kill_at is not None else None
        if doc is not None and doc.get("done", 0) >= kill_at:
            os.killpg(proc.pid, signal.SIGKILL)
            killed = True
            break
    code = proc.wait()
    stop.set()
    sampler.join(5)
    err = proc.stderr.read()
    return {"seconds": time.perf_counter() - t, "code": code, "killed": killed, "rss_mib": peak[0] / 2**20,
            "report": _report(out), "stderr": err[-2000:]}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--workdir", default="/tmp/archive-bench-ingest", help="bench_ingest.py many's --workdir")
    ap.add_argument("--kill-at", type=int, default=None, help="flights done when the first run is killed "
                    "(default: half the archive)")
    ap.add_argument("--workers", type=int, default=2, help="local cluster worker processes (default 2)")
    ap.add_argument("--gsd", default="0.1", help="metres (default 0.1)")
    args = ap.parse_args()
    archive = Path(args.workdir) / "many" / "archive"
    items = sorted((archive / "catalog" / "items").glob("*.json"))
    if not items:
        raise SystemExit(f"{archive}: no archive; run bench/bench_ingest.py many --workdir {args.workdir} first")
    n = len(items)
    kill_at = args.kill_at or n // 2
    out = Path(args.workdir) / "scale-batch"
    shutil.rmtree(out, ignore_errors=True)
    cmd = [PY, "-m", "archive", "render", "--archive", str(archive), "--query-bbox", "-180,-90,180,90", "--gsd",
           args.gsd, "--out", str(out), "--format", "zarr", "--workers", str(args.workers), "--quiet"]
    print(f"# {n} flights in {archive}; load {os.getloadavg()[0]:.2f}")
    first = _run(cmd, out, kill_at)
    if not first["killed"]:
        raise SystemExit(f"the first run ended (exit {first['code']}) before {kill_at} flights were done: "
                         f"{first['stderr']}")
    before = first["report"] or {}
    second = _run([*cmd, "--resume"], out, None)
    after = second["report"] or {}
    left = n - before.get("done", 0)
    print("| run | wall s | flights done by it | per flight s | peak RSS MiB | exit | load after |")
    print("|---|---|---|---|---|---|---|")
    print(f"| first, SIGKILLed at {kill_at} done | {first['seconds']:.1f} | {before.get('done', 0)} | "
          f"{first['seconds'] / max(before.get('done', 1), 1):.3f} | {first['rss_mib']:.0f} | killed | "
          f"{os.getloadavg()[0]:.2f} |")
    print(f"| --resume | {second['seconds']:.1f} | {after.get('done', 0)} "
          f"({after.get('skipped', 0)} skipped) | {second['seconds'] / max(left, 1):.3f} | {second['rss_mib']:.0f} | "
          f"{second['code']} | {os.getloadavg()[0]:.2f} |")
    whole = after.get("complete") and after.get("failed", 1) == 0 and after.get("done", 0) + after.get("skipped", 0) == n \
        and after.get("skipped", 0) >= before.get("done", 0)
    print(f"final report: complete={after.get('complete')}, done={after.get('done')}, skipped={after.get('skipped')}, "
          f"failed={after.get('failed')}, pending={after.get('pending')}: {'every flight once' if whole else 'NOT WHOLE'}")
    if second["code"] != 0:
        print(second["stderr"])
    return 0 if whole else 1


if __name__ == "__main__":
    sys.exit(main())
