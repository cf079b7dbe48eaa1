"""The Cloud-Optimized GeoTIFF output: tiles compressed by the graph's tasks, laid out at the end.

:class:`CogSink`: each writer task compresses its tiles (512 px, one band per tile) and the first
overview level computed from them into a spool file; overview tasks compute each further level from
the one below (:meth:`CogSink.overview`); a layout task per band group copies the group's
full-resolution tiles into the COG's data file in their final order (:meth:`CogSink.lay_out`), and
:func:`assemble_cog` puts the header and the overviews in front of them at the end, without decoding
any tile (:mod:`archive.outputs.tiff`). :data:`FORMAT` (:class:`CogFormat`) is the format's
entry of the registry (:mod:`archive.outputs.registry`); provenance layers go to a sibling
``<stem>_provenance.tif`` with nearest-neighbour overviews.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from archive.catalog.product import COG_MEDIA_TYPE
from archive.errors import RenderError
from archive.files import remove_path
from archive.grid import Grid
from archive.outputs.base import (CHUNK, OutputFormat, OutputMeta, Sink, TileWriter, all_nan, check_bands, check_tile,
                                  chunk_buffer)
from archive.outputs.layers import layers_cog_metadata, sibling_path

__all__ = ["FORMAT", "CogFormat", "CogSink", "assemble_cog", "read_band"]


@dataclass(frozen=True)
class CogSink(Sink):
    """A COG being written as spool files of compressed tiles in the directory ``spool``.

    Levels: 0 is the full resolution, 1.. the overviews (:func:`archive.outputs.tiff.level_shapes`). A writer
    task of output tile (R, C) spools its (up to) 2 x 2 full-resolution COG tiles per band and the
    tile of level 1 it covers, (R, C); an overview task of level L >= 2 spools tile (r, c) of
    level L from the (up to) 2 x 2 tiles (2r.., 2c..) of level L - 1 (:meth:`overview`).
    """

    spool: str
    nbands: int
    height: int
    width: int
    nearest: bool = False   #: overviews by nearest neighbour (top-left of each 2 x 2) instead of averages
    compression: str = "fast"   #: how tiles are encoded: a name of :data:`archive.codecs.COMPRESSIONS`

    @classmethod
    def create(cls, spool: str | os.PathLike, nbands: int, height: int, width: int,
               nearest: bool = False, compression: str | None = None) -> CogSink:
        from archive.codecs import compression as named

        os.mkdir(spool)
        sink = cls(os.fspath(spool), nbands, height, width, nearest, named(compression).name)
        open(sink.data_path, "wb").close()
        return sink

    @property
    def data_path(self) -> str:
        """The file the full resolution is laid out in, band group after band group
        (:meth:`lay_out`), and that becomes the COG (:func:`assemble_cog`)."""
        return os.path.join(self.spool, "L0.data")

    def lay_out(self, band0: int, nbands: int, start: int) -> int:
        """Copy the full-resolution tiles of bands band0.. (a band group whose writer tasks all ran)
        from their spool files into :attr:`data_path` from byte ``start`` on, in COG order, record
        where (an index file) and delete those spool files; returns the byte after them (where the
        next group starts). Run again (a task retried) it returns what the index recorded."""
        from archive.outputs.tiff import read_part_index, write_level_part, write_part_index

        index = os.path.join(self.spool, f"P0-{band0}.index")
        if os.path.exists(index):
            return read_part_index(index).end
        rows, cols = (-(-n // CHUNK) for n in (self.height, self.width))
        spools = {(0, r, c, band0): self.spool_path(0, r, c, band0) for r in range(rows) for c in range(cols)}
        for path in spools.values():
            if not os.path.exists(path):
                raise ValueError(f"{path}: missing: a writer task of bands {band0}.. did not complete")
        part = write_level_part(self.data_path, spools, height=self.height, width=self.width, band0=band0,
                                nbands=nbands, area_tiles=CHUNK // 512, start=start)
        write_part_index(index, part)
        for path in spools.values():
            os.remove(path)
        return part.end

    def encode(self, tile: np.ndarray) -> bytes:
        """One (TILE, TILE) float32 tile compressed as :attr:`compression` says
        (:func:`archive.outputs.tiff.encode_tile`)."""
        from archive.codecs import compression
        from archive.outputs.tiff import encode_tile

        c = compression(self.compression)
        return encode_tile(tile, c.cog_zstd, c.cog_predictor)

    def nan_tile(self) -> bytes:
        """The encoded all-NaN tile (computed once per process and compression)."""
        return _nan_tile(self.compression)

    def downsample(self, block: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """One overview step of ``block`` (..., h, w) -> (..., ceil(h/2), ceil(w/2)) float32 (into
        ``out`` when given; returned): the NaN-aware 2 x 2 average
        (:func:`archive.outputs.tiff.downsample2`), or with ``nearest`` each window's top-left pixel."""
        from archive.outputs.tiff import downsample2

        if not self.nearest:
            return downsample2(block, out)
        if out is None:
            return np.array(block[..., ::2, ::2])
        out[...] = block[..., ::2, ::2]
        return out

    @property
    def levels(self) -> list[tuple[int, int]]:
        """(height, width) of every level, full resolution first."""
        from archive.outputs.tiff import level_shapes

        return level_shapes(self.height, self.width)

    @property
    def overview_levels(self) -> int:  # type: ignore[override]
        return len(self.levels) - 1

    def tiles(self, level: int) -> tuple[int, int]:
        """(rows, cols) of COG tiles of ``level``."""
        from archive.outputs.tiff import TILE

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
        check_tile(tile, self.height, self.width)
        check_bands(band0, nbands, self.nbands, f"of a {self.nbands}-band COG")
        return _CogTileWriter(self, band0, tile, nbands)

    def overview(self, level: int, r: int, c: int, band0: int, nbands: int,
                 children: Sequence[np.ndarray | None]) -> np.ndarray | None:
        """Spool tile (r, c) of overview ``level`` >= 2 for bands band0.. from the quarters its
        children computed (each child of level - 1 returns its own 2 x 2 average, (nbands, <= TILE/2,
        <= TILE/2), in :meth:`children` order; None: all NaN or beyond the edge). Returns this
        tile's quarter of the next level (its 2 x 2 average) when there is one and some value is
        finite, else None: only quarter-size blocks travel between tasks."""
        from archive.outputs.tiff import TILE, write_spool

        h, w = self.levels[level]
        h, w = min(TILE, h - r * TILE), min(TILE, w - c * TILE)
        further = level + 1 <= self.overview_levels
        present = [(k, child) for k, child in enumerate(children) if child is not None]
        quarter = np.full((nbands, -(-h // 2), -(-w // 2)), np.nan, np.float32) if further and present else None
        tile = chunk_buffer()[:TILE, :TILE]
        encoded = []
        for b in range(nbands):
            if not present:
                encoded.append([self.nan_tile()])
                continue
            tile[...] = np.nan
            half = TILE // 2
            for k, child in present:
                i, j = divmod(k, 2)
                ch, cw = child.shape[1:]
                tile[i * half:i * half + ch, j * half:j * half + cw] = child[b]
            encoded.append([self.encode(tile)])
            if quarter is not None:
                self.downsample(tile[:h, :w], out=quarter[b])
        write_spool(self.spool_path(level, r, c, band0), encoded)
        return quarter if quarter is not None and np.isfinite(quarter).any() else None


@functools.lru_cache(maxsize=8)
def _nan_tile(compression: str) -> bytes:
    """The all-NaN COG tile encoded with ``compression`` (computed once per process)."""
    from archive.codecs import compression as named
    from archive.outputs.tiff import TILE, encode_tile

    c = named(compression)
    return encode_tile(np.full((TILE, TILE), np.nan, np.float32), c.cog_zstd, c.cog_predictor)


class _CogTileWriter(TileWriter):
    """Compresses each band's COG tiles and its first overview level tile as they come, keeps the
    2 x 2 average of the latter (this tile's quarter of level 2); writes both spool files on close."""

    def __init__(self, sink: CogSink, band0: int, tile, nbands: int):
        from archive.outputs.tiff import TILE

        super().__init__(band0, tile)
        self.sink, self.nbands = sink, nbands
        self.h, self.w = h, w = tile[2:]
        self.rows, self.cols = -(-h // TILE), -(-w // TILE)
        self.encoded: list[list[bytes]] = [[] for _ in range(nbands)]
        self.first: list[bytes | None] = [None] * nbands
        self.levels = sink.overview_levels
        self.oh, self.ow = -(-h // 2), -(-w // 2)  # extent of this tile in level 1
        # its level-1 tile, band after band: NaN beyond the grid (as the chunk), the rest overwritten
        self.down = np.full((TILE, TILE), np.nan, np.float32) if self.levels >= 1 else None
        self.block = (np.full((nbands, -(-self.oh // 2), -(-self.ow // 2)), np.nan, np.float32)
                      if self.levels >= 2 else None)
        self.finite = False

    def write(self, b: int, chunk: np.ndarray) -> None:
        from archive.outputs.tiff import TILE

        if all_nan(chunk):
            nan = self.sink.nan_tile()
            self.encoded[b] = [nan] * (self.rows * self.cols)
            self.first[b] = nan
            return
        self.encoded[b] = [self.sink.encode(chunk[i * TILE:(i + 1) * TILE, j * TILE:(j + 1) * TILE])
                           for i in range(self.rows) for j in range(self.cols)]
        if self.levels >= 1:
            # only the grid's part is averaged (the windows beyond it are NaN in self.down already)
            inside = self.sink.downsample(chunk[:self.h, :self.w], out=self.down[:self.oh, :self.ow])
            self.first[b] = self.sink.encode(self.down)
            if self.block is not None:
                self.sink.downsample(inside, out=self.block[b])
                self.finite = True

    def close(self):
        from archive.outputs.tiff import write_spool

        missing = [b for b, tiles in enumerate(self.encoded) if not tiles]
        if missing:
            raise ValueError(f"band {self.band0 + missing[0]} of tile {self.tile} was not written")
        row, col = self.tile[0] // CHUNK, self.tile[1] // CHUNK
        write_spool(self.sink.spool_path(0, row, col, self.band0), self.encoded)
        if self.levels >= 1:
            write_spool(self.sink.spool_path(1, row, col, self.band0), [[t] for t in self.first])
        return self.block if self.finite else None


def _cog_metadata(meta: OutputMeta) -> str:
    """GDAL_METADATA of a COG: dataset items (variable, source bands, wavelength and fwhm lists in nm)
    and per band its description, ``wavelength``/``fwhm`` (nm) and, in the IMAGERY domain, GDAL's
    standard ``CENTRAL_WAVELENGTH_UM`` and ``FWHM_UM`` (micrometres; GDAL >= 3.10)."""
    from archive.outputs.tiff import gdal_metadata

    dataset = {"variable": meta.variable, "source_bands": ",".join(str(i) for i in meta.band_indices)}
    if meta.wavelengths is not None:
        dataset.update(wavelength="{" + ", ".join(f"{w:.4f}" for w in meta.wavelengths) + "}",
                       wavelength_units="nm")
    if meta.fwhm is not None:
        dataset.update(fwhm="{" + ", ".join(f"{w:.4f}" for w in meta.fwhm) + "}")
    bands, imagery = [], []
    for b, label in enumerate(meta.labels):
        items = {"DESCRIPTION": label}
        if meta.units is not None:
            items["UNITTYPE"] = meta.units   # GDAL's band unit (rasterio .units, QGIS's band info)
        standard = {}
        if meta.wavelengths is not None:
            items.update(wavelength=f"{meta.wavelengths[b]:.4f}", wavelength_units="nm")
            standard["CENTRAL_WAVELENGTH_UM"] = _micrometres(meta.wavelengths[b])
        if meta.fwhm is not None:
            items["fwhm"] = f"{meta.fwhm[b]:.4f}"
            standard["FWHM_UM"] = _micrometres(meta.fwhm[b])
        bands.append(items)
        imagery.append({"IMAGERY": standard} if standard else {})
    return gdal_metadata(dataset, bands, imagery)


def _micrometres(nm: float) -> str:
    """``nm`` in micrometres, to 0.0001 nm (as the nm items are written)."""
    return f"{nm / 1000.0:.7f}".rstrip("0").rstrip(".")


def _spools(sink: CogSink) -> tuple[dict[tuple[int, int, int, int], str], list]:
    """The spool files of a COG sink by (level, tile row, tile col, first band), and the parts of
    the full resolution already laid out (:meth:`CogSink.lay_out`)."""
    from archive.outputs.tiff import read_part_index

    spools, parts = {}, []
    for name in os.listdir(sink.spool):
        if name.endswith(".tiles") and name.startswith("L"):
            level, r, c, band0 = (int(v) for v in name[1:-len(".tiles")].split("-"))
            spools[level, r, c, band0] = os.path.join(sink.spool, name)
        elif name.startswith("P0-") and name.endswith(".index"):
            parts.append(read_part_index(os.path.join(sink.spool, name)))
    return spools, parts


def assemble_cog(sink: CogSink, path: str | os.PathLike, grid: Grid, nbands: int, metadata: str,
                 insert: bool = True, remove_spools: bool = False) -> int:
    """Lay the tiles of ``sink`` out as a COG at ``path`` (no decoding), with the ``GDAL_METADATA``
    ``metadata``; returns its size. The full resolution comes from the sink's data file where the
    graph laid it out (:meth:`CogSink.lay_out`; ``insert``: put the rest in front of it without
    copying it, where the file system can), else from the spool files (``remove_spools``: each
    deleted once copied; the caller removes the spool afterwards). RenderError when a tile is
    missing."""
    from archive.codecs import compression
    from archive.outputs.tiff import assemble

    spools, parts = _spools(sink)
    c = compression(sink.compression)
    try:
        return assemble(path, spools, height=grid.height, width=grid.width, nbands=nbands, epsg=grid.epsg,
                        transform=grid.transform, metadata=metadata,
                        area_tiles=[CHUNK // 512] + [1] * sink.overview_levels,
                        level0=(sink.data_path, parts) if parts else None, insert=insert,
                        compression=c.cog_tag, predictor=c.cog_predictor, remove_spools=remove_spools)
    except ValueError as exc:
        raise RenderError(f"{path}: {exc}") from exc


def read_band(path: str | os.PathLike, grid: Grid, b: int, step: int) -> np.ndarray:
    """Every step-th pixel of band b of a GeoTIFF, read in strips of full-resolution rows."""
    import rasterio
    from rasterio.windows import Window

    parts = []
    with rasterio.open(path) as ds:
        for row0 in range(0, grid.height, 512 * step):
            h = min(512 * step, grid.height - row0)
            parts.append(ds.read(b + 1, window=Window(0, row0, grid.width, h))[::step, ::step])
    return np.concatenate(parts).astype(np.float32, copy=False)


class CogFormat(OutputFormat):
    """The COG format (:class:`~archive.outputs.base.OutputFormat`): one ``.tif``; provenance layers
    in a sibling ``<stem>_provenance.tif``."""

    name = "cog"
    suffixes = (".tif", ".tiff")
    label = "Cloud-Optimized GeoTIFF"
    media_type = COG_MEDIA_TYPE
    sink = CogSink

    def sibling(self, path: Path) -> Path | None:
        return sibling_path(path)

    @staticmethod
    def create(temp, path: Path, meta: OutputMeta) -> CogSink:
        return CogSink.create(temp(path, ".tiles"), meta.nbands, meta.grid.height, meta.grid.width,
                              compression=meta.compression)

    def create_layers(self, temp, path: Path, sink, meta: OutputMeta, spec) -> CogSink:
        return CogSink.create(temp(self.sibling(path), ".tiles"), len(spec.names), meta.grid.height,
                              meta.grid.width, nearest=True, compression=meta.compression)

    @staticmethod
    def finish(temp, path: Path, sink: CogSink, meta: OutputMeta):
        cog = temp(path)
        assemble_cog(sink, cog, meta.grid, meta.nbands, _cog_metadata(meta), remove_spools=True)
        remove_path(sink.spool)
        return [(cog, path)], lambda b, step: read_band(cog, meta.grid, b, step)

    def finish_layers(self, temp, path: Path, layers: CogSink, meta: OutputMeta, spec) -> list:
        sibling = self.sibling(path)
        cog = temp(sibling)
        assemble_cog(layers, cog, meta.grid, len(spec.names), layers_cog_metadata(spec), remove_spools=True)
        remove_path(layers.spool)
        return [(cog, sibling)]

    def stac_assets(self, out: Path, href, variable: str, data: dict) -> dict[str, dict]:
        return {"data": {"href": href(out), "type": self.media_type,
                         "title": f"{variable} ({self.label}, float32, NaN where not covered)", **data}}

    def provenance_assets(self, provenance: Path, href, fields: dict, describe) -> dict[str, dict]:
        bands, names = describe(provenance)
        return {"provenance": {"href": href(provenance), "type": self.media_type,
                               "title": f"Provenance layers ({self.label})", "roles": ["metadata"], **fields,
                               "raster:bands": bands, "archive:layers": names}}


#: The COG format's entry of :mod:`archive.outputs.registry`.
FORMAT = CogFormat()
