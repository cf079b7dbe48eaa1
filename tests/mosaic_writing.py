"""Test-only ways to write a mosaic: tiles assembled in this process (no render graph), written
through the same sinks and :class:`~archive.outputs.publish.Output` as ``archive render``."""

from __future__ import annotations

import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from archive.grid import Grid
from archive.outputs.base import CHUNK, OutputMeta
from archive.outputs.publish import Output
from archive.outputs.quicklook import quicklook_png
from archive.outputs.zarr import MosaicStore


@dataclass(frozen=True)
class Tile:
    """One assembled output tile of a band group.

    band0: position of values[0] among the output bands; row0, col0: top-left pixel in the grid.
    values: (nb, h, w) float32, NaN where uncovered. saturated: (h, w) bool or None.
    """

    band0: int
    row0: int
    col0: int
    values: np.ndarray
    saturated: np.ndarray | None = None


def write_values(store: MosaicStore, band0: int, row0: int, col0: int, values: np.ndarray) -> None:
    """Write whole chunks into ``store``: values (nb, h, w) float32 at bands band0.., rows row0.., cols col0.."""
    values = np.asarray(values, dtype=np.float32)
    store.check_aligned(values.shape, row0, col0)
    nb, h, w = values.shape
    writer = store.chunk_writer()
    for b in range(nb):
        for r in range(0, h, CHUNK):
            for c in range(0, w, CHUNK):
                part = values[b, r:r + CHUNK, c:c + CHUNK]
                if part.shape != (CHUNK, CHUNK) or not part.flags.c_contiguous:
                    buffer = writer.buffer()
                    buffer[:part.shape[0], :part.shape[1]] = part
                    buffer[part.shape[0]:] = np.nan  # zarr pads edge chunks with the fill value
                    buffer[:part.shape[0], part.shape[1]:] = np.nan
                    part = buffer
                writer.write(band0 + b, (row0 + r) // CHUNK, (col0 + c) // CHUNK, part)


def write_tile(store: MosaicStore, tile: Tile) -> None:
    write_values(store, tile.band0, tile.row0, tile.col0, tile.values)
    if tile.saturated is not None:
        store.write_saturated(tile.row0, tile.col0, tile.saturated)


def copy_store(store: MosaicStore, sink, band_group: int = 16) -> None:
    """Write every tile of a finished Zarr ``store`` through ``sink`` in this process, with the same
    tile writers (and, for a COG, the same overview pyramid) as the render graph's tasks."""
    values = store._array(store.variable)
    nb = values.shape[0]
    grid = store.grid
    blocks: dict[tuple[int, int, int], np.ndarray | None] = {}
    for row0, col0, g in grid.tiles(getattr(sink, "tile_size", (CHUNK, CHUNK))):
        tile = (row0, col0, g.height, g.width)
        for b0 in range(0, nb, band_group):
            n = min(band_group, nb - b0)
            with sink.open_tile(b0, tile, n) as writer:
                for b in range(n):
                    buffer = writer.buffer()
                    buffer[...] = np.nan
                    buffer[:g.height, :g.width] = values[b0 + b, row0:row0 + g.height, col0:col0 + g.width]
                    writer.write(b, buffer)
                blocks[row0 // CHUNK, col0 // CHUNK, b0] = writer.close()
    for level in range(2, sink.overview_levels + 1):
        rows, cols = sink.tiles(level)
        below, blocks = blocks, {}
        for r in range(rows):
            for c in range(cols):
                for b0 in range(0, nb, band_group):
                    kids = [None if k is None else below.get((*k, b0)) for k in sink.children(level, r, c)]
                    blocks[r, c, b0] = sink.overview(level, r, c, b0, min(band_group, nb - b0), kids)


def write_quicklook(store: MosaicStore, path: str | os.PathLike, max_size: int = 2048) -> None:
    """Write an RGBA PNG preview of a Zarr mosaic (see :func:`quicklook_png`)."""
    values = store._array(store.variable)
    quicklook_png(lambda b, step: np.asarray(values[b, ::step, ::step], dtype=np.float32), store.grid,
                  store.wavelengths, values.shape[0], path, max_size)


def write_mosaic(
    path: str | os.PathLike,
    grid: Grid,
    tiles: Iterable[Tile],
    *,
    wavelengths: Sequence[float] | None = None,
    band_indices: Sequence[int],
    variable: str = "radiance",
    overwrite: bool = False,
    quicklook: str | os.PathLike | None = None,
    attrs: dict | None = None,
) -> Output:
    """Write chunk-aligned tiles (in this process) into an output of any format, atomically.

    tiles: :class:`Tile` objects, each covering whole 1024 px chunks of ``grid`` (edge tiles smaller).
    COG and ENVI: the tiles are gathered in a temporary Zarr store first, then written through the
    format's sink by :func:`copy_store`. If the iterable or a writer raises, nothing is left at ``path``.
    """
    out = Output(Path(path), overwrite=overwrite, quicklook=quicklook)
    meta = OutputMeta(grid, tuple(band_indices), None if wavelengths is None else tuple(wavelengths), variable, attrs)
    try:
        if out.format.sink is MosaicStore:
            store = out.sink(meta)
        else:
            out.check()
            out._make_dirs()
            store = MosaicStore.create(out._temp(out.path, ".zarr"), grid, meta.wavelengths, meta.band_indices,
                                       variable, attrs)
        for tile in tiles:
            write_tile(store, tile)
        if out.format.sink is not MosaicStore:
            copy_store(store, out.sink(meta))
        out.finalize()
    finally:
        out.cleanup()
    return out
