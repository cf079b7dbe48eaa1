"""What every output writer shares: the tile grid, the sink interface and the output's metadata.

A *sink* is the small picklable handle through which the render graph's tile tasks write one
output format, one output tile (CHUNK x CHUNK px, chunk-aligned; ENVI: row strips) of a range of
bands at a time; tiles never share bytes, so tasks need no locks. Every sink derives from
:class:`Sink` and declares what it can do (its capabilities, read by the graph builder instead of
testing which format it is):

- ``saturation``: it records the saturation flags (``write_saturated``; Zarr);
- ``blank_tiles``: tiles no cube touches must be written (NaN), having no fill value (ENVI, COG);
- ``overview_levels``: overview levels the graph computes (``tiles``, ``children``, ``overview``; COG);
- ``tile_size``: (height, width) of the graph's output tiles for it.

``open_tile(band0, tile, nbands)`` returns a :class:`TileWriter`. Rasters are ``(band, y, x)``
float32, NaN where no line covers a pixel; ``y`` grows southwards (row 0 is the northern edge).
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

import numpy as np

from archive.catalog.product import UNITS
from archive.errors import InputError
from archive.grid import Grid

__all__ = ["CHUNK", "OutputFormat", "OutputMeta", "Sink", "TileWriter", "all_nan", "band_labels", "check_bands",
           "check_tile", "chunk_buffer", "variable_for_mode"]

#: Output tile = Zarr chunk edge, pixels.
CHUNK = 1024

_local = threading.local()


def chunk_buffer(width: int = CHUNK) -> np.ndarray:
    """This thread's reusable (CHUNK, width) float32 C-contiguous tile buffer (contents undefined):
    one per thread and width (CHUNK for chunk tiles, a row strip's width for ENVI)."""
    buffers = getattr(_local, "buffers", None)
    if buffers is None:
        buffers = _local.buffers = {}
    buffer = buffers.get(width)
    if buffer is None:
        if len(buffers) > 2:   # strips of several outputs' widths: keep the chunk buffer only
            for w in [w for w in buffers if w != CHUNK]:
                del buffers[w]
        buffer = buffers[width] = np.empty((CHUNK, width), np.float32)
    return buffer


class Sink:
    """The capabilities of a sink, as the graph builder reads them (the defaults: a format without
    fill value, without saturation flags and overviews, in CHUNK x CHUNK tiles). Subclasses override
    what differs and implement ``open_tile``."""

    saturation: ClassVar[bool] = False
    blank_tiles: ClassVar[bool] = True
    overview_levels: ClassVar[int] = 0

    @property
    def tile_size(self) -> tuple[int, int]:
        """(height, width) of the graph's output tiles for this sink, pixels."""
        return (CHUNK, CHUNK)

    def open_tile(self, band0: int, tile: tuple[int, int, int, int], nbands: int) -> TileWriter:
        raise NotImplementedError


class TileWriter:
    """Writes one output tile (row0, col0, height, width) of ``nbands`` bands from band ``band0``.

    ``buffer()``, called before each band, is a reusable (CHUNK, CHUNK) float32 buffer of this
    thread (an ENVI row strip's: (CHUNK, strip width)); ``write(b, chunk)`` takes band ``band0 + b``
    as such a float32 C-contiguous array whose part outside the grid is NaN, and may go on reading it
    (ENVI: written by another thread) until a later ``buffer()`` returns it again, so a caller fills
    each band into the buffer ``buffer()`` just returned; ``close()`` finishes the tile and returns
    what the graph passes on (COG: the tile's first overview level; others: None). Usable as a
    context manager (closed on success only).
    """

    def __init__(self, band0: int, tile: tuple[int, int, int, int]):
        self.band0, self.tile = band0, tile

    def buffer(self) -> np.ndarray:
        return chunk_buffer()

    def write(self, b: int, chunk: np.ndarray) -> None:
        raise NotImplementedError

    def close(self):
        return None

    def abort(self) -> None:
        """Release what the writer holds without finishing the tile (after an error)."""

    def __enter__(self):
        return self

    def __exit__(self, kind, value, tb) -> None:
        if kind is not None:
            self.abort()


def all_nan(chunk: np.ndarray) -> bool:
    return bool(np.isnan(chunk[CHUNK // 2]).all() and np.isnan(chunk).all())


def check_tile(tile, height: int, width: int, size: tuple[int, int] = (CHUNK, CHUNK)) -> None:
    row0, col0, h, w = tile
    th, tw = size
    if row0 % th or col0 % tw or not (0 < h <= th and 0 < w <= tw) \
            or h != min(th, height - row0) or w != min(tw, width - col0):
        raise ValueError(f"tile {tile} is not one {th} x {tw} px tile of a {height} x {width} mosaic")


def check_bands(band0: int, nbands: int, total: int, what: str) -> None:
    """ValueError unless bands band0 .. band0 + nbands - 1 lie within the ``total`` of a sink (``what``
    names them: 'of a 3-band ENVI file')."""
    if not 0 <= band0 < band0 + nbands <= total:
        raise ValueError(f"bands {band0}..{band0 + nbands - 1} {what}")


_VARIABLES = {"raw": "dn", "relative": "relative", "radiance": "radiance", "reflectance": "reflectance"}

#: Units of each data variable, UDUNITS strings (CF ``units``; GDAL's band unit type; the Item's
#: ``raster:bands`` unit): :data:`archive.catalog.product.UNITS`.
VARIABLE_UNITS = UNITS


def variable_for_mode(mode: str) -> str:
    """Name of the data variable for a radiometric mode ('raw' -> 'dn', 'radiance' -> 'radiance'...)."""
    try:
        return _VARIABLES[mode]
    except KeyError:
        raise InputError("--mode", f"unknown mode {mode!r}", f"use one of {', '.join(_VARIABLES)}") from None


def band_labels(band_indices: Sequence[int], wavelengths: Sequence[float] | None) -> list[str]:
    """Band names as GDAL, QGIS and ENVI show them: the wavelength (nm) with its unit ("650.0 nm"),
    else the source band counted from 1 as those tools count bands ("source band 4")."""
    if wavelengths is None:
        return [f"source band {int(i) + 1}" for i in band_indices]
    return [f"{float(w):.1f} nm" for w in wavelengths]


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
    zarr_format: int = 2   #: the Zarr version of a .zarr output (other formats ignore it)
    compression: str = "fast"   #: :data:`archive.codecs.COMPRESSIONS` name (Zarr chunks, COG tiles; not ENVI)
    names: tuple[str, ...] | None = None   #: band names instead of the wavelengths' (an index output's: the indices)

    def __post_init__(self) -> None:
        object.__setattr__(self, "band_indices", tuple(int(i) for i in self.band_indices))
        if self.names is not None:
            object.__setattr__(self, "names", tuple(str(n) for n in self.names))
            if len(self.names) != len(self.band_indices):
                raise ValueError(f"{len(self.names)} band names for {len(self.band_indices)} bands")
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
        """Band names as GDAL, QGIS and ENVI show them: the wavelength with its unit ("650.0 nm"),
        else the source band counted from 1 as those tools count bands ("source band 4"); ``names``
        when given (an index output's: "NDVI")."""
        return list(self.names) if self.names is not None else band_labels(self.band_indices, self.wavelengths)

    @property
    def units(self) -> str | None:
        """The values' unit (:data:`VARIABLE_UNITS`), None for an unknown variable."""
        return VARIABLE_UNITS.get(self.variable)


#: ``href(path)``: a file's address relative to the STAC Item that names it (the catalog's).
Href = Callable[[Path], str]
#: ``describe(path)``: (raster:bands or None, layer names) of a written provenance output, read from
#: it (the catalog's: rasterio for a raster file, the store's variables for a Zarr store).
Describe = Callable[[Path], tuple[list[dict] | None, list[str]]]


class OutputFormat:
    """One output format, everything the package knows of it (:mod:`archive.outputs.registry` lists
    them; each format module exports its one instance as ``FORMAT``):

    - ``name`` ('zarr' | 'cog' | 'envi'), ``suffixes`` (the first is the one written when only the
      format is given: ``archive render --query... --format``), ``spellings`` (the words that name
      it on the command line: its name and its suffixes without the dot), ``label`` (for people),
      ``media_type`` (of its data asset), ``sink`` (the :class:`Sink` class its tiles are written
      through);
    - ``files(path)``: the paths an output at ``path`` occupies (ENVI: data and header);
      ``sidecars(path)``: those besides ``path`` itself; ``sibling(path)``: where its provenance
      layers go (None: into the output itself);
    - ``create``, ``create_layers``, ``finish``, ``finish_layers``: the sinks under temporary names
      and their finishing (header, COG layout; returns the renames), driven by
      :class:`~archive.outputs.publish.Output`;
    - ``stac_assets``, ``provenance_assets``: its assets in the STAC Item the catalog writes
      (:func:`archive.catalog.product.product_item`).

    Instances are stateless: one per format (equal when of the same format, also after pickling).
    """

    name: ClassVar[str]
    suffixes: ClassVar[tuple[str, ...]]
    label: ClassVar[str]
    media_type: ClassVar[str]
    sink: ClassVar[type[Sink]]

    @property
    def suffix(self) -> str:
        """The suffix written when only the format is named ('.zarr', '.tif', '.hdr')."""
        return self.suffixes[0]

    @property
    def spellings(self) -> tuple[str, ...]:
        """The words naming this format on the command line: its name, then its suffixes without the dot."""
        return tuple(dict.fromkeys((self.name, *(s.lstrip(".") for s in self.suffixes))))

    def files(self, path: Path) -> list[Path]:
        """Every path an output at ``path`` occupies (``path`` included)."""
        return [path, *self.sidecars(path)]

    def sidecars(self, path: Path) -> list[Path]:
        """The files an output at ``path`` occupies besides ``path`` itself (none by default)."""
        return []

    def sibling(self, path: Path) -> Path | None:
        raise NotImplementedError

    def stac_assets(self, out: Path, href: Href, variable: str, data: dict) -> dict[str, dict]:
        """The assets of output ``out`` in its STAC Item: ``data`` (the values, carrying the fields
        ``data``: roles, projection, raster:bands, eo:bands) and any sidecar asset."""
        raise NotImplementedError

    def provenance_assets(self, provenance: Path, href: Href, fields: dict, describe: Describe) -> dict[str, dict]:
        """The assets of a provenance output of this format at ``provenance`` (a sibling file, or a
        store of its own): ``provenance`` (``fields``: the projection; plus ``raster:bands`` and
        ``archive:layers`` as ``describe`` reads them) and any sidecar asset."""
        raise NotImplementedError

    def __repr__(self) -> str:
        return f"<output format {self.name}>"

    def __eq__(self, other: object) -> bool:
        return isinstance(other, OutputFormat) and other.name == self.name

    def __hash__(self) -> int:
        return hash(self.name)
