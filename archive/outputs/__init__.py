"""Writers of rendered mosaics: Zarr, Cloud-Optimized GeoTIFF, ENVI BSQ, provenance layers, quicklook.

Every format is written by the render graph's own tile tasks, tile by tile, straight into the
output under its temporary name; no writer ever holds the whole mosaic, and no format is converted
from another. The package, top to bottom:

- :mod:`~archive.outputs.base`: the tile grid (``CHUNK``), the :class:`~archive.outputs.base.Sink`
  interface and its capabilities, tile writers, the output's metadata (what the graph imports);
- :mod:`~archive.outputs.registry`: the formats (suffix or command-line word -> format object);
- :mod:`~archive.outputs.zarr`, :mod:`~archive.outputs.cog` (+ :mod:`~archive.outputs.tiff`, the
  COG file layout), :mod:`~archive.outputs.envi`: one module per format, its sink and its format
  object ``FORMAT`` (:class:`~archive.outputs.base.OutputFormat`: name, suffixes, media type, sink,
  sidecars, STAC assets);
- :mod:`~archive.outputs.layers`: what the provenance layers say in each format;
- :mod:`~archive.outputs.quicklook`: the RGB preview;
- :mod:`~archive.outputs.publish`: :class:`~archive.outputs.publish.Output`, temporary names ->
  rename into place.

The package itself imports nothing (the graph imports :mod:`archive.outputs.base` without any
concrete writer); the names below are looked up in their modules on first use.
"""

from importlib import import_module

#: Public name -> the module of the package that owns it.
_OWNERS = {
    "CHUNK": "base", "OutputFormat": "base", "OutputMeta": "base", "Sink": "base", "TileWriter": "base",
    "variable_for_mode": "base",
    "FORMATS": "registry", "format_named": "registry", "output_format": "registry",
    "MosaicStore": "zarr", "LayersStore": "zarr", "mosaic_dataset": "zarr", "geozarr_attrs": "zarr",
    "CogSink": "cog", "EnviSink": "envi", "envi_data_path": "envi", "quicklook_bands": "quicklook",
    "Output": "publish",
}

__all__ = sorted(_OWNERS)


def __getattr__(name: str):
    if name in _OWNERS:
        return getattr(import_module(f"archive.outputs.{_OWNERS[name]}"), name)
    raise AttributeError(f"module 'archive.outputs' has no attribute {name!r}")
