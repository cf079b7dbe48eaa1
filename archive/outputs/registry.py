"""The output formats: which suffix is which format, and which writer writes it.

Each writer (a class of the format's module) says which files an output occupies (``files``) and
where its provenance sibling goes (``sibling``), creates the sinks the render graph writes through
under temporary names (``create``, ``create_layers``) and finishes them (``finish``,
``finish_layers``: header, COG layout; returns the renames). :class:`~archive.outputs.publish.Output`
drives them without knowing which format it holds; adding a format is adding an entry here.
"""

from __future__ import annotations

import importlib
import os
from pathlib import Path

from archive.errors import InputError

__all__ = ["FORMATS", "WRITERS", "output_format", "writer"]

#: Output suffix -> format name.
FORMATS = {".zarr": "zarr", ".tif": "cog", ".tiff": "cog", ".hdr": "envi"}
#: Format name -> its writer, ``module:class`` (imported when used).
WRITERS = {"zarr": "archive.outputs.zarr:ZarrWriter", "cog": "archive.outputs.cog:CogWriter",
           "envi": "archive.outputs.envi:EnviWriter"}


def output_format(path: str | os.PathLike) -> str:
    """'zarr' | 'cog' | 'envi' from the output suffix; InputError for anything else."""
    suffix = Path(path).suffix.lower()
    if suffix not in FORMATS:
        raise InputError(
            path, f"unknown output type {suffix or '(no suffix)'!r}",
            "end the path in .zarr (Zarr), .tif/.tiff (Cloud-Optimized GeoTIFF) or .hdr (ENVI BSQ)",
        )
    return FORMATS[suffix]


def writer(fmt: str):
    """The writer of format ``fmt`` ('zarr' | 'cog' | 'envi')."""
    module, name = WRITERS[fmt].split(":")
    return getattr(importlib.import_module(module), name)
