"""The tiles of a COG (:mod:`archive.outputs.tiff`), compressed where they are rendered: the floating-point
predictor + Zstandard codec of one 512 x 512 float32 band tile (:func:`encode_tile`, :func:`decode_tile`),
the overviews' 2 x 2 NaN-mean (:func:`downsample2`, :func:`level_shapes`), and the *spool* files a writer
task puts its compressed tiles in (:func:`write_spool`, :func:`read_spool`)."""

from __future__ import annotations

import functools
import os
import struct
import threading
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from archive.files import write_atomic

__all__ = ["COMPRESSION", "PREDICTOR", "SPARSE_SHARE", "TILE", "ZSTD_LEVEL", "Spool", "decode_tile", "downsample2",
           "encode_tile", "float_predictor", "frame", "level_shapes", "read_spool", "write_spool"]

#: COG tile edge, pixels (GDAL's default block size).
TILE = 512
#: TIFF compression code of Zstandard (libtiff COMPRESSION_ZSTD).
COMPRESSION = 50000
#: Floating-point horizontal predictor (TIFF technical note 3).
PREDICTOR = 3
#: Zstandard level (negative: zstd's fast levels; any level decodes the same). Measured with the
#: predictor on rendered radiance tiles, one thread (bench/RESULTS.md, issue 10): -3 ~1250 MB/s at
#: ratio 1.62 (Zarr's Blosc LZ4: 1.60), 1 ~600 MB/s at 1.79, 3 ~300 MB/s; DEFLATE 1 ~110 MB/s.
ZSTD_LEVEL = -3

_SPOOL_MAGIC = b"ASPL"


# ---------------------------------------------------------------------------------------------
# Tiles
# ---------------------------------------------------------------------------------------------
@functools.lru_cache(maxsize=8)
def _codec(level: int = ZSTD_LEVEL):
    """The numcodecs Zstd of ``level`` (one per process and level: stateless, safe across threads)."""
    import numcodecs

    return numcodecs.Zstd(level=level)


_buffers = threading.local()


def float_predictor(tile: np.ndarray) -> np.ndarray:
    """TIFF's floating-point horizontal predictor (predictor 3, libtiff's ``fpDiff``) of a (h, w)
    float32 tile: (h, 4 w) uint8, each row's bytes in planes, most significant byte first (byte k
    of pixel x at column ``k * w + x``), each byte then replaced by its difference (modulo 256) with
    the previous one along the row. The array is this thread's buffer, valid until
    its next call.

    The planes come from the pixels' bits as uint32, each shifted and narrowed into its plane in one
    pass (no byte-strided transpose copy); ``tile`` may be a strided view (rows of a larger chunk).
    """
    h, w = tile.shape
    bits = np.asarray(tile, dtype="<f4").view("<u4")
    # this thread's buffers, reused tile after tile (the encoded bytes are a copy of them)
    planes, data = _scratch("planes", (h, 4, w), np.uint8), _scratch("differences", (h, 4 * w), np.uint8)
    for k, shift in enumerate((24, 16, 8)):
        np.right_shift(bits, shift, out=planes[:, k, :], casting="unsafe")
    np.copyto(planes[:, 3, :], bits, casting="unsafe")   # the low byte: narrowing keeps it
    rows = planes.reshape(h, 4 * w)
    data[:, 0] = rows[:, 0]
    np.subtract(rows[:, 1:], rows[:, :-1], out=data[:, 1:])
    return data


def encode_tile(tile: np.ndarray, level: int | None = ZSTD_LEVEL, predictor: int = PREDICTOR) -> bytes:
    """One (TILE, TILE) float32 tile as TIFF stores it: with ``predictor`` 3 the floating-point
    predictor (:func:`float_predictor`), then Zstandard at ``level`` (None: stored uncompressed;
    predictor 1: none)."""
    if predictor == 3:
        data = float_predictor(tile)
    elif predictor == 1:
        data = np.ascontiguousarray(tile, dtype="<f4")
    else:
        raise ValueError(f"TIFF predictor {predictor!r}: 1 (none) or 3 (floating point)")
    return data.tobytes() if level is None else bytes(_codec(level).encode(data))


def decode_tile(data: bytes, shape: tuple[int, int] = (TILE, TILE), compressed: bool = True,
                predictor: int = PREDICTOR) -> np.ndarray:
    """Inverse of :func:`encode_tile` (for checks)."""
    h, w = shape
    raw = np.frombuffer(_codec().decode(data) if compressed else data, np.uint8)
    if predictor == 1:
        return raw.view("<f4").reshape(h, w).copy()
    rows = np.cumsum(raw.reshape(h, 4 * w), axis=1, dtype=np.uint8)
    return rows.reshape(h, 4, w).transpose(0, 2, 1)[:, :, ::-1].copy().view("<f4").reshape(h, w)


def frame(data: bytes) -> tuple[bytes, bytes, bytes]:
    """(leader, data, trailer) of a tile as laid out in the file: its size as uint32 little-endian
    before it and its last 4 bytes repeated after it (GDAL's BLOCK_LEADER / BLOCK_TRAILER)."""
    return struct.pack("<I", len(data)), data, data[-4:]


#: Up to this share of a block's windows holding a non-finite pixel, :func:`downsample2` averages
#: those windows one by one (gathered by index); beyond it, every window the NaN-aware way.
SPARSE_SHARE = 0.25


def downsample2(block: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """NaN-aware 2 x 2 average of ``block`` (..., h, w) float32 -> (..., ceil(h/2), ceil(w/2)) float32
    (into ``out`` when given, of that shape; returned).

    Each output pixel is the mean of the finite input pixels of its 2 x 2 window (a window reaching
    past an odd edge averages what it has), NaN where none is finite (GDAL's AVERAGE overview
    resampling with a NaN nodata). Summed in float32 as (top-left + bottom-left) + (top-right +
    bottom-right), then divided by the count; no-data pixels are ``np.nan`` exactly.

    Every window is first summed as if all were finite and scaled by 1/4 (x * 0.25 is x / 4, bit for
    bit); the windows whose sum is not finite (a NaN or infinite pixel, or an overflow) are then
    averaged the NaN-aware way (:func:`_nan_mean`): one by one, gathered by index, where they are
    up to :data:`SPARSE_SHARE` of the windows (a tile at a coverage edge), else all windows (the
    same bits for the finite ones); the windows past an odd edge on their own.
    """
    block = np.asarray(block, np.float32)
    *lead, h, w = block.shape
    h2, w2 = h // 2, w // 2   # whole windows down and across
    if out is None:
        out = np.empty((*lead, h - h2, w - w2), np.float32)
    if h2 and w2:
        inner = out[..., :h2, :w2]
        pairs = np.add(block[..., 0:2 * h2:2, :2 * w2], block[..., 1:2 * h2:2, :2 * w2],
                       out=_scratch("pairs", (*lead, h2, 2 * w2), np.float32))
        np.add(pairs[..., 0::2], pairs[..., 1::2], out=inner)
        bad = np.isfinite(inner, out=_scratch("bad", inner.shape, np.bool_))
        np.logical_not(bad, out=bad)
        inner *= np.float32(0.25)
        at = np.flatnonzero(bad)
        if at.size > SPARSE_SHARE * bad.size:   # many: the NaN-aware mean of every window
            inner[...] = _nan_mean(*(block[..., i:2 * h2:2, j:2 * w2:2] for j in (0, 1) for i in (0, 1)))
        elif at.size:   # a few (a coverage edge): those windows' pixels gathered by index
            *lead_at, r, c = np.unravel_index(at, bad.shape)
            if not lead and block.strides[1] == 4 and block.strides[0] % 4 == 0:   # a tile, rows of pixels
                step = block.strides[0] // 4   # pixels from one row to the next (a view of a chunk: its width)
                flat = np.lib.stride_tricks.as_strided(block, ((h - 1) * step + w,), (4,), writeable=False)
                top_left = 2 * r * step + 2 * c
                pixels = [flat.take(top_left + k) for k in (0, step, 1, step + 1)]
            else:
                pixels = [block[(*lead_at, 2 * r + i, 2 * c + j)] for j in (0, 1) for i in (0, 1)]
            inner[(*lead_at, r, c)] = _nan_mean(*pixels)
    if h % 2:   # the last row of windows: its bottom pixels past the edge
        row = block[..., h - 1, :]
        left = row[..., 0::2]
        right = np.full(left.shape, np.nan, np.float32)
        right[..., :w2] = row[..., 1::2]
        none = np.full(left.shape, np.nan, np.float32)
        out[..., h2, :] = _nan_mean(left, none, right, none)
    if w % 2 and h2:   # the last column of windows (above the last row): its right pixels past the edge
        column = block[..., :2 * h2, w - 1]
        none = np.full((*lead, h2), np.nan, np.float32)
        out[..., :h2, w2] = _nan_mean(column[..., 0::2], column[..., 1::2], none, none)
    return out


def _scratch(name: str, shape: tuple[int, ...], dtype) -> np.ndarray:
    """This thread's scratch array ``name`` of ``shape`` (contents undefined), from a buffer kept
    between calls (the predictor's byte planes, the overviews' sums): a fresh 1-2 MB temporary per
    tile or chunk was given back to the system and faulted in again under Dask's malloc settings
    (``MALLOC_TRIM_THRESHOLD_``), ~0.4 ms per chunk."""
    n = int(np.prod(shape)) * np.dtype(dtype).itemsize
    buffers = getattr(_buffers, "scratch", None)
    if buffers is None:
        buffers = _buffers.scratch = {}
    raw = buffers.get(name)
    if raw is None or raw.size < n:
        raw = buffers[name] = np.empty(max(n, 1), np.uint8)
    return raw[:n].view(dtype).reshape(shape)


def _nan_mean(top_left: np.ndarray, bottom_left: np.ndarray, top_right: np.ndarray,
              bottom_right: np.ndarray) -> np.ndarray:
    """The NaN-aware mean of windows given as their four pixels (same shapes, float32): non-finite
    pixels count as absent (+0 in the sum), (tl + bl) + (tr + br) in float32 divided by the uint8
    count of finite pixels; ``np.nan`` exactly where none is finite."""
    zeroed, count = [], None
    for pixels in (top_left, bottom_left, top_right, bottom_right):
        finite = np.isfinite(pixels)
        zeroed.append(np.where(finite, pixels, np.float32(0)))
        count = finite.view(np.uint8) if count is None else count + finite.view(np.uint8)
    total = (zeroed[0] + zeroed[1]) + (zeroed[2] + zeroed[3])
    mean = np.full(total.shape, np.nan, np.float32)
    return np.divide(total, count, out=mean, where=count > 0)


def level_shapes(height: int, width: int) -> list[tuple[int, int]]:
    """(height, width) of the full resolution and of each overview: halved (rounding up) while the
    previous level is larger than one tile (GDAL's ``OVERVIEWS=AUTO``)."""
    shapes = [(height, width)]
    while max(shapes[-1]) > TILE:
        h, w = shapes[-1]
        shapes.append((-(-h // 2), -(-w // 2)))
    return shapes


# ---------------------------------------------------------------------------------------------
# Spool files: the compressed tiles of one task (one area of one level, a range of bands)
# ---------------------------------------------------------------------------------------------
def write_spool(path: str | os.PathLike, tiles: Sequence[Sequence[bytes]]) -> None:
    """Write tiles[band][k] (compressed, k row-major over the task's area) framed, atomically
    (a temporary file renamed into place: a task run again after a worker died replaces it)."""
    nbands, ntiles = len(tiles), len(tiles[0]) if tiles else 0
    sizes = np.array([len(t) for band in tiles for t in band], "<u4")
    parts: list[bytes] = [_SPOOL_MAGIC + struct.pack("<III", 1, nbands, ntiles), sizes.tobytes()]
    for band in tiles:
        for t in band:
            parts.extend(frame(t))
    write_atomic(path, parts)


@dataclass(frozen=True)
class Spool:
    """Index of a spool file: compressed size of tile k of band b at ``sizes[b, k]``; its framed
    bytes (leader, data, trailer) start at ``starts[b, k]`` in the file."""

    path: str
    sizes: np.ndarray
    starts: np.ndarray


def read_spool(path: str | os.PathLike) -> Spool:
    with open(path, "rb") as f:
        head = f.read(16)
        if len(head) != 16 or head[:4] != _SPOOL_MAGIC:
            raise ValueError(f"{path}: not a tile spool file")
        _, nbands, ntiles = struct.unpack("<III", head[4:])
        sizes = np.frombuffer(f.read(4 * nbands * ntiles), "<u4").astype(np.int64).reshape(nbands, ntiles)
    framed = (sizes + 8).ravel()
    starts = 16 + 4 * sizes.size + np.concatenate([[0], np.cumsum(framed)[:-1]]).reshape(sizes.shape)
    return Spool(os.fspath(path), sizes, starts)

