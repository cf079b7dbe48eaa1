"""Index outputs (``archive render --index NDVI --expression NAME=EXPR``): one band per spectral index,
computed from the rendered camera bands tile by tile as each tile is written.

:class:`IndexSink` wraps the output's own sink (Zarr, COG, ENVI: any :class:`~archive.outputs.base.Sink`)
for the render graph: the graph renders and mosaics the camera bands the indices read (one band
group holding them all) and writes each output tile's bands into it; its tile writer keeps those
bands (one tile of each: a few MB) and, when the tile closes, evaluates every index on them
(:func:`archive.outputs.bandmath.evaluate`: float32, NaN where a band has no value or the formula no
finite one) and writes the index bands through the wrapped sink's own tile writer. No second pass,
no whole mosaic in memory; the wrapped sink's capabilities (saturation flags, blank tiles, COG
overviews and layout) are the wrapper's, its band numbers those of the indices.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from archive.outputs.bandmath import BoundIndex, evaluate
from archive.outputs.base import Sink, TileWriter

__all__ = ["IndexSink", "index_properties"]


@dataclass(frozen=True, eq=False)
class IndexSink(Sink):
    """The sink the graph writes an index output through: ``inner`` (the output's sink, created for
    ``len(indices)`` bands named by the indices), ``wavelengths`` (nm) of the rendered bands in the
    graph's band order, ``indices`` (:class:`~archive.outputs.bandmath.BoundIndex`, the output bands
    in order). The graph writes bands 0.. of the rendered bands in one band group."""

    inner: Sink
    wavelengths: tuple[float, ...]
    indices: tuple[BoundIndex, ...]

    @property
    def saturation(self) -> bool:   # type: ignore[override]
        return self.inner.saturation

    @property
    def blank_tiles(self) -> bool:   # type: ignore[override]
        return self.inner.blank_tiles

    @property
    def overview_levels(self) -> int:   # type: ignore[override]
        return self.inner.overview_levels

    @property
    def tile_size(self) -> tuple[int, int]:
        return self.inner.tile_size

    def open_tile(self, band0: int, tile, nbands: int) -> _IndexTileWriter:
        if band0 != 0 or nbands != len(self.wavelengths):
            raise ValueError(f"an index output's tiles take its {len(self.wavelengths)} rendered bands in one group, "
                             f"got bands {band0}..{band0 + nbands - 1}")
        return _IndexTileWriter(self, tile)

    def __getattr__(self, name: str):
        """What else the graph asks of a sink (a COG's ``tiles``, ``children``, ``overview``,
        ``lay_out``; Zarr's ``write_saturated``) is the wrapped sink's, on the index bands."""
        if name.startswith("__") or name in ("inner", "wavelengths", "indices"):
            raise AttributeError(name)
        value = getattr(self.inner, name)
        n = len(self.indices)
        if name == "overview":
            return lambda level, r, c, band0, nbands, children: value(level, r, c, 0, n, children)
        if name == "lay_out":
            return lambda band0, nbands, start: value(0, n, start)
        return value

    def __dask_tokenize__(self):
        from dask.base import tokenize

        return ("archive.outputs.indexed.IndexSink", tokenize(self.inner), self.wavelengths,
                [(i.name, i.spec.text, i.bands, i.spec.constants) for i in self.indices])


class _IndexTileWriter(TileWriter):
    """Keeps one tile of each rendered band (a buffer of its own per band), then writes the indices."""

    def __init__(self, sink: IndexSink, tile):
        super().__init__(0, tile)
        self.sink = sink
        self.bands: list[np.ndarray | None] = [None] * len(sink.wavelengths)
        self.next = 0

    def buffer(self) -> np.ndarray:
        return np.empty(self.sink.tile_size, np.float32)   # kept until the tile closes: one per band

    def write(self, b: int, chunk: np.ndarray) -> None:
        self.bands[b] = chunk

    def close(self):
        h, w = self.tile[2], self.tile[3]
        missing = [b for b, v in enumerate(self.bands) if v is None]
        if missing:
            raise ValueError(f"an index tile was closed without its rendered bands {missing}")
        values = {nm: band[:h, :w] for nm, band in zip(self.sink.wavelengths, self.bands)}
        with self.sink.inner.open_tile(0, self.tile, len(self.sink.indices)) as writer:
            for k, index in enumerate(self.sink.indices):
                out = evaluate(index, values)
                buffer = writer.buffer()
                buffer[:h, :w] = out
                buffer[h:] = np.nan   # the grid's outside part (zarr's padding of edge chunks)
                buffer[:h, w:] = np.nan
                writer.write(k, buffer)
            passed = writer.close()
        self.bands = [None] * len(self.bands)
        return passed


def index_properties(indices: Sequence[BoundIndex]) -> list[dict]:
    """What an output's STAC Item and recipe record of its indices, in band order: name, formula,
    whether from the catalogue, the camera band (nm) each symbol took, the constants used."""
    return [{"name": i.name, "formula": i.spec.text, "catalogue": i.spec.catalogue,
             "bands": {s: float(nm) for s, nm in i.bands}, "describe": i.describe(),
             **({"constants": {k: float(v) for k, v in i.spec.constants}} if i.spec.constants else {})}
            for i in indices]
