"""Where the provenance layers (:mod:`archive.provenance`) of a render are written.

- Zarr output: extra (y, x) float32 variables of the same store, one per layer, chunked like the
  values (1024 x 1024), NaN fill, CF attributes (``units``, ``long_name``, ``grid_mapping``; the
  time layer's ``units`` = ``seconds since <time_reference>``, so xarray decodes it as datetime64)
  and the GeoZarr ``proj:`` / ``spatial:`` attributes of the values.
- COG output ``<stem>.tif``: a sibling COG ``<stem>_provenance.tif``, one float32 band per layer
  (band descriptions = layer names), NaN nodata, overviews by nearest neighbour (an average of
  line numbers would be no line at all).
- ENVI output ``<stem>.hdr``: a sibling ENVI BSQ ``<stem>_provenance`` + ``<stem>_provenance.hdr``,
  band names = layer names.

Every file also says the cube table (``provenance_cubes``, JSON: per cube index the source id, cube
file base name and index within its flight) and the time reference.
"""

from __future__ import annotations

import json
import os
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np

from archive.grid import Grid
from archive.provenance import LAYERS, ProvenanceSpec
from archive.sinks import CHUNK, TileWriter

__all__ = ["LayersStore", "add_zarr_layers", "layer_attrs", "layers_cog_metadata", "layers_envi_header",
           "sibling_path"]

_BY_NAME = {layer.name: layer for layer in LAYERS}


def sibling_path(path: Path, fmt: str) -> Path | None:
    """The provenance file beside output ``path`` of format ``fmt`` ('cog': ``<stem>_provenance.tif``,
    'envi': the header ``<stem>_provenance.hdr``), None for 'zarr' (layers go into the store)."""
    path = Path(path)
    if fmt == "zarr":
        return None
    return path.with_name(f"{path.stem}_provenance{path.suffix}")


def layer_attrs(spec: ProvenanceSpec, name: str) -> dict:
    """CF-style attributes of one layer."""
    layer = _BY_NAME[name]
    attrs = {"long_name": layer.description, "grid_mapping": "spatial_ref"}
    if name == "time":
        attrs["units"] = spec.time_units   # CF: xarray decodes it as datetime64
    else:
        attrs["units"] = layer.units
    if name in ("view_zenith", "sun_zenith"):
        attrs.update(valid_min=0.0, valid_max=180.0)
    if name in ("view_azimuth", "sun_azimuth"):
        attrs.update(valid_min=0.0, valid_max=360.0)
    return attrs


def _common(spec: ProvenanceSpec) -> dict:
    return {"provenance_layers": ",".join(spec.names), "provenance_cubes": json.dumps(list(spec.cubes)),
            "time_reference": spec.reference_utc, "time_units": spec.time_units,
            "provenance_nodata": "NaN"}


def add_zarr_layers(path: str | os.PathLike, grid: Grid, spec: ProvenanceSpec, grid_attrs: dict | None = None) -> None:
    """Add the (y, x) float32 layer variables of ``spec`` to the mosaic store at ``path`` (metadata
    only: unwritten chunks read as NaN), with their attributes (plus ``grid_attrs``, the store's
    GeoZarr attributes of ``grid``), and the cube table at the root."""
    import dask.array as da
    import xarray as xr

    x, y = grid.xy_centres()
    data = {name: (("y", "x"), da.full(grid.shape, np.nan, dtype=np.float32, chunks=(CHUNK, CHUNK)))
            for name in spec.names}
    ds = xr.Dataset(data, coords={"y": y, "x": x})
    for name in spec.names:
        ds[name].attrs.update(layer_attrs(spec, name))
        ds[name].attrs.update(grid_attrs or {})
        ds[name].encoding.update({"chunks": (CHUNK, CHUNK), "_FillValue": np.float32(np.nan)})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")   # consolidated metadata is not in the Zarr v3 spec yet
        ds.drop_vars(["x", "y"]).to_zarr(os.fspath(path), mode="a", compute=False, zarr_format=3,
                                         consolidated=True)
    import zarr

    group = zarr.open_group(os.fspath(path), mode="r+")
    group.attrs.update(_common(spec))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        zarr.consolidate_metadata(os.fspath(path))


@dataclass(frozen=True)
class LayersStore:
    """Sink writing provenance layers into the variables ``names`` of a mosaic Zarr store: band b
    of a tile is layer ``names[band0 + b]``."""

    path: str
    names: tuple[str, ...]

    saturation: ClassVar[bool] = False
    blank_tiles: ClassVar[bool] = False
    overview_levels: ClassVar[int] = 0

    def open_tile(self, band0: int, tile, nbands: int) -> _LayersTileWriter:
        if not 0 <= band0 < band0 + nbands <= len(self.names):
            raise ValueError(f"layers {band0}..{band0 + nbands - 1} of {len(self.names)}")
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


def layers_cog_metadata(spec: ProvenanceSpec) -> str:
    """The GDAL_METADATA of the provenance COG: dataset items (cube table, time reference) and per
    band its DESCRIPTION (the layer name), units and meaning."""
    from archive.cog import gdal_metadata

    bands = []
    for name in spec.names:
        attrs = layer_attrs(spec, name)
        bands.append({"DESCRIPTION": name, "units": attrs["units"], "long_name": attrs["long_name"]})
    return gdal_metadata(_common(spec), bands)


def layers_envi_header(grid: Grid, spec: ProvenanceSpec, map_info: str) -> str:
    """The ENVI header of the provenance BSQ (float32 little-endian, NaN = no source)."""
    lines = [
        "ENVI",
        f"description = {{archive render provenance layers; NaN where not covered; time: {spec.time_units}}}",
        f"samples = {grid.width}",
        f"lines = {grid.height}",
        f"bands = {len(spec.names)}",
        "header offset = 0",
        "file type = ENVI Standard",
        "data type = 4",
        "interleave = bsq",
        "byte order = 0",
        f"map info = {map_info}",
        f"coordinate system string = {{{grid.crs.to_wkt(version='WKT1_ESRI')}}}",
        "data ignore value = NaN",
        "band names = {" + ", ".join(spec.names) + "}",
        f"time reference = {spec.reference_utc}",
        # cube index i of the 'cube' layer = the i-th entry: <source id>/<cube file base name>
        "provenance cubes = {" + ", ".join(f"{c['source']}/{c['cube']}" for c in spec.cubes) + "}",
    ]
    return "\n".join(lines) + "\n"
