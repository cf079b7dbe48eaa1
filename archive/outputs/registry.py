"""The output formats, one object each: which suffix and which command-line word is which format.

Each format module exports one :class:`~archive.outputs.base.OutputFormat` as ``FORMAT`` (name,
suffixes, media type, sink, sidecars, provenance sibling, its sinks' creation and finishing, its STAC
assets); :data:`FORMATS` lists them. :class:`~archive.outputs.publish.Output` drives them without
knowing which format it holds, the catalog asks them for their STAC assets, the CLI and the batch
render for their names; adding a format is adding a module and an entry here.
"""

from __future__ import annotations

import os
from pathlib import Path

from archive.errors import InputError
from archive.outputs.base import OutputFormat
from archive.outputs.cog import FORMAT as COG
from archive.outputs.envi import FORMAT as ENVI
from archive.outputs.zarr import FORMAT as ZARR

__all__ = ["FORMATS", "SPELLINGS", "format_named", "looks_like_output", "output_format"]

#: Every output format, Zarr (the default) first.
FORMATS: tuple[OutputFormat, ...] = (ZARR, COG, ENVI)
#: Every word that names a format on the command line (its name and its suffixes without the dot:
#: 'zarr', 'cog', 'tif', 'tiff', 'envi', 'hdr') -> the format.
SPELLINGS: dict[str, OutputFormat] = {word: fmt for fmt in FORMATS for word in fmt.spellings}
_BY_SUFFIX = {suffix: fmt for fmt in FORMATS for suffix in fmt.suffixes}


def _suffix_hint() -> str:
    each = [f"{'/'.join(f.suffixes)} ({f.label})" for f in FORMATS]
    return ", ".join(each[:-1]) + " or " + each[-1]


def output_format(path: str | os.PathLike) -> OutputFormat:
    """The format of an output named ``path``, from its suffix (any case); InputError for anything else."""
    suffix = Path(path).suffix.lower()
    if suffix not in _BY_SUFFIX:
        raise InputError(path, f"unknown output type {suffix or '(no suffix)'!r}", f"end the path in {_suffix_hint()}")
    return _BY_SUFFIX[suffix]


def looks_like_output(path) -> bool:
    """Whether ``path`` (a local path, or a path-like with a ``suffix``: an object-storage location)
    ends in an output suffix (any case): a single output, not a folder of them."""
    suffix = path.suffix if hasattr(path, "suffix") else Path(path).suffix
    return suffix.lower() in _BY_SUFFIX


def format_named(word: str | OutputFormat, where: str = "--format") -> OutputFormat:
    """The format a command-line word names (:data:`SPELLINGS`, any case; a format object is itself);
    InputError naming ``where`` for anything else."""
    if isinstance(word, OutputFormat):
        return word
    fmt = SPELLINGS.get(str(word).lower())
    if fmt is None:
        raise InputError(where, f"unknown output format {word!r}", f"use one of {', '.join(SPELLINGS)}")
    return fmt
