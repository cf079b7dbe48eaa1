"""archive watch: cube close -> listed with imagery, and whether the ingest keeps pace (issue 47).

A simulated flight is replayed into an empty folder at the camera's pace by tests/recorder.py (the
``.bil`` growing block by block, ``.times``/``.lcf`` with it, the header last) while ``archive watch``
follows the folder (inotify, the live map on loopback). For each cube: the time from the moment its
header was complete to the moment ``/api/live`` listed it AND a 256 x 256 band-value tile over its
centre answered with imagery (measured by this client, polling every 20 ms). Each cube's DN chunks are
encoded as it closes (the watcher's thread): their seconds a cube against the recorder's seconds a
cube; then, after ``--idle``, the flight's ingest (``archive ingest --prewritten`` in the watcher's
child process, moving those chunks in), and the backlog (the collection ready this long after the
last cube closed, less the idle wait). One run; prints the figures.

    .venv/bin/python bench/bench_watch.py                      # paper shape: 900 samples x 1000 lines x 300 bands, 249 Hz
    .venv/bin/python bench/bench_watch.py --cubes 6 --bands 30   # lighter cubes, same 900 samples
"""

from __future__ import annotations

import argparse
import json
import re
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))


def get(url: str):
    with urllib.request.urlopen(url, timeout=120) as r:
        return r.status, r.read()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cubes", type=int, default=8, help="cubes of the flight (default 8: the paper's flight)")
    ap.add_argument("--bands", type=int, default=300)
    ap.add_argument("--samples", type=int, default=900)
    ap.add_argument("--lines", type=int, default=1000)
    ap.add_argument("--idle", type=float, default=5.0)
    ap.add_argument("--zoom", type=int, default=20, help="zoom of the tile asked over each cube (20: ~31 m at 35 N)")
    ap.add_argument("--work", help="folder for the flight, the recorder folder and the archive (default: a temporary one)")
    args = ap.parse_args()

    import mercantile

    from archive.simulator.command import simulate_flight
    from recorder import replay

    work = Path(args.work or tempfile.mkdtemp(prefix="bench-watch-"))
    source = work / f"source-{args.cubes}x{args.lines}x{args.samples}x{args.bands}"
    if not (source / "calibration.icp").exists():
        t = time.perf_counter()
        simulate_flight(source, cubes=args.cubes, bands=args.bands, samples=args.samples, lines=args.lines,
                        overwrite=True)
        print(f"simulated {source.name} in {time.perf_counter() - t:.0f} s", flush=True)
    folder, archive = work / "recorder", work / "archive"
    for p in (folder, archive):
        subprocess.run(["rm", "-rf", str(p)], check=True)
    folder.mkdir()
    watcher = subprocess.Popen([sys.executable, "-m", "archive", "watch", str(folder), "--archive", str(archive),
                                "--fov", "47.5", "--idle", str(args.idle), "--port", "0", "--quiet"],
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=ROOT)
    lines: list[tuple[float, str]] = []

    def read():
        for line in watcher.stdout:
            lines.append((time.time(), line.rstrip()))
    threading.Thread(target=read, daemon=True).start()
    while not any("live map at" in text for _, text in lines):
        if watcher.poll() is not None:
            print("\n".join(t for _, t in lines))
            return 1
        time.sleep(0.05)
    url = re.search(r"http://\S+/", next(t for _, t in lines if "live map at" in t)).group(0)

    closed: list = []
    writer = threading.Thread(target=lambda: closed.extend(replay(source, folder)))
    t_start = time.time()
    writer.start()
    shown: dict[str, float] = {}
    while writer.is_alive() or len(shown) < args.cubes:
        for flight in json.loads(get(url + "api/live")[1])["flights"]:
            for cid in flight["cube_ids"]:
                if cid in shown:
                    continue
                fc = json.loads(get(url + "api/collections")[1])
                w, s, e, n = next(f for f in fc["features"] if f["id"] == cid)["bbox"]
                t = mercantile.tile((w + e) / 2, (s + n) / 2, args.zoom)
                status, _ = get(f"{url}api/collections/{cid}/values/{t.z}/{t.x}/{t.y}?bands=0&mode=raw")
                if status == 200:
                    shown[cid] = time.time()
        time.sleep(0.02)
    writer.join()
    replay_s = time.time() - t_start
    rss = [json.loads(get(url + "api/status")[1]).get("rss_bytes") or 0]
    latency = [shown[next(i for i in shown if i.startswith(c.base + "-"))] - c.closed for c in closed]
    while not any("ingested as" in t or "not ingested" in t for _, t in lines):
        time.sleep(0.2)
    done_at, done = next((at, t) for at, t in lines if "ingested as" in t or "not ingested" in t)
    rss.append(json.loads(get(url + "api/status")[1]).get("rss_bytes") or 0)
    watcher.terminate()
    watcher.wait(60)
    per_cube_record = args.lines / 249.0
    m = re.search(r"in ([\d.]+) s", done)
    ingest_s = float(m.group(1)) if m else float("nan")
    print(f"shape: {args.cubes} cubes x {args.lines} lines x {args.samples} samples x {args.bands} bands at 249 Hz "
          f"({per_cube_record:.2f} s a cube); replay {replay_s:.1f} s")
    print("cube close -> listed with imagery (s): " + ", ".join(f"{v:.2f}" for v in latency))
    print(f"  median {statistics.median(latency):.2f} s, worst {max(latency):.2f} s")
    cube_mb = args.lines * args.samples * args.bands * 2 / 1e6
    print(f"watcher resident memory: {rss[0] / 1e6:.0f} MB after the last cube, {rss[1] / 1e6:.0f} MB after the "
          f"ingest (cubes of {cube_mb:.0f} MB, {args.cubes * cube_mb:.0f} MB in all; the ingest is a child process)")
    print(f"ingest: {done}")
    ahead = re.search(r"(\d+) encoded as they closed, (\d+) moved in, ([\d.]+) s a cube", done)
    if ahead:   # each cube encoded as it closed (issue 47); the ingest then moves them in
        per = float(ahead.group(3))
        print(f"  encoded as they closed: {ahead.group(1)} cubes, {ahead.group(2)} moved in by the ingest; "
              f"{per:.2f} s a cube against {per_cube_record:.2f} s a cube recorded: ratio {per / per_cube_record:.2f}")
        print(f"  the ingest after --idle: {ingest_s:.1f} s")
    else:
        print(f"  {ingest_s:.1f} s for {args.cubes} cubes = {ingest_s / args.cubes:.2f} s a cube against "
              f"{per_cube_record:.2f} s a cube recorded: ratio {ingest_s / args.cubes / per_cube_record:.2f}")
    print(f"  collection ready {done_at - closed[-1].closed:.1f} s after the last cube closed "
          f"(idle {args.idle:g} s + ingest)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
