"""Sinks that write an output format tile by tile from the render graph's tasks: ENVI BSQ and COG.

(The Zarr sink is :class:`archive.outputs.MosaicStore`.) A sink is a small picklable handle; its
``open_tile(band0, tile, nbands)`` returns a :class:`TileWriter` for one output tile (1024 x 1024 px,
chunk-aligned) of a range of bands. Tiles never share bytes, so tasks need no locks.
"""

from __future__ import annotations

import errno
import os
import sys
import threading
from collections.abc import Sequence
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

__all__ = ["CHUNK", "CogSink", "EnviSink", "TileWriter", "chunk_buffer"]

#: Output tile = Zarr chunk edge, pixels.
CHUNK = 1024

_local = threading.local()


def chunk_buffer(width: int = CHUNK) -> np.ndarray:
    """This thread's reusable (CHUNK, width) float32 C-contiguous tile buffer (contents undefined):
    one per thread and width (CHUNK for chunk tiles, a row strip's width for ENVI)."""
    buffers = getattr(_local, "buffers", None)
    if buffers is None:
        buffers = _local.buffers = {}
    buffer = buffers.get(width)
    if buffer is None:
        if len(buffers) > 2:   # strips of several outputs' widths: keep the chunk buffer only
            for w in [w for w in buffers if w != CHUNK]:
                del buffers[w]
        buffer = buffers[width] = np.empty((CHUNK, width), np.float32)
    return buffer


# ---------------------------------------------------------------------------------------------
# Tile writers: what the graph's writer tasks write one output tile through
# ---------------------------------------------------------------------------------------------
class TileWriter:
    """Writes one output tile (row0, col0, height, width) of ``nbands`` bands from band ``band0``.

    ``buffer()`` is this thread's reusable (CHUNK, CHUNK) float32 buffer (an ENVI row strip's:
    (CHUNK, strip width)); ``write(b, chunk)`` takes band ``band0 + b`` as such a float32
    C-contiguous array whose part outside the grid is NaN; ``close()`` finishes the tile and returns
    what the graph passes on (COG: the tile's first overview level; others: None). Usable as a
    context manager (closed on success only).
    """

    def __init__(self, band0: int, tile: tuple[int, int, int, int]):
        self.band0, self.tile = band0, tile

    def buffer(self) -> np.ndarray:
        return chunk_buffer()

    def write(self, b: int, chunk: np.ndarray) -> None:
        raise NotImplementedError

    def close(self):
        return None

    def abort(self) -> None:
        """Release what the writer holds without finishing the tile (after an error)."""

    def __enter__(self):
        return self

    def __exit__(self, kind, value, tb) -> None:
        if kind is not None:
            self.abort()


def _all_nan(chunk: np.ndarray) -> bool:
    return bool(np.isnan(chunk[CHUNK // 2]).all() and np.isnan(chunk).all())


def _check_tile(tile, height: int, width: int, size: tuple[int, int] = (CHUNK, CHUNK)) -> None:
    row0, col0, h, w = tile
    th, tw = size
    if row0 % th or col0 % tw or not (0 < h <= th and 0 < w <= tw) \
            or h != min(th, height - row0) or w != min(tw, width - col0):
        raise ValueError(f"tile {tile} is not one {th} x {tw} px tile of a {height} x {width} mosaic")


#: Widest ENVI tile (px): tiles are CHUNK rows x up to this many columns. Mosaics up to this wide are
#: written in whole-width row strips; wider ones in strips of this width, so that the renders a tile
#: waits for stay those near it (a whole-width strip of a wide flight would touch every pass).
ENVI_STRIP_MAX = 4 * CHUNK


@dataclass(frozen=True)
class EnviSink:
    """ENVI BSQ data file being written: float32 little-endian (band, y, x), preallocated.

    Its tiles are CHUNK rows x up to ENVI_STRIP_MAX columns (:attr:`tile_size`): a mosaic at most
    that wide is written in whole-width row strips, each band of a strip with ONE ``os.pwrite`` (a
    band's rows are contiguous in BSQ; a 1024-px tile took one call per row, ~5 us each: seconds of
    CPU for a 300-band mosaic); wider mosaics one call per row of 4 x 1024 px. Nothing is
    memory-mapped: the written pages are the page cache's, not the process's.
    """

    data: str
    nbands: int
    height: int
    width: int

    saturation: ClassVar[bool] = False
    blank_tiles: ClassVar[bool] = True
    overview_levels: ClassVar[int] = 0

    @property
    def tile_size(self) -> tuple[int, int]:
        """(height, width) of the graph's output tiles for this sink, pixels."""
        return (CHUNK, min(self.width, ENVI_STRIP_MAX))

    @classmethod
    def create(cls, data: str | os.PathLike, nbands: int, height: int, width: int) -> EnviSink:
        """Create the data file at its full size (space reserved when the file system can:
        a full disk fails here, before any rendering)."""
        size = nbands * height * width * 4
        fd = os.open(data, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        try:
            try:
                os.posix_fallocate(fd, 0, size)
            except OSError as exc:
                if exc.errno == errno.ENOSPC:
                    raise
                os.ftruncate(fd, size)  # no fallocate here (EOPNOTSUPP, EINVAL): a sparse file
        finally:
            os.close(fd)
        return cls(os.fspath(data), nbands, height, width)

    def open_tile(self, band0: int, tile, nbands: int) -> _EnviTileWriter:
        _check_tile(tile, self.height, self.width, self.tile_size)
        if not 0 <= band0 < band0 + nbands <= self.nbands:
            raise ValueError(f"bands {band0}..{band0 + nbands - 1} of a {self.nbands}-band ENVI file")
        return _EnviTileWriter(self, band0, tile)


class _EnviTileWriter(TileWriter):
    def __init__(self, sink: EnviSink, band0: int, tile):
        super().__init__(band0, tile)
        self.sink = sink
        self.fd = os.open(sink.data, os.O_WRONLY)

    def buffer(self) -> np.ndarray:
        return chunk_buffer(self.sink.tile_size[1])

    def write(self, b: int, chunk: np.ndarray) -> None:
        row0, col0, h, w = self.tile
        s = self.sink
        if sys.byteorder != "little":
            chunk = chunk.astype("<f4")
        base = (((self.band0 + b) * s.height + row0) * s.width + col0) * 4
        if w == s.width:  # whole rows: one contiguous range
            os.pwrite(self.fd, chunk[:h, :w] if w == chunk.shape[1] else np.ascontiguousarray(chunk[:h, :w]), base)
            return
        stride = s.width * 4
        for r in range(h):
            os.pwrite(self.fd, chunk[r, :w], base + r * stride)

    def close(self):
        os.close(self.fd)

    def abort(self) -> None:
        os.close(self.fd)


@dataclass(frozen=True)
class CogSink:
    """A COG being written as spool files of compressed tiles in the directory ``spool``.

    Levels: 0 is the full resolution, 1.. the overviews (:func:`archive.cog.level_shapes`). A writer
    task of output tile (R, C) spools its (up to) 2 x 2 full-resolution COG tiles per band and the
    tile of level 1 it covers, (R, C); an overview task of level L >= 2 spools tile (r, c) of
    level L from the (up to) 2 x 2 tiles (2r.., 2c..) of level L - 1 (:meth:`overview`).
    """

    spool: str
    nbands: int
    height: int
    width: int
    nearest: bool = False   #: overviews by nearest neighbour (top-left of each 2 x 2) instead of averages

    saturation: ClassVar[bool] = False
    blank_tiles: ClassVar[bool] = True

    @classmethod
    def create(cls, spool: str | os.PathLike, nbands: int, height: int, width: int,
               nearest: bool = False) -> CogSink:
        os.mkdir(spool)
        return cls(os.fspath(spool), nbands, height, width, nearest)

    def downsample(self, block: np.ndarray) -> np.ndarray:
        """One overview step of ``block`` (..., h, w) -> (..., ceil(h/2), ceil(w/2)) float32: the
        NaN-aware 2 x 2 average (:func:`archive.cog.downsample2`), or with ``nearest`` each window's
        top-left pixel."""
        from archive.cog import downsample2

        return np.array(block[..., ::2, ::2]) if self.nearest else downsample2(block)

    @property
    def levels(self) -> list[tuple[int, int]]:
        """(height, width) of every level, full resolution first."""
        from archive.cog import level_shapes

        return level_shapes(self.height, self.width)

    @property
    def overview_levels(self) -> int:  # type: ignore[override]
        return len(self.levels) - 1

    def tiles(self, level: int) -> tuple[int, int]:
        """(rows, cols) of COG tiles of ``level``."""
        from archive.cog import TILE

        h, w = self.levels[level]
        return -(-h // TILE), -(-w // TILE)

    def children(self, level: int, r: int, c: int) -> list[tuple[int, int] | None]:
        """The tiles (row, col) of ``level - 1`` that tile (r, c) of ``level`` >= 2 is made from, as
        [top-left, top-right, bottom-left, bottom-right], None beyond the level's edge."""
        rows, cols = self.tiles(level - 1)
        return [(2 * r + i, 2 * c + j) if 2 * r + i < rows and 2 * c + j < cols else None
                for i in (0, 1) for j in (0, 1)]

    def spool_path(self, level: int, r: int, c: int, band0: int) -> str:
        return os.path.join(self.spool, f"L{level}-{r}-{c}-{band0}.tiles")

    def open_tile(self, band0: int, tile, nbands: int) -> _CogTileWriter:
        _check_tile(tile, self.height, self.width)
        if not 0 <= band0 < band0 + nbands <= self.nbands:
            raise ValueError(f"bands {band0}..{band0 + nbands - 1} of a {self.nbands}-band COG")
        return _CogTileWriter(self, band0, tile, nbands)

    def overview(self, level: int, r: int, c: int, band0: int, nbands: int,
                 children: Sequence[np.ndarray | None]) -> np.ndarray | None:
        """Spool tile (r, c) of overview ``level`` >= 2 for bands band0.. from the quarters its
        children computed (each child of level - 1 returns its own 2 x 2 average, (nbands, <= TILE/2,
        <= TILE/2), in :meth:`children` order; None: all NaN or beyond the edge). Returns this
        tile's quarter of the next level (its 2 x 2 average) when there is one and some value is
        finite, else None: only quarter-size blocks travel between tasks."""
        from archive.cog import TILE, encode_tile, write_spool

        h, w = self.levels[level]
        h, w = min(TILE, h - r * TILE), min(TILE, w - c * TILE)
        further = level + 1 <= self.overview_levels
        present = [(k, child) for k, child in enumerate(children) if child is not None]
        quarter = np.full((nbands, -(-h // 2), -(-w // 2)), np.nan, np.float32) if further and present else None
        tile = chunk_buffer()[:TILE, :TILE]
        encoded = []
        for b in range(nbands):
            if not present:
                encoded.append([_nan_tile()])
                continue
            tile[...] = np.nan
            half = TILE // 2
            for k, child in present:
                i, j = divmod(k, 2)
                ch, cw = child.shape[1:]
                tile[i * half:i * half + ch, j * half:j * half + cw] = child[b]
            encoded.append([encode_tile(tile)])
            if quarter is not None:
                quarter[b] = self.downsample(tile[:h, :w])
        write_spool(self.spool_path(level, r, c, band0), encoded)
        return quarter if quarter is not None and np.isfinite(quarter).any() else None


def _nan_tile() -> bytes:
    """The compressed all-NaN COG tile (computed once per process)."""
    data = getattr(_nan_tile, "value", None)
    if data is None:
        from archive.cog import TILE, encode_tile

        data = _nan_tile.value = encode_tile(np.full((TILE, TILE), np.nan, np.float32))
    return data


class _CogTileWriter(TileWriter):
    """Compresses each band's COG tiles and its first overview level tile as they come, keeps the
    2 x 2 average of the latter (this tile's quarter of level 2); writes both spool files on close."""

    def __init__(self, sink: CogSink, band0: int, tile, nbands: int):
        from archive.cog import TILE

        super().__init__(band0, tile)
        self.sink, self.nbands = sink, nbands
        h, w = tile[2:]
        self.rows, self.cols = -(-h // TILE), -(-w // TILE)
        self.encoded: list[list[bytes]] = [[] for _ in range(nbands)]
        self.first: list[bytes | None] = [None] * nbands
        self.levels = sink.overview_levels
        self.oh, self.ow = -(-h // 2), -(-w // 2)  # extent of this tile in level 1
        self.block = (np.full((nbands, -(-self.oh // 2), -(-self.ow // 2)), np.nan, np.float32)
                      if self.levels >= 2 else None)
        self.finite = False

    def write(self, b: int, chunk: np.ndarray) -> None:
        from archive.cog import TILE, encode_tile

        if _all_nan(chunk):
            self.encoded[b] = [_nan_tile()] * (self.rows * self.cols)
            self.first[b] = _nan_tile()
            return
        self.encoded[b] = [encode_tile(chunk[i * TILE:(i + 1) * TILE, j * TILE:(j + 1) * TILE])
                           for i in range(self.rows) for j in range(self.cols)]
        if self.levels >= 1:
            down = self.sink.downsample(chunk)  # (TILE, TILE): NaN beyond the grid, as the chunk
            self.first[b] = encode_tile(down)
            if self.block is not None:
                self.block[b] = self.sink.downsample(down[:self.oh, :self.ow])
                self.finite = True

    def close(self):
        from archive.cog import write_spool

        missing = [b for b, tiles in enumerate(self.encoded) if not tiles]
        if missing:
            raise ValueError(f"band {self.band0 + missing[0]} of tile {self.tile} was not written")
        row, col = self.tile[0] // CHUNK, self.tile[1] // CHUNK
        write_spool(self.sink.spool_path(0, row, col, self.band0), self.encoded)
        if self.levels >= 1:
            write_spool(self.sink.spool_path(1, row, col, self.band0), [[t] for t in self.first])
        return self.block if self.finite else None
