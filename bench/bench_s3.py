"""Benchmark (issue 35): render a flight from an archive in S3 (moto's server on loopback) vs from a
local archive of the same flight.

    python bench/bench_s3.py [--cubes 2] [--bands 300] [--samples 900] [--lines 1000] [--gsd 0.04]
                             [--workdir DIR] [--repeats 2] [--json FILE] [--s3-out]
    python bench/bench_s3.py --libraries    # zarr's ObjectStore (obstore) vs FsspecStore (s3fs), reads only

Defaults are the paper shape of bench/bench_render.py: 2 cubes of 900 samples x 1000 lines x 300
bands. One run: simulate the flight (kept in --workdir while its marker exists), ingest it into a
local archive and into ``s3://bench/arc`` on a ``ThreadedMotoServer`` in this process (127.0.0.1),
then ``archive render ID --archive A --out X.zarr`` in a subprocess for each archive, alternately,
``--repeats`` times each (the output local in both cases; with ``--s3-out`` also from the s3 archive
to ``s3://bench/out/mosaic.zarr``, its chunks PUT by the workers). Reported per render: wall (s, the
subprocess), requests made to the server (GET / HEAD / LIST, from the server's request log), bytes
read (sum of the sizes of the objects fetched by GET; the local render reads the same chunk files,
by construction), and that both renders are equal bit for bit.

moto on loopback is a Python server (werkzeug, one thread per request) sharing this machine's cores
with the render: its per-request cost is far above a real S3 endpoint's CPU cost per request, and
its latency far below a real endpoint's; the ratio says what the client side costs, not what a
bucket in a data centre would.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import re
import shutil
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np


class _Requests(logging.Handler):
    """Counts the S3 server's requests from werkzeug's access log lines."""

    pattern = re.compile(r'"(GET|HEAD|PUT|POST|DELETE) (\S+) HTTP')

    def __init__(self):
        super().__init__()
        self.lines: list[tuple[str, str]] = []

    def emit(self, record: logging.LogRecord) -> None:
        m = self.pattern.search(record.getMessage())
        if m:
            self.lines.append((m.group(1), m.group(2)))


def compare_libraries(repeats: int = 3) -> None:
    """Read 64 chunks of 1024 x 900 uint16 (1.8 MB each, one array, Blosc-less) through zarr's
    ObjectStore (obstore) and FsspecStore (s3fs) from moto on loopback: whole array in one call, 8
    threads chunk by chunk, and one thread chunk by chunk (s, best and worst of ``repeats``)."""
    from concurrent.futures import ThreadPoolExecutor

    import zarr
    from obstore.store import S3Store
    from zarr.storage import FsspecStore, ObjectStore

    a = np.random.default_rng(0).integers(0, 4096, (64, 1024, 900)).astype("<u2")
    g = zarr.open_group(FsspecStore.from_url("s3://bench/lib.zarr"), mode="w", zarr_format=3)
    g.create_array("dn", shape=a.shape, chunks=(1, 1024, 900), dtype="<u2")[...] = a
    makers = {"FsspecStore (s3fs)": lambda: FsspecStore.from_url("s3://bench/lib.zarr", read_only=True),
              "ObjectStore (obstore)": lambda: ObjectStore(S3Store("bench", prefix="lib.zarr",
                                                                   client_options={"allow_http": True}),
                                                           read_only=True)}
    for name, make in makers.items():
        times = {"whole": [], "8 threads": [], "1 thread": []}
        for _ in range(repeats):
            z = zarr.open_array(make(), path="dn", mode="r")
            t = time.perf_counter()
            assert np.array_equal(z[...], a)
            times["whole"].append(time.perf_counter() - t)
            t = time.perf_counter()
            with ThreadPoolExecutor(8) as ex:
                list(ex.map(lambda b: z[b], range(64)))
            times["8 threads"].append(time.perf_counter() - t)
            t = time.perf_counter()
            for b in range(64):
                z[b]
            times["1 thread"].append(time.perf_counter() - t)
        print(f"{name}: " + "; ".join(f"{k} {min(v):.2f}-{max(v):.2f} s" for k, v in times.items()), flush=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cubes", type=int, default=2)
    ap.add_argument("--bands", type=int, default=300)
    ap.add_argument("--samples", type=int, default=900)
    ap.add_argument("--lines", type=int, default=1000)
    ap.add_argument("--gsd", type=float, default=0.04)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--workdir", default="/tmp/bench_s3")
    ap.add_argument("--json", default=None)
    ap.add_argument("--libraries", action="store_true", help="only compare obstore and s3fs reading chunks")
    ap.add_argument("--s3-out", action="store_true", help="also render from the s3 archive to an s3 Zarr output")
    args = ap.parse_args()

    from moto.server import ThreadedMotoServer

    counter = _Requests()
    log = logging.getLogger("werkzeug")
    log.setLevel(logging.INFO)
    log.propagate = False
    log.addHandler(counter)
    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    host, port = server.get_host_and_port()
    os.environ.update(AWS_ENDPOINT_URL=f"http://{host}:{port}", AWS_ACCESS_KEY_ID="bench", AWS_SECRET_ACCESS_KEY="bench",
                      AWS_DEFAULT_REGION="us-east-1")
    import boto3

    s3 = boto3.client("s3")
    s3.create_bucket(Bucket="bench")
    if args.libraries:
        compare_libraries()
        server.stop()
        return 0
    work = Path(args.workdir)
    shape = f"c{args.cubes}_b{args.bands}_s{args.samples}_l{args.lines}"
    flight = work / f"flight_{shape}"
    if not (flight / ".complete").exists():
        from archive.simulator.command import simulate_flight

        shutil.rmtree(flight, ignore_errors=True)
        simulate_flight(flight, seed=0, cubes=args.cubes, bands=args.bands, samples=args.samples, lines=args.lines,
                        cubes_per_pass=args.cubes)
        (flight / ".complete").touch()
    os.environ["XDG_CACHE_HOME"] = str(work / "cache")
    from archive.ingest.command import ingest

    local = work / f"archive_{shape}"
    shutil.rmtree(local, ignore_errors=True)
    t = time.perf_counter()
    (r,) = ingest([str(flight)], local, 47.5, progress=False)
    ingest_local = time.perf_counter() - t
    t = time.perf_counter()
    ingest([str(flight)], "s3://bench/arc", 47.5, progress=False)
    ingest_s3 = time.perf_counter() - t
    cid = r.cid
    sizes = {}
    for page in s3.get_paginator("list_objects_v2").paginate(Bucket="bench", Prefix="arc/"):
        sizes.update({"/bench/" + o["Key"]: o["Size"] for o in page.get("Contents", [])})
    stored = sum(sizes.values())

    rows = []
    outs = {}
    kinds = [("local", str(local), None), ("s3", "s3://bench/arc", None)]
    if args.s3_out:
        kinds.append(("s3 to s3", "s3://bench/arc", "s3://bench/out/mosaic.zarr"))
    for rep in range(args.repeats):
        for kind, archive, target in kinds:
            out = work / f"out_{kind.replace(' ', '_')}.zarr"
            shutil.rmtree(out, ignore_errors=True)
            Path(str(out) + ".json").unlink(missing_ok=True)
            counter.lines.clear()
            t = time.perf_counter()
            p = subprocess.run([sys.executable, "-m", "archive", "render", cid, "--archive", archive,
                                "--out", target or str(out), "--gsd", str(args.gsd), "--fov", "47.5", "--quiet"]
                               + (["--overwrite"] if target else []), capture_output=True, text=True)
            wall = time.perf_counter() - t
            if p.returncode != 0:
                print(p.stderr, file=sys.stderr)
                return 1
            methods = Counter(m for m, _ in counter.lines)
            got = [path.split("?")[0] for m, path in counter.lines if m == "GET" and "?" not in path]
            lists = sum(1 for m, path in counter.lines if m == "GET" and "list-type" in path)
            rows.append({"archive": kind, "repeat": rep, "wall_s": round(wall, 2),
                         "requests": sum(methods.values()), "gets": len(got), "heads": methods.get("HEAD", 0),
                         "lists": lists, "bytes_read": sum(sizes.get(k, 0) for k in got)})
            rows[-1]["puts"] = methods.get("PUT", 0)
            outs[kind] = target or out
            print(json.dumps(rows[-1]), flush=True)
    import xarray as xr

    a = xr.open_zarr(outs["local"], consolidated=False)
    b = xr.open_zarr(outs["s3"], consolidated=False)
    equal = all(np.array_equal(a[v].values, b[v].values, equal_nan=True) for v in a.data_vars)
    if args.s3_out:
        from archive.storage import zarr_store

        c = xr.open_zarr(zarr_store(outs["s3 to s3"]), consolidated=False)
        equal = equal and all(np.array_equal(a[v].values, c[v].values, equal_nan=True) for v in a.data_vars)
    walls = {k: min(r["wall_s"] for r in rows if r["archive"] == k) for k, _, _ in kinds}
    summary = {"shape": vars(args), "collection": cid, "stored_bytes_s3": stored, "ingest_local_s": round(ingest_local, 1),
               "ingest_s3_s": round(ingest_s3, 1), "renders": rows, "best_wall_s": walls,
               "ratio_s3_over_local": round(walls["s3"] / walls["local"], 3), "outputs_equal": bool(equal),
               "load": os.getloadavg()}
    print(json.dumps(summary, indent=1))
    if args.json:
        Path(args.json).write_text(json.dumps(summary, indent=1) + "\n")
    server.stop()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
