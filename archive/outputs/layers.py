"""What the provenance layers (:mod:`archive.geometry.provenance`) of a render say in every output format.

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

The Zarr variables are created by :func:`archive.outputs.zarr.add_zarr_layers`, the ENVI header by
:func:`archive.outputs.envi.envi_header`, the COG by :mod:`archive.outputs.cog`; this module gives
them the file names and the attributes.
"""

from __future__ import annotations

import json
from pathlib import Path

from archive.geometry.provenance import LAYERS, ProvenanceSpec

__all__ = ["layer_attrs", "layers_cog_metadata", "layers_metadata", "sibling_path"]

_BY_NAME = {layer.name: layer for layer in LAYERS}


def sibling_path(path: Path) -> Path:
    """The provenance file beside a single-file output ``path`` (COG: ``<stem>_provenance.tif``,
    ENVI: the header ``<stem>_provenance.hdr``); a Zarr output has none (the layers go into the store)."""
    path = Path(path)
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


def layers_metadata(spec: ProvenanceSpec) -> dict:
    """Dataset-level items every provenance output carries: the layer names, the cube table
    (``provenance_cubes``, JSON), the time reference and units, the nodata value."""
    return {"provenance_layers": ",".join(spec.names), "provenance_cubes": json.dumps(list(spec.cubes)),
            "time_reference": spec.reference_utc, "time_units": spec.time_units,
            "provenance_nodata": "NaN"}


def layers_cog_metadata(spec: ProvenanceSpec) -> str:
    """The GDAL_METADATA of the provenance COG: dataset items (cube table, time reference) and per
    band its DESCRIPTION (the layer name), units and meaning."""
    from archive.outputs.tiff import gdal_metadata

    bands = []
    for name in spec.names:
        attrs = layer_attrs(spec, name)
        bands.append({"DESCRIPTION": name, "units": attrs["units"], "long_name": attrs["long_name"]})
    return gdal_metadata(layers_metadata(spec), bands)
