"""Issue 45's ingest benchmarks, run through ``bench/bench_ingest.py floor|profile|many`` (its docstring).

    .venv/bin/python bench/bench_ingest.py floor --flight DIR [--rounds 2] [--cold] [--compression fast]
    .venv/bin/python bench/bench_ingest.py profile --flight DIR
    .venv/bin/python bench/bench_ingest.py many --flights 300

Without --flight, ``floor`` and ``profile`` simulate a flight of ``--cubes`` x 1000 lines x 900 samples x
``--bands`` into ``--workdir`` (kept and reused). Every figure printed comes from this one run.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
PY = sys.executable
BLOCK = 16 << 20


def _flight(args) -> Path:
    if args.flight:
        return Path(args.flight)
    from archive.simulator.command import simulate_flight

    d = Path(args.workdir) / f"flight-{args.cubes}x{args.bands}"
    if not (d / ".bench-complete").exists():
        shutil.rmtree(d, ignore_errors=True)
        simulate_flight(d, cubes=args.cubes, bands=args.bands, samples=900, lines=1000, cubes_per_pass=2, seed=1)
        (d / ".bench-complete").touch()
    return d


def _bils(flight: Path) -> list[Path]:
    from archive.formats.flight import discover_flight

    return [c.data for c in discover_flight(flight).cubes]


def _evict(paths) -> None:
    for p in paths:
        fd = os.open(p, os.O_RDONLY)
        try:
            os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
        finally:
            os.close(fd)


def _read_all(paths) -> int:
    buf, n = bytearray(BLOCK), 0
    for p in paths:
        with open(p, "rb", buffering=0) as f:
            while k := f.readinto(buf):
                n += k
    return n


def _run(cmd: list[str]) -> dict:
    """Run ``cmd``, then ``sync``: wall (s, start to after the sync), CPU-s and peak RSS (GB) of the process
    (and the children it waited for)."""
    t = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    out, err = proc.stdout.read().decode(), proc.stderr.read().decode()
    if proc.returncode:
        raise SystemExit(f"{' '.join(cmd)} failed ({proc.returncode}): {err[-2000:]}")
    os.sync()
    return {"wall": time.perf_counter() - t, "cpu": usage.ru_utime + usage.ru_stime, "rss": usage.ru_maxrss / 1e6,
            "out": out}


def _floor(bils, stored: int, target: Path) -> dict:
    """Read every BIL, then write ``stored`` bytes into one file and fdatasync it: seconds."""
    t = time.perf_counter()
    read = _read_all(bils)
    t_read = time.perf_counter() - t
    block = np.random.default_rng(0).integers(0, 256, BLOCK, np.uint8).tobytes()
    with open(target, "wb", buffering=0) as f:
        left = stored
        while left > 0:
            left -= f.write(block[:min(left, BLOCK)])
        os.fdatasync(f.fileno())
    wall = time.perf_counter() - t
    target.unlink()
    return {"wall": wall, "read": t_read, "write": wall - t_read, "bytes_read": read}


def _size(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def to_zarr_main(flight: str, out: str, cname: str, clevel: str, shuffle: str) -> None:
    """The hand-written xarray/dask ``to_zarr`` of a flight's DN: each BIL a memory map seen as (band,
    line, sample), the cubes concatenated along lines, chunks (1, cube lines, samples), the same Blosc codec."""
    import dask.array as da
    import xarray as xr
    from zarr.codecs import BloscCodec

    from archive.formats.envi import read_header
    from archive.formats.flight import discover_flight

    arrays = []
    for cube in discover_flight(flight).cubes:
        h = read_header(cube.header)
        mm = np.memmap(cube.data, dtype=h.dtype, mode="r", offset=h.header_offset, shape=(h.lines, h.bands, h.samples))
        arrays.append(da.from_array(mm, chunks=(h.lines, 1, h.samples)).transpose(1, 0, 2))
    dn = da.concatenate(arrays, axis=1)
    ds = xr.Dataset({"dn": (("band", "line", "sample"), dn)})
    ds.to_zarr(out, mode="w-", zarr_format=3, consolidated=False,
               encoding={"dn": {"compressors": [BloscCodec(cname=cname, clevel=int(clevel), shuffle=shuffle)]}})


def floor(args) -> int:
    from archive.collection.layout import DEFAULT_DN_COMPRESSION, DN_COMPRESSIONS

    flight = _flight(args)
    bils = _bils(flight)
    raw = sum(p.stat().st_size for p in bils)
    work = Path(args.workdir) / "floor"
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    codec = DN_COMPRESSIONS[args.compression or DEFAULT_DN_COMPRESSION]
    _read_all(bils)   # warm page cache (unless --cold evicts it before each step)
    print(f"flight {flight}: {len(bils)} cubes, {raw / 1e9:.2f} GB of BIL; ingest --compression "
          f"{args.compression or DEFAULT_DN_COMPRESSION} ({codec}), --checksum {args.checksum or 'default'}; "
          f"{'cold' if args.cold else 'warm'} page cache; load {os.getloadavg()[0]:.2f}")
    print("| round | step | wall + sync s | CPU s | peak RSS GB | written GB | ratio to the floor |")
    print("|---|---|---|---|---|---|---|")
    rows = []
    for r in range(args.rounds):
        arch = work / f"archive{r}"
        cmd = [PY, "-m", "archive", "ingest", str(flight), "--archive", str(arch), "--fov", "47.5", "--ground-height",
               "80", "--quiet"]
        cmd += ["--compression", args.compression] if args.compression else []
        cmd += ["--checksum", args.checksum] if args.checksum else []
        if args.cold:
            _evict(bils)
        ing = _run(cmd)
        stored = _size(arch / "collections")
        if args.cold:
            _evict(bils)
        fl = _floor(bils, stored, work / "floor.bin")
        if args.cold:
            _evict(bils)
        zdir = work / f"to_zarr{r}.zarr"
        tz = _run([PY, str(Path(__file__).resolve()), "_to_zarr", str(flight), str(zdir), codec["cname"],
                   str(codec["clevel"]), codec["shuffle"]])
        zstored = _size(zdir)
        rows.append((ing, fl, tz))
        print(f"| {r} | I/O floor (read {fl['bytes_read'] / 1e9:.2f} GB: {fl['read']:.2f} s; write {stored / 1e9:.2f} "
              f"GB + fdatasync: {fl['write']:.2f} s) | {fl['wall']:.2f} | - | - | {stored / 1e9:.2f} | 1.00 |")
        print(f"| {r} | archive ingest (process + sync) | {ing['wall']:.2f} | {ing['cpu']:.1f} | {ing['rss']:.2f} | "
              f"{stored / 1e9:.2f} | {ing['wall'] / fl['wall']:.2f} |")
        print(f"| {r} | xarray/dask to_zarr (process + sync) | {tz['wall']:.2f} | {tz['cpu']:.1f} | {tz['rss']:.2f} | "
              f"{zstored / 1e9:.2f} | {tz['wall'] / fl['wall']:.2f} |")
        shutil.rmtree(arch, ignore_errors=True)
        shutil.rmtree(zdir, ignore_errors=True)
    best = [min(x[i]["wall"] for x in rows) for i in range(3)]
    print(f"best of {args.rounds}: floor {best[1]:.2f} s, ingest {best[0]:.2f} s ({best[0] / best[1]:.2f}x the floor, "
          f"{best[0] / best[2]:.2f}x to_zarr), to_zarr {best[2]:.2f} s ({best[2] / best[1]:.2f}x); "
          f"load {os.getloadavg()[0]:.2f}")
    return 0


def _ms(f, n: int) -> float:
    """CPU milliseconds of this thread per call of ``f`` (what the machine's other load does not inflate)."""
    t = time.thread_time()
    for _ in range(n):
        f()
    return (time.thread_time() - t) / n * 1e3


def profile(args) -> int:
    """Where ingest's CPU goes: per-chunk steps on one thread, then the per-flight steps of one ingest."""
    import hashlib

    import blake3
    import numcodecs

    from archive.codecs import numcodecs_blosc
    from archive.collection import chunk_groups
    from archive.files import write_atomic
    from archive.formats.envi import EnviCube

    numcodecs.blosc.use_threads = False   # as in a task: one thread each
    flight = _flight(args)
    bils = _bils(flight)
    cube = EnviCube(bils[0])
    bands, lines, samples = cube.shape
    _read_all(bils[:1])
    group = chunk_groups([str(bils[0])], [lines], bands, lines, samples, cube.header.dtype.itemsize)[0]
    run = group.band1 - group.band0
    chunks = [np.ascontiguousarray(b, "<u2") for b in cube.bands(range(0, bands, max(1, bands // 40)))]   # ~40 bands
    nchunks = bands * len(bils)   # one line chunk per cube (equal cubes)
    print(f"flight {flight}: {len(bils)} cubes of {bands} x {lines} x {samples}; {nchunks} dn chunks of "
          f"{chunks[0].nbytes / 1e6:.2f} MB ({len(chunks)} bands sampled across the range); CPU time of one thread; load {os.getloadavg()[0]:.2f}")
    steps = {
        "read one band (one preadv per line)": _ms(lambda: cube.band(bands // 2), 10),
        f"read a run of {run} bands, per band (write_chunks)": _ms(lambda: cube.bands(range(group.band0, group.band1)),
                                                                   3) / run,
        "sha256 of a chunk": _ms(lambda: [hashlib.sha256(c.reshape(-1).view(np.uint8)).digest() for c in chunks], 2)
        / len(chunks),
        "BLAKE3 of a chunk": _ms(lambda: [blake3.blake3(c.reshape(-1).view(np.uint8)).digest() for c in chunks], 2)
        / len(chunks),
    }
    print("| step | CPU ms per chunk | CPU-s per flight |")
    print("|---|---|---|")
    for name, ms in steps.items():
        print(f"| {name} | {ms:.2f} | {ms * nchunks / 1e3:.1f} |")
    raw = sum(c.nbytes for c in chunks)
    print("\n| Blosc codec | ratio | encode CPU ms per chunk | decode CPU ms per chunk | encode CPU-s per flight |")
    print("|---|---|---|---|---|")
    table = [("lz4", 1, "bitshuffle"), ("lz4", 5, "bitshuffle"), ("lz4", 9, "bitshuffle"), ("lz4", 9, "shuffle"),
             ("zstd", 1, "bitshuffle"), ("zstd", 3, "bitshuffle"), ("zstd", 5, "bitshuffle"), ("zstd", 1, "shuffle"),
             ("lz4hc", 1, "bitshuffle"), ("blosclz", 5, "bitshuffle")]
    encoded = None
    for cname, clevel, shuffle in table:
        codec = numcodecs_blosc(cname, clevel, shuffle)
        enc = [codec.encode(c) for c in chunks]
        e = _ms(lambda codec=codec: [codec.encode(c) for c in chunks], 1) / len(chunks)
        d = _ms(lambda codec=codec, enc=enc: [codec.decode(x) for x in enc], 1) / len(chunks)
        encoded = enc if (cname, clevel) == ("lz4", 9) and shuffle == "bitshuffle" else encoded
        print(f"| {cname} {clevel} {shuffle} | {raw / sum(len(x) for x in enc):.3f} | {e:.2f} | {d:.2f} | "
              f"{e * nchunks / 1e3:.1f} |")
    target = Path(args.workdir) / "profile-chunks"
    shutil.rmtree(target, ignore_errors=True)
    target.mkdir(parents=True)
    ms = _ms(lambda: [write_atomic(target / f"{k}", x) for k, x in enumerate(encoded)], 1) / len(encoded)
    print(f"\nwrite one encoded chunk (temporary name, rename; page cache): {ms:.2f} ms, "
          f"{ms * nchunks / 1e3:.1f} s per flight")
    shutil.rmtree(target, ignore_errors=True)
    _flight_steps(flight, Path(args.workdir) / "profile-archive")
    return 0


def _flight_steps(flight: Path, out: Path) -> None:
    from archive.catalog.describe import catalog_collection
    from archive.ingest.checks import open_archive_root
    from archive.ingest.command import write_flight
    from archive.ingest.flight import PrepareArguments
    from archive.ingest.previews import add_previews

    shutil.rmtree(out, ignore_errors=True)
    print("\n| per-flight step | wall s | CPU s (user + sys) |")
    print("|---|---|---|")
    state = {}

    def step(name, f):
        t, c = time.perf_counter(), os.times()
        state[name] = f()
        c2 = os.times()
        print(f"| {name} | {time.perf_counter() - t:.2f} | {c2.user - c.user:.2f} + {c2.system - c.system:.2f} |",
              flush=True)

    step("checks (prepare_flight: headers, times, navigation, poses)",
         lambda: PrepareArguments(47.5, ground_height=80.0).prepare(str(flight)))
    plan = state[next(iter(state))]
    root = open_archive_root(out)
    step("dn chunks + raw-file checksums, marker, rename (write_flight, every core)",
         lambda: write_flight(plan, root, None, False))
    step("catalog (Item, index row, root catalog)", lambda: catalog_collection(root, plan.cid))
    step("previews (ingest/previews.py)", lambda: add_previews(root, [plan.cid]))
    step("sync", os.sync)
    shutil.rmtree(out, ignore_errors=True)


def _copy_moved(base: Path, to: Path, seconds: float) -> None:
    """A copy of the flight ``base`` with its clocks (the .lcf's and the .bil.times') moved by ``seconds``: a
    flight of its own id (its start second moves)."""
    from archive.formats.lcf import read_lcf, write_lcf
    from archive.formats.times import read_times, write_times

    shutil.copytree(base, to, ignore=shutil.ignore_patterns("truth"))
    for lcf in to.glob("*.lcf"):
        data = read_lcf(lcf)
        write_lcf(lcf, dataclasses.replace(data, time=data.time + seconds))
    for times in to.glob("*.bil.times"):
        write_times(times, read_times(times) + seconds)


def _scheduler(logs: Path):
    """``dask scheduler`` + two ``dask worker --nthreads 1`` on 127.0.0.1: (address, processes)."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    address = f"tcp://127.0.0.1:{port}"
    logs.mkdir(parents=True, exist_ok=True)
    procs = [subprocess.Popen([PY, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1", "--port", str(port),
                               "--no-dashboard"], stdout=open(logs / "scheduler.log", "w"), stderr=subprocess.STDOUT,
                              start_new_session=True)]
    for i in range(2):
        procs.append(subprocess.Popen([PY, "-m", "distributed.cli.dask_worker", address, "--nthreads", "1",
                                       "--no-dashboard", "--local-directory", str(logs / f"w{i}")],
                                      stdout=open(logs / f"worker{i}.log", "w"), stderr=subprocess.STDOUT,
                                      start_new_session=True))
    from distributed import Client

    with Client(address, timeout="60s") as client:
        client.wait_for_workers(2, timeout=60)
    return address, procs


def many(args) -> int:
    """``--flights`` tiny flights (2 cubes x 100 lines x 64 samples x 4 bands, one simulated, the others
    copies with their clocks moved by a minute each) ingested through a scheduler with two workers in
    three commands (the first 100 into an empty archive, the middle ones, the last 100): seconds of each,
    per flight, and the projection to 100,000 flights from the first and the last 100."""
    import signal

    from archive.ingest.command import ingest
    from archive.simulator.command import simulate_flight

    n = max(200, args.flights)
    work = Path(args.workdir) / "many"
    shutil.rmtree(work, ignore_errors=True)
    base = work / "raw" / "f00000"
    simulate_flight(base, cubes=2, bands=4, samples=64, lines=100, cubes_per_pass=2, seed=3)
    t = time.perf_counter()
    dirs = [base] + [work / "raw" / f"f{k:05d}" for k in range(1, n)]
    for k, d in enumerate(dirs[1:], start=1):
        _copy_moved(base, d, 60.0 * k)
    print(f"{n} tiny flights (2 cubes x 100 x 64 x 4 bands) made in {time.perf_counter() - t:.1f} s; "
          f"load {os.getloadavg()[0]:.2f}")
    address, procs = _scheduler(work / "dask")
    archive = work / "archive"
    import threading

    from distributed import Client

    peak, stop = [0], threading.Event()

    def watch() -> None:   # the tasks the scheduler holds, every 0.2 s
        with Client(address, timeout="30s") as c:
            while not stop.wait(0.2):
                peak[0] = max(peak[0], c.run_on_scheduler(lambda dask_scheduler: len(dask_scheduler.tasks)))

    watcher = threading.Thread(target=watch, daemon=True)
    watcher.start()
    try:
        parts = [("first 100 (empty archive)", dirs[:100]), (f"middle {n - 200}", dirs[100:n - 100]),
                 (f"last 100 (into {n - 100} flights)", dirs[n - 100:])]
        print("| command | flights | seconds | per flight s | load |")
        print("|---|---|---|---|---|")
        timed = []
        for name, part in parts:
            if not part:
                continue
            t = time.perf_counter()
            results = ingest([str(d) for d in part], archive, 47.5, ground_height=80.0, scheduler=address,
                             progress=False)
            seconds = time.perf_counter() - t
            assert all(r.status == "ingested" for r in results), [r for r in results if r.status != "ingested"][:3]
            timed.append(seconds / len(part))
            print(f"| {name} | {len(part)} | {seconds:.1f} | {seconds / len(part):.3f} | {os.getloadavg()[0]:.2f} |")
    finally:
        stop.set()
        watcher.join(10)
        for proc in procs:
            try:
                os.killpg(proc.pid, signal.SIGTERM)
                proc.wait(10)
            except (ProcessLookupError, subprocess.TimeoutExpired):
                pass
    first, last = timed[0], timed[-1]
    slope = max(0.0, (last - first) / max(n - 100, 1))   # s more per flight, per flight already in the archive
    projected = 100_000 * first + slope * 100_000 ** 2 / 2
    growth = (f"{slope * 1e6:.2f} ms more per flight for every 1,000 flights already there" if slope > 0 else
              "no growth measured")
    print(f"last 100 / first 100: {last / first:.2f}x; per flight {first:.3f} s, {growth}: 100,000 flights through "
          f"this scheduler ~{projected / 3600:.1f} h (the last one {first + slope * 100_000:.2f} s); the scheduler "
          f"held at most {peak[0]} tasks (sampled every 0.2 s)")
    return 0


if __name__ == "__main__" and len(sys.argv) > 1 and sys.argv[1] == "_to_zarr":
    to_zarr_main(*sys.argv[2:7])
