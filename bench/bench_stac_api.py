"""STAC API latency over a large synthetic catalog (issue 21).

Writes N synthetic Items (default 100,000; footprints scattered over the USA, 10 years of flights,
50..300-band ranges between 380 and 1200 nm; ``--bands`` eo:bands entries each, which sets the Item
size) into a fresh archive, indexes them, starts ``archive view`` on loopback in its own process
and times ``/stac/search`` over one keep-alive connection: p50/p95 per query (bbox, datetime,
wavelength filter, combined; GET and POST) and paging through 10,000 results by ``next`` links.

    python bench/bench_stac_api.py [--items 100000] [--bands 60] [--repeat 40] [--results bench/RESULTS.md]
"""

from __future__ import annotations

import argparse
import http.client
import json
import os
import shlex
import statistics
import subprocess
import sys
import tempfile
import time
from datetime import UTC, datetime, timedelta
from pathlib import Path
from urllib.parse import urlencode, urlsplit

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_render import load, machine  # noqa: E402


def build(root_dir: Path, items: int, bands: int) -> tuple[float, float, int]:
    """Write the Items and the index; returns (seconds writing Items, seconds indexing, mean Item bytes)."""
    from archive.catalog.index import add_rows, row_from_item
    from archive.catalog.root import create_archive
    from archive.catalog.stac import make_item, write_item
    from archive.catalog.tree import COLLECTION_ID, item_links

    rng = np.random.default_rng(0)
    root = create_archive(root_dir)
    t0 = datetime(2015, 1, 1, tzinfo=UTC)
    rows, size = [], 0
    t = time.perf_counter()
    for k in range(items):
        cid = f"sim-{k:06d}"
        lon, lat = rng.uniform(-120, -70), rng.uniform(25, 50)
        w, h = rng.uniform(0.001, 0.02, 2)
        ring = [[lon, lat], [lon + w, lat], [lon + w, lat + h], [lon, lat + h], [lon, lat]]
        start = t0 + timedelta(seconds=float(rng.uniform(0, 10 * 365 * 86400)))
        lo = float(rng.uniform(380, 600))
        wl = np.linspace(lo, lo + rng.uniform(100, 600), bands)
        item = make_item(cid, {"type": "Polygon", "coordinates": [ring]}, [lon, lat, lon + w, lat + h], start,
                         start + timedelta(minutes=float(rng.uniform(1, 30))), list(wl), bands, "Pika L-SIM", 0.04,
                         f"../../collections/{cid}.zarr", collection=COLLECTION_ID, links=item_links())
        path = write_item(root.item_path(cid), item)
        size += path.stat().st_size
        rows.append(row_from_item(item, path.relative_to(root.path).as_posix()))
    t_items = time.perf_counter() - t
    t = time.perf_counter()
    add_rows(root.index_path, rows)
    return t_items, time.perf_counter() - t, size // max(items, 1)


def start_server(archive: Path) -> tuple[subprocess.Popen, str]:
    proc = subprocess.Popen([sys.executable, "-m", "archive", "view", "--archive", str(archive), "--port", "0"],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    line = proc.stdout.readline()
    url = next((w for w in line.split() if w.startswith("http://")), None)
    if url is None:
        proc.kill()
        raise SystemExit(f"archive view did not start: {line}{proc.stdout.read()}")
    return proc, url.rstrip("/") + "/stac"


class Client:
    """One keep-alive HTTP connection; returns (seconds, JSON)."""

    def __init__(self, base: str):
        parts = urlsplit(base)
        self.conn = http.client.HTTPConnection(parts.hostname, parts.port, timeout=60)
        self.prefix = parts.path

    def get(self, url: str):
        parts = urlsplit(url)
        return self._send("GET", parts.path + (f"?{parts.query}" if parts.query else ""), None)

    def post(self, path: str, body: dict):
        return self._send("POST", path, json.dumps(body).encode())

    def _send(self, method, path, body):
        t = time.perf_counter()
        headers = {"Content-Type": "application/json"} if body else {}
        self.conn.request(method, path, body=body, headers=headers)
        r = self.conn.getresponse()
        data = r.read()
        dt = time.perf_counter() - t
        if r.status != 200:
            raise SystemExit(f"{method} {path}: {r.status} {data[:300]!r}")
        return dt, json.loads(data)


def pct(values, q) -> float:
    return float(np.percentile(np.asarray(values) * 1e3, q))


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--items", type=int, default=100_000)
    p.add_argument("--bands", type=int, default=60, help="eo:bands entries per Item (sets its size; default 60)")
    p.add_argument("--repeat", type=int, default=40, help="requests per query (default 40)")
    p.add_argument("--page", type=int, default=100, help="limit when paging (default 100)")
    p.add_argument("--results", help="append the figures to this Markdown file")
    args = p.parse_args()
    out: list[str] = []
    with tempfile.TemporaryDirectory() as tmp:
        archive = Path(tmp) / "archive"
        t_items, t_index, size = build(archive, args.items, args.bands)
        out.append(f"{args.items} synthetic Items ({args.bands} bands, {size / 1e3:.1f} kB each) written in "
                   f"{t_items:.0f} s, indexed in {t_index:.1f} s")
        proc, base = start_server(archive)
        try:
            c = Client(base)
            path = c.prefix + "/search"
            wl = "hsi:wavelength_min <= 900 AND hsi:wavelength_max >= 900"
            queries = {
                "bbox 0.5 deg": {"bbox": [-100.0, 35.0, -99.5, 35.5]},
                "bbox 5 deg": {"bbox": [-100.0, 35.0, -95.0, 40.0]},
                "datetime one month": {"datetime": "2020-06-01T00:00:00Z/2020-07-01T00:00:00Z"},
                "wavelength 900 nm (CQL2)": {"filter": wl, "filter-lang": "cql2-text"},
                "bbox 5 deg + year + 900 nm": {"bbox": [-100.0, 35.0, -95.0, 40.0],
                                               "datetime": "2020-01-01T00:00:00Z/2021-01-01T00:00:00Z",
                                               "filter": wl, "filter-lang": "cql2-text"},
                "s_intersects polygon + t_intersects (CQL2 JSON)": {"filter-lang": "cql2-json", "filter": {
                    "op": "and", "args": [
                        {"op": "s_intersects", "args": [{"property": "geometry"}, {"type": "Polygon", "coordinates": [
                            [[-100, 35], [-95, 35], [-97, 40], [-100, 35]]]}]},
                        {"op": "t_intersects", "args": [{"property": "datetime"},
                                                        {"interval": ["2018-01-01T00:00:00Z", ".."]}]}]}},
            }
            for _ in range(5):  # warm-up: connection, page cache
                c.post(path, {"limit": 10})
            import psutil

            server = psutil.Process(proc.pid)
            rss_warm = server.memory_info().rss
            out += ["", "| query | method | limit | returned | p50 ms | p95 ms |", "|---|---|---|---|---|---|"]
            for name, q in queries.items():
                for method in ("GET", "POST"):
                    if method == "GET" and isinstance(q.get("filter"), dict):
                        continue
                    for limit in (10, 100):
                        times, n = [], 0
                        for _ in range(args.repeat):
                            if method == "POST":
                                dt, doc = c.post(path, {**q, "limit": limit})
                            else:
                                params = {k: (",".join(map(str, v)) if isinstance(v, list) else v) for k, v in q.items()}
                                dt, doc = c.get(f"{path}?{urlencode({**params, 'limit': limit})}")
                            times.append(dt)
                            n = len(doc["features"])
                        out.append(f"| {name} | {method} | {limit} | {n} | {pct(times, 50):.1f} | {pct(times, 95):.1f} |")
            # paging through 10,000 results by next links
            for method in ("GET", "POST"):
                times, seen = [], 0
                if method == "GET":
                    dt, doc = c.get(f"{path}?{urlencode({'filter': wl, 'limit': args.page})}")
                else:
                    dt, doc = c.post(path, {"filter": wl, "filter-lang": "cql2-text", "limit": args.page})
                times.append(dt)
                seen += len(doc["features"])
                while seen < 10_000:
                    nxt = next((ln for ln in doc["links"] if ln["rel"] == "next"), None)
                    if nxt is None:  # fewer matches than 10,000
                        break
                    dt, doc = c.get(nxt["href"]) if method == "GET" else c.post(urlsplit(nxt["href"]).path, nxt["body"])
                    times.append(dt)
                    seen += len(doc["features"])
                out.append(f"| paging to 10,000 results of 900 nm, {len(times)} pages | {method} | {args.page} | "
                           f"{seen} | {pct(times, 50):.1f} | {pct(times, 95):.1f} (last page "
                           f"{times[-1] * 1e3:.1f}, total {sum(times):.1f} s) |")
            rss_end = server.memory_info().rss
            out += ["", f"Server RSS {rss_warm / 2**20:.0f} MiB after the warm-up, {rss_end / 2**20:.0f} MiB after "
                    "every query above."]
        finally:
            proc.terminate()
            proc.wait(10)
        # `archive catalog rebuild` as a user runs it: every Item file linked and read, the index and the tree
        t = time.perf_counter()
        done = subprocess.run([sys.executable, "-m", "archive", "catalog", "rebuild", "--archive", str(archive)],
                              capture_output=True, text=True)
        rebuild = time.perf_counter() - t
        # exit 1 with one DAMAGED line per Item: the synthetic Items have no collection stores
        if done.returncode not in (0, 1) or (done.returncode == 1 and "DAMAGED" not in done.stdout):
            raise SystemExit(f"catalog rebuild failed ({done.returncode}): {done.stdout[-300:]}{done.stderr[-500:]}")
        out.append(f"`archive catalog rebuild` (a process: every Item file read, the index and the STAC tree "
                   f"written): {rebuild:.1f} s (exit {done.returncode}: "
                   f"{done.stdout.count('DAMAGED')} Items named DAMAGED, their synthetic stores do not exist).")
    m = machine()
    head = (f"\n## STAC API /stac/search over {args.items} Items\n\n"
            f"Machine: {m['cpu']}, {m['cores']} cores, {m['ram_gb']} GB RAM, Python {m['python']}; load average "
            f"{load()} (at the end). Command: `python bench/{Path(__file__).name} "
            f"{' '.join(shlex.quote(a) for a in sys.argv[1:])}`. One keep-alive client on loopback, "
            f"{args.repeat} requests per row; times include the server's reading of the page's Item files.\n")
    text = head + "\n" + "\n".join(out) + "\n"
    print(text)
    if args.results:
        with open(args.results, "a", encoding="utf-8") as f:
            f.write(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
