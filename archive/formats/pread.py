"""Reading bands of an interleaved raw cube (ENVI BSQ, BIL, BIP) with ``os.preadv`` into arrays.

Why not ``np.memmap``: the pages of a mapped file count in the process's resident memory while the
mapping lives (the kernel maps pages around each one touched), so a render reading a few bands of a
BIL cube showed file pages in the worker's RSS: 0.5 GB of the 2.55 GB peak of the 40-cube, 300-band
paper flight. Read here, the bytes go through the page cache (shared, reclaimable, in no process's
RSS) and only the requested bands are in the process, in its own arrays. CPU, a paper cube (900
samples x 1000 lines x 300 bands, uint16 BIL), page cache warm, median of 11: contiguous bands as a
render reads them (8 or 6 bands, 32 bands) as fast as the map (4.6 vs 4.0-4.7 ms, 17 vs 16 ms);
scattered bands slower (every 12th band, 25 bands in groups of 8: 50 vs 24 ms: each needs its own
call per line, or the lines read whole, where the map touches only their pages).

Read pattern per interleave (file order ``bsq (band, line, sample)``, ``bil (line, band, sample)``,
``bip (line, sample, band)``): for BIL the requested bands, sorted, are merged into *segments*
(contiguous band ranges; two runs merge when the bands between them are at most :data:`GAP_BYTES`
per line). BSQ reads each band in one call straight into the output (swapped in place); BIL
reads each segment line by line (one call per line: the segment is contiguous inside each line
record) into a staging block of at most :data:`STAGE_BYTES`, then copies the bands out; BIP reads
blocks of whole lines (a band is one value per pixel record: nothing smaller is contiguous). The
staging arrays have the file's byte order, so the copy out converts to native order. No file
stays open.

BIL lines not in the page cache (a cold file, or pages the kernel dropped since: this project's VM
drops page-cache folios nobody touched for seconds, whatever the free memory; bench/RESULTS.md)
are asked of the disk together: each staging block's lines are first read with ``RWF_NOWAIT``
(only what the page cache holds, no extra call when it holds everything), then the kernel reads
the rest of every short line at once (``posix_fadvise`` WILLNEED), and only then are they read
whole, instead of one synchronous disk read per line. A 15-band group of a paper cube, the file
evicted first: 28-39 ms instead of 74-90 ms (readahead on or off); in the page cache: 6.8-8.1 ms
against 6.8-7.3. Held-out flight to Zarr, sampled thread states: task threads waiting in such reads
while a core idled 0.2-0.7 core-seconds (2 runs), 0.3-1.0 with one read per line (2 runs, alternated).
A file system that refuses ``RWF_NOWAIT`` (EOPNOTSUPP: tmpfs, for one) is read line by line, as before.
"""

from __future__ import annotations

import errno
import os
from collections.abc import Sequence

import numpy as np

from archive.errors import FormatError

__all__ = ["GAP_BYTES", "STAGE_BYTES", "read_bands"]

#: Bytes of unwanted bands per line read rather than split a read in two (one call costs ~2 us, as
#: much as copying ~20-40 KiB; 25 bands, every 12th, of a paper cube in groups of 8: 60 ms with
#: 16 KiB, 50 ms with 64 KiB or 256 KiB).
GAP_BYTES = 64 * 1024
#: Largest staging block (BIL and BIP): bounded memory whatever the cube's size.
STAGE_BYTES = 4 * 1024**2


def _read_full(fd: int, buf: memoryview, offset: int, path) -> None:
    """Fill ``buf`` (bytes) from ``offset``; a short read (file truncated since it was opened) raises."""
    done, size = 0, len(buf)
    while done < size:
        n = os.preadv(fd, [buf[done:]], offset + done)
        if n <= 0:
            raise FormatError(path, f"data file ended at byte {offset + done} while reading "
                                    f"{size} bytes from {offset}", "re-copy the cube")
        done += n


def _read_lines(fd: int, view: memoryview, row: int, offsets: Sequence[int], path, nowait: bool) -> bool:
    """Fill ``view[i * row:(i + 1) * row]`` from ``offsets[i]`` for each line i: what the page cache
    holds read at once (``RWF_NOWAIT``, where ``nowait``), the rest asked of the disk for all lines
    together (WILLNEED), then read. Returns whether to try ``RWF_NOWAIT`` on the file's next lines
    (False once its file system refused it)."""
    flag = getattr(os, "RWF_NOWAIT", None) if nowait else None
    if flag is None:
        for i, off in enumerate(offsets):
            _read_full(fd, view[i * row:(i + 1) * row], off, path)
        return nowait
    short: list[tuple[int, int]] = []   # (line, bytes already read)
    for i, off in enumerate(offsets):
        try:
            n = os.preadv(fd, [view[i * row:(i + 1) * row]], off, flag)
        except BlockingIOError:   # nothing of it in the page cache
            n = 0
        except OSError as exc:
            if exc.errno not in (errno.EOPNOTSUPP, errno.EINVAL):
                raise
            nowait = False    # this file system reads only blocking: this line on, as the short ones
            short += [(j, 0) for j in range(i, len(offsets))]
            break
        if n < row:
            short.append((i, n))
    for i, n in short:
        try:
            os.posix_fadvise(fd, offsets[i] + n, row - n, os.POSIX_FADV_WILLNEED)
        except OSError:   # advice only: the read below fetches the line anyway
            break
    for i, n in short:
        _read_full(fd, view[i * row + n:(i + 1) * row], offsets[i] + n, path)
    return nowait


def _segments(wanted: Sequence[int], per_band: int) -> list[tuple[int, int]]:
    """Sorted distinct bands -> [(first, stop)) ranges, merging runs whose gap is <= GAP_BYTES."""
    segs: list[list[int]] = []
    for b in wanted:
        if segs and (b - segs[-1][1]) * per_band <= GAP_BYTES:
            segs[-1][1] = b + 1
        else:
            segs.append([b, b + 1])
    return [(a, z) for a, z in segs]


def read_bands(path: str | os.PathLike, dtype: np.dtype, interleave: str, shape: tuple[int, int, int],
               offset: int, idx: Sequence[int]) -> np.ndarray:
    """Bands ``idx`` (checked by the caller, any order, repeats allowed) of the raw cube at ``path``
    as ``(len(idx), lines, samples)`` in native byte order. ``dtype`` is the file's (byte order
    included); ``shape`` is ``(bands, lines, samples)``; ``offset`` the header offset in bytes."""
    nbands, lines, samples = shape
    dtype = np.dtype(dtype)
    item = dtype.itemsize
    out = np.empty((len(idx), lines, samples), dtype.newbyteorder("="))
    where: dict[int, list[int]] = {}
    for k, b in enumerate(idx):
        where.setdefault(int(b), []).append(k)
    wanted = sorted(where)
    if not wanted or out.size == 0:
        return out
    fd = os.open(path, os.O_RDONLY)
    nowait = True   # RWF_NOWAIT until the file system refuses it
    try:
        if interleave == "bsq":   # a band is contiguous: one read each, straight into the output
            for b in wanted:
                first, *repeats = where[b]
                _read_full(fd, memoryview(out[first]).cast("B"), offset + b * lines * samples * item, path)
                if not dtype.isnative and item > 1:
                    out[first].byteswap(inplace=True)
                for k in repeats:
                    out[k] = out[first]
        elif interleave == "bil":
            record = nbands * samples * item
            for a, z in _segments(wanted, samples * item):
                row = (z - a) * samples * item
                block = max(1, min(lines, STAGE_BYTES // row))
                stage = np.empty((block, z - a, samples), dtype)
                view = memoryview(stage).cast("B")
                for l0 in range(0, lines, block):
                    l1 = min(lines, l0 + block)
                    nowait = _read_lines(fd, view, row, range(offset + l0 * record + a * samples * item,
                                                              offset + l1 * record + a * samples * item, record),
                                         path, nowait)
                    for b in range(a, z):
                        for k in where.get(b, ()):
                            out[k, l0:l1] = stage[:l1 - l0, b - a]
        elif interleave == "bip":
            row = samples * nbands * item
            block = max(1, min(lines, STAGE_BYTES // row))
            stage = np.empty((block, samples, nbands), dtype)
            view = memoryview(stage).cast("B")
            for l0 in range(0, lines, block):
                l1 = min(lines, l0 + block)
                _read_full(fd, view[:(l1 - l0) * row], offset + l0 * row, path)
                for b in wanted:
                    for k in where[b]:
                        out[k, l0:l1] = stage[:l1 - l0, :, b]
        else:
            raise FormatError(path, f"unknown interleave {interleave!r}", "use bil, bip or bsq")
    finally:
        os.close(fd)
    return out
