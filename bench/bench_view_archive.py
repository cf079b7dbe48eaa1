"""The archive part of ``bench/bench_view.py --browser --flights N`` (issue 22): an archive of N
simulated flights that tile the map (a few overlapping), opened in Debian's Chromium through
Playwright with no hash, so every flight is drawn at the zoom that fits them all; the time from page
load to a full screen on a new server and a warm one, and after a zoom out. Run through
bench_view.py (its options); kept apart to keep that module under 600 lines.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np

from bench_view import _ACTION_JS, DEFAULT_WORKDIR, FOV, Server, cpu_seconds, machine, percentile, render_counts

__all__ = ["archive_bench", "archive_main", "make_flights_archive", "memory_main"]

#: The archive bench's layout: flights on a grid this many degrees apart (lon, lat; ~100 x 90 m at
#: 35 N, each flight ~75 x 65 m at the simulator's 40 m altitude: they tile the map, 20 over ~0.5 x
#: 0.35 km), every ARCHIVE_PAIR-th one moved onto its western neighbour so that a few overlap.
ARCHIVE_STEP = (0.0011, 0.0008)
ARCHIVE_PAIR = 6


def make_flights_archive(workdir: Path, args: argparse.Namespace) -> tuple[Path, list[str]]:
    """An archive of ``args.flights`` simulated flights (``archive simulate`` --cubes/--bands/
    --samples/--lines, seeds 0..N-1, a day apart) on a 5-column grid ARCHIVE_STEP degrees apart near
    the simulator's site (``args.step``: another spacing), every ARCHIVE_PAIR-th overlapping its western neighbour, ingested at --fov
    47.5 (ingest makes each flight's overview previews); reused while its marker file exists (the raw
    flights are deleted; previews are added to a reused archive that lacks them). (archive, ids)."""
    archive = workdir / "archive"
    import shutil

    step = getattr(args, "step", None) or ARCHIVE_STEP
    marker = workdir / f".bench-view-flights-{step[0]}-{step[1]}-{args.flights}-{args.cubes}-{args.bands}-{args.samples}-{args.lines}"
    if not marker.exists():
        from datetime import datetime, timedelta, timezone

        from archive.ingest.command import ingest
        from archive.simulator.command import simulate_flight

        shutil.rmtree(workdir, ignore_errors=True)
        workdir.mkdir(parents=True)
        t0 = datetime(2024, 6, 1, 15, tzinfo=timezone.utc)
        for i in range(args.flights):
            col, row = i % 5, i // 5
            lon = -89.94 + step[0] * (col - (0.85 if i % ARCHIVE_PAIR == ARCHIVE_PAIR - 1 else 0))
            raw = workdir / f"flight{i:02d}"
            simulate_flight(raw, cubes=args.cubes, bands=args.bands, samples=args.samples, lines=args.lines, seed=i,
                            lat=35.12 + step[1] * row, lon=lon,
                            start=(t0 + timedelta(days=i)).strftime("%Y-%m-%dT%H:%M:%SZ"))
            ingest([raw], archive, FOV, progress=False)
            shutil.rmtree(raw)
        marker.touch()
    from archive.catalog.root import open_root
    from archive.ingest.previews import add_previews

    root = open_root(archive)
    if getattr(args, "no_previews", False):   # the baseline: every tile from the DN
        from archive.drawing.preview_layout import GROUP

        for cid in root.collection_ids():
            shutil.rmtree(root.store(cid) / GROUP, ignore_errors=True)
    else:
        add_previews(root, root.collection_ids())   # an archive made before ingest made previews gets them (issue 36)
    items = [json.loads(p.read_text()) for p in (archive / "catalog" / "items").glob("*.json")]
    return archive, sorted(item["id"] for item in items)


def archive_bench(archive: Path, reps: int, cold: int, cache_mb: int, width: int = 1400, height: int = 900,
                  code: Path | None = None) -> dict:
    """Time from page load (navigation start) to a full screen (``viewer.settledAt``) of the page
    opened with no hash (every flight drawn at the zoom that fits them all), then to one after a
    zoom out: ``cold`` times on a new server each, then ``reps`` new pages on one warm server (its
    first page not counted) and ``reps`` zooms out and in there. Seconds, the server's CPU-seconds,
    and the last page's band-value requests (empty ones, flights with values)."""
    from playwright.sync_api import sync_playwright

    out: dict = {k: [] for k in ("cold", "warm", "zoom_cold", "zoom")}
    cpu: dict = {k: [] for k in out}

    def timed(key, server, fn):
        c = cpu_seconds(server.proc.pid)
        out[key].append(fn())
        cpu[key].append(cpu_seconds(server.proc.pid) - c)

    def load(browser, server, key):
        page = browser.new_page(viewport={"width": width, "height": height})
        answers = []   # (flight id, status) of every band-value tile answered, batched or not

        def answered(r):
            if "/values/batch" in r.url:
                from urllib.parse import parse_qs, urlsplit

                parts = parse_qs(urlsplit(r.url).query).get("parts", [""])[0].split(";")
                index = json.loads(r.headers.get("x-parts") or "[]")
                answers.extend((p.split("/")[0], i[0]) for p, i in zip(parts, index, strict=False))
                batches.append(len(parts))
            elif "/values/" in r.url:
                answers.append((r.url.split("/")[-5], r.status))
        batches = []
        page.on("response", answered)

        def go():
            page.goto(f"http://127.0.0.1:{server.port}/")
            # viewer.booted: the first view is set (older pages: the fit's zoom reached)
            page.wait_for_function("() => viewer.settled && viewer.draws > 0 && (viewer.booted === undefined ? "
                                   "viewer.map.getZoom() > 5 : viewer.booted)", timeout=180_000)
            return page.evaluate("viewer.settledAt") / 1000.0
        timed(key, server, go)
        out.update(zoom_level=page.evaluate("viewer.map.getZoom()"), requests=len(answers), batches=len(batches),
                   empty=sum(s == 204 for _, s in answers), with_values=len({i for i, s in answers if s == 200}))
        return page

    def zoom(page, server, key, k):
        def go():
            page.evaluate("() => { viewer.settled = false; }")
            t0 = page.evaluate(f"(k) => {{ const t = performance.now(); ({_ACTION_JS['zoom']})(k); return t; }}", k)
            page.wait_for_function("() => viewer.settled", timeout=120_000)
            return (page.evaluate("viewer.settledAt") - t0) / 1000.0
        timed(key, server, go)

    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path="/usr/bin/chromium",
                                     args=["--headless", "--no-sandbox", "--disable-gpu"])
        try:
            for i in range(cold + 1):
                server = Server(archive, cache_mb, code)
                try:
                    page = load(browser, server, "cold" if i < cold else "warm")
                    if i < cold:
                        out["render_cold"] = render_counts(server.port)   # what the new server's first screen drew
                        zoom(page, server, "zoom_cold", 1)   # odd: out
                        page.close()
                        continue
                    out["warm"].clear(), cpu["warm"].clear()
                    for _ in range(reps):
                        page.close()
                        page = load(browser, server, "warm")
                    for k in range(reps):
                        zoom(page, server, "zoom", k + 1)
                    out["render"] = render_counts(server.port)
                finally:
                    server.stop()
        finally:
            browser.close()
    out["cpu"] = cpu
    return out


def archive_main(args: argparse.Namespace) -> str:
    """The archive measurement (``--browser --flights N``) as a Markdown section."""
    workdir = args.workdir if args.workdir != DEFAULT_WORKDIR else Path("/tmp/archive-bench-view-flights")
    archive, ids = make_flights_archive(workdir, args)
    load_before = os.getloadavg()
    out = archive_bench(archive, args.reps, args.cold, args.cache_mb, code=getattr(args, "code", None))
    load_after = os.getloadavg()
    m = machine()
    rows = [f"| {label} | {percentile(out[k], 50):.0f} | {percentile(out[k], 95):.0f} | {percentile(out[k], 100):.0f} | "
            f"{len(out[k])} | {np.median(out['cpu'][k]):.2f} |" for k, label in (
                ("cold", "open, new server (from navigation start)"), ("warm", "open, warm server (new page, from navigation start)"),
                ("zoom_cold", "zoom out after the new server's open (from the change)"),
                ("zoom", "zoom out / in, warm (from the change)"))]
    lines = [
        f"## Viewer in the browser, an archive of {len(ids)} flights (issue 22): each {args.cubes} cubes x "
        f"{args.lines} lines x {args.samples} samples x {args.bands} bands",
        "",
        f"Command: `.venv/bin/python bench/bench_view.py {' '.join(sys.argv[1:])}` (Debian's Chromium, headless, "
        "through Playwright; 1400 x 900 window; `archive view` in a subprocess). The page opened with no hash: every "
        f"flight drawn, at the zoom that fits them all (zoom {out['zoom_level']}); time to a full screen "
        "(`viewer.settledAt`: every tile in view drawn).",
        f"Machine: {m['cpu']}, {m['cores']} cores; GL: {m['gl']}; load average before {load_before[0]:.2f} "
        f"{load_before[1]:.2f} {load_before[2]:.2f}, after {load_after[0]:.2f} {load_after[1]:.2f} {load_after[2]:.2f} "
        "(the VM is shared with other engineers' jobs).",
        "",
        "| measure | p50 ms | p95 ms | max ms | n | server CPU s (median) |",
        "|---|---|---|---|---|---|",
        *rows,
        "",
        f"A page load: {out['requests']} band-value tiles ({out['empty']} empty; {out.get('batches', 0)} requests of "
        f"several flights' tiles), values from {out['with_values']} "
        f"of the {len(ids)} flights; the warm server's render jobs: {out['render']['done']} drawn, "
        f"{out['render']['skipped'] + out['render']['stopped']} dropped; band-value tiles answered from the ingest "
        f"previews: {out['render']['from_previews']} (overview previews {'taken out (--no-previews)' if args.no_previews else 'in the archive'}); "
        f"a new server's first screen: {out['render_cold']['done']} tiles drawn from the DN, "
        f"{out['render_cold']['from_previews']} answered from the previews.",
        "",
    ]
    if args.json:
        args.json.write_text(json.dumps({"load_before": load_before, "load_after": load_after, "machine": m, **out},
                                        indent=1, default=str))
    return "\n".join(lines)


def memory_bench(archive: Path, ids: list[str], cache_mb: int) -> list[dict]:
    """The server's resident memory while it draws from the DN (issue 36): ``archive view --cache-mb``
    in a subprocess; the tiles over 40 flights at zooms 15-17 and 20 flights at 18-19, each at the
    recorded ground height and another (two geometries), ``cubes=0-LAST`` so that the previews do not
    answer; after each zoom: VmRSS, its peak so far, and each cache's bytes and limit
    (``/api/status``)."""
    import http.client

    from bench_view import tiles_over

    server = Server(archive, cache_mb)
    rows = []
    try:
        conn = http.client.HTTPConnection("127.0.0.1", server.port, timeout=120)

        def get(path):
            conn.request("GET", path)
            r = conn.getresponse()
            return r.status, r.read()
        features = json.loads(get("/api/collections")[1])["features"]
        rows.append({"step": "idle", "requests": 0, "rss": server.rss(), "peak": server.peak, "caches": {}})
        n = 0
        for z in (15, 16, 17, 18, 19):
            for f in features[:40 if z < 18 else 20]:
                last = f["properties"]["cubes"] - 1
                for _, x, y in tiles_over(f["bbox"], z):
                    for extra in ("", f"&ground_height={z * 3}"):
                        get(f"/api/collections/{f['id']}/values/{z}/{x}/{y}?bands=0,3,6&cubes=0-{last}{extra}&window=1")
                        n += 1
            caches = json.loads(get("/api/status")[1])["caches"]
            rows.append({"step": f"zoom {z}", "requests": n, "rss": server.rss(), "peak": server.peak,
                         "caches": {k: (v["bytes"], v["limit"]) for k, v in caches.items()}})
    finally:
        server.stop()
    return rows


def memory_main(args: argparse.Namespace) -> str:
    """``--memory --flights N [--cache-mb M]``: :func:`memory_bench` as a Markdown section."""
    workdir = args.workdir if args.workdir != DEFAULT_WORKDIR else Path("/tmp/archive-bench-view-flights")
    archive, ids = make_flights_archive(workdir, args)
    load = os.getloadavg()
    rows = memory_bench(archive, ids, args.cache_mb)
    mb = 1 << 20
    lines = [f"`archive view --cache-mb {args.cache_mb}` on the {len(ids)}-flight archive (load average before "
             f"{load[0]:.2f} {load[1]:.2f} {load[2]:.2f}, after {os.getloadavg()[0]:.2f}):", "",
             "| step | requests | RSS MiB | peak MiB | cached MiB (tiles, bands, lookups, flights) | cached / limit MiB |",
             "|---|---|---|---|---|---|"]
    for r in rows:
        held = sum(b for b, _ in r["caches"].values())
        limit = sum(lim for _, lim in r["caches"].values())
        parts = ", ".join(f"{b / mb:.1f}" for b, _ in r["caches"].values())
        lines.append(f"| {r['step']} | {r['requests']} | {r['rss'] / mb:.0f} | {r['peak'] / mb:.0f} | {parts or '-'} | "
                     f"{held / mb:.0f} / {limit / mb:.0f} |")
    return "\n".join(lines) + "\n"
