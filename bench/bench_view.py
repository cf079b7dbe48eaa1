"""Load bench of ``archive view`` (issue 13): tile latency on loopback, cold and warm, first tile of a
newly opened flight, and the server's memory.

    python bench/bench_view.py [--clients 8] [--requests 200] [--restarts 3] [--cache-mb 512]
                               [--cubes 4 --bands 8 --samples 128 --lines 250] [--workdir DIR]
                               [--json FILE] [--results bench/RESULTS.md]

    python bench/bench_view.py --browser [--reps 12] [--cubes 8 --bands 60 --samples 900 --lines 1000]
    python bench/bench_view.py --browser --flights 20 [--cold 3] [--reps 12] [--cubes 4 --bands 24 --samples 200 --lines 600]

``--browser --flights 20`` opens an archive of 20 flights of --cubes x --lines x --samples x --bands
(tiling the map, a few overlapping; in /tmp/archive-bench-view-flights unless --workdir) with every
flight drawn, at the zoom that fits them all: time to a full screen from page load on a new server
(--cold times) and on a warm one (--reps), and after a zoom out (bench_view_archive.py; issue 22).

``--browser`` measures the page instead (issue 22): Debian's Chromium through Playwright opens the
flight and times, --reps times each, the way to a full screen after open, pan, zoom, band, mode,
ground-height and stretch changes (p50/p95) with the server's CPU-seconds per change (comparable
when the machine is loaded and wall times are not), and the ground slider's preview rate; the load
average is printed.

Bounded: it makes clients x requests tile requests twice and stops by itself. Steps:

1. simulate a flight (``archive simulate`` defaults: the demo's) and ingest it into an archive in
   --workdir (reused while its marker file exists);
2. first tile, --restarts times: start ``archive view --archive A --port 0`` (a subprocess), wait
   for its URL, ask the catalog (what the page does first) then the tile at the centre of the
   flight at zoom 20 with the default parameters (RGB, radiance, flight 2 %/98 % stretch): its
   latency includes opening the flight, its meshes, the GL context and the flight's percentiles;
3. cold: --clients threads, each with one keep-alive HTTP/1.1 connection, make --requests 3-band
   tile requests over the flight at zooms 18-22, every URL distinct (a fixed stretch that differs
   per request), so that each one is rendered (flight, meshes, bands warm; lookups of a tile
   shared by later requests of the same tile, as when a user changes bands or stretch);
4. warm: the same requests again (tile cache hits).

The server's resident memory (VmRSS) is sampled every 0.1 s; its /api/status gives the render and
cache counters. Prints a Markdown table; --results appends it, with the machine and command, to a
RESULTS.md.
"""

from __future__ import annotations

import argparse
import http.client
import json
import math
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_render as br  # noqa: E402  (machine)

ROOT = Path(__file__).resolve().parents[1]
FOV = 47.5
HALF_WORLD = math.pi * 6378137.0
DEFAULT_WORKDIR = Path("/tmp/archive-bench-view")


def machine() -> dict:
    gl = subprocess.run([sys.executable, "-c", "from archive.render.context import gl_info; i = gl_info(); "
                         "print(i['renderer'], '|', i['version'])"], capture_output=True, text=True, cwd=ROOT)
    return {**br.machine(), "gl": gl.stdout.strip() or gl.stderr.strip()[-200:], "load": os.getloadavg()}


def rss(pid: int) -> int:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process (all its threads), s (Linux /proc)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return float("nan")


class Server:
    """``archive view`` in a subprocess, with its peak resident memory sampled."""

    def __init__(self, archive: Path, cache_mb: int, code: Path | None = None):
        env = dict(os.environ, PYTHONUNBUFFERED="1")   # code: another checkout's archive view (its page too)
        self.proc = subprocess.Popen([sys.executable, "-m", "archive", "view", "--archive", str(archive), "--port", "0",
                                      "--cache-mb", str(cache_mb)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                     text=True, cwd=code or ROOT, env=env)
        line = self.proc.stdout.readline()
        found = re.search(r"http://127\.0\.0\.1:(\d+)/", line)
        if not found:
            self.proc.kill()
            raise SystemExit(f"archive view did not start: {line}{self.proc.stderr.read()}")
        self.port = int(found.group(1))
        self.peak = 0
        self._stop = threading.Event()
        self._sampler = threading.Thread(target=self._sample, daemon=True)
        self._sampler.start()

    def _sample(self):
        while not self._stop.is_set():
            self.peak = max(self.peak, rss(self.proc.pid))
            time.sleep(0.1)

    def rss(self) -> int:
        return rss(self.proc.pid)

    def stop(self):
        self._stop.set()
        self.proc.send_signal(signal.SIGINT)
        try:
            self.proc.wait(20)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()


def get(conn: http.client.HTTPConnection, path: str) -> tuple[int, bytes, float]:
    t = time.perf_counter()
    conn.request("GET", path, headers={"Host": "127.0.0.1"})
    response = conn.getresponse()
    body = response.read()
    return response.status, body, time.perf_counter() - t


def render_counts(port: int) -> dict:
    """The server's render-thread counters (``/api/status``'s ``render``: drawn, dropped, overtaken...)."""
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=60)
    try:
        status = json.loads(get(conn, "/api/status")[1])
        return {**status["render"], "from_previews": status.get("from_previews", 0)}
    finally:
        conn.close()


def tiles_over(bbox, z: int, pad: int = 0) -> list[tuple[int, int, int]]:
    x0 = HALF_WORLD * math.radians(bbox[0]) / math.pi
    x1 = HALF_WORLD * math.radians(bbox[2]) / math.pi

    def merc_y(lat):
        return 6378137.0 * math.log(math.tan(math.pi / 4 + math.radians(lat) / 2))

    y0, y1 = merc_y(bbox[1]), merc_y(bbox[3])
    side = 2 * HALF_WORLD / 2**z
    cols = range(int((x0 + HALF_WORLD) // side) - pad, int((x1 + HALF_WORLD) // side) + 1 + pad)
    rows = range(int((HALF_WORLD - y1) // side) - pad, int((HALF_WORLD - y0) // side) + 1 + pad)
    return [(z, x, y) for x in cols for y in rows]


def make_archive(workdir: Path, args) -> tuple[Path, str, dict]:
    archive = workdir / "archive"
    marker = workdir / f".bench-view-{args.cubes}-{args.bands}-{args.samples}-{args.lines}"
    if not marker.exists():
        import shutil

        from archive.ingest.command import ingest
        from archive.simulator.command import simulate_flight

        shutil.rmtree(workdir, ignore_errors=True)
        workdir.mkdir(parents=True)
        simulate_flight(workdir / "flight", cubes=args.cubes, bands=args.bands, samples=args.samples, lines=args.lines)
        ingest([workdir / "flight"], archive, FOV, progress=False)
        marker.touch()
    (item,) = [json.loads(p.read_text()) for p in (archive / "catalog" / "items").glob("*.json")]
    return archive, item["id"], item


def percentile(values, q) -> float:
    return float(np.percentile(np.asarray(values) * 1000.0, q)) if values else float("nan")


def run_clients(port: int, plans: list[list[str]]) -> tuple[list[float], int]:
    """Each plan on its own thread and connection; (latencies s, non-200 count)."""
    latencies: list[list[float]] = [[] for _ in plans]
    failures = [0] * len(plans)

    def client(i):
        conn = http.client.HTTPConnection("127.0.0.1", port, timeout=60)
        for path in plans[i]:
            status, body, dt = get(conn, path)
            latencies[i].append(dt)
            if status != 200 or not body.startswith(b"\x89PNG"):
                failures[i] += 1
        conn.close()

    threads = [threading.Thread(target=client, args=(i,)) for i in range(len(plans))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return [x for lat in latencies for x in lat], sum(failures)


# ---- browser level (issue 22) ---------------------------------------------------------------
ACTIONS = ("open", "pan", "zoom", "band", "mode", "ground", "sync", "cubes", "stretch")
#: JavaScript of each measured change (argument: the repetition); each returns nothing and the page
#: reports when every tile in view shows the change (window.viewer.settledAt).
_ACTION_JS = {
    "pan": "(i) => { const m = viewer.map, s = m.getSize(); m.panBy([(i % 2 ? -1 : 1) * s.x * 0.45, (i % 3 - 1) * s.y * 0.3], {animate: false}); }",
    "zoom": "(i) => { const m = viewer.map; m.setZoom(m.getZoom() + (i % 2 ? -1 : 1), {animate: false}); }",
    "band": "(i) => { const s = document.getElementById('band-r'); s.selectedIndex = (s.selectedIndex + 7 + i) % s.options.length; s.dispatchEvent(new Event('change')); }",
    "mode": "(i) => { const s = document.getElementById('mode'); s.selectedIndex = (s.selectedIndex + 1) % s.options.length; viewer.clearCache(); s.dispatchEvent(new Event('change')); }",
    "ground": "(i) => { const g = document.getElementById('ground'); g.value = String(Number(g.min) + 0.5 * ((i * 7) % 60 + 10)); g.dispatchEvent(new Event('input')); g.dispatchEvent(new Event('change')); }",
    "sync": "(i) => { const g = document.getElementById('sync'); g.value = String(Number(g.min) + 0.005 * ((i * 7) % 90 + 5)); g.dispatchEvent(new Event('input')); g.dispatchEvent(new Event('change')); }",
    "cubes": "(i) => { const a = document.getElementById('cube-first'), b = document.getElementById('cube-last'); a.value = String(1 + i % 3); b.value = String(Number(b.max) - (i % 4)); b.dispatchEvent(new Event('change')); }",
    "stretch": "(i) => { const s = document.getElementById('stretch'); s.value = i % 2 ? 'flight' : 'view'; s.dispatchEvent(new Event('change')); }",
}


def browser_bench(archive: Path, cid: str, reps: int, cache_mb: int, width: int = 1400, height: int = 900) -> dict:
    """Time to a full screen (every tile in view drawn with the change) after each action, in
    Debian's Chromium through Playwright, ``reps`` times each; and the slider preview's frame rate."""
    from playwright.sync_api import sync_playwright

    server = Server(archive, cache_mb)
    url = f"http://127.0.0.1:{server.port}/#flights={cid}&open={cid}"
    out: dict = {a: [] for a in ACTIONS}
    cpu: dict = {a: [] for a in ACTIONS}   # the server's CPU-seconds per change
    try:
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path="/usr/bin/chromium",
                                         args=["--headless", "--no-sandbox", "--disable-gpu"])
            try:
                for i in range(reps):   # open: a fresh page each time (the server's caches stay warm after the first)
                    page = browser.new_page(viewport={"width": width, "height": height})
                    c = cpu_seconds(server.proc.pid)
                    t = time.perf_counter()
                    page.goto(url)
                    page.wait_for_function(f"() => viewer.open === '{cid}' && viewer.settled && viewer.draws > 0",
                                           timeout=120_000)
                    out["open"].append(time.perf_counter() - t)
                    cpu["open"].append(cpu_seconds(server.proc.pid) - c)
                    if i < reps - 1:
                        page.close()
                for action in ACTIONS[1:]:
                    for i in range(reps):
                        page.evaluate("() => { viewer.settled = false; }")
                        c = cpu_seconds(server.proc.pid)
                        t0 = page.evaluate(f"(i) => {{ const t = performance.now(); ({_ACTION_JS[action]})(i); return t; }}", i)
                        page.wait_for_function("() => viewer.settled", timeout=120_000)
                        out[action].append((page.evaluate("viewer.settledAt") - t0) / 1000.0)
                        cpu[action].append(cpu_seconds(server.proc.pid) - c)
                # slider preview: input events every 50 ms for 3 s (a drag), previews drawn per second
                before = page.evaluate("viewer.previews")
                c = cpu_seconds(server.proc.pid)
                for k in range(60):
                    page.evaluate("(k) => { const g = document.getElementById('ground'); g.value = String(Number(g.min) + 5 + 0.5 * (k % 40)); "
                                  "g.dispatchEvent(new Event('input')); }", k)
                    page.wait_for_timeout(50)
                drag_s = 3.0 + 0.0
                out["preview_fps"] = (page.evaluate("viewer.previews") - before) / drag_s
                out["preview_cpu_s"] = cpu_seconds(server.proc.pid) - c
                out["requests"] = page.evaluate("viewer.requests")
                out["render"] = render_counts(server.port)
            finally:
                browser.close()
    finally:
        server.stop()
    out["cpu"] = cpu
    return out


def server_steps(archive: Path, cid: str) -> list[tuple[str, float, float]]:
    """What each change costs the server, in this process (no HTTP, no browser): the render
    thread's calls for the tiles that cover the flight at the deepest zoom where it fits a 1400 x
    900 window (19 for the paper flight), with the server's default caches, one change after the
    other. [(step, wall s, CPU s of the process, worker threads included)]."""
    from archive.drawing.query import parse_query
    from archive.view.registry import FlightRegistry
    from archive.grid import TILE, tile_grid, zoom_gsd

    registry = FlightRegistry(archive)
    flight = registry.flight(cid)
    info = flight.describe()
    west, south, east, north = info["bounds_3857"]
    gsd = float(registry.feature(cid)["properties"]["gsd"])
    fit = max(z for z in range(10, 26) if (east - west) / (TILE * zoom_gsd(z)) <= 1400 / TILE
              and (north - south) / (TILE * zoom_gsd(z)) <= 900 / TILE)

    def tiles(z):
        side = TILE * zoom_gsd(z)
        xs = range(int((west + HALF_WORLD) // side), int((east + HALF_WORLD) // side) + 1)
        ys = range(int((HALF_WORLD - north) // side), int((HALF_WORLD - south) // side) + 1)
        return [(z, x, y) for x in xs for y in ys]

    def draw(z, **params):
        query = parse_query({"mode": "radiance", "overlap": "last", **{k: str(v) for k, v in params.items()}})
        for t in tiles(z):
            flight.band_values(tile_grid(*t), query, gsd)

    bands = info["default_bands"]
    rgb = ",".join(map(str, bands))
    new = (bands[0] + 7) % info["bands"]
    ground = info["ground_height"]
    steps = [
        ("whole-flight 2/98 % at open (3 bands)", lambda: flight.flight_percentiles(bands, "radiance", range(len(info["cubes"])), (2, 98))),
        (f"the {len(tiles(fit))} tiles at open (zoom {fit})", lambda: draw(fit, bands=rgb)),
        ("2/98 % of a new band", lambda: flight.flight_percentiles([new], "radiance", range(len(info["cubes"])), (2, 98))),
        ("the tiles of a new band", lambda: draw(fit, bands=new)),
        ("the tiles after a ground change (the first after a band change)", lambda: draw(fit, bands=rgb, ground_height=ground + 3)),
        ("the tiles after another ground change", lambda: draw(fit, bands=rgb, ground_height=ground + 3.5)),
        ("a slider preview (the tiles two zooms up, new meshes)", lambda: draw(fit - 2, bands=rgb, ground_height=ground + 4)),
        ("a mode change (statistics and tiles of 3 new bands)", lambda: (
            flight.flight_percentiles(bands, "relative", range(len(info["cubes"])), (2, 98)),
            draw(fit, bands=rgb, mode="relative"))),
    ]
    out = []
    for name, step in steps:
        c, t = time.process_time(), time.perf_counter()
        step()
        out.append((name, time.perf_counter() - t, time.process_time() - c))
    getattr(registry, "close", lambda: None)()   # (older checkouts have no close)
    return out


def browser_main(args, archive: Path, cid: str) -> str:
    load_before = os.getloadavg()
    out = browser_bench(archive, cid, args.reps, args.cache_mb)
    load_after = os.getloadavg()
    m = machine()
    rows = []
    for a in ACTIONS:
        v = out[a]
        c = out["cpu"][a]
        rows.append(f"| {a} | {percentile(v, 50):.0f} | {percentile(v, 95):.0f} | {percentile(v, 100):.0f} | {len(v)} | "
                    f"{np.median(c):.2f} | {np.max(c):.2f} |")
    lines = [
        f"## Viewer in the browser (issue 22): {args.cubes} cubes x {args.lines} lines x {args.samples} samples x {args.bands} bands",
        "",
        f"Command: `.venv/bin/python bench/bench_view.py --browser {' '.join(a for a in sys.argv[1:] if a != '--browser')}` "
        "(Debian's Chromium, headless, through Playwright; 1400 x 900 window; `archive view` in a subprocess). "
        "Time from the change to a full screen: every tile in view drawn with it (the page's `viewer.settledAt`). "
        "open: a fresh page loading `#flights=ID&open=ID` (the first one cold, then the server's caches are warm); "
        "pan: 45 % of the width; zoom: +-1 level; band: R to another of the bands (new values); mode: the next "
        "mode with the page's value cache emptied; ground: a new height each time (new meshes); sync: a new offset each time (new poses and "
        "meshes); cubes: another cube range (new statistics); stretch: flight <-> view percentiles (no request).",
        f"Machine: {m['cpu']}, {m['cores']} cores; GL: {m['gl']}; load average before {load_before[0]:.2f} "
        f"{load_before[1]:.2f} {load_before[2]:.2f}, after {load_after[0]:.2f} {load_after[1]:.2f} {load_after[2]:.2f} "
        "(the VM is shared with other engineers' jobs).",
        "",
        "| change | p50 ms | p95 ms | max ms | n | server CPU s (median) | server CPU s (max) |",
        "|---|---|---|---|---|---|---|",
        *rows,
        "",
        f"Ground slider dragged (input events every 50 ms for 3 s): {out['preview_fps']:.1f} coarse previews drawn per "
        f"second (the open flight at a quarter of the resolution; server CPU {out['preview_cpu_s']:.2f} s over the 3 s). "
        f"Band-value requests in all: {out['requests']}; the server's render jobs: {out['render']['done']} drawn, "
        f"{out['render']['skipped'] + out['render']['stopped']} dropped (their request abandoned), "
        f"{out['render'].get('overtaken', 0)} drawn after a newer view's (latest view first).",
        "",
    ]
    if args.json:
        record = {"load_before": load_before, "load_after": load_after, "machine": m, **out}
        args.json.write_text(json.dumps(record, indent=1, default=str))
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--clients", type=int, default=8)
    ap.add_argument("--requests", type=int, default=200, help="tile requests per client and phase")
    ap.add_argument("--restarts", type=int, default=3, help="server starts measured for the first tile")
    ap.add_argument("--cache-mb", type=int, default=512)
    ap.add_argument("--cubes", type=int, default=4)
    ap.add_argument("--bands", type=int, default=8)
    ap.add_argument("--samples", type=int, default=128)
    ap.add_argument("--lines", type=int, default=250)
    ap.add_argument("--workdir", type=Path, default=DEFAULT_WORKDIR)
    ap.add_argument("--json", type=Path)
    ap.add_argument("--results", type=Path, help="append the Markdown section to this file")
    ap.add_argument("--browser", action="store_true", help="measure the page in Chromium instead (issue 22)")
    ap.add_argument("--reps", type=int, default=12, help="--browser: repetitions of each change")
    ap.add_argument("--server-steps", action="store_true",
                    help="what each change costs the server, in this process (issue 22; PYTHONPATH=<another "
                         "checkout> measures that code)")
    ap.add_argument("--flights", type=int, default=0,
                    help="--browser: an archive of this many flights (each --cubes x --lines x --samples x --bands) "
                         "opened at the zoom that fits them all, instead of one flight's changes")
    ap.add_argument("--cold", type=int, default=3, help="--browser --flights: page loads on a new server each")
    ap.add_argument("--no-previews", action="store_true",
                    help="--browser --flights: take the ingest's overview previews out of the archive (in --workdir): "
                         "every tile drawn from the DN, the baseline they are measured against")
    ap.add_argument("--step", type=lambda t: tuple(float(v) for v in t.split(",")), metavar="LON,LAT",
                    help="--browser --flights: the flights' grid spacing, degrees (default 0.0011,0.0008: they tile "
                         "the map; 0.00025,0.00015: packed, overlapping, fitted at a zoom finer than their previews)")
    ap.add_argument("--code", type=Path, metavar="CHECKOUT",
                    help="--browser --flights: run another checkout's 'archive view' (server and page; e.g. an export "
                         "of an older commit), the archive made by this one")
    ap.add_argument("--memory", action="store_true",
                    help="with --flights: the server's resident memory and cache accounting while it draws many "
                         "tiles from the DN at --cache-mb (issue 36)")
    args = ap.parse_args(argv)
    if args.memory:
        from bench_view_archive import memory_main

        print(memory_main(args))
        return 0
    if args.server_steps:
        archive, cid, _ = make_archive(args.workdir, args)
        load = os.getloadavg()
        rows = server_steps(archive, cid)
        print(f"load average before {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}, after "
              "{:.2f} {:.2f} {:.2f}".format(*os.getloadavg()))
        print("| step | wall s | CPU s |\n|---|---|---|")
        for name, wall, cpu_s in rows:
            print(f"| {name} | {wall:.3f} | {cpu_s:.3f} |")
        return 0
    if args.browser:
        if args.flights:
            from bench_view_archive import archive_main

            text = archive_main(args)
        else:
            archive, cid, _ = make_archive(args.workdir, args)
            text = browser_main(args, archive, cid)
        print(text)
        if args.results:
            with open(args.results, "a") as f:
                f.write("\n" + text)
        return 0

    R: dict = {"machine": machine(), "args": {k: str(v) for k, v in vars(args).items()}}
    archive, cid, item = make_archive(args.workdir, args)
    bbox = item["bbox"]
    R["flight"] = {"id": cid, "cubes": args.cubes, "bands": args.bands, "samples": args.samples, "lines": args.lines,
                   "bbox": bbox}
    base = f"/api/collections/{cid}/tiles"

    # ---- first tile of a newly opened flight -------------------------------------------------
    lon, lat = (bbox[0] + bbox[2]) / 2, (bbox[1] + bbox[3]) / 2
    (centre,) = tiles_over([lon, lat, lon, lat], 20)
    firsts, starts = [], []
    for _ in range(max(args.restarts, 1)):
        t = time.perf_counter()
        server = Server(archive, args.cache_mb)
        starts.append(time.perf_counter() - t)
        conn = http.client.HTTPConnection("127.0.0.1", server.port, timeout=60)
        status, _, _ = get(conn, "/api/collections")
        assert status == 200
        status, body, dt = get(conn, f"{base}/{centre[0]}/{centre[1]}/{centre[2]}.png")
        assert status == 200 and body.startswith(b"\x89PNG"), body[:200]
        firsts.append(dt)
        conn.close()
        server.stop()
    R["first_tile_ms"] = [round(x * 1000, 1) for x in firsts]
    R["server_start_s"] = [round(x, 2) for x in starts]

    # ---- load: cold then warm ------------------------------------------------------------------
    tiles = [t for z in range(18, 23) for t in tiles_over(bbox, z)]
    server = Server(archive, args.cache_mb)
    rss_idle = server.rss()
    plans = []
    wavelengths = ["650,550,450", "800,650,550", "900,700,500"]
    for i in range(args.clients):
        plan = []
        for j in range(args.requests):
            k = i * args.requests + j
            z, x, y = tiles[(k * 7919) % len(tiles)]  # spread over zooms and tiles
            plan.append(f"{base}/{z}/{x}/{y}.png?wavelengths={wavelengths[k % 3]}&stretch=0,{1000 + k}")
        plans.append(plan)
    t = time.perf_counter()
    cold, cold_fail = run_clients(server.port, plans)
    cold_s = time.perf_counter() - t
    t = time.perf_counter()
    warm, warm_fail = run_clients(server.port, plans)
    warm_s = time.perf_counter() - t
    conn = http.client.HTTPConnection("127.0.0.1", server.port, timeout=60)
    status = json.loads(get(conn, "/api/status")[1])
    conn.close()
    rss_end = server.rss()
    server.stop()
    n = args.clients * args.requests
    R["tiles_in_rotation"] = len(tiles)
    R["cold"] = {"p50_ms": percentile(cold, 50), "p95_ms": percentile(cold, 95), "max_ms": percentile(cold, 100),
                 "req_per_s": n / cold_s, "failed": cold_fail}
    R["warm"] = {"p50_ms": percentile(warm, 50), "p95_ms": percentile(warm, 95), "max_ms": percentile(warm, 100),
                 "req_per_s": n / warm_s, "failed": warm_fail}
    R["server"] = {"rss_idle_mb": rss_idle / 1e6, "rss_end_mb": rss_end / 1e6, "rss_peak_mb": server.peak / 1e6,
                   "status": status}
    R["machine"]["load_after"] = os.getloadavg()

    m = R["machine"]
    caches = status["caches"]
    lines = [
        f"## Viewer load (issue 13): {args.cubes} cubes x {args.lines} lines x {args.samples} samples x {args.bands} bands",
        "",
        f"Command: `.venv/bin/python bench/bench_view.py {' '.join(sys.argv[1:] if argv is None else argv)}` (flight: `archive simulate` {args.cubes} cubes x {args.lines} lines x "
        f"{args.samples} samples x {args.bands} bands, ingested; `archive view` in a subprocess, clients on "
        "loopback, one keep-alive HTTP/1.1 connection per client thread).",
        f"Machine: {m['cpu']}, {m['cores']} cores, {m['ram_gb']} GB RAM; GL: {m['gl']}; load average "
        f"before {m['load'][0]:.2f}, after {m['load_after'][0]:.2f} (the VM is shared with other engineers' jobs).",
        "",
        "| measure | p50 ms | p95 ms | max ms | tiles/s |",
        "|---|---|---|---|---|",
        f"| cold: 3-band tile rendered ({n} requests, {args.clients} clients, all URLs distinct) | "
        f"{R['cold']['p50_ms']:.1f} | {R['cold']['p95_ms']:.1f} | {R['cold']['max_ms']:.1f} | {R['cold']['req_per_s']:.1f} |",
        f"| warm: the same requests again (tile cache) | {R['warm']['p50_ms']:.1f} | {R['warm']['p95_ms']:.1f} | "
        f"{R['warm']['max_ms']:.1f} | {R['warm']['req_per_s']:.1f} |",
        "",
        f"First tile of a newly opened flight (fresh server each time, zoom 20 centre tile, flight stretch): "
        f"{', '.join(f'{x:.0f}' for x in R['first_tile_ms'])} ms; server start to URL printed: "
        f"{', '.join(f'{x:.1f}' for x in R['server_start_s'])} s.",
        f"Server memory (VmRSS): {R['server']['rss_idle_mb']:.0f} MB idle, peak {R['server']['rss_peak_mb']:.0f} MB, "
        f"{R['server']['rss_end_mb']:.0f} MB at the end; caches at the end: tiles {caches['tiles']['entries']} "
        f"({caches['tiles']['bytes'] / 1e6:.1f} MB of {caches['tiles']['limit'] / 1e6:.0f}), bands "
        f"{caches['bands']['bytes'] / 1e6:.1f} MB, lookups {caches['lookups']['bytes'] / 1e6:.1f} MB of "
        f"{caches['lookups']['limit'] / 1e6:.0f} ({caches['lookups']['evictions']} evicted); renders "
        f"{status['render']['done']}, failed requests {cold_fail + warm_fail}.",
        "",
    ]
    text = "\n".join(lines)
    print(text)
    if args.json:
        args.json.write_text(json.dumps(R, indent=1, default=str))
    if args.results:
        with open(args.results, "a") as f:
            f.write("\n" + text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
