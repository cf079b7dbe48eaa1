"""Benchmarks of the archive side: DN codecs, ingest throughput, catalog search latency.

    python bench/bench_ingest.py codecs  [--flight DIR]   # ratio + encode/decode MB/s per codec
    python bench/bench_ingest.py ingest  [--flight DIR]   # ingest MB/s of raw input vs copying the files
    python bench/bench_ingest.py catalog [--items 10000]  # search latency over synthetic Items
    python bench/bench_ingest.py floor --flight DIR       # issue 45: ingest vs the I/O floor vs to_zarr, one run
    python bench/bench_ingest.py profile --flight DIR     # issue 45: where ingest's CPU goes, per chunk
    python bench/bench_ingest.py many --flights 300       # issue 45: tiny flights through a scheduler

``floor`` (bench_ingest_floor.py): ``archive ingest`` as a user runs it (a process, then ``sync``), the I/O
floor measured in the same run (read every BIL + write the bytes of the collection it made, fdatasync)
and a hand-written xarray/dask ``to_zarr`` of the same DN (same chunks, same Blosc codec), alternated
``--rounds`` times; wall, CPU and peak RSS of each process. ``profile``: the per-chunk CPU of each step
on one thread (band-run read, checksums, each codec, the write) and the per-flight steps (checks,
catalog, previews). ``many``: ``--flights`` tiny flights (copies of one with their clocks moved) through a
scheduler and two workers, the first and the last 100 timed.

Without --flight a flight is simulated into a temporary directory (900 samples x 1000 lines, 12-bit
DN, the size of a real Pika L cube). Prints Markdown rows for bench/RESULTS.md.
"""

from __future__ import annotations

import argparse
import os
import platform
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def _flight(args, tmp: Path) -> Path:
    if args.flight:
        return Path(args.flight)
    from archive.simulator.command import simulate_flight

    d = tmp / "flight"
    simulate_flight(d, cubes=args.cubes, bands=args.bands, samples=900, lines=1000, cubes_per_pass=2, seed=1)
    return d


def bench_codecs(args) -> None:
    import numcodecs

    from archive.formats.envi import EnviCube
    from archive.formats.flight import discover_flight

    with tempfile.TemporaryDirectory() as tmp:
        flight = discover_flight(_flight(args, Path(tmp)))
        cube = EnviCube(flight.cubes[0].data)
        chunks = [np.ascontiguousarray(cube.band(b)) for b in range(cube.header.bands)]
    raw = sum(c.nbytes for c in chunks)
    B = numcodecs.Blosc
    codecs = {
        "blosc zstd 3 bitshuffle": B(cname="zstd", clevel=3, shuffle=B.BITSHUFFLE),
        "blosc zstd 5 bitshuffle": B(cname="zstd", clevel=5, shuffle=B.BITSHUFFLE),
        "blosc zstd 3 byte-shuffle": B(cname="zstd", clevel=3, shuffle=B.SHUFFLE),
        "blosc lz4 5 bitshuffle": B(cname="lz4", clevel=5, shuffle=B.BITSHUFFLE),
        "zstd 3 (no shuffle)": numcodecs.Zstd(level=3),
    }
    print(f"DN chunks: {len(chunks)} x {chunks[0].shape} {chunks[0].dtype} "
          f"(max DN {max(int(c.max()) for c in chunks)}), {raw / 1e6:.1f} MB, one thread")
    print("| codec | ratio | encode MB/s | decode MB/s |")
    print("|---|---|---|---|")
    for name, codec in codecs.items():
        enc_t, dec_t, size = [], [], 0
        for _ in range(args.repeat):
            t = time.perf_counter()
            encoded = [codec.encode(c) for c in chunks]
            enc_t.append(time.perf_counter() - t)
            t = time.perf_counter()
            for e, c in zip(encoded, chunks, strict=True):
                out = np.frombuffer(codec.decode(e), c.dtype)
            dec_t.append(time.perf_counter() - t)
            assert np.array_equal(out, chunks[-1].ravel())
            size = sum(len(e) for e in encoded)
        print(f"| {name} | {raw / size:.2f} | {raw / min(enc_t) / 1e6:.0f} | {raw / min(dec_t) / 1e6:.0f} |")


def bench_ingest(args) -> None:
    from archive.ingest.command import ingest

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        flight = _flight(args, tmp)
        size = sum(p.stat().st_size for p in flight.iterdir() if p.is_file())
        copies, ingests = [], []
        for k in range(args.repeat):
            t = time.perf_counter()
            shutil.copytree(flight, tmp / f"copy{k}", ignore=shutil.ignore_patterns("truth"))
            os.sync()
            copies.append(time.perf_counter() - t)
            t = time.perf_counter()
            ingest([str(flight)], tmp / f"archive{k}", 47.5, ground_height=80.0, threads=args.workers, progress=False)
            os.sync()
            ingests.append(time.perf_counter() - t)
        stored = sum(p.stat().st_size for p in (tmp / "archive0").rglob("*") if p.is_file())
    print(f"raw input {size / 1e6:.1f} MB, stored {stored / 1e6:.1f} MB (ratio {size / stored:.2f}), "
          f"{args.workers or os.cpu_count()} worker threads, best of {args.repeat}")
    print("| operation | seconds | MB/s of raw input |")
    print("|---|---|---|")
    print(f"| copy raw files (shutil.copytree + sync) | {min(copies):.2f} | {size / min(copies) / 1e6:.0f} |")
    print(f"| archive ingest (checks, Zarr, sha256, catalog) | {min(ingests):.2f} | {size / min(ingests) / 1e6:.0f} |")


def bench_catalog(args) -> None:
    from datetime import UTC, datetime, timedelta

    from archive.catalog.index import rebuild_index, search
    from archive.catalog.root import create_archive
    from archive.catalog.stac import make_item, write_item

    rng = np.random.default_rng(0)
    with tempfile.TemporaryDirectory() as tmp:
        root = create_archive(Path(tmp) / "archive")
        t0 = datetime(2015, 1, 1, tzinfo=UTC)
        t = time.perf_counter()
        for k in range(args.items):
            lon, lat = rng.uniform(-120, -70), rng.uniform(25, 50)
            w, h = rng.uniform(0.001, 0.02, 2)
            ring = [[lon, lat], [lon + w, lat], [lon + w, lat + h], [lon, lat + h], [lon, lat]]
            start = t0 + timedelta(seconds=float(rng.uniform(0, 10 * 365 * 86400)))
            bands = int(rng.integers(50, 300))
            lo = float(rng.uniform(380, 600))
            wl = np.linspace(lo, lo + rng.uniform(100, 600), bands)
            item = make_item(f"sim-{k:05d}", {"type": "Polygon", "coordinates": [ring]}, [lon, lat, lon + w, lat + h],
                             start, start + timedelta(minutes=float(rng.uniform(1, 30))), list(wl), bands,
                             "Pika L-SIM", 0.04, f"../../collections/sim-{k:05d}.zarr")
            write_item(root.item_path(f"sim-{k:05d}"), item)
        t_items = time.perf_counter() - t
        t = time.perf_counter()
        rebuild_index(root)
        t_index = time.perf_counter() - t
        queries = {
            "bbox 0.5 deg": dict(bbox=(-100.0, 35.0, -99.5, 35.5)),
            "bbox 5 deg": dict(bbox=(-100.0, 35.0, -95.0, 40.0)),
            "one month": dict(start=datetime(2020, 6, 1, tzinfo=UTC).timestamp(),
                              end=datetime(2020, 7, 1, tzinfo=UTC).timestamp()),
            "wavelength 900 nm": dict(wavelength=900.0),
            "bbox 5 deg + year + 900 nm": dict(bbox=(-100.0, 35.0, -95.0, 40.0),
                                               start=datetime(2020, 1, 1, tzinfo=UTC).timestamp(),
                                               end=datetime(2021, 1, 1, tzinfo=UTC).timestamp(), wavelength=900.0),
        }
        print(f"{args.items} synthetic Items written in {t_items:.1f} s; index rebuilt from the files in {t_index:.2f} s")
        print("| query | hits | median ms (incl. connect) |")
        print("|---|---|---|")
        for name, q in queries.items():
            times = []
            for _ in range(args.repeat * 5):
                t = time.perf_counter()
                hits = search(root.index_path, **q)
                times.append(time.perf_counter() - t)
            print(f"| {name} | {len(hits)} | {statistics.median(times) * 1e3:.2f} |")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("what", choices=["codecs", "ingest", "catalog", "floor", "profile", "many"])
    p.add_argument("--flight", help="raw flight directory (default: simulate one)")
    p.add_argument("--bands", type=int, default=16, help="bands of the simulated flight (default 16)")
    p.add_argument("--cubes", type=int, default=2, help="cubes of the simulated flight (default 2)")
    p.add_argument("--items", type=int, default=10000, help="synthetic Items for 'catalog' (default 10000)")
    p.add_argument("--workers", type=int, help="ingest threads (default CPU count)")
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--rounds", type=int, default=2, help="floor: alternated rounds (default 2)")
    p.add_argument("--workdir", default="/tmp/archive-bench-ingest", help="floor/many: where archives are written")
    p.add_argument("--compression", default=None, help="floor: ingest --compression (default: its default)")
    p.add_argument("--checksum", default=None, help="floor: ingest --checksum (default: its default)")
    p.add_argument("--cold", action="store_true", help="floor: evict the BIL from the page cache before each step")
    p.add_argument("--flights", type=int, default=300, help="many: tiny flights (default 300)")
    args = p.parse_args()
    print(f"# {args.what} on {platform.node()} ({os.cpu_count()} CPUs, Python {platform.python_version()})")
    if args.what in ("floor", "profile", "many"):
        import bench_ingest_floor

        return {"floor": bench_ingest_floor.floor, "profile": bench_ingest_floor.profile,
                "many": bench_ingest_floor.many}[args.what](args)
    {"codecs": bench_codecs, "ingest": bench_ingest, "catalog": bench_catalog}[args.what](args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
