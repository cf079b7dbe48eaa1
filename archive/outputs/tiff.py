"""Cloud-Optimized GeoTIFF assembled from tiles compressed elsewhere: no tile is decoded or recompressed.

The writer tasks of the render graph compress their own tiles (:func:`encode_tile`: floating-point
predictor + Zstandard, 512 x 512 float32, one band per tile) and compute the overviews from them
(:func:`downsample2`, each level from the one below), and put the compressed tiles in *spool* files
(:func:`write_spool`: one per task). Once a band group's writers ran, :func:`write_level_part`
copies that group's full-resolution tiles into the COG's data file in their final order
(pread + pwrite from the page cache, while the render goes on; the spool files
are deleted before they reach the disk). :func:`assemble` then lays the rest out as GDAL's COG
driver does and puts it in front of the full resolution: by ``fallocate(FALLOC_FL_INSERT_RANGE)``
where the file system allows (ext4, XFS: no byte of the full resolution is copied again), else by
copying. Without laid-out parts it copies every level from the spool files. The file:

- the TIFF (or BigTIFF, beyond 4 GiB) header, then GDAL's "ghost" structural metadata
  (``LAYOUT=IFDS_BEFORE_DATA``, ``BLOCK_ORDER=ROW_MAJOR``, ``BLOCK_LEADER=SIZE_AS_UINT4``,
  ``BLOCK_TRAILER=LAST_4_BYTES_REPEATED``, ``KNOWN_INCOMPATIBLE_EDITION=NO``), which GDAL reads as
  ``LAYOUT=COG``;
- the IFDs of the full-resolution image and of each overview (largest first), each followed by its
  long tag values;
- the tile data, smallest overview first and full resolution last (from a multiple of
  :data:`DATA_ALIGN` bytes on when laid out ahead; zeros before it); within a level band after band
  (``PlanarConfiguration`` = separate, GDAL's ``INTERLEAVE=BAND``: each band's tiles contiguous, so
  reading a few bands reads only their bytes), tiles row-major; each tile preceded by its size
  (uint32) and followed by a repeat of its last 4 bytes.

Georeferencing: ``ModelPixelScale`` + ``ModelTiepoint`` (pixel-is-area) and the EPSG code of the
projected CRS; ``GDAL_NODATA`` = nan; ``GDAL_METADATA`` holds band descriptions and tags. Overviews
follow GDAL's ``OVERVIEWS=AUTO`` (halve until the level fits in one tile), of size ceil(n / 2^k).
"""

from __future__ import annotations

import functools
import os
import struct
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from xml.sax.saxutils import escape

import numpy as np

from archive.files import write_atomic
from archive.outputs.tiff_tiles import (COMPRESSION, PREDICTOR, TILE, ZSTD_LEVEL, Spool, decode_tile,  # noqa: F401
                                        downsample2, encode_tile, float_predictor, frame, level_shapes, read_spool,
                                        write_spool)

__all__ = ["COMPRESSION", "DATA_ALIGN", "GHOST", "PREDICTOR", "TILE", "TYPES", "ZSTD_LEVEL", "LevelPart", "Spool",
           "assemble", "read_part_index", "write_level_part", "write_part_index", "decode_tile",
           "downsample2", "encode_tile", "float_predictor", "frame", "level_shapes", "read_spool", "write_spool"]


#: GDAL's structural metadata, as its COG driver writes it (read back as LAYOUT=COG).
GHOST = ("LAYOUT=IFDS_BEFORE_DATA\nBLOCK_ORDER=ROW_MAJOR\nBLOCK_LEADER=SIZE_AS_UINT4\n"
         "BLOCK_TRAILER=LAST_4_BYTES_REPEATED\nKNOWN_INCOMPATIBLE_EDITION=NO\n ")


# ---------------------------------------------------------------------------------------------
# TIFF structure
# ---------------------------------------------------------------------------------------------
_SHORT, _LONG, _DOUBLE, _ASCII, _LONG8 = 3, 4, 12, 2, 16
TYPES = {_SHORT: ("H", 2), _LONG: ("I", 4), _DOUBLE: ("d", 8), _ASCII: ("s", 1), _LONG8: ("Q", 8)}


def _entry(tag: int, kind: int, values) -> tuple[int, int, bytes, int]:
    """(tag, type, packed little-endian values, count)."""
    if kind == _ASCII:
        data = values.encode("ascii", "replace") + b"\0"
        return tag, kind, data, len(data)
    arr = np.asarray(values, dtype=f"<{TYPES[kind][0]}").ravel()
    return tag, kind, arr.tobytes(), arr.size


def _ifd_size(entries, bigtiff: bool) -> int:
    """Bytes of an IFD and its out-of-line values (each out-of-line value word-aligned)."""
    count_size, entry_size, next_size, inline = (8, 20, 8, 8) if bigtiff else (2, 12, 4, 4)
    size = count_size + entry_size * len(entries) + next_size
    for _, _, data, _ in entries:
        if len(data) > inline:
            size += len(data) + len(data) % 2
    return size


def _ifd_bytes(entries, offset: int, next_ifd: int, bigtiff: bool) -> bytes:
    """The IFD at file ``offset`` with its out-of-line values right after it."""
    count_fmt, entry_fmt, off_fmt, inline = ("<Q", "<HHQ", "<Q", 8) if bigtiff else ("<H", "<HHI", "<I", 4)
    entries = sorted(entries, key=lambda e: e[0])
    head = [struct.pack(count_fmt, len(entries))]
    tail: list[bytes] = []
    extra = offset + struct.calcsize(count_fmt) + len(entries) * (20 if bigtiff else 12) + struct.calcsize(off_fmt)
    for tag, kind, data, count in entries:
        head.append(struct.pack(entry_fmt, tag, kind, count))
        if len(data) <= inline:
            head.append(data.ljust(inline, b"\0"))
        else:
            head.append(struct.pack(off_fmt, extra))
            padded = data + b"\0" * (len(data) % 2)
            tail.append(padded)
            extra += len(padded)
    head.append(struct.pack(off_fmt, next_ifd))
    return b"".join(head + tail)


def _geokeys(epsg: int) -> list[int]:
    """GeoKeyDirectory of a projected CRS given by EPSG code, pixel-is-area."""
    keys = [(1024, 0, 1, 1),      # GTModelTypeGeoKey = projected
            (1025, 0, 1, 1),      # GTRasterTypeGeoKey = PixelIsArea
            (3072, 0, 1, epsg)]   # ProjectedCSTypeGeoKey
    return [1, 1, 0, len(keys)] + [v for k in keys for v in k]


def gdal_metadata(dataset: dict[str, str], bands: Sequence[dict[str, str]],
                  band_domains: Sequence[dict[str, dict[str, str]]] | None = None) -> str:
    """GDAL's GDAL_METADATA XML: dataset items, then per band (``sample`` 0-based) its items; a band
    item named DESCRIPTION is the band description (``role="description"``), UNITTYPE its unit
    (``role="unittype"``). ``band_domains``: per
    band, ``{domain: {name: value}}`` written with ``domain="..."`` (e.g. GDAL's standard IMAGERY
    items ``CENTRAL_WAVELENGTH_UM`` and ``FWHM_UM``, which GDAL >= 3.10 reports as the band's)."""
    items = [f'<Item name="{escape(k)}">{escape(v)}</Item>' for k, v in dataset.items()]
    for i, band in enumerate(bands):
        for k, v in band.items():
            role = {"DESCRIPTION": ' role="description"', "UNITTYPE": ' role="unittype"'}.get(k, "")
            items.append(f'<Item name="{escape(k)}" sample="{i}"{role}>{escape(v)}</Item>')
        for domain, domain_items in (band_domains[i] if band_domains else {}).items():
            for k, v in domain_items.items():
                items.append(f'<Item name="{escape(k)}" sample="{i}" domain="{escape(domain)}">{escape(v)}</Item>')
    return "<GDALMetadata>\n" + "\n".join("  " + item for item in items) + "\n</GDALMetadata>\n"


@dataclass(frozen=True)
class _Level:
    height: int
    width: int
    rows: int       # tiles down
    cols: int       # tiles across


def _levels(height: int, width: int) -> list[_Level]:
    return [_Level(h, w, -(-h // TILE), -(-w // TILE)) for h, w in level_shapes(height, width)]


@dataclass(frozen=True)
class LevelPart:
    """Bands ``band0 .. band0 + len(offsets)`` of the full resolution, already laid out (band after
    band, tiles row-major, framed) in a data file by :func:`write_level_part`: tile (r, c) of band
    ``band0 + k`` at ``offsets[k, r, c]`` (bytes from the data file's start), ``counts[k, r, c]``
    bytes long; the part fills ``start .. end`` of the data file."""

    band0: int
    start: int
    end: int
    offsets: np.ndarray
    counts: np.ndarray


def _by_area(spools: dict[tuple[int, int, int, int], str]) -> dict[tuple[int, int, int], list[tuple[int, Spool]]]:
    """Spool indexes by (level, area row, area col), each a list of (first band, spool)."""
    by_area: dict[tuple[int, int, int], list[tuple[int, Spool]]] = {}
    for (level, r, c, band0), path in spools.items():
        by_area.setdefault((level, r, c), []).append((band0, read_spool(path)))
    for parts in by_area.values():
        parts.sort(key=lambda p: p[0])
    return by_area


def _level_runs(by_area, li: int, lv: _Level, span: int, bands: Sequence[int], position: int):
    """The data of ``bands`` of level ``li`` in file order (band after band, tiles row-major) from
    byte ``position`` on: (runs [(spool path, start in spool, framed length)], offsets and counts
    (len(bands), rows, cols) of each tile's data, the position after the last tile)."""
    runs: list[tuple[str, int, int]] = []
    off = np.zeros((len(bands), lv.rows, lv.cols), np.int64)
    cnt = np.zeros((len(bands), lv.rows, lv.cols), np.int64)
    for k, b in enumerate(bands):
        for ty in range(lv.rows):
            R, i = divmod(ty, span)
            for C in range(-(-lv.cols // span)):
                sp, row = _find(by_area.get((li, R, C), []), b, li, R, C)
                n = min(span, lv.cols - C * span)
                sizes = sp.sizes[row, i * n:i * n + n]
                start = int(sp.starts[row, i * n])
                length = int((sizes + 8).sum())
                if runs and runs[-1][0] == sp.path and runs[-1][1] + runs[-1][2] == start:
                    runs[-1] = (sp.path, runs[-1][1], runs[-1][2] + length)
                else:
                    runs.append((sp.path, start, length))
                framed = np.concatenate([[0], np.cumsum(sizes + 8)[:-1]])
                off[k, ty, C * span:C * span + n] = position + framed + 4
                cnt[k, ty, C * span:C * span + n] = sizes
                position += length
    return runs, off, cnt, position


def _place(runs: Sequence[tuple[str, int, int]], at: int) -> list[tuple[str, int, int, int]]:
    """Runs with their destination offsets, laid end to end from ``at``."""
    targets = []
    for path, start, length in runs:
        targets.append((path, start, length, at))
        at += length
    return targets


def write_level_part(data: str | os.PathLike, spools: dict[tuple[int, int, int, int], str], *, height: int,
                     width: int, band0: int, nbands: int, area_tiles: int, start: int, threads: int = 1) -> LevelPart:
    """Copy the full-resolution tiles of bands band0.. from their spool files (level 0, keyed as for
    :func:`assemble`) into the existing file ``data`` from byte ``start`` on, band after band, tiles
    row-major, framed as in the COG (from the page cache: :func:`_copy_runs`); returns where they went.

    Run once per band group while the render goes on, so that most of a COG's bytes are written once,
    in their final order, while the spool files are still in the page cache (:func:`assemble` then
    puts the header and the overviews in front without copying them again where it can)."""
    lv = _levels(height, width)[0]
    runs, off, cnt, end = _level_runs(_by_area(spools), 0, lv, area_tiles, range(band0, band0 + nbands), start)
    targets = _place(runs, start)
    fd = os.open(data, os.O_WRONLY)
    try:
        _copy_runs(fd, targets, threads)
        _write_back(fd, start, end - start)
    finally:
        os.close(fd)
    return LevelPart(band0, start, end, off, cnt)


def _write_back(fd: int, start: int = 0, length: int = 0) -> None:
    """Start writing bytes start.. (``length`` 0: to the end) of ``fd`` to its disk now and drop
    those already written from the page cache (``posix_fadvise`` DONTNEED; nothing where the
    system has no such advice). For the full resolution laid out during the render: ``assemble``'s
    ``FALLOC_FL_INSERT_RANGE`` first writes every dirty page of the file and waits (a 4 GB data file
    left dirty: 0.85 s at the end of the render, on one core; bench/RESULTS.md, issue 37)."""
    advise = getattr(os, "posix_fadvise", None)
    if advise is not None:
        try:
            advise(fd, start, length, os.POSIX_FADV_DONTNEED)
        except OSError:
            pass


_PART_MAGIC = b"APRT"


def write_part_index(path: str | os.PathLike, part: LevelPart) -> None:
    """Save ``part``'s index (atomically: the part is complete once its index exists)."""
    nb, rows, cols = part.offsets.shape
    write_atomic(path, [_PART_MAGIC, struct.pack("<6q", part.band0, nb, rows, cols, part.start, part.end),
                        part.offsets.astype("<i8").tobytes(), part.counts.astype("<i8").tobytes()])


def read_part_index(path: str | os.PathLike) -> LevelPart:
    with open(path, "rb") as f:
        raw = f.read()
    if raw[:4] != _PART_MAGIC or len(raw) < 52:
        raise ValueError(f"{path}: not a COG part index")
    band0, nb, rows, cols, start, end = struct.unpack_from("<6q", raw, 4)
    n = nb * rows * cols
    if len(raw) != 52 + 16 * n:
        raise ValueError(f"{path}: truncated COG part index")
    arrays = np.frombuffer(raw, "<i8", 2 * n, 52).astype(np.int64).reshape(2, nb, rows, cols)
    return LevelPart(band0, start, end, arrays[0], arrays[1])


def assemble(dest: str | os.PathLike, spools: dict[tuple[int, int, int, int], str], *, height: int, width: int,
             nbands: int, epsg: int, transform, metadata: str, area_tiles: Sequence[int],
             threads: int = 4, level0: tuple[str, Sequence[LevelPart]] | None = None,
             insert: bool = True, compression: int = COMPRESSION, predictor: int = PREDICTOR,
             remove_spools: bool = False) -> int:
    """Write the COG at ``dest`` from spool files; returns its size in bytes (``remove_spools``:
    each spool file deleted once copied).

    spools: (level, area row, area col, first band) -> spool path; an area of level L spans
    ``area_tiles[L]`` x ``area_tiles[L]`` tiles (its spool holds them row-major, per band, for its
    bands). Every tile of every band of every level must be in some spool (ValueError otherwise).
    transform: the affine (gsd, 0, x0, 0, -gsd, y0) of the full resolution; metadata: GDAL_METADATA
    XML (:func:`gdal_metadata`); compression, predictor: the TIFF tags of how the tiles were
    encoded (:func:`encode_tile`: 50000 Zstandard or 1 none; 3 floating point or 1 none).

    level0: (data file, its parts) when the full resolution was laid out already
    (:func:`write_level_part`; level 0's spools are then not used): the header, the IFDs and the
    overviews go in front of it, their end padded to a multiple of ``DATA_ALIGN`` bytes; with
    ``insert``, by making room at the data file's start (``fallocate`` ``FALLOC_FL_INSERT_RANGE``:
    ext4, XFS; no data moves) and renaming it to ``dest``; where the file system cannot, by copying
    it behind them into ``dest`` (the same bytes).
    """
    levels = _levels(height, width)
    by_area = _by_area({k: v for k, v in spools.items() if level0 is None or k[0] > 0})

    # Data in file order: smallest overview first, full resolution last (offsets relative to the data start)
    runs: list[tuple[str, int, int]] = []
    offsets: list[np.ndarray] = [np.empty(0)] * len(levels)
    counts: list[np.ndarray] = [np.empty(0)] * len(levels)
    position = 0
    for li in range(len(levels) - 1, -1 if level0 is None else 0, -1):
        level_runs, offsets[li], counts[li], position = _level_runs(by_area, li, levels[li], area_tiles[li],
                                                                    range(nbands), position)
        runs += level_runs
    front = position   # bytes of tile data before the data file's (level0) or all of it
    if level0 is not None:
        data0, parts = level0
        offsets[0], counts[0], data0_size = _parts_index(parts, nbands, levels[0])

    ghost = GHOST.encode("ascii")
    ghost = f"GDAL_STRUCTURAL_METADATA_SIZE={len(ghost):06d} bytes\n".encode("ascii") + ghost
    a, _, x0, _, e, y0 = tuple(transform)[:6]
    main_only = [_entry(33550, _DOUBLE, [a, -e, 0.0]), _entry(33922, _DOUBLE, [0, 0, 0, x0, y0, 0]),
                 _entry(34735, _SHORT, _geokeys(epsg)), _entry(42112, _ASCII, metadata)]

    def entries(li: int, bigtiff: bool, offs: np.ndarray, cnts: np.ndarray) -> list:
        lv = levels[li]
        wide = _LONG8 if bigtiff else _LONG
        out = [_entry(254, _LONG, [0 if li == 0 else 1]), _entry(256, _LONG, [lv.width]),
               _entry(257, _LONG, [lv.height]), _entry(258, _SHORT, [32] * nbands),
               _entry(259, _SHORT, [compression]), _entry(262, _SHORT, [1]), _entry(277, _SHORT, [nbands]),
               _entry(284, _SHORT, [2]), _entry(317, _SHORT, [predictor]), _entry(322, _SHORT, [TILE]),
               _entry(323, _SHORT, [TILE]), _entry(324, wide, offs.ravel()), _entry(325, wide, cnts.ravel()),
               _entry(339, _SHORT, [3] * nbands), _entry(42113, _ASCII, "nan")]
        if nbands > 1:
            out.append(_entry(338, _SHORT, [0] * (nbands - 1)))
        return out + (main_only if li == 0 else [])

    for bigtiff in (False, True):
        header_size = 16 if bigtiff else 8
        first_ifd = header_size + len(ghost)
        first_ifd += first_ifd % 2
        sizes = [_ifd_size(entries(li, bigtiff, offsets[li], counts[li]), bigtiff) for li in range(len(levels))]
        data_start = first_ifd + sum(sizes)
        data_start += data_start % 2
        total = data_start + front
        if level0 is not None:   # the data file from a block boundary on
            data0_at = -(-total // DATA_ALIGN) * DATA_ALIGN
            total = data0_at + data0_size
        if bigtiff or total < 2**32 - 1:
            break
    if level0 is not None:
        offsets[0] = offsets[0] + (data0_at - data_start)   # every offset gets data_start below

    head = bytearray()
    head += (b"II" + struct.pack("<HHHQ", 43, 8, 0, first_ifd)) if bigtiff else (b"II" + struct.pack("<HI", 42, first_ifd))
    head += ghost
    head += b"\0" * (first_ifd - len(head))
    where = first_ifd
    for li in range(len(levels)):
        nxt = where + sizes[li] if li + 1 < len(levels) else 0
        head += _ifd_bytes(entries(li, bigtiff, offsets[li] + data_start, counts[li]), where, nxt, bigtiff)
        where += sizes[li]
    head += b"\0" * (data_start - len(head))

    targets = _place(runs, data_start)
    spent = frozenset(os.fspath(path) for path in spools.values()) if remove_spools else frozenset()
    if level0 is not None and insert and _insert_front(data0, data0_at):
        fd = os.open(data0, os.O_WRONLY)
        try:
            os.pwrite(fd, bytes(head), 0)
            _copy_runs(fd, targets, threads, spent)
        finally:
            os.close(fd)
        os.replace(data0, dest)
        return total
    fd = os.open(dest, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    try:
        os.pwrite(fd, bytes(head), 0)
        if level0 is not None:
            targets.append((os.fspath(data0), 0, data0_size, data0_at))
        _copy_runs(fd, targets, threads, spent)
        os.ftruncate(fd, total)
    finally:
        os.close(fd)
    return total


#: The full resolution's data starts at a multiple of this many bytes when laid out ahead
#: (:func:`write_level_part`): ``FALLOC_FL_INSERT_RANGE`` works in whole file-system blocks.
DATA_ALIGN = 65536
_FALLOC_FL_INSERT_RANGE = 0x20
#: File systems whose ``FALLOC_FL_INSERT_RANGE`` the COG's layout counts on (Linux: ext4, XFS).
INSERT_RANGE_FS = ("ext4", "xfs")


def _insert_front(path: str | os.PathLike, length: int) -> bool:
    """Make ``length`` bytes of room (a hole) at the start of the file ``path``, moving its data
    up without copying it (Linux ``fallocate(FALLOC_FL_INSERT_RANGE)``); False where the file
    system, the kernel or the C library cannot (the caller then copies)."""
    import ctypes

    if os.path.getsize(path) == 0:
        return False
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        fallocate = libc.fallocate
    except (OSError, AttributeError):
        return False
    fallocate.argtypes = [ctypes.c_int, ctypes.c_int, ctypes.c_int64, ctypes.c_int64]
    fallocate.restype = ctypes.c_int
    fd = os.open(path, os.O_RDWR)
    try:
        # the insert first writes every dirty page of the file and waits: the last band group's part
        # goes to disk now, and the parts already written leave the page cache (nothing to shift).
        # Only where the insert works: elsewhere the caller copies the file, from the page cache.
        if _fs_type(os.fstat(fd).st_dev) in INSERT_RANGE_FS:
            _write_back(fd)
        return fallocate(fd, _FALLOC_FL_INSERT_RANGE, 0, length) == 0
    finally:
        os.close(fd)


def _parts_index(parts: Sequence[LevelPart], nbands: int, lv: _Level) -> tuple[np.ndarray, np.ndarray, int]:
    """Offsets and counts (nbands, rows, cols) of the full resolution from the parts of its data
    file, and the file's data size; ValueError unless the parts hold every band once, end to end."""
    offsets = np.zeros((nbands, lv.rows, lv.cols), np.int64)
    counts = np.zeros_like(offsets)
    end, band = 0, 0
    for part in sorted(parts, key=lambda p: p.band0):
        if part.band0 != band or part.start != end or part.offsets.shape[1:] != (lv.rows, lv.cols):
            raise ValueError(f"no laid-out full-resolution tiles of band {band}: a band group's layout did not complete")
        nb = part.offsets.shape[0]
        offsets[band:band + nb], counts[band:band + nb] = part.offsets, part.counts
        band, end = band + nb, part.end
    if band != nbands:
        raise ValueError(f"no laid-out full-resolution tiles of band {band}: a band group's layout did not complete")
    return offsets, counts, end


def _find(parts: list[tuple[int, Spool]], band: int, level: int, r: int, c: int) -> tuple[Spool, int]:
    """The spool of an area holding ``band`` and the band's row in it."""
    for band0, sp in parts:
        if band0 <= band < band0 + sp.sizes.shape[0]:
            return sp, band - band0
    raise ValueError(f"no compressed tiles of band {band} for area ({r}, {c}) of level {level}: "
                     "a writer task did not complete")


#: File systems on which ``copy_file_range`` copies on the server (no byte through this client):
#: there runs are copied in the kernel. Elsewhere (ext4, XFS, tmpfs, Lustre) the kernel splices
#: page by page, which cost 1.5x the CPU of pread + pwrite through one buffer (512 MB between two
#: files in the page cache, ext4: 0.17 against 0.115 CPU-s; bench/RESULTS.md, issue 37).
SERVER_COPY_FS = ("nfs", "nfs4", "cifs", "smb3", "ceph")
#: Bytes of the buffer each copying thread reads a run into (pread + pwrite).
COPY_BUFFER = 4 << 20


@functools.lru_cache(maxsize=16)
def _fs_type(dev: int) -> str:
    """The type of the file system of device ``dev`` (st_dev) from /proc/self/mountinfo, '' when
    unknown."""
    want = f"{os.major(dev)}:{os.minor(dev)}"
    try:
        with open("/proc/self/mountinfo") as f:
            for line in f:
                fields = line.split()
                if len(fields) > 2 and fields[2] == want and " - " in line:
                    return line.split(" - ", 1)[1].split()[0]
    except OSError:
        pass
    return ""


def _copy_runs(fd: int, runs: list[tuple[str, int, int, int]], threads: int, remove: frozenset[str] = frozenset()) -> None:
    """Copy (source path, source offset, length, destination offset) runs into ``fd``: through a
    :data:`COPY_BUFFER` per thread (pread + pwrite), or in the kernel (``copy_file_range``) where
    the destination's file system copies on the server (:data:`SERVER_COPY_FS`). A source in
    ``remove`` is deleted by its thread once copied (the spool files: deleted one after the other
    once the COG was laid out, they took 0.42 s on one core at the end of the held-out render)."""
    by_source: dict[str, list[tuple[int, int, int]]] = {}
    for path, start, length, dest in runs:
        by_source.setdefault(path, []).append((start, length, dest))
    in_kernel = _fs_type(os.fstat(fd).st_dev) in SERVER_COPY_FS

    def copy(path: str) -> None:
        buffer = None if in_kernel else memoryview(bytearray(min(COPY_BUFFER, max(n for _, n, _ in by_source[path]))))
        src = os.open(path, os.O_RDONLY)
        try:
            for start, length, dest in by_source[path]:
                _copy(src, fd, start, length, dest, buffer)
        finally:
            os.close(src)
        if path in remove:
            os.unlink(path)

    if threads <= 1 or len(by_source) <= 1:
        for path in by_source:
            copy(path)
        return
    with ThreadPoolExecutor(threads) as pool:
        for _ in pool.map(copy, list(by_source)):
            pass


def _copy(src: int, dst: int, start: int, length: int, dest: int, buffer: memoryview | None = None) -> None:
    """Copy ``length`` bytes from ``start`` of ``src`` to ``dest`` of ``dst``: through ``buffer``
    (pread + pwrite), or without one by ``copy_file_range`` (pread/pwrite where the kernel cannot)."""
    while length > 0:
        n = 0
        if buffer is None:
            try:
                n = os.copy_file_range(src, dst, length, start, dest)
            except OSError:  # not supported between these files (other file systems, old kernels)
                n = 0
        if n <= 0:
            view = buffer if buffer is not None else memoryview(bytearray(min(length, 64 << 20)))
            n = os.preadv(src, [view[:min(length, len(view))]], start)
            if n <= 0:
                raise OSError(f"tile spool ended early at byte {start}")
            done = 0
            while done < n:
                done += os.pwrite(dst, view[done:n], dest + done)
        start, dest, length = start + n, dest + n, length - n
