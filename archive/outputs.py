"""Writers for rendered mosaics: Zarr, Cloud-Optimized GeoTIFF, ENVI BSQ and an RGB quicklook.

Every format is written by the render graph's own tile tasks, tile by tile, straight into the
output under its temporary name; no writer ever holds the whole mosaic, and no format is converted
from another. A *sink* is the small picklable handle those tasks write through (one output tile,
1024 x 1024 px, of a range of bands at a time; tiles never share bytes, so tasks need no locks):

- :class:`MosaicStore` (Zarr): one chunk is one band of one tile, encoded and written whole;
- :class:`~archive.sinks.EnviSink` (ENVI BSQ): positioned writes (``os.pwrite``) of the tile's rows into the data
  file, preallocated at its final size (no memory map); the header is written last;
- :class:`~archive.sinks.CogSink` (COG): each task compresses its tiles (512 px, one band per tile) and the first
  overview level computed from them into a spool file; overview tasks compute each further level
  from the one below; :func:`archive.cog.assemble` then lays the compressed tiles out as a COG
  without decoding them.

Rasters are ``(band, y, x)`` float32, NaN where no line covers a pixel; ``y`` grows southwards (row 0
is the northern edge).

Nothing is ever half-written at the requested path: :class:`Output` writes to hidden temporary
siblings (``.<name>.partial-<pid>...``), renames them into place only when complete, and removes them
on failure. An existing output is refused unless ``overwrite`` is set, and then it is replaced only
once the new one is complete.
"""

from __future__ import annotations

import errno
import json
import math
import os
import shutil
import sys
import warnings
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

import numpy as np

from archive.errors import InputError, OutputExistsError, RenderError
from archive.files import write_atomic
from archive.grid import Grid
from archive.sinks import CHUNK, CogSink, EnviSink, TileWriter, chunk_buffer

__all__ = [
    "CHUNK",
    "FORMATS",
    "ChunkWriter",
    "CogSink",
    "EnviSink",
    "MosaicStore",
    "Output",
    "OutputMeta",
    "Tile",
    "copy_store",
    "envi_data_path",
    "output_format",
    "quicklook_bands",
    "variable_for_mode",
    "write_mosaic",
    "write_quicklook",
]

#: Output suffix -> format name.
FORMATS = {".zarr": "zarr", ".tif": "cog", ".tiff": "cog", ".hdr": "envi"}
_VARIABLES = {"raw": "dn", "relative": "relative", "radiance": "radiance", "reflectance": "reflectance"}
_UNITS = {"raw": "DN", "relative": "DN (exposure-normalised)", "radiance": "calibration radiance units",
          "reflectance": "1"}
_GRID_ATTR = "archive_grid"
# Quicklook targets (nm) for red, green, blue.
_RGB_NM = (640.0, 550.0, 460.0)


def variable_for_mode(mode: str) -> str:
    """Name of the data variable for a radiometric mode ('raw' -> 'dn', 'radiance' -> 'radiance'...)."""
    try:
        return _VARIABLES[mode]
    except KeyError:
        raise InputError("--mode", f"unknown mode {mode!r}", f"use one of {', '.join(_VARIABLES)}") from None


def output_format(path: str | os.PathLike) -> str:
    """'zarr' | 'cog' | 'envi' from the output suffix; InputError for anything else."""
    suffix = Path(path).suffix.lower()
    if suffix not in FORMATS:
        raise InputError(
            path, f"unknown output type {suffix or '(no suffix)'!r}",
            "end the path in .zarr (Zarr), .tif/.tiff (Cloud-Optimized GeoTIFF) or .hdr (ENVI BSQ)",
        )
    return FORMATS[suffix]


def _exists(path: Path) -> bool:
    return path.exists() or path.is_symlink()


def _remove(path: Path) -> None:
    """Delete a file or directory tree; silent when absent."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        try:
            path.unlink()
        except FileNotFoundError:
            pass


# ---------------------------------------------------------------------------------------------
# The Zarr mosaic store (written tile by tile, possibly by many processes)
# ---------------------------------------------------------------------------------------------
def _values_codecs() -> tuple:
    """Compressor of the float32 mosaic chunks: Blosc LZ4 with byte shuffle.

    Measured on rendered 1024^2 radiance chunks (25 % NaN; bench/RESULTS.md "Render (issue 4)"):
    about 560 MB/s to write at ratio 1.7, against 130 MB/s (ratio 2.1) for zarr's default zstd
    level 0 and 260 MB/s (ratio 1.9) for zstd level 1: writing is on the render's critical path.
    """
    from zarr.codecs import BloscCodec

    return (BloscCodec(cname="lz4", clevel=5, shuffle="shuffle"),)


def _direct_codec(array, directory: str):
    """The numcodecs Blosc that encodes a chunk of ``array`` exactly as zarr does, or None when
    ``array`` is not the layout :class:`ChunkWriter` writes directly: a local Zarr v3 float32 array
    with NaN fill, (1, CHUNK, CHUNK) chunks and the codecs little-endian bytes + Blosc, on a
    little-endian machine.

    Built from the codec's public description (``BloscCodec.to_dict()``, the same configuration
    zarr gives numcodecs, typesize included), not from zarr's internals.
    """
    import inspect

    import numcodecs
    import zarr
    from zarr.codecs import BloscCodec, BytesCodec

    meta = array.metadata
    codecs = tuple(getattr(meta, "codecs", ()))
    if not (meta.zarr_format == 3 and sys.byteorder == "little" and len(codecs) == 2
            and isinstance(codecs[0], BytesCodec) and isinstance(codecs[1], BloscCodec)
            and array.dtype == np.float32 and tuple(array.chunks) == (1, CHUNK, CHUNK)
            and np.isnan(array.fill_value) and isinstance(array.store, zarr.storage.LocalStore)
            and os.path.isdir(directory)):
        return None
    endian = codecs[0].to_dict().get("configuration", {}).get("endian", "little")
    if endian != "little" or "typesize" not in inspect.signature(numcodecs.Blosc).parameters:
        return None  # numcodecs < 0.16: zarr compresses with typesize 1 there; let zarr write
    config = codecs[1].to_dict()["configuration"]
    shuffle = {"noshuffle": numcodecs.Blosc.NOSHUFFLE, "shuffle": numcodecs.Blosc.SHUFFLE,
               "bitshuffle": numcodecs.Blosc.BITSHUFFLE}[config["shuffle"]]
    return numcodecs.Blosc(cname=config["cname"], clevel=config["clevel"], shuffle=shuffle,
                           blocksize=config["blocksize"], typesize=config["typesize"])


class ChunkWriter:
    """Writes whole (1, CHUNK, CHUNK) float32 chunks of one local Zarr v3 array, one call per chunk.

    The bytes are those zarr itself writes (little-endian, then the array's Blosc codec, in a
    temporary file renamed into place), without zarr's per-chunk pipeline, which costs about as
    much again as the compression (measured: 540-630 MB/s direct vs 255 MB/s through
    ``zarr.Array.__setitem__``, one thread). A chunk that is all NaN (the fill value) is not
    written, and an older file of it is removed, as zarr does. Arrays of any other layout (codecs,
    dtype, chunk shape, store) go through zarr's ``__setitem__``. Checked byte for byte against zarr
    (bench/RESULTS.md "Render (issue 4)").
    """

    def __init__(self, array, directory: str):
        self.array, self.directory, self.meta = array, directory, array.metadata
        self.codec = _direct_codec(array, directory)
        self._made: set[str] = set()  # chunk directories known to exist

    @staticmethod
    def buffer() -> np.ndarray:
        """This thread's reusable (CHUNK, CHUNK) float32 chunk buffer (contents undefined)."""
        return chunk_buffer()

    def write(self, band: int, row: int, col: int, chunk: np.ndarray) -> None:
        """Write chunk (band, row, col) (chunk indices): ``chunk`` (CHUNK, CHUNK) float32 C-contiguous,
        the grid's outside part NaN (zarr's padding of edge chunks)."""
        if self.codec is None:
            h = min(CHUNK, self.array.shape[1] - row * CHUNK)
            w = min(CHUNK, self.array.shape[2] - col * CHUNK)
            self.array[band, row * CHUNK:row * CHUNK + h, col * CHUNK:col * CHUNK + w] = chunk[:h, :w]
            return
        path = os.path.join(self.directory, self.meta.encode_chunk_key((band, row, col)))
        middle = chunk[CHUNK // 2]
        if np.isnan(middle).all() and np.isnan(chunk).all():
            try:
                os.remove(path)
            except FileNotFoundError:
                pass
            return
        data = self.codec.encode(chunk)
        parent = os.path.dirname(path)
        if parent not in self._made:
            os.makedirs(parent, exist_ok=True)
            self._made.add(parent)
        write_atomic(path, data)


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


#: CF ``units`` of the data variable by name (UDUNITS: "1" for counts and ratios); radiance has none.
_CF_UNITS = {"dn": "1", "relative": "1", "reflectance": "1"}
#: Zarr-conventions declarations (``zarr_conventions`` attribute) of the GeoZarr ``proj:`` and
#: ``spatial:`` conventions, v1, as rioxarray declares and recognises them.
_PROJ_CONVENTION = {
    "schema_url": "https://raw.githubusercontent.com/zarr-experimental/geo-proj/refs/tags/v1/schema.json",
    "spec_url": "https://github.com/zarr-experimental/geo-proj/blob/v1/README.md",
    "uuid": "f17cb550-5864-4468-aeb7-f3180cfb622f",
    "name": "proj:",
    "description": "Coordinate reference system information for geospatial data",
}
_SPATIAL_CONVENTION = {
    "schema_url": "https://raw.githubusercontent.com/zarr-conventions/spatial/refs/tags/v1/schema.json",
    "spec_url": "https://github.com/zarr-conventions/spatial/blob/v1/README.md",
    "uuid": "689b58e2-cf7b-45e0-9fff-9cfc0883d6b4",
    "name": "spatial:",
    "description": "Spatial coordinate information",
}


def geozarr_attrs(grid: Grid, wkt2: bool = False) -> dict:
    """Attributes describing ``grid`` by the GeoZarr conventions (the modular Zarr conventions that
    replaced the monolithic GeoZarr draft in 2025: ``proj:`` = zarr-experimental/geo-proj v1 and
    ``spatial:`` = zarr-conventions/spatial v1), declared in ``zarr_conventions``.

    ``proj:code`` "EPSG:<n>" (and ``proj:wkt2``, WKT2:2019, with ``wkt2``);
    ``spatial:dimensions`` ["y", "x"]; ``spatial:transform`` the affine [a, b, c, d, e, f] (rasterio
    order: x = a col + b row + c, y = d col + e row + f, (col, row) = (0, 0) at the north-west corner
    of the north-west pixel); ``spatial:transform_type`` "affine"; ``spatial:shape`` [height, width];
    ``spatial:bbox`` [xmin, ymin, xmax, ymax] in metres; ``spatial:registration`` "pixel" (values
    are cell averages, the transform gives cell corners).
    """
    t = grid.transform
    attrs: dict = {
        "zarr_conventions": [dict(_PROJ_CONVENTION), dict(_SPATIAL_CONVENTION)],
        "proj:code": f"EPSG:{grid.epsg}",
    }
    if wkt2:
        attrs["proj:wkt2"] = grid.crs.to_wkt(version="WKT2_2019")
    attrs.update({
        "spatial:dimensions": ["y", "x"],
        "spatial:transform_type": "affine",
        "spatial:transform": [float(t.a), float(t.b), float(t.c), float(t.d), float(t.e), float(t.f)],
        "spatial:shape": [int(grid.height), int(grid.width)],
        "spatial:bbox": [float(v) for v in grid.bounds],
        "spatial:registration": "pixel",
    })
    return attrs


def mosaic_dataset(grid: Grid, values, saturated, band_indices: Sequence[int],
                   wavelengths: Sequence[float] | None, fwhm: Sequence[float] | None, variable: str,
                   attrs: dict | None = None):
    """The ``xarray.Dataset`` of a mosaic (the Zarr output's layout, also :func:`archive.mosaic`'s):
    ``variable`` (band, y, x) = ``values`` and ``saturated`` (y, x), any array kind (numpy, dask);
    coordinates ``band`` (source band index), x/y pixel centres (m), ``wavelength`` and ``fwhm`` (nm,
    when known); CF attributes, the CRS (rioxarray ``spatial_ref``) and the GeoZarr attributes
    (:func:`geozarr_attrs`) of ``grid``; ``attrs`` at the root."""
    import rioxarray  # noqa: F401  (registers .rio)
    import xarray as xr

    x, y = grid.xy_centres()
    coords = {"band": np.asarray(band_indices, dtype=np.int32), "y": y, "x": x}
    if wavelengths is not None:
        coords["wavelength"] = ("band", np.asarray(wavelengths, dtype=np.float64))
    if fwhm is not None:
        coords["fwhm"] = ("band", np.asarray(fwhm, dtype=np.float64))
    ds = xr.Dataset({variable: (("band", "y", "x"), values), "saturated": (("y", "x"), saturated)}, coords=coords)
    ds[variable].attrs.update({"long_name": variable, "_description": "NaN where no image line covers the pixel"})
    if variable in _CF_UNITS:  # radiance is in the calibration's units, which it does not name
        ds[variable].attrs["units"] = _CF_UNITS[variable]
    ds["saturated"].attrs.update({"long_name": "saturated", "flag_values": [0, 1],
                                  "flag_meanings": "ok saturated_in_some_band"})
    ds["band"].attrs.update({"long_name": "source band index (0-based)"})
    if wavelengths is not None:
        ds["wavelength"].attrs.update({"units": "nm", "long_name": "band centre wavelength",
                                       "standard_name": "radiation_wavelength"})
    if fwhm is not None:
        ds["fwhm"].attrs.update({"units": "nm", "long_name": "band spectral full width at half maximum"})
    ds["x"].attrs.update({"units": "m", "standard_name": "projection_x_coordinate",
                          "long_name": "easting of the pixel centre", "axis": "X"})
    ds["y"].attrs.update({"units": "m", "standard_name": "projection_y_coordinate",
                          "long_name": "northing of the pixel centre", "axis": "Y"})
    ds.attrs.update(attrs or {})
    ds.attrs.setdefault("Conventions", "CF-1.10")
    ds = ds.rio.write_crs(grid.epsg).rio.write_transform(grid.transform)
    ds.attrs.update(geozarr_attrs(grid, wkt2=True))
    for name in (variable, "saturated"):
        ds[name].attrs.update(geozarr_attrs(grid))
    return ds


@dataclass(frozen=True)
class MosaicStore:
    """Handle on a mosaic Zarr store (only paths and names: cheap to pickle into tasks).

    The store holds ``<variable>`` (band, y, x) float32 chunked (1, 1024, 1024) with NaN fill,
    ``saturated`` (y, x) uint8 chunked (1024, 1024) with 0 fill, x/y pixel-centre coordinates,
    ``wavelength`` (band) and ``fwhm`` (band, spectral full width at half maximum, when known) in nm,
    ``spatial_ref`` (rioxarray CRS + GeoTransform) and the grid as a root attribute. Reopen with
    ``xr.open_zarr(path, decode_coords="all")``.

    Metadata conventions (see :func:`geozarr_attrs`): CF-1.10 (root ``Conventions``; ``units``,
    ``standard_name``, ``long_name`` on coordinates and variables, ``grid_mapping`` pointing at
    ``spatial_ref``), and the GeoZarr ``proj:`` and ``spatial:`` Zarr conventions on the root group
    and on the two data arrays.
    """

    path: str
    variable: str

    #: What the graph does for this sink: record saturation flags; write tiles no cube touches
    #: (unwritten Zarr chunks read as NaN: no); overview levels computed by the graph (none).
    saturation: ClassVar[bool] = True
    blank_tiles: ClassVar[bool] = False
    overview_levels: ClassVar[int] = 0

    @classmethod
    def create(
        cls,
        path: str | os.PathLike,
        grid: Grid,
        wavelengths: Sequence[float] | None,
        band_indices: Sequence[int],
        variable: str = "radiance",
        attrs: dict | None = None,
        fwhm: Sequence[float] | None = None,
    ) -> MosaicStore:
        """Write the store's metadata and coordinates (no chunk data: unwritten chunks read as NaN).

        wavelengths: nm per output band (or None); band_indices: the source band index of each output band;
        fwhm: spectral full width at half maximum per output band, nm (or None).
        """
        import dask.array as da

        nb = len(band_indices)
        if wavelengths is not None and len(wavelengths) != nb:
            raise ValueError(f"{len(wavelengths)} wavelengths for {nb} bands")
        if fwhm is not None and len(fwhm) != nb:
            raise ValueError(f"{len(fwhm)} fwhm values for {nb} bands")
        values = da.full((nb, grid.height, grid.width), np.nan, dtype=np.float32,
                         chunks=(1, CHUNK, CHUNK))
        saturated = da.zeros(grid.shape, dtype=np.uint8, chunks=(CHUNK, CHUNK))
        ds = mosaic_dataset(grid, values, saturated, band_indices, wavelengths, fwhm, variable, attrs)
        ds.attrs[_GRID_ATTR] = json.dumps(
            {"epsg": grid.epsg, "gsd": grid.gsd, "x0": grid.x0, "y0": grid.y0,
             "width": grid.width, "height": grid.height}
        )
        ds[variable].encoding.update({"chunks": (1, CHUNK, CHUNK), "_FillValue": np.float32(np.nan),
                                      "compressors": _values_codecs()})
        ds["saturated"].encoding.update({"chunks": (CHUNK, CHUNK)})
        for name in ("x", "y", "wavelength", "fwhm"):
            if name in ds.coords:  # CF: coordinate variables have no missing values
                ds[name].encoding["_FillValue"] = None
        with warnings.catch_warnings():
            # zarr warns that consolidated metadata is not yet in the v3 spec; xarray reads it fine.
            warnings.simplefilter("ignore")
            ds.to_zarr(os.fspath(path), mode="w-", compute=False, zarr_format=3, consolidated=True)
        return cls(os.fspath(path), variable)

    # ---- reading back ------------------------------------------------------------------------
    def _array(self, name: str, mode: str = "r"):
        import zarr

        return zarr.open_array(self.path, path=name, mode=mode)

    @property
    def grid(self) -> Grid:
        import zarr

        meta = json.loads(zarr.open_group(self.path, mode="r").attrs[_GRID_ATTR])
        return Grid(**meta)

    @property
    def wavelengths(self) -> np.ndarray | None:
        import zarr

        group = zarr.open_group(self.path, mode="r")
        return np.asarray(group["wavelength"][:]) if "wavelength" in group else None

    @property
    def band_indices(self) -> np.ndarray:
        return np.asarray(self._array("band")[:])

    # ---- writing tiles -----------------------------------------------------------------------
    def check_aligned(self, shape: tuple[int, ...], row0: int, col0: int) -> None:
        """ValueError unless a (..., height, width) tile at pixel (row0, col0) covers whole chunks
        (edge chunks: up to the mosaic's edge)."""
        height, width = shape[-2:]
        full_h, full_w = self._array(self.variable).shape[1:]
        for start, size, full in ((row0, height, full_h), (col0, width, full_w)):
            if start % CHUNK or not (size == CHUNK or start + size == full) or start + size > full:
                raise ValueError(
                    f"{self.path}: tile at ({row0}, {col0}) of {height} x {width} px is not aligned to "
                    f"the {CHUNK} px chunks of a {full_h} x {full_w} mosaic"
                )

    def write_values(self, band0: int, row0: int, col0: int, values: np.ndarray) -> None:
        """Write whole chunks: values (nb, h, w) float32 at bands band0.., rows row0.., cols col0.."""
        values = np.asarray(values, dtype=np.float32)
        self.check_aligned(values.shape, row0, col0)
        nb, h, w = values.shape
        writer = self.chunk_writer()
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

    def open_tile(self, band0: int, tile: tuple[int, int, int, int], nbands: int) -> _ZarrTileWriter:
        """A writer of one output tile (row0, col0, height, width) of bands band0.. (see :class:`archive.sinks.TileWriter`)."""
        self.check_aligned(tile[2:], tile[0], tile[1])
        return _ZarrTileWriter(self.chunk_writer(), band0, tile)

    def chunk_writer(self) -> ChunkWriter:
        """A :class:`ChunkWriter` on the values array (it checks no tile alignment: see write_values)."""
        return ChunkWriter(self._array(self.variable, "r+"), os.path.join(self.path, self.variable))

    def write_saturated(self, row0: int, col0: int, mask: np.ndarray) -> None:
        """Write whole chunks of the saturation flags: mask (h, w) bool."""
        mask = np.asarray(mask)
        self.check_aligned(mask.shape, row0, col0)
        h, w = mask.shape
        self._array("saturated", "r+")[row0:row0 + h, col0:col0 + w] = mask.astype(np.uint8)

    def write_tile(self, tile: Tile) -> None:
        self.write_values(tile.band0, tile.row0, tile.col0, tile.values)
        if tile.saturated is not None:
            self.write_saturated(tile.row0, tile.col0, tile.saturated)

    def chunks(self) -> list[tuple[int, int, int, int]]:
        """(row0, col0, height, width) of every spatial chunk, row-major."""
        grid = self.grid
        return [(r, c, g.height, g.width) for r, c, g in grid.tiles(CHUNK)]


# ---------------------------------------------------------------------------------------------
# The Zarr sink's tile writer
# ---------------------------------------------------------------------------------------------
class _ZarrTileWriter(TileWriter):
    def __init__(self, writer: ChunkWriter, band0: int, tile):
        super().__init__(band0, tile)
        self.writer = writer

    def write(self, b: int, chunk: np.ndarray) -> None:
        self.writer.write(self.band0 + b, self.tile[0] // CHUNK, self.tile[1] // CHUNK, chunk)


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


# ---------------------------------------------------------------------------------------------
# Output metadata, headers, tags
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class OutputMeta:
    """What an output says besides its pixels: the grid, the wavelength (nm) and source band index
    of each band, the variable name ('radiance', 'dn'...), the processing attributes and the spectral
    full width at half maximum (nm) of each band (``fwhm``, None when unknown)."""

    grid: Grid
    band_indices: tuple[int, ...]
    wavelengths: tuple[float, ...] | None = None
    variable: str = "radiance"
    attrs: dict | None = field(default=None, compare=False)
    fwhm: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "band_indices", tuple(int(i) for i in self.band_indices))
        if self.wavelengths is not None:
            object.__setattr__(self, "wavelengths", tuple(float(w) for w in self.wavelengths))
            if len(self.wavelengths) != len(self.band_indices):
                raise ValueError(f"{len(self.wavelengths)} wavelengths for {len(self.band_indices)} bands")
        if self.fwhm is not None:
            object.__setattr__(self, "fwhm", tuple(float(w) for w in self.fwhm))
            if len(self.fwhm) != len(self.band_indices):
                raise ValueError(f"{len(self.fwhm)} fwhm values for {len(self.band_indices)} bands")

    @property
    def nbands(self) -> int:
        return len(self.band_indices)

    @property
    def labels(self) -> list[str]:
        if self.wavelengths is None:
            return [f"band {i}" for i in self.band_indices]
        return [f"band {i}: {w:.1f} nm" for i, w in zip(self.band_indices, self.wavelengths)]


def _cog_metadata(meta: OutputMeta) -> str:
    """GDAL_METADATA of a COG: dataset items (variable, source bands, wavelength and fwhm lists in nm)
    and per band its description, ``wavelength``/``fwhm`` (nm) and, in the IMAGERY domain, GDAL's
    standard ``CENTRAL_WAVELENGTH_UM`` and ``FWHM_UM`` (micrometres; GDAL >= 3.10)."""
    from archive.cog import gdal_metadata

    dataset = {"variable": meta.variable, "source_bands": ",".join(str(i) for i in meta.band_indices)}
    if meta.wavelengths is not None:
        dataset.update(wavelength="{" + ", ".join(f"{w:.4f}" for w in meta.wavelengths) + "}",
                       wavelength_units="nm")
    if meta.fwhm is not None:
        dataset.update(fwhm="{" + ", ".join(f"{w:.4f}" for w in meta.fwhm) + "}")
    bands, imagery = [], []
    for b, label in enumerate(meta.labels):
        items = {"DESCRIPTION": label}
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


def _spools(sink: CogSink) -> dict[tuple[int, int, int, int], str]:
    """The spool files of a COG sink by (level, tile row, tile col, first band)."""
    spools = {}
    for name in os.listdir(sink.spool):
        if name.endswith(".tiles") and name.startswith("L"):
            level, r, c, band0 = (int(v) for v in name[1:-len(".tiles")].split("-"))
            spools[level, r, c, band0] = os.path.join(sink.spool, name)
    return spools


def assemble_cog(sink: CogSink, meta: OutputMeta, path: str | os.PathLike) -> int:
    """Lay the spooled tiles of ``sink`` out as a COG at ``path`` (no decoding); returns its size."""
    from archive.cog import assemble

    spools = _spools(sink)
    grid = meta.grid
    try:
        return assemble(path, spools, height=grid.height, width=grid.width, nbands=meta.nbands, epsg=grid.epsg,
                        transform=grid.transform, metadata=_cog_metadata(meta),
                        area_tiles=[CHUNK // 512] + [1] * sink.overview_levels)
    except ValueError as exc:
        raise RenderError(f"{path}: {exc}") from exc


def _envi_map_info(grid: Grid) -> str:
    zone, north = None, True
    if 32601 <= grid.epsg <= 32660:
        zone = grid.epsg - 32600
    elif 32701 <= grid.epsg <= 32760:
        zone, north = grid.epsg - 32700, False
    if zone is None:
        return f"{{Arbitrary, 1, 1, {grid.x0!r}, {grid.y0!r}, {grid.gsd!r}, {grid.gsd!r}, units=Meters}}"
    hemisphere = "North" if north else "South"
    return (f"{{UTM, 1, 1, {grid.x0!r}, {grid.y0!r}, {grid.gsd!r}, {grid.gsd!r}, {zone}, {hemisphere}, "
            f"WGS-84, units=Meters}}")


def envi_data_path(header: str | os.PathLike) -> Path:
    """The BSQ data file of an ENVI output ``<name>.hdr``: ``<name>`` (the header path minus .hdr)."""
    header = Path(header)
    return header.with_name(header.name[: -len(".hdr")]) if header.name.lower().endswith(".hdr") else header


def envi_header(meta: OutputMeta) -> str:
    """The ENVI header text of a float32 little-endian BSQ output (``wavelength`` and ``fwhm`` in nm
    when known)."""
    grid = meta.grid
    lines = [
        "ENVI",
        f"description = {{archive render mosaic: {meta.variable}, NaN where not covered}}",
        f"samples = {grid.width}",
        f"lines = {grid.height}",
        f"bands = {meta.nbands}",
        "header offset = 0",
        "file type = ENVI Standard",
        "data type = 4",
        "interleave = bsq",
        "byte order = 0",
        f"map info = {_envi_map_info(grid)}",
        f"coordinate system string = {{{grid.crs.to_wkt(version='WKT1_ESRI')}}}",
        "data ignore value = NaN",
        "band names = {" + ", ".join(lbl.replace(",", ";") for lbl in meta.labels) + "}",
    ]
    if meta.wavelengths is not None:
        lines += ["wavelength units = Nanometers",
                  "wavelength = {" + ", ".join(f"{w:.4f}" for w in meta.wavelengths) + "}"]
    if meta.fwhm is not None:  # in 'wavelength units' (nm), which ENVI applies to fwhm too
        if meta.wavelengths is None:
            lines.append("wavelength units = Nanometers")
        lines.append("fwhm = {" + ", ".join(f"{w:.4f}" for w in meta.fwhm) + "}")
    return "\n".join(lines) + "\n"


def quicklook_bands(wavelengths: Sequence[float] | None, nbands: int) -> tuple[int, int, int]:
    """Output band positions for (red, green, blue).

    The bands nearest 640 / 550 / 460 nm when those lie within the bands' range; else the last /
    middle / first band (which for ascending wavelengths keeps long wavelengths red).
    """
    if wavelengths is not None and len(wavelengths) == nbands and nbands > 0:
        wl = np.asarray(wavelengths, dtype=float)
        half = (wl.max() - wl.min()) / max(nbands - 1, 1) / 2 if nbands > 1 else 0.0
        if all(wl.min() - half <= t <= wl.max() + half for t in _RGB_NM):
            return tuple(int(np.argmin(np.abs(wl - t))) for t in _RGB_NM)  # type: ignore[return-value]
    return (nbands - 1, nbands // 2, 0)


def write_quicklook(store: MosaicStore, path: str | os.PathLike, max_size: int = 2048) -> None:
    """Write an RGBA PNG preview of a Zarr mosaic (see :func:`quicklook_png`)."""
    values = store._array(store.variable)
    quicklook_png(lambda b, step: np.asarray(values[b, ::step, ::step], dtype=np.float32), store.grid,
                  store.wavelengths, values.shape[0], path, max_size)


def quicklook_png(read_band, grid: Grid, wavelengths, nbands: int, path: str | os.PathLike,
                  max_size: int = 2048) -> None:
    """Write an RGBA PNG preview: 2 %/98 % stretch per channel over covered pixels, uncovered transparent.

    ``read_band(b, step)`` returns every ``step``-th pixel of band b (both axes); step is chosen so
    that the longer side is at most ``max_size``.
    """
    from PIL import Image

    step = max(1, math.ceil(max(grid.height, grid.width) / max_size))
    bands = quicklook_bands(wavelengths, nbands)
    channels = [read_band(b, step) for b in bands]
    covered = np.zeros(channels[0].shape, dtype=bool)
    for c in channels:
        covered |= np.isfinite(c)
    rgba = np.zeros(channels[0].shape + (4,), dtype=np.uint8)
    for i, c in enumerate(channels):
        ok = np.isfinite(c)
        if ok.any():
            lo, hi = np.percentile(c[ok], [2.0, 98.0])
            scale = 255.0 / (hi - lo) if hi > lo else 0.0
            stretched = np.clip((np.where(ok, c, lo) - lo) * scale, 0, 255)
            rgba[..., i] = np.where(ok, np.round(stretched), 0).astype(np.uint8)
    rgba[..., 3] = np.where(covered, 255, 0)
    Image.fromarray(rgba, mode="RGBA").save(path, format="PNG")


def _envi_band(data: str | os.PathLike, grid: Grid, b: int, step: int) -> np.ndarray:
    """Every step-th pixel of band b of a BSQ float32 file, read row by row (pread)."""
    rows = range(0, grid.height, step)
    out = np.empty((len(rows), -(-grid.width // step)), np.float32)
    fd = os.open(data, os.O_RDONLY)
    try:
        for k, r in enumerate(rows):
            raw = os.pread(fd, grid.width * 4, ((b * grid.height + r) * grid.width) * 4)
            out[k] = np.frombuffer(raw, "<f4")[::step]
    finally:
        os.close(fd)
    return out


def _cog_band(path: str | os.PathLike, grid: Grid, b: int, step: int) -> np.ndarray:
    """Every step-th pixel of band b of a GeoTIFF, read in strips of full-resolution rows."""
    import rasterio
    from rasterio.windows import Window

    parts = []
    with rasterio.open(path) as ds:
        for row0 in range(0, grid.height, 512 * step):
            h = min(512 * step, grid.height - row0)
            parts.append(ds.read(b + 1, window=Window(0, row0, grid.width, h))[::step, ::step])
    return np.concatenate(parts).astype(np.float32, copy=False)


# ---------------------------------------------------------------------------------------------
# Output paths: temporary siblings, refusal of existing outputs, publication
# ---------------------------------------------------------------------------------------------
def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else
        return True
    return True


def _remove_stale_temps(final: Path) -> None:
    """Remove ``.<name>.partial-<pid>...`` siblings of ``final`` whose process is gone."""
    if not final.parent.is_dir():
        return
    prefix = f".{final.name}.partial-"
    for tmp in final.parent.glob(f"{prefix}*"):
        digits = ""
        for ch in tmp.name[len(prefix):]:
            if not ch.isdigit():
                break
            digits += ch
        if digits and int(digits) != os.getpid() and not _pid_alive(int(digits)):
            _remove(tmp)


@dataclass
class Output:
    """One requested output (plus an optional quicklook) and the temporary files that build it.

    Use: ``out.check()`` early; ``sink = out.sink(meta)`` creates the format's sink under temporary
    names (:class:`MosaicStore`, :class:`EnviSink` or :class:`CogSink`); write every tile through it
    (the render graph's tasks do); then ``out.finalize()``; always ``out.cleanup()`` in a ``finally``
    (it removes temporaries only).
    """

    path: Path
    overwrite: bool = False
    quicklook: Path | None = None
    provenance: bool = False   #: provenance layers: sibling file (COG, ENVI) or store variables (Zarr)
    _temps: list[Path] = field(default_factory=list, repr=False)
    _made_dirs: list[Path] = field(default_factory=list, repr=False)

    def __post_init__(self) -> None:
        self.path = Path(self.path)
        self.quicklook = None if self.quicklook is None else Path(self.quicklook)
        self.format = output_format(self.path)
        if self.quicklook is not None and self.quicklook.suffix.lower() != ".png":
            raise InputError(self.quicklook, "the quicklook must be a .png file", "name it <something>.png")
        self._sink = self._meta = None
        self._layers = self._layers_spec = None

    @property
    def provenance_path(self) -> Path | None:
        """The provenance sibling (COG: ``<stem>_provenance.tif``; ENVI: its header), None for Zarr
        (the layers are variables of the store) or without ``provenance``."""
        from archive.provenance_files import sibling_path

        return sibling_path(self.path, self.format) if self.provenance else None

    def _temp(self, final: Path, tag: str = "") -> Path:
        tmp = final.with_name(f".{final.name}.partial-{os.getpid()}{tag}")
        self._temps.append(tmp)
        return tmp

    @property
    def finals(self) -> list[Path]:
        """Every path this output will occupy (ENVI: data and header; plus the quicklook)."""
        paths = [envi_data_path(self.path), self.path] if self.format == "envi" else [self.path]
        sibling = self.provenance_path
        if sibling is not None:
            paths += [envi_data_path(sibling), sibling] if self.format == "envi" else [sibling]
        return paths + [self.item_path] + ([self.quicklook] if self.quicklook is not None else [])

    @property
    def item_path(self) -> Path:
        """The output's STAC Item, ``<out>.json`` (:mod:`archive.catalog.product`)."""
        return self.path.with_name(self.path.name + ".json")

    def check(self) -> None:
        """OutputExistsError if a final path exists and overwrite is off; InputError for a parent
        that is not a directory or not writable.

        Also removes the temporaries a killed earlier run left beside a final path (their process,
        named in the temporary's name, no longer runs on this machine).
        """
        for final in self.finals:
            _remove_stale_temps(final)
            if final.parent.exists() and not final.parent.is_dir():
                raise InputError(final.parent, "is not a directory", "choose another output path")
            if _exists(final) and not self.overwrite:
                raise OutputExistsError(final)
            if _exists(final) and final.is_dir() != (final.suffix.lower() == ".zarr"):
                raise InputError(final, "exists and is of another kind (file vs directory)",
                                 "remove it or choose another output path")
            _check_writable(final.parent)

    def _make_dirs(self) -> None:
        for final in self.finals:
            missing = [d for d in (final.parent, *final.parent.parents) if not d.exists()]
            try:
                final.parent.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise _unwritable(final.parent, exc) from None
            self._made_dirs.extend(missing)  # deepest first: removed again if left empty

    def sink(self, meta: OutputMeta):
        """Create the temporary output of ``meta`` (metadata only, no pixels) and return its sink."""
        if self._sink is not None:
            raise RuntimeError(f"{self.path}: sink created twice")
        self.check()
        self._make_dirs()
        grid = meta.grid
        try:
            if self.format == "zarr":
                sink = MosaicStore.create(self._temp(self.path), grid, meta.wavelengths, meta.band_indices,
                                          meta.variable, meta.attrs, fwhm=meta.fwhm)
            elif self.format == "envi":
                data = envi_data_path(self.path)
                sink = EnviSink.create(self._temp(data), meta.nbands, grid.height, grid.width)
            else:
                sink = CogSink.create(self._temp(self.path, ".tiles"), meta.nbands, grid.height, grid.width)
        except OSError as exc:
            if exc.errno == errno.ENOSPC:
                size = meta.nbands * grid.height * grid.width * 4
                raise InputError(self.path.parent, f"not enough free space for a {size / 1e9:.1f} GB output",
                                 "free some space or choose another folder") from None
            raise _unwritable(self.path.parent, exc) from None
        self._sink, self._meta = sink, meta
        return sink

    def layers_sink(self, spec):
        """Create the temporary provenance output of the layers ``spec`` (an
        :class:`~archive.provenance.ProvenanceSpec`; after :meth:`sink`) and return its sink: a
        :class:`~archive.provenance_files.LayersStore` into the Zarr store, or an ENVI / COG sink
        of one band per layer for the sibling file."""
        from archive.provenance_files import LayersStore, add_zarr_layers

        if self._sink is None or not self.provenance:
            raise RuntimeError(f"{self.path}: layers_sink needs provenance=True and the values sink first")
        grid = self._meta.grid
        nb = len(spec.names)
        try:
            if self.format == "zarr":
                add_zarr_layers(self._sink.path, grid, spec, geozarr_attrs(grid))
                layers = LayersStore(self._sink.path, tuple(spec.names))
            elif self.format == "envi":
                layers = EnviSink.create(self._temp(envi_data_path(self.provenance_path)), nb, grid.height, grid.width)
            else:
                layers = CogSink.create(self._temp(self.provenance_path, ".tiles"), nb, grid.height, grid.width,
                                        nearest=True)
        except OSError as exc:
            raise _unwritable(self.path.parent, exc) from None
        self._layers, self._layers_spec = layers, spec
        return layers

    def _finish_layers(self) -> list[tuple[Path, Path]]:
        """Moves of the provenance sibling (COG laid out, ENVI header written); none for Zarr."""
        from archive.cog import assemble
        from archive.provenance_files import layers_cog_metadata, layers_envi_header

        layers, spec, grid = self._layers, self._layers_spec, self._meta.grid
        if layers is None or self.format == "zarr":
            return []
        sibling = self.provenance_path
        if self.format == "cog":
            cog = self._temp(sibling)
            try:
                assemble(cog, _spools(layers), height=grid.height, width=grid.width, nbands=len(spec.names),
                         epsg=grid.epsg, transform=grid.transform, metadata=layers_cog_metadata(spec),
                         area_tiles=[CHUNK // 512] + [1] * layers.overview_levels)
            except ValueError as exc:
                raise RenderError(f"{sibling}: {exc}") from exc
            _remove(Path(layers.spool))
            return [(cog, sibling)]
        header = self._temp(sibling)
        header.write_text(layers_envi_header(grid, spec, _envi_map_info(grid)), encoding="ascii")
        return [(Path(layers.data), envi_data_path(sibling)), (header, sibling)]

    def finalize(self, sink=None, item=None) -> None:
        """Finish the output (ENVI header, COG layout) and move everything into place; then, with
        ``item`` (a function returning the output's STAC Item, a dict, made from the files in
        place), write ``<out>.json`` last: an Item beside an output says it is complete."""
        sink = self._sink if sink is None else sink
        meta = self._meta
        grid = meta.grid
        moves: list[tuple[Path, Path]] = self._finish_layers()
        if self.format == "zarr":
            moves.append((Path(sink.path), self.path))
            values = sink._array(sink.variable)
            read_band = lambda b, step: np.asarray(values[b, ::step, ::step], np.float32)
        elif self.format == "cog":
            cog = self._temp(self.path)
            assemble_cog(sink, meta, cog)
            _remove(Path(sink.spool))
            moves.append((cog, self.path))
            read_band = lambda b, step: _cog_band(cog, grid, b, step)
        else:
            header = self._temp(self.path)
            header.write_text(envi_header(meta), encoding="ascii")
            moves += [(Path(sink.data), envi_data_path(self.path)), (header, self.path)]  # header last
            read_band = lambda b, step: _envi_band(sink.data, grid, b, step)
        if self.quicklook is not None:
            tmp = self._temp(self.quicklook)
            quicklook_png(read_band, grid, meta.wavelengths, meta.nbands, tmp)
            moves.append((tmp, self.quicklook))
        self.check()  # something may have appeared meanwhile
        for tmp, final in moves:
            _replace(tmp, final)
        if item is not None:
            from archive.catalog.stac import write_item

            write_item(self.item_path, item())

    def cleanup(self) -> None:
        """Remove every temporary this output created (never the final paths)."""
        for tmp in self._temps:
            _remove(tmp)
        self._temps.clear()
        for d in self._made_dirs:
            try:
                d.rmdir()  # only when empty: after a failure, leave no trace at all
            except OSError:
                pass
        self._made_dirs.clear()


def _unwritable(where: Path, exc: OSError) -> InputError:
    return InputError(where, f"cannot write there ({exc.strerror or exc})",
                      "choose an output folder you can write to")


def _check_writable(folder: Path) -> None:
    """InputError unless ``folder`` (or, when it does not exist yet, its nearest existing parent)
    lets this process create files."""
    existing = next((d for d in (folder, *folder.parents) if d.exists()), None)
    if existing is not None and existing.is_dir() and not os.access(existing, os.W_OK | os.X_OK):
        raise InputError(existing, "is not writable", "choose an output folder you can write to")


def _replace(tmp: Path, final: Path) -> None:
    """Rename tmp to final; an existing final is moved aside first and deleted only afterwards."""
    old = None
    if _exists(final):
        old = final.with_name(f".{final.name}.old-{os.getpid()}")
        _remove(old)
        os.replace(final, old)
    try:
        os.replace(tmp, final)
    except BaseException:
        if old is not None:
            os.replace(old, final)
        raise
    if old is not None:
        _remove(old)


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
        if out.format == "zarr":
            store = out.sink(meta)
        else:
            out.check()
            out._make_dirs()
            store = MosaicStore.create(out._temp(out.path, ".zarr"), grid, meta.wavelengths, meta.band_indices,
                                       variable, attrs)
        for tile in tiles:
            store.write_tile(tile)
        if out.format != "zarr":
            copy_store(store, out.sink(meta))
        out.finalize()
    finally:
        out.cleanup()
    return out
