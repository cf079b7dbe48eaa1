"""The Zarr output: a mosaic store written chunk by chunk by the render graph's tile tasks.

:class:`MosaicStore` is the values' sink (one chunk is one band of one tile, encoded and written
whole by :class:`ChunkWriter`); :class:`LayersStore` writes the provenance layers into variables of
the same store (:func:`add_zarr_layers`); :func:`mosaic_dataset` is the dataset layout both the
store and :func:`archive.mosaic` have (CF and GeoZarr attributes, :func:`geozarr_attrs`);
:data:`FORMAT` (:class:`ZarrFormat`) is the format's entry of the registry (:mod:`archive.outputs.registry`).
"""

from __future__ import annotations

import functools
import json
import os
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np

from archive.catalog.stac import ZARR_MEDIA_TYPE
from archive.codecs import compression as compression_named
from archive.codecs import numcodecs_blosc
from archive.files import write_atomic
from archive.grid import Grid
from archive.outputs.base import (CHUNK, VARIABLE_UNITS, OutputFormat, OutputMeta, Sink, TileWriter, band_labels,
                                  check_bands, chunk_buffer)
from archive.outputs.layers import layer_attrs, layers_metadata
from archive.outputs.pam import band_texts, write_band_pam
from archive.outputs.zarr_metadata import ArraySpec, add_arrays, write_store

__all__ = ["FORMAT", "GDAL_ZARR_MEDIA_TYPE", "ChunkWriter", "LayersStore", "MosaicStore", "ZarrFormat",
           "add_zarr_layers", "gdal_crs", "geozarr_attrs", "located_attrs", "mosaic_dataset", "store_layout",
           "store_version"]

_GRID_ATTR = "archive_grid"
#: Media type of the GDAL asset of a Zarr output's Item (one array, read by GDAL's Zarr driver): no
#: registered type names a Zarr array; odc-stac counts this (unregistered) one among the raster
#: types it opens with rasterio, and xarray readers go by the store's :data:`ZARR_MEDIA_TYPE`.
GDAL_ZARR_MEDIA_TYPE = "application/x-zarr"


class _Uncompressed:
    """The "codec" of chunks stored as they are (``--compression none``): the little-endian C-order bytes."""

    @staticmethod
    def encode(chunk: np.ndarray) -> bytes:
        return np.ascontiguousarray(chunk, dtype="<f4").tobytes()


def _direct_codec(array, directory: str):
    """The numcodecs Blosc that encodes a chunk of ``array`` exactly as zarr does (or
    :class:`_Uncompressed` for an array without compressor), or None when ``array`` is not the
    layout :class:`ChunkWriter` writes directly: a local Zarr v2 or v3 float32 array with NaN fill,
    (1, CHUNK, CHUNK) chunks and the codecs little-endian bytes + Blosc (or no compressor), on a
    little-endian machine.

    Built from the codec's public description (``BloscCodec.to_dict()``, the same configuration
    zarr gives numcodecs, typesize included), not from zarr's internals.
    """
    import inspect

    import numcodecs
    import zarr
    from zarr.codecs import BloscCodec, BytesCodec

    meta = array.metadata
    if meta.zarr_format == 2:   # v2: the compressor alone, on the little-endian C-order bytes
        compressor = getattr(meta, "compressor", None)
        ok = (sys.byteorder == "little" and (compressor is None or isinstance(compressor, numcodecs.Blosc))
              and not meta.filters
              and array.dtype == np.float32 and getattr(meta.dtype, "endianness", "little") == "little"
              and meta.order == "C" and tuple(array.chunks) == (1, CHUNK, CHUNK)
              and np.isnan(array.fill_value) and isinstance(array.store, zarr.storage.LocalStore)
              and os.path.isdir(directory)
              and "typesize" in inspect.signature(numcodecs.Blosc).parameters)
        return (_Uncompressed() if compressor is None else compressor) if ok else None
    codecs = tuple(getattr(meta, "codecs", ()))
    if not (meta.zarr_format == 3 and sys.byteorder == "little" and len(codecs) in (1, 2)
            and isinstance(codecs[0], BytesCodec) and (len(codecs) == 1 or isinstance(codecs[1], BloscCodec))
            and array.dtype == np.float32 and tuple(array.chunks) == (1, CHUNK, CHUNK)
            and np.isnan(array.fill_value) and isinstance(array.store, zarr.storage.LocalStore)
            and os.path.isdir(directory)):
        return None
    endian = codecs[0].to_dict().get("configuration", {}).get("endian", "little")
    if endian != "little":
        return None
    if len(codecs) == 1:
        return _Uncompressed()
    if "typesize" not in inspect.signature(numcodecs.Blosc).parameters:
        return None  # numcodecs < 0.16: zarr compresses with typesize 1 there; let zarr write
    config = codecs[1].to_dict()["configuration"]
    return numcodecs_blosc(config["cname"], config["clevel"], config["shuffle"], config["blocksize"],
                           config["typesize"])


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

    def __init__(self, array, directory: str, remote: str | None = None):
        self.array, self.directory, self.meta = array, directory, array.metadata
        self.codec = _direct_codec(array, directory)
        #: s3:// URL of the array in a bucket: chunks are PUT there (one object each) instead of ``directory``
        self.remote = remote
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
        key = self.meta.encode_chunk_key((band, row, col))
        if self.remote is not None:   # into the bucket, from this worker; all-NaN chunks are left out
            if not (np.isnan(chunk[CHUNK // 2]).all() and np.isnan(chunk).all()):
                from archive import storage

                storage.write_bytes(f"{self.remote}/{key}", self.codec.encode(chunk))
            return
        path = os.path.join(self.directory, key)
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


#: CF attributes of the coordinates and of the saturation flags (the Zarr output's and archive.mosaic's).
_BAND_ATTRS = {"long_name": "source band index (0-based)", "units": "1"}
_WAVELENGTH_ATTRS = {"units": "nm", "long_name": "band centre wavelength", "standard_name": "radiation_wavelength"}
_FWHM_ATTRS = {"units": "nm", "long_name": "band spectral full width at half maximum"}
_X_ATTRS = {"units": "m", "standard_name": "projection_x_coordinate", "long_name": "easting of the pixel centre",
            "axis": "X"}
_Y_ATTRS = {"units": "m", "standard_name": "projection_y_coordinate", "long_name": "northing of the pixel centre",
            "axis": "Y"}
_SATURATED_ATTRS = {"long_name": "saturated", "flag_values": [0, 1], "flag_meanings": "ok saturated_in_some_band"}


def gdal_crs(grid: Grid) -> dict:
    """GDAL's own CRS attribute of a Zarr array (``_CRS``: the EPSG code as an OGC URL), which its
    Zarr driver reads when an array is opened by its own path (``<store>/radiance``: the href
    odc-stac opens), where it does not see the group's ``spatial_ref`` that ``grid_mapping`` names."""
    return {"_CRS": {"url": f"http://www.opengis.net/def/crs/EPSG/0/{int(grid.epsg)}"}}


def located_attrs(grid: Grid, coordinates: Sequence[str] = ()) -> dict:
    """What ties a data variable (values, saturation flags, provenance layers) to its grid, after its
    own and the GeoZarr attributes: :func:`gdal_crs`, CF ``coordinates`` (``coordinates`` and the grid
    mapping ``spatial_ref``, sorted: so that plain ``xr.open_zarr``, whose default
    ``decode_coords=True`` reads only that attribute, makes ``spatial_ref`` a coordinate and
    rioxarray finds the CRS) and CF ``grid_mapping`` (``spatial_ref``: what ``decode_coords="all"``,
    GDAL and other CF readers follow)."""
    return {**gdal_crs(grid), "coordinates": " ".join(sorted({*coordinates, "spatial_ref"})),
            "grid_mapping": "spatial_ref"}


def _values_attrs(variable: str) -> dict:
    attrs = {"long_name": variable, "_description": "NaN where no image line covers the pixel"}
    if variable in VARIABLE_UNITS:  # CF units; GDAL's Zarr driver shows them as the band unit
        attrs["units"] = VARIABLE_UNITS[variable]
    return attrs


def _root_attrs(grid: Grid, attrs: dict | None) -> dict:
    out = dict(attrs or {})
    out.setdefault("Conventions", "CF-1.10")
    out.update(geozarr_attrs(grid, wkt2=True))
    return out


def mosaic_dataset(grid: Grid, values, saturated, band_indices: Sequence[int],
                   wavelengths: Sequence[float] | None, fwhm: Sequence[float] | None, variable: str,
                   attrs: dict | None = None):
    """The ``xarray.Dataset`` of a mosaic (the Zarr output's layout, also :func:`archive.mosaic`'s):
    ``variable`` (band, y, x) = ``values`` and ``saturated`` (y, x), any array kind (numpy, dask);
    coordinates ``band`` (source band index), x/y pixel centres (m), ``wavelength`` and ``fwhm`` (nm,
    when known); CF attributes, the CRS (rioxarray ``spatial_ref``, named in the data variables'
    ``coordinates`` and ``grid_mapping``: :func:`located_attrs`) and the GeoZarr attributes
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
    ds[variable].attrs.update(_values_attrs(variable))
    ds[variable].encoding["_FillValue"] = np.float32(np.nan)   # NaN is nodata: .rio.nodata, GDAL, to_zarr
    ds["saturated"].attrs.update(_SATURATED_ATTRS)
    ds["band"].attrs.update(_BAND_ATTRS)
    if wavelengths is not None:
        ds["wavelength"].attrs.update(_WAVELENGTH_ATTRS)
    if fwhm is not None:
        ds["fwhm"].attrs.update(_FWHM_ATTRS)
    ds["x"].attrs.update(_X_ATTRS)
    ds["y"].attrs.update(_Y_ATTRS)
    ds.attrs.update(attrs or {})
    ds.attrs.setdefault("Conventions", "CF-1.10")
    ds = ds.rio.write_crs(grid.epsg).rio.write_transform(grid.transform)
    ds.attrs.update(geozarr_attrs(grid, wkt2=True))
    extra = [name for name in ("wavelength", "fwhm") if name in ds.coords]
    for name, coordinates in ((variable, extra), ("saturated", [])):
        ds[name].attrs.update(geozarr_attrs(grid))
        ds[name].attrs.update(gdal_crs(grid))
        # xarray writes a grid mapping into no variable's 'coordinates': named here, it is (located_attrs)
        ds[name].encoding["coordinates"] = located_attrs(grid, coordinates)["coordinates"]
    return ds


@functools.lru_cache(maxsize=16)
def _crs_attrs(epsg: int) -> tuple:
    """rioxarray's ``write_crs`` attributes of EPSG:``epsg`` (its steps: pyproj's CF grid mapping of
    the rasterio CRS, then ``spatial_ref`` and ``crs_wkt`` = rasterio's WKT), without importing
    xarray and rioxarray into the command (a serial second of its start; issue 37);
    tests/test_outputs_zarr_metadata.py compares them with rioxarray's."""
    import pyproj
    import rasterio.crs

    crs = rasterio.crs.CRS.from_user_input(int(epsg))
    try:
        attrs = pyproj.CRS.from_user_input(crs).to_cf()
    except KeyError:
        attrs = {}
    wkt = crs.to_wkt()
    attrs["spatial_ref"] = wkt
    attrs["crs_wkt"] = wkt
    return tuple(attrs.items())


def _spatial_ref_attrs(grid: Grid) -> dict:
    """rioxarray's grid-mapping attributes of ``grid`` (CF projection parameters, ``crs_wkt``,
    ``spatial_ref``, then ``GeoTransform`` written as rioxarray's ``write_transform`` writes it), as
    :func:`mosaic_dataset` gets them; the CRS part made once per EPSG code (~2 ms)."""
    attrs = dict(_crs_attrs(grid.epsg))
    attrs["GeoTransform"] = " ".join(str(item) for item in grid.transform.to_gdal())
    return attrs


def store_layout(grid: Grid, band_indices: Sequence[int], wavelengths: Sequence[float] | None,
                 fwhm: Sequence[float] | None, variable: str, attrs: dict | None = None,
                 compression: str | None = None, names: Sequence[str] | None = None) -> tuple[dict, list[ArraySpec]]:
    """(root attributes, arrays) of the Zarr output: what ``to_zarr`` of :func:`mosaic_dataset`
    writes (its CF encoding: ``coordinates`` and ``grid_mapping`` on the data variables), values
    (band, y, x) float32 chunked (1, CHUNK, CHUNK) and saturation (y, x) uint8 chunked (CHUNK,
    CHUNK) without data, the coordinates with theirs; ``attrs`` at the root, then the grid's;
    ``compression``: the values' :data:`archive.codecs.COMPRESSIONS` name (None: the default);
    ``names``: each band's name (an index output's), the text coordinate ``band_name`` (band)."""
    nb = len(band_indices)
    x, y = grid.xy_centres()
    extra = [name for name, v in (("wavelength", wavelengths), ("fwhm", fwhm), ("band_name", names)) if v is not None]
    values_attrs = {**_values_attrs(variable), **geozarr_attrs(grid), **located_attrs(grid, extra)}
    saturated_attrs = {**_SATURATED_ATTRS, **geozarr_attrs(grid), **located_attrs(grid)}
    arrays = [
        ArraySpec(variable, np.dtype(np.float32), (nb, grid.height, grid.width), (1, CHUNK, CHUNK), ("band", "y", "x"),
                  values_attrs, fill=float("nan"), values_codec=True,
                  values_blosc=compression_named(compression).zarr_blosc),
        ArraySpec("saturated", np.dtype(np.uint8), grid.shape, (CHUNK, CHUNK), ("y", "x"), saturated_attrs),
        ArraySpec("band", np.dtype(np.int32), (nb,), (nb,), ("band",), dict(_BAND_ATTRS),
                  data=np.asarray(band_indices, np.int32)),
        ArraySpec("x", np.dtype(np.float64), (grid.width,), (grid.width,), ("x",), dict(_X_ATTRS), data=x),
        ArraySpec("y", np.dtype(np.float64), (grid.height,), (grid.height,), ("y",), dict(_Y_ATTRS), data=y),
        ArraySpec("spatial_ref", np.dtype(np.int64), (), (), (), _spatial_ref_attrs(grid), data=np.int64(0)),
    ]
    for name, v, cf in (("wavelength", wavelengths, _WAVELENGTH_ATTRS), ("fwhm", fwhm, _FWHM_ATTRS)):
        if v is not None:
            arrays.append(ArraySpec(name, np.dtype(np.float64), (nb,), (nb,), ("band",), dict(cf),
                                    data=np.asarray(v, np.float64)))
    if names is not None:   # fixed-width text: what xarray reads back as str
        text = np.asarray([str(n) for n in names], dtype=str)
        arrays.append(ArraySpec("band_name", text.dtype, (nb,), (nb,), ("band",), {"long_name": "band name"},
                                data=text))
    root = _root_attrs(grid, attrs)
    root[_GRID_ATTR] = json.dumps({"epsg": grid.epsg, "gsd": grid.gsd, "x0": grid.x0, "y0": grid.y0,
                                   "width": grid.width, "height": grid.height})
    return root, arrays


@dataclass(frozen=True)
class MosaicStore(Sink):
    """Handle on a mosaic Zarr store (only paths and names: cheap to pickle into tasks).

    The store holds ``<variable>`` (band, y, x) float32 chunked (1, 1024, 1024) with NaN fill,
    ``saturated`` (y, x) uint8 chunked (1024, 1024) with 0 fill, x/y pixel-centre coordinates,
    ``wavelength`` (band) and ``fwhm`` (band, spectral full width at half maximum, when known) in nm,
    ``spatial_ref`` (rioxarray CRS + GeoTransform) and the grid as a root attribute. Reopen with
    ``xr.open_zarr(path)`` (``spatial_ref`` is a coordinate, ``.rio.crs`` set), or through GDAL
    (``ZARR:"path":/radiance`` or the array's folder ``path/radiance``; Zarr v2: band names from
    :mod:`archive.outputs.pam`).

    Metadata conventions (see :func:`geozarr_attrs`): CF-1.10 (root ``Conventions``; ``units``,
    ``standard_name``, ``long_name`` on coordinates and variables, ``grid_mapping`` pointing at
    ``spatial_ref``), and the GeoZarr ``proj:`` and ``spatial:`` Zarr conventions on the root group
    and on the two data arrays; GDAL's ``_CRS`` on the data arrays (:func:`located_attrs`).
    """

    path: str
    variable: str
    remote: str | None = None   #: s3:// URL the value chunks are written to (a Zarr output in a bucket)

    #: Capabilities (:class:`~archive.outputs.base.Sink`): it records saturation flags; tiles no
    #: cube touches are not written (unwritten chunks read as NaN).
    saturation: ClassVar[bool] = True
    blank_tiles: ClassVar[bool] = False

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
        zarr_format: int = 2,
        compression: str | None = None,
        names: Sequence[str] | None = None,
    ) -> MosaicStore:
        """Write the store's metadata and coordinates (no chunk data: unwritten chunks read as NaN).

        wavelengths: nm per output band (or None); band_indices: the source band index of each output band;
        fwhm: spectral full width at half maximum per output band, nm (or None); zarr_format: 2
        (GDAL >= 3.10 opens it) or 3; compression: the values' :data:`archive.codecs.COMPRESSIONS`
        name (None: the default).
        """
        nb = len(band_indices)
        if wavelengths is not None and len(wavelengths) != nb:
            raise ValueError(f"{len(wavelengths)} wavelengths for {nb} bands")
        if fwhm is not None and len(fwhm) != nb:
            raise ValueError(f"{len(fwhm)} fwhm values for {nb} bands")
        root, arrays = store_layout(grid, band_indices, wavelengths, fwhm, variable, attrs, compression, names)
        write_store(path, root, arrays, zarr_format)
        if zarr_format == 2:   # the band names GDAL shows (archive.outputs.pam); names: an index output's
            labels = list(names) if names is not None else band_labels(band_indices, wavelengths)
            write_band_pam(path, variable, 3, band_texts(labels, wavelengths, fwhm))
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

    def open_tile(self, band0: int, tile: tuple[int, int, int, int], nbands: int) -> _ZarrTileWriter:
        """A writer of one output tile (row0, col0, height, width) of bands band0.. (see :class:`~archive.outputs.base.TileWriter`)."""
        self.check_aligned(tile[2:], tile[0], tile[1])
        return _ZarrTileWriter(self.chunk_writer(), band0, tile)

    def chunk_writer(self) -> ChunkWriter:
        """A :class:`ChunkWriter` on the values array (it checks no tile alignment: see :meth:`check_aligned`)."""
        array = self._array(self.variable, "r+")
        remote = None if self.remote is None else f"{self.remote}/{self.variable}"
        writer = ChunkWriter(array, os.path.join(self.path, self.variable), remote)
        if remote is not None and writer.codec is None:
            raise ValueError(f"{self.path}: this Zarr layout cannot be written straight into a bucket")
        return writer

    def write_saturated(self, row0: int, col0: int, mask: np.ndarray) -> None:
        """Write whole chunks of the saturation flags: mask (h, w) bool at pixel (row0, col0)."""
        mask = np.asarray(mask)
        self.check_aligned(mask.shape, row0, col0)
        h, w = mask.shape
        self._array("saturated", "r+")[row0:row0 + h, col0:col0 + w] = mask.astype(np.uint8)



class _ZarrTileWriter(TileWriter):
    def __init__(self, writer: ChunkWriter, band0: int, tile):
        super().__init__(band0, tile)
        self.writer = writer

    def write(self, b: int, chunk: np.ndarray) -> None:
        self.writer.write(self.band0 + b, self.tile[0] // CHUNK, self.tile[1] // CHUNK, chunk)


def add_zarr_layers(path: str | os.PathLike, grid: Grid, spec, grid_attrs: dict | None = None) -> None:
    """Add the (y, x) float32 layer variables of ``spec`` to the mosaic store at ``path`` (metadata
    only: unwritten chunks read as NaN), with their attributes (plus ``grid_attrs``, the store's
    GeoZarr attributes of ``grid``), and the cube table at the root (beside the store's own root
    attributes)."""
    arrays = [ArraySpec(name, np.dtype(np.float32), grid.shape, (CHUNK, CHUNK), ("y", "x"),
                        {**layer_attrs(spec, name), **(grid_attrs or {})}, fill=float("nan"))
              for name in spec.names]
    add_arrays(path, arrays, layers_metadata(spec))


@dataclass(frozen=True)
class LayersStore(Sink):
    """Sink writing provenance layers into the variables ``names`` of a mosaic Zarr store: band b
    of a tile is layer ``names[band0 + b]``."""

    path: str
    names: tuple[str, ...]

    blank_tiles: ClassVar[bool] = False   # unwritten chunks read as NaN

    def open_tile(self, band0: int, tile, nbands: int) -> _LayersTileWriter:
        check_bands(band0, nbands, len(self.names), f"of {len(self.names)} layers")
        return _LayersTileWriter(self, band0, tile)


class _LayersTileWriter(TileWriter):
    def __init__(self, sink: LayersStore, band0: int, tile):
        import zarr

        super().__init__(band0, tile)
        self.sink = sink
        self.group = zarr.open_group(sink.path, mode="r+")   # the metadata read once per tile

    def write(self, b: int, chunk: np.ndarray) -> None:
        row0, col0, h, w = self.tile
        self.group[self.sink.names[self.band0 + b]][row0:row0 + h, col0:col0 + w] = chunk[:h, :w]


class ZarrFormat(OutputFormat):
    """The Zarr format (:class:`~archive.outputs.base.OutputFormat`): a store directory; provenance
    layers are its variables."""

    name = "zarr"
    suffixes = (".zarr",)
    label = "Zarr"
    media_type = ZARR_MEDIA_TYPE
    sink = MosaicStore

    def sibling(self, path: Path) -> Path | None:
        return None   # the layers are variables of the store

    @staticmethod
    def create(temp, path: Path, meta: OutputMeta) -> MosaicStore:
        return MosaicStore.create(temp(path), meta.grid, meta.wavelengths, meta.band_indices, meta.variable,
                                  meta.attrs, fwhm=meta.fwhm, zarr_format=meta.zarr_format,
                                  compression=meta.compression, names=meta.names)

    @staticmethod
    def create_layers(temp, path: Path, sink: MosaicStore, meta: OutputMeta, spec) -> LayersStore:
        add_zarr_layers(sink.path, meta.grid, spec, {**geozarr_attrs(meta.grid), **located_attrs(meta.grid)})
        return LayersStore(sink.path, tuple(spec.names))

    @staticmethod
    def finish(temp, path: Path, sink: MosaicStore, meta: OutputMeta):
        values = sink._array(sink.variable)
        return [(Path(sink.path), path)], lambda b, step: np.asarray(values[b, ::step, ::step], np.float32)

    @staticmethod
    def finish_layers(temp, path: Path, layers, meta: OutputMeta, spec) -> list:
        return []   # written into the store, which moves with the values

    def stac_assets(self, out: Path, href, variable: str, data: dict, dims: str = "band, y, x") -> dict[str, dict]:
        """``data``: the store (the group: what xarray opens, ``xr.open_zarr(href)``) and, for a Zarr
        v2 store, ``<variable>``: the values array by its own folder, what GDAL's Zarr driver opens
        as a raster, with the media type odc-stac reads through rasterio (:data:`GDAL_ZARR_MEDIA_TYPE`;
        ``zarr:node_type`` "array" says it is one array, not a group for xarray). ``dims``: the
        variable's dimensions, for the titles."""
        version = store_version(out)
        zarr_fields = {} if version is None else {"zarr:zarr_format": version}
        # the band names (eo:bands, odc-stac's aliases b<i>) on one asset only: the one loaders read
        store = {k: v for k, v in data.items() if k != "eo:bands"} if version == 2 else data
        assets = {"data": {"href": href(out), "type": self.media_type,
                           "title": f"{variable} ({self.label}{'' if version is None else f' v{version}'}, variable "
                                    f"'{variable}' ({dims}), float32, NaN where not covered)",
                           "archive:variable": variable, **zarr_fields, "zarr:node_type": "group",
                           "zarr:consolidated": True, **store}}
        if version == 2:
            assets[variable] = {"href": href(out / variable), "type": GDAL_ZARR_MEDIA_TYPE,
                                "title": f"{variable} ({dims}) as one raster, bands in that order (GDAL's Zarr "
                                         "driver: rasterio, odc-stac, QGIS)",
                                "archive:variable": variable, **zarr_fields, "zarr:node_type": "array", **data}
        return assets

    def provenance_assets(self, provenance: Path, href, fields: dict, describe) -> dict[str, dict]:
        _, names = describe(provenance)
        return {"provenance": {"href": href(provenance), "type": self.media_type,
                               "title": f"Provenance layers ({self.label})", "roles": ["metadata"], **fields,
                               "archive:layers": names}}


def store_version(path: str | os.PathLike) -> int | None:
    """The Zarr version of the store at ``path`` read from its root metadata (``zarr.json``: 3,
    ``.zgroup``: 2), None when it holds neither."""
    path = Path(path)
    if (path / "zarr.json").is_file():
        return 3
    return 2 if (path / ".zgroup").is_file() else None


#: The Zarr format's entry of :mod:`archive.outputs.registry`.
FORMAT = ZarrFormat()
