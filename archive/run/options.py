"""The options of one render, typed and checked once: :class:`RenderOptions`.

``archive render`` (:mod:`archive.run.command`), the library (:func:`archive.georectify`,
:func:`archive.mosaic`, :func:`archive.api.plan`) build the same object with
:meth:`RenderOptions.create`, from Python values or the command line's text; its defaults are the
defaults (:data:`~archive.params.DEFAULT_MAX_VIEW_ANGLE` for the view-angle limit). Checks that read
no pixels (:meth:`RenderOptions.check`) run before anything starts and give the
:class:`~archive.params.NavigationParams` the sources are opened with.
"""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from archive.errors import InputError, MissingInputError
from archive.geometry.navigation import projected_epsg
from archive.overlap import LAST, RULES, OverlapRule, overlap_rule
from archive.params import DEFAULT_MAX_VIEW_ANGLE, NavigationParams
from archive.sources.base import MODES
from archive.sources.select import parse_bands

__all__ = ["DEFAULT_MAX_VIEW_ANGLE", "KEYWORDS", "RenderOptions", "check_gsd", "grid_request", "parse_bounds"]


def _navigation(value) -> str | None:
    """``--navigation``: a trajectory file (made absolute), or a navigation source's name ('lcf', a track)."""
    if value is None:
        return None
    return os.path.abspath(value) if os.path.exists(value) or os.sep in str(value) else str(value)


def _navigation_columns(text) -> str | None:
    """``--navigation-columns`` checked (:func:`archive.formats.trajectory.parse_columns`), kept as given."""
    from archive.formats.trajectory import parse_columns

    parse_columns(text)
    return None if text is None else str(text)


def _parse_floats(text: str, option: str) -> list[float]:
    try:
        values = [float(v) for v in text.replace(" ", "").split(",") if v]
    except ValueError:
        raise InputError(option, f"expected comma-separated numbers, got {text!r}", f"e.g. {option} 550,650") from None
    if not values or not all(math.isfinite(v) for v in values):
        raise InputError(option, f"expected comma-separated numbers, got {text!r}", f"e.g. {option} 550,650")
    return values


def _wavelength_list(value) -> tuple[float, ...] | None:
    """None, 'NM,NM,...' (the CLI's text), one number or a sequence of numbers -> nm tuple."""
    if value is None:
        return None
    if isinstance(value, str):
        return tuple(_parse_floats(value, "--wavelengths"))
    items = [value] if isinstance(value, (int, float, np.number)) else list(value)
    try:
        values = tuple(float(v) for v in items)
    except (TypeError, ValueError):
        raise InputError("--wavelengths", f"expected wavelengths in nm, got {value!r}", "e.g. [650, 550, 450]") from None
    if not values or not all(math.isfinite(v) for v in values):
        raise InputError("--wavelengths", f"expected finite wavelengths in nm, got {value!r}", "e.g. [650, 550, 450]")
    return values


def _number(value, option: str, what: str) -> float | None:
    if value is None:
        return None
    try:
        return float(value)
    except (TypeError, ValueError):
        raise InputError(option, f"expected {what}, got {value!r}") from None


def _triple(value, option: str) -> tuple[float, float, float] | None:
    if value is None:
        return None
    try:
        out = tuple(float(v) for v in value)
    except (TypeError, ValueError):
        out = ()
    if len(out) != 3 or not all(math.isfinite(v) for v in out):
        raise InputError(option, f"expected three numbers, got {value!r}")
    return out  # type: ignore[return-value]


def parse_bounds(value, option: str = "--bounds") -> tuple[float, float, float, float] | None:
    """None, 'W,S,E,N' (the CLI's text) or four numbers -> (west, south, east, north), metres;
    InputError naming ``option`` unless four finite numbers with west < east and south < north."""
    if value is None:
        return None
    if isinstance(value, str):
        values = _parse_floats(value, option)
    else:
        try:
            values = [float(v) for v in value]
        except (TypeError, ValueError):
            values = []
    if len(values) != 4 or not all(math.isfinite(v) for v in values):
        raise InputError(option, f"expected four numbers W,S,E,N (metres in the output CRS), got {value!r}",
                         f"e.g. {option} 236000,3890000,236500,3890400")
    w, s, e, n = values
    if not (w < e and s < n):
        raise InputError(option, f"W,S,E,N = {value if isinstance(value, str) else values} is not a box",
                         "give west < east and south < north, metres in the output CRS")
    return (w, s, e, n)


def check_gsd(gsd) -> None:
    if gsd is None:
        raise InputError("--gsd", "the output pixel size is required", "pass --gsd M, or --like FILE to take "
                         "the grid of an existing output")
    if not (isinstance(gsd, (int, float)) and not isinstance(gsd, bool) and math.isfinite(gsd) and gsd > 0):
        raise InputError("--gsd", f"must be a positive number of metres, got {gsd!r}", "e.g. --gsd 0.25")


@dataclass(frozen=True)
class RenderOptions:
    """What to render and how: the options of ``archive render``, the keywords of
    :func:`archive.georectify`, :func:`archive.mosaic` and :func:`archive.api.plan` (same names).

    sources: raw flight directories and/or collection ids of ``archive``; gsd: output pixel size,
    m; fov: across-track field of view, degrees (None: the one the collections were ingested with;
    required for raw directories); calibration: a .icp file for raw sources; ground_height: metres
    above the ellipsoid, or 'auto' (the headers' 'ground elevation', a collection's ingest value);
    wavelengths: nm, the nearest bands are rendered (else ``bands``: 'all' or 0-based indices);
    mode: 'raw' | 'relative' | 'radiance' | 'reflectance' (None: radiance, raw DN when a source has no
    calibration); white_reference: the (nm, radiance) text file for 'reflectance'; sync_offset (s),
    boresight (roll, pitch, yaw deg), lever_arm (x, y, z m): None means as ingested for a collection,
    else 0; overlap: the :class:`~archive.overlap.OverlapRule` (resolved by :meth:`create` from its name,
    'last' | 'nadir' | 'mean'); crs: the output's projected CRS (None: the UTM zone holding most
    of the flights); max_view_angle: degrees off nadir at the field-of-view edge beyond which lines
    are left out of the meshes (turns); dem: a DEM GeoTIFF (any CRS) the meshes follow instead of
    the flat ground (exclusive with a numeric ground_height; :mod:`archive.terrain.dem`); dem_datum: its
    heights' vertical datum when its CRS does not declare one ('ellipsoid' | 'egm96' | 'egm2008');
    provenance: also write the per-pixel provenance layers (:mod:`archive.geometry.provenance`; written
    outputs only); zarr_format: 2 (default: what GDAL 3.10, hence QGIS 3.40 and rasterio, opens) or 3,
    the Zarr version of a .zarr output; compression: how Zarr chunks and COG tiles are compressed, a
    name of :data:`archive.codecs.COMPRESSIONS` ('fast', the default; 'small'; 'none').

    Build one with :meth:`create`, which normalises what callers give (a single source, CLI text
    such as ``'550,650'``, paths); :meth:`check` checks the rest without opening a file.
    """

    sources: tuple[str, ...]
    gsd: float
    archive: str | None = None
    fov: float | None = None
    calibration: str | None = None
    ground_height: float | str = "auto"
    wavelengths: tuple[float, ...] | None = None
    bands: str | tuple[int, ...] = "all"
    mode: str | None = None
    white_reference: str | None = None
    irradiance_calibration: str | None = None
    navigation: str | None = None   #: a raw flight's post-processed trajectory (SBET, CSV) instead of its .lcf
    navigation_columns: str | None = None   #: a CSV trajectory's column names, time=COL,lat=COL,...
    panels: str | None = None
    sync_offset: float | None = None
    boresight: tuple[float, float, float] | None = None
    lever_arm: tuple[float, float, float] | None = None
    overlap: OverlapRule = LAST
    crs: str | None = None
    max_view_angle: float = DEFAULT_MAX_VIEW_ANGLE
    dem: str | None = None
    dem_datum: str | None = None
    provenance: bool = False
    zarr_format: int = 2
    compression: str = "fast"
    bounds: tuple[float, float, float, float] | None = None
    align: bool = False
    like: str | None = None
    index: tuple[str, ...] = ()   #: spectral indices of the catalogue (NDVI...): one output band each
    expression: tuple[str, ...] = ()   #: NAME=EXPR band math (R<nm>): one output band each, after ``index``

    @classmethod
    def create(cls, sources, *, gsd=None, archive=None, fov=None, calibration=None, ground_height="auto",
               wavelengths=None, bands="all", mode=None, white_reference=None, irradiance_calibration=None,
               navigation=None, navigation_columns=None, panels=None, sync_offset=None,
               boresight=None, lever_arm=None, overlap=LAST, crs=None,
               max_view_angle=DEFAULT_MAX_VIEW_ANGLE, dem=None, dem_datum=None, provenance=False,
               zarr_format=2, compression=None, bounds=None, align=False, like=None, index=(),
               expression=()) -> RenderOptions:
        """A request from API keywords (or CLI values); InputError for malformed values. With
        ``like`` and no ``gsd``, the GSD is the one of that output (read here, metadata only)."""
        if isinstance(sources, (str, os.PathLike)):
            sources = [sources]
        def fspath(p):
            return None if p is None else os.fspath(p)

        like = None if like is None else os.path.abspath(os.fspath(like))
        if gsd is None and like is not None:
            from archive.outputs.like import read_grid

            gsd = read_grid(like).gsd
        return cls(
            sources=tuple(os.fspath(s) for s in (sources or ())), gsd=gsd, archive=fspath(archive),
            fov=_number(fov, "--fov", "degrees"), calibration=fspath(calibration),
            ground_height="auto" if ground_height is None else ground_height,
            wavelengths=_wavelength_list(wavelengths), bands=parse_bands(bands), mode=mode,
            white_reference=fspath(white_reference),
            irradiance_calibration=None if irradiance_calibration is None else os.path.abspath(irradiance_calibration),
            navigation=_navigation(navigation),
            navigation_columns=_navigation_columns(navigation_columns),
            panels=None if panels is None else os.path.abspath(panels),
            sync_offset=_number(sync_offset, "--sync-offset", "seconds"),
            boresight=_triple(boresight, "--boresight"), lever_arm=_triple(lever_arm, "--lever-arm"),
            overlap=overlap_rule(overlap), crs=None if crs is None else str(crs),
            max_view_angle=_number(max_view_angle, "--max-view-angle", "degrees"),
            dem=fspath(dem), dem_datum=None if dem_datum is None else str(dem_datum), provenance=bool(provenance),
            zarr_format=_zarr_format(zarr_format), compression=_compression(compression),
            bounds=parse_bounds(bounds), align=bool(align), like=like,
            index=_texts(index, r",", "--index"), expression=_texts(expression, r",(?=\s*[A-Za-z_][\w.+-]*\s*=)",
                                                                    "--expression"))

    def indices(self) -> list:
        """The :class:`~archive.outputs.bandmath.IndexSpec` of ``index`` then ``expression`` (checked,
        no camera needed; [] without either): an output of one band per index."""
        from archive.outputs.bandmath import parse_indices

        return parse_indices(self.index, self.expression) if self.index or self.expression else []

    def with_sources(self, sources: Sequence[str]) -> RenderOptions:
        """This request for other sources."""
        return dataclasses.replace(self, sources=tuple(os.fspath(s) for s in sources))

    def check(self) -> NavigationParams:
        """Checks that open no file (fast, before anything starts: no collection, DEM or output is
        read); the navigation parameters the sources are opened with. The meshes' field of view is
        decided once, with the ground, in :func:`archive.run.pipeline.open_inputs` (the
        :class:`~archive.params.MeshSpec`: ``fov``, else the one the collections were ingested with,
        :func:`archive.run.pipeline.field_of_view`)."""
        check_gsd(self.gsd)
        if not self.sources:
            raise InputError("SOURCE", "nothing to render",
                             "give flight directories or collection ids, or --archive A with --query-bbox/"
                             "--query-datetime/--query-wavelength")
        collections = [src for src in self.sources if not Path(src).is_dir()]
        if collections and self.archive is None:
            raise MissingInputError(collections[0], "flight directory",
                                    "give a raw flight directory, or a collection id together with --archive ARCHIVE")
        fov = self.fov
        if fov is None and len(collections) < len(self.sources):
            raise InputError("--fov", "the field of view is required for raw flight directories",
                             "pass --fov DEG (47.5 for a Pika L and for 'archive simulate' flights)")
        if fov is not None and not (math.isfinite(fov) and 0 < fov < 180):
            raise InputError("--fov", f"must be between 0 and 180 degrees, got {fov:g}")
        if self.sync_offset is not None and not math.isfinite(self.sync_offset):
            raise InputError("--sync-offset", f"must be a finite number of seconds, got {self.sync_offset!r}")
        if self.mode is not None and self.mode not in MODES:
            raise InputError("--mode", f"unknown radiometric mode {self.mode!r}", f"use one of {', '.join(MODES)}")
        if not (self.max_view_angle is not None and 0 < self.max_view_angle < 90):
            raise InputError("--max-view-angle", f"must be between 0 and 90 degrees, got {self.max_view_angle!r}",
                             f"the default is {DEFAULT_MAX_VIEW_ANGLE:g}")
        if self.crs is not None:
            projected_epsg(self.crs)
        if self.provenance and not self.overlap.single_source:
            single = [rule.name for rule in RULES.values() if rule.single_source]
            raise InputError("--provenance", f"with --overlap {self.overlap.name} an output pixel has no single source "
                             "pixel, so its provenance layers cannot be written",
                             f"use --overlap {' or '.join(single)} with --provenance")
        # reflectance without --white-reference: the flight's downwelling spectra, else the source refuses
        if self.panels and (self.mode != "reflectance" or self.white_reference or self.dem):
            raise InputError("--panels", "fits the empirical line of --mode reflectance on a flat ground",
                             "use --panels with --mode reflectance, without --white-reference or --dem")
        _check_dem(self)
        if self.index or self.expression:
            self.indices()
            if self.wavelengths is not None or self.bands != "all":
                flag = "--index" if self.index else "--expression"
                raise InputError(flag, f"chooses the bands its indices read, so --{'wavelengths' if self.wavelengths else 'bands'} "
                                 "has nothing to choose", f"leave --wavelengths/--bands out, or {flag}")
        if self.like is not None and (self.bounds is not None or self.align):
            raise InputError("--like", f"takes the whole grid of {self.like}, so --bounds and --align have nothing "
                             "to decide", "leave --bounds/--align out, or --like")
        return NavigationParams(sync_offset=None if self.sync_offset is None else float(self.sync_offset),
                                boresight_deg=self.boresight, lever_arm_m=self.lever_arm)


def grid_request(options: RenderOptions):
    """The :class:`~archive.grid.GridRequest` of ``options`` (``--like``'s output read once, here:
    metadata only), checked against ``--gsd`` and ``--crs``."""
    from archive.grid import GridRequest

    if options.like is None:
        return GridRequest(None, options.bounds, options.align)
    from archive.outputs.like import read_grid

    like = read_grid(options.like)
    if not math.isclose(float(options.gsd), like.gsd, rel_tol=1e-9):
        raise InputError("--gsd", f"{options.gsd:g} m, but --like {options.like} has {like.gsd:g} m pixels",
                         "leave --gsd out with --like")
    if options.crs is not None and projected_epsg(options.crs) != like.epsg:
        raise InputError("--crs", f"{options.crs}, but --like {options.like} is in EPSG:{like.epsg}",
                         "leave --crs out with --like")
    return GridRequest(like)


def _check_dem(options: RenderOptions) -> None:
    """--dem / --dem-datum: exclusive with a numeric --ground-height (the DEM itself is opened, once,
    by :func:`archive.run.pipeline.open_inputs`)."""
    if options.dem is None:
        if options.dem_datum is not None:
            raise InputError("--dem-datum", "gives the vertical datum of a DEM, but no --dem was given",
                             "add --dem FILE, or leave --dem-datum out")
        return
    if str(options.ground_height).strip().lower() != "auto":
        raise InputError("--dem", f"--dem and --ground-height {options.ground_height} are exclusive: the DEM "
                         "gives the ground", "leave --ground-height out")


def _texts(value, separator: str, option: str) -> tuple[str, ...]:
    """--index / --expression: None, one text or several -> a tuple of texts; a text holding several
    (the recipe's command line joins them: 'NDVI,EVI') split at ``separator`` (a regular expression)."""
    import re

    if value is None:
        return ()
    items = [value] if isinstance(value, str) else list(value)
    if not all(isinstance(v, str) for v in items):
        raise InputError(option, f"expected names or texts, got {value!r}")
    return tuple(t.strip() for v in items for t in re.split(separator, v) if t.strip())


def _compression(value) -> str:
    """--compression: a name of :data:`archive.codecs.COMPRESSIONS` (None: the default)."""
    from archive.codecs import compression

    return compression(value).name


def _zarr_format(value) -> int:
    """--zarr-format: 2 or 3."""
    try:
        version = int(str(value).strip())
    except ValueError:
        version = 0
    if version not in (2, 3):
        raise InputError("--zarr-format", f"expected 2 or 3, got {value!r}",
                         "2 opens in GDAL >= 3.10 (QGIS, rasterio); 3 in zarr-python 3 and xarray")
    return version


#: The keyword names of :class:`RenderOptions` besides ``sources``: what :func:`archive.mosaic` and
#: :func:`archive.georectify` accept as render options.
KEYWORDS = tuple(f.name for f in dataclasses.fields(RenderOptions) if f.name != "sources")
