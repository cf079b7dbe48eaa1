"""Band-group reads of raw BIL cubes, in the page cache or evicted from it (archive.formats.pread).

    python bench/bench_pread.py FLIGHT_DIR [--bands 15] [--rounds 3]

For each ``*.bil`` cube of FLIGHT_DIR (a simulated flight, e.g. bench_outputs.py's held-out one) and
each round, reads one group of ``--bands`` contiguous bands (a different group each round) with
:func:`archive.formats.pread.read_bands` four ways, alternated: the file evicted from the page cache
first (``posix_fadvise`` DONTNEED) or left in it, each with the lines the cache lacks asked of the
disk together (``RWF_NOWAIT`` then WILLNEED: the package's reader) or read one synchronous call per
line (the reader as it was: ``os.RWF_NOWAIT`` hidden from it). Prints the median milliseconds per
band group of each way and the ratios; checks that both ways read the same bytes.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from pathlib import Path

import numpy as np

from archive.formats import pread
from archive.formats.envi import EnviCube


def _evict(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
    finally:
        os.close(fd)


def _read(cube: EnviCube, bands: list[int], batched: bool) -> tuple[float, np.ndarray]:
    hidden = None
    if not batched:
        hidden = os.RWF_NOWAIT
        del os.RWF_NOWAIT
    try:
        t = time.perf_counter()
        got = cube.bands(bands)
        return (time.perf_counter() - t) * 1000, got
    finally:
        if hidden is not None:
            os.RWF_NOWAIT = hidden


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("flight", type=Path)
    ap.add_argument("--bands", type=int, default=15)
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args()
    if not hasattr(os, "RWF_NOWAIT"):
        raise SystemExit("this platform has no RWF_NOWAIT: the reader reads line by line anyway")
    cubes = [EnviCube(p) for p in sorted(args.flight.glob("*.bil"))]
    if not cubes:
        raise SystemExit(f"{args.flight}: no .bil cube")
    times: dict[tuple[str, str], list[float]] = {}
    for r in range(args.rounds):
        for cube in cubes:
            b0 = (r * 7 * args.bands) % max(1, cube.header.bands - args.bands)
            bands = list(range(b0, b0 + args.bands))
            values = []
            for cache in ("evicted", "cached"):
                for way in (("batched", "per line") if r % 2 == 0 else ("per line", "batched")):
                    if cache == "evicted":
                        _evict(cube.path)
                    else:
                        cube.bands(bands)   # warm
                    ms, got = _read(cube, bands, way == "batched")
                    times.setdefault((cache, way), []).append(ms)
                    values.append(got)
            assert all(np.array_equal(values[0], v) for v in values[1:]), f"{cube.path}: ways disagree"
    h = cubes[0].header
    print(f"{len(cubes)} cubes ({h.samples} samples x {h.lines} lines x {h.bands} bands, {h.interleave}), "
          f"{args.bands}-band groups, {args.rounds} rounds")
    print("| page cache | lines missing asked together (ms) | one read per line (ms) | ratio |")
    print("|---|---|---|---|")
    for cache in ("evicted", "cached"):
        a, b = statistics.median(times[cache, "batched"]), statistics.median(times[cache, "per line"])
        print(f"| {cache} | {a:.1f} | {b:.1f} | {a / b:.2f} |")


if __name__ == "__main__":
    main()
