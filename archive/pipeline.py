"""``archive render`` and ``archive.mosaic``: georectify flights into one mosaic on Dask.

One request (:class:`RenderRequest`: the options of ``archive render``, the keywords of
:func:`archive.render` and :func:`archive.mosaic`) goes through the same steps whatever comes out:

1. :func:`check_request`: checks that read no pixels (clear one-line errors, before anything starts);
2. :func:`open_inputs`: open the sources (:func:`archive.sources.open_source`), select the bands,
   settle the radiometric mode and the ground height;
3. :func:`plan_output`: cube meshes, output grid and cube windows (metadata only, no GL);
4. either :func:`render`: build the render graph (:mod:`archive.graph.build`), whose tile tasks
   write the requested format directly (Zarr chunks, ENVI rows, compressed COG tiles) under a
   temporary name, run it on a local cluster (one worker process with a thread per core: render
   tasks draw on its GL thread while the other threads write) or on ``scheduler``, then finish the
   output (ENVI header, COG layout) and move it into place (nothing is left at ``out`` when
   anything fails); or :func:`mosaic`: the same plan as a lazy ``xarray.Dataset``
   (:mod:`archive.graph.lazy`) computed on demand.

Batch jobs (``per_flight``): one output per source, ``out/<name>.<format>``, all in one graph (one
progress bar). Band groups are sized from the workers' memory limits (:func:`_task_budget`).
"""

from __future__ import annotations

import dataclasses
import math
import os
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from archive.errors import ArchiveError, InputError, MissingInputError, RenderError
from archive.graph.mosaic import KEYED, RULES, WINNER_RULES
from archive.outputs import Output, mosaic_dataset, variable_for_mode
from archive.navigation import DEFAULT_MAX_VIEW_ANGLE, projected_epsg
from archive.params import NavigationParams, RenderParams
from archive.sources.base import MODES

if TYPE_CHECKING:
    from archive.graph.plan import RenderPlan

__all__ = ["OUTPUT_BUDGET", "TASK_BUDGET_BYTES", "Inputs", "OutputPlan", "RenderRequest", "build_output",
           "check_request", "check_size", "describe", "mosaic", "open_inputs", "plan", "plan_output", "render",
           "resolve_ground_height", "select_bands"]

#: Largest render task: cube window x 4 bands x float32 (plus its flags), bytes.
TASK_BUDGET_BYTES = 2 * 1024**3
#: Largest output, in pixels x bands.
OUTPUT_BUDGET = 4e10
#: A requested wavelength must lie within this many band widths of a band.
WAVELENGTH_TOLERANCE = 1.5


# ---------------------------------------------------------------------------------------------
# The request
# ---------------------------------------------------------------------------------------------
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


def _band_list(value) -> str | tuple[int, ...]:
    """'all' (or None), '2,4' (the CLI's text), one index or a sequence of 0-based indices."""
    if value is None or (isinstance(value, str) and value.strip().lower() == "all"):
        return "all"
    if isinstance(value, str):
        try:
            out = tuple(int(b) for b in value.split(",") if b.strip())
        except ValueError:
            raise InputError("--bands", f"expected 'all' or 0-based band indices, got {value!r}") from None
        if not out:
            raise InputError("--bands", f"expected 'all' or 0-based band indices, got {value!r}")
        return out
    items = [value] if isinstance(value, (int, np.integer)) else list(value)
    if not items or not all(isinstance(b, (int, np.integer)) and not isinstance(b, bool) for b in items):
        raise InputError("--bands", f"expected 'all' or 0-based band indices, got {value!r}")
    return tuple(int(b) for b in items)


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


@dataclass(frozen=True)
class RenderRequest:
    """What to render: the options of ``archive render`` (keyword names as in :func:`archive.render`).

    sources: raw flight directories and/or collection ids of ``archive``; gsd: output pixel size,
    m; fov: across-track field of view, degrees (None: the one the collections were ingested with;
    required for raw directories); calibration: a .icp file for raw sources; ground_height: metres
    above the ellipsoid, or 'auto' (the headers' 'ground elevation', a collection's ingest value);
    wavelengths: nm, the nearest bands are rendered (else ``bands``: 'all' or 0-based indices);
    mode: 'raw' | 'relative' | 'radiance' | 'reflectance' (None: radiance, raw DN when a source has no
    calibration); white_reference: the (nm, radiance) text file for 'reflectance'; sync_offset (s),
    boresight (roll, pitch, yaw deg), lever_arm (x, y, z m): None means as ingested for a collection,
    else 0; overlap: 'last' | 'nadir' | 'mean'; crs: the output's projected CRS (None: the UTM zone holding most
    of the flights); max_view_angle: degrees off nadir at the field-of-view edge beyond which lines
    are left out of the meshes (turns); dem: a DEM GeoTIFF (any CRS) the meshes follow instead of
    the flat ground (exclusive with a numeric ground_height; :mod:`archive.dem`); dem_datum: its
    heights' vertical datum when its CRS does not declare one ('ellipsoid' | 'egm96' | 'egm2008');
    provenance: also write the per-pixel provenance layers (:mod:`archive.provenance`).

    Build one with :meth:`create`, which normalises what callers give (a single source, CLI text
    such as ``'550,650'``, paths); checks that need files are :func:`check_request`'s.
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
    sync_offset: float | None = None
    boresight: tuple[float, float, float] | None = None
    lever_arm: tuple[float, float, float] | None = None
    overlap: str = "last"
    crs: str | None = None
    max_view_angle: float = DEFAULT_MAX_VIEW_ANGLE
    dem: str | None = None
    dem_datum: str | None = None
    provenance: bool = False

    @classmethod
    def create(cls, sources, *, gsd, archive=None, fov=None, calibration=None, ground_height="auto",
               wavelengths=None, bands="all", mode=None, white_reference=None, sync_offset=None,
               boresight=None, lever_arm=None, overlap="last", crs=None,
               max_view_angle=DEFAULT_MAX_VIEW_ANGLE, dem=None, dem_datum=None, provenance=False) -> RenderRequest:
        """A request from API keywords (or CLI values); InputError for malformed values."""
        if isinstance(sources, (str, os.PathLike)):
            sources = [sources]
        def fspath(p):
            return None if p is None else os.fspath(p)

        return cls(
            sources=tuple(os.fspath(s) for s in (sources or ())), gsd=gsd, archive=fspath(archive),
            fov=_number(fov, "--fov", "degrees"), calibration=fspath(calibration),
            ground_height="auto" if ground_height is None else ground_height,
            wavelengths=_wavelength_list(wavelengths), bands=_band_list(bands), mode=mode,
            white_reference=fspath(white_reference),
            sync_offset=_number(sync_offset, "--sync-offset", "seconds"),
            boresight=_triple(boresight, "--boresight"), lever_arm=_triple(lever_arm, "--lever-arm"),
            overlap=overlap, crs=None if crs is None else str(crs),
            max_view_angle=_number(max_view_angle, "--max-view-angle", "degrees"),
            dem=fspath(dem), dem_datum=None if dem_datum is None else str(dem_datum), provenance=bool(provenance))

    def with_sources(self, sources: Sequence[str]) -> RenderRequest:
        """This request for other sources."""
        return dataclasses.replace(self, sources=tuple(os.fspath(s) for s in sources))


# ---------------------------------------------------------------------------------------------
# Checks
# ---------------------------------------------------------------------------------------------
def select_bands(source, wavelengths: Sequence[float] | None = None,
                 bands: str | Sequence[int] | None = "all") -> list[int]:
    """Source band indices to render: nearest bands to ``wavelengths`` (nm), else ``bands``.

    bands: 'all', comma-separated 0-based indices, or a sequence of them. A wavelength farther than
    1.5 band widths from every band is an InputError naming the source's range.
    """
    nbands = source.cubes[0].bands
    where = source.label
    if wavelengths is not None:
        wl = None if source.wavelengths is None else np.asarray(source.wavelengths, float)
        if wl is None or len(wl) == 0:
            raise InputError(where, "the cubes have no 'wavelength' list", "use --bands all")
        spacing = np.abs(np.gradient(wl)) if len(wl) > 1 else np.array([10.0])
        out: list[int] = []
        for w in wavelengths:
            i = int(np.argmin(np.abs(wl - w)))
            if abs(wl[i] - w) > WAVELENGTH_TOLERANCE * spacing[i]:
                raise InputError(
                    "--wavelengths", f"no band near {w:g} nm in {where} (bands span "
                    f"{wl.min():.1f}-{wl.max():.1f} nm, nearest {wl[i]:.1f} nm)",
                    "choose wavelengths inside the cubes' range",
                )
            if i not in out:
                out.append(i)
        return out
    chosen = _band_list(bands)
    if chosen == "all":
        return list(range(nbands))
    bad = [b for b in chosen if not 0 <= b < nbands]
    if bad:
        raise InputError("--bands", f"band {bad[0]} out of range 0..{nbands - 1}")
    return list(dict.fromkeys(chosen))


def resolve_ground_height(value: str | float | None, sources: Sequence) -> float:
    """A number (metres above the ellipsoid), or 'auto' (:func:`archive.sources.ground.auto_ground_height`:
    a collection's ingest record, else the headers' 'ground elevation'); refused when the camera is
    not plausibly above it."""
    from archive.sources.ground import auto_ground_height, camera_altitudes, check_ground_height

    if value is not None and str(value).strip().lower() != "auto":
        try:
            h = float(value)
        except ValueError:
            raise InputError("--ground-height", f"expected metres or 'auto', got {value!r}") from None
        if not math.isfinite(h):
            raise InputError("--ground-height", f"expected a finite height, got {value!r}")
        for source in sources:
            check_ground_height(h, camera_altitudes(source), source.label, "--ground-height")
        return h
    return auto_ground_height(sources)


def _nice(x: float) -> float:
    """Round up to 1, 2 or 5 x 10^k."""
    k = 10 ** math.floor(math.log10(x))
    return next(m * k for m in (1, 2, 5, 10) if m * k >= x)


def check_size(plan, gsd: float) -> None:
    """InputError when the output or a render task would be absurdly large for this GSD."""
    grid = plan.grid
    total = grid.width * grid.height * plan.nbands
    group = max(b1 - b0 for b0, b1 in plan.groups)
    biggest = max((job.window.width * job.window.height for job in plan.jobs), default=0)
    task = biggest * (group * 4 + 2)
    if total > OUTPUT_BUDGET:
        suggest = _nice(gsd * math.sqrt(total / OUTPUT_BUDGET))
        raise InputError(
            "--gsd", f"{gsd:g} m gives a {grid.width} x {grid.height} px x {plan.nbands}-band output "
            f"({total:.3g} pixel-bands, {total * 4 / 1024**4:.1f} TiB), over the {OUTPUT_BUDGET:.0e} limit",
            f"use --gsd {suggest:g} or larger, or fewer --wavelengths",
        )
    if task > TASK_BUDGET_BYTES:
        suggest = _nice(gsd * math.sqrt(task / TASK_BUDGET_BYTES))
        raise InputError(
            "--gsd", f"{gsd:g} m makes one cube cover {biggest:.3g} px ({task / 1024**3:.1f} GiB per "
            f"{group}-band render task, limit {TASK_BUDGET_BYTES / 1024**3:.0f} GiB)",
            f"use --gsd {suggest:g} or larger",
        )


def _read_white_reference(path: str, wavelengths) -> np.ndarray:
    """(bands,) white radiance from a two-column text file (nm, radiance), interpolated to the bands."""
    p = Path(path)
    if not p.is_file():
        raise MissingInputError(p, "white reference spectrum", "check --white-reference")
    try:
        table = np.loadtxt(p, delimiter=None if "," not in p.read_text()[:200] else ",", ndmin=2)
    except ValueError as exc:
        raise InputError(p, f"cannot read a (wavelength nm, radiance) table: {exc}") from None
    if table.shape[1] < 2 or table.shape[0] < 2:
        raise InputError(p, "expected two columns (wavelength nm, radiance) and at least two rows")
    if wavelengths is None:
        raise InputError(p, "the cubes have no wavelengths to interpolate the white reference to")
    order = np.argsort(table[:, 0])
    wl = np.asarray(wavelengths, float)
    step = float(np.min(np.abs(np.diff(wl)))) if len(wl) > 1 else 1.0
    lo, hi = float(table[order[0], 0]), float(table[order[-1], 0])
    if wl.min() < lo - step / 2 or wl.max() > hi + step / 2:  # np.interp would clamp silently
        raise InputError(p, f"the white reference spans {lo:g}-{hi:g} nm but the bands span "
                         f"{wl.min():g}-{wl.max():g} nm", "give a white reference covering every band")
    return np.interp(wl, table[order, 0], table[order, 1])


def _check_gsd(gsd) -> None:
    if not (isinstance(gsd, (int, float)) and not isinstance(gsd, bool) and math.isfinite(gsd) and gsd > 0):
        raise InputError("--gsd", f"must be a positive number of metres, got {gsd!r}", "e.g. --gsd 0.25")


def check_request(request: RenderRequest) -> NavigationParams:
    """Checks that read no pixels (fast, before anything starts); the navigation parameters the
    sources are opened with (the field of view of collections read from their records)."""
    _check_gsd(request.gsd)
    if not request.sources:
        raise InputError("SOURCE", "nothing to render",
                         "give flight directories or collection ids, or --archive A with --query-bbox/"
                         "--query-datetime/--query-wavelength")
    collections = [src for src in request.sources if not Path(src).is_dir()]
    if collections and request.archive is None:
        raise MissingInputError(collections[0], "flight directory",
                                "give a raw flight directory, or a collection id together with --archive ARCHIVE")
    fov = request.fov
    if fov is None and len(collections) < len(request.sources):
        raise InputError("--fov", "the field of view is required for raw flight directories",
                         "pass --fov DEG (47.5 for a Pika L and for 'archive simulate' flights)")
    if fov is None:
        fov = _collection_fov(request.archive, collections)
    if not (math.isfinite(fov) and 0 < fov < 180):
        raise InputError("--fov", f"must be between 0 and 180 degrees, got {fov:g}")
    if request.sync_offset is not None and not math.isfinite(request.sync_offset):
        raise InputError("--sync-offset", f"must be a finite number of seconds, got {request.sync_offset!r}")
    if request.mode is not None and request.mode not in MODES:
        raise InputError("--mode", f"unknown radiometric mode {request.mode!r}", f"use one of {', '.join(MODES)}")
    if not (request.max_view_angle is not None and 0 < request.max_view_angle < 90):
        raise InputError("--max-view-angle", f"must be between 0 and 90 degrees, got {request.max_view_angle!r}",
                         f"the default is {DEFAULT_MAX_VIEW_ANGLE:g}")
    if request.crs is not None:
        projected_epsg(request.crs)
    if request.overlap not in RULES:
        raise InputError("--overlap", f"unknown overlap rule {request.overlap!r}", f"use one of {', '.join(RULES)}")
    if request.provenance and request.overlap not in WINNER_RULES:
        raise InputError("--provenance", f"with --overlap {request.overlap} an output pixel has no single source "
                         "pixel, so its provenance layers cannot be written",
                         f"use --overlap {' or '.join(WINNER_RULES)} with --provenance")
    if request.mode == "reflectance" and not request.white_reference:
        raise InputError("--mode", "reflectance needs a white reference spectrum", "pass --white-reference FILE")
    _check_dem(request)
    return NavigationParams(fov_deg=float(fov),
                            sync_offset=None if request.sync_offset is None else float(request.sync_offset),
                            boresight_deg=request.boresight, lever_arm_m=request.lever_arm)


def _check_dem(request: RenderRequest) -> None:
    """--dem / --dem-datum: exclusive with a numeric --ground-height; the DEM opens (a raster with a
    CRS, whose vertical datum is declared or given, and whose geoid grid PROJ finds): metadata only."""
    if request.dem is None:
        if request.dem_datum is not None:
            raise InputError("--dem-datum", "gives the vertical datum of a DEM, but no --dem was given",
                             "add --dem FILE, or leave --dem-datum out")
        return
    if str(request.ground_height).strip().lower() != "auto":
        raise InputError("--dem", f"--dem and --ground-height {request.ground_height} are exclusive: the DEM "
                         "gives the ground", "leave --ground-height out")
    from archive.dem import open_dem

    open_dem(request.dem, request.dem_datum)


def _collection_fov(archive, ids: Sequence[str]) -> float:
    """The field of view the collections were ingested with (they must agree); reads their records
    (attributes only)."""
    from archive.catalog.root import open_archive
    from archive.collection import read_info

    root = open_archive(archive)
    fovs = {read_info(root.require_collection(i), navigation=False).fov_deg for i in ids}
    if len(fovs) != 1:
        raise InputError("--fov", f"the collections were ingested with different fields of view {sorted(fovs)}",
                         "pass --fov DEG")
    return fovs.pop()


def _check_same_bands(sources: Sequence, bands: Sequence[Sequence[int]]) -> None:
    """InputError unless every source renders as many bands, at the same wavelengths (to 1/2 band)."""
    first = sources[0]
    for s, b in zip(sources[1:], bands[1:]):
        if len(b) != len(bands[0]):
            raise InputError(s.label, f"{len(b)} bands selected, but {len(bands[0])} in the first source",
                             "render sources with the same bands together, or pick --wavelengths")
        if first.wavelengths is None or s.wavelengths is None:
            continue
        w0 = np.asarray(first.wavelengths, float)
        tol = 0.5 * float(np.min(np.abs(np.diff(w0)))) if len(w0) > 1 else 1.0
        wa = w0[list(bands[0])]
        wb = np.asarray(s.wavelengths, float)[list(b)]
        worst = int(np.argmax(np.abs(wa - wb)))
        if abs(wa[worst] - wb[worst]) > tol:
            raise InputError(s.label, f"band at {wb[worst]:.1f} nm does not match {wa[worst]:.1f} nm of the "
                             "first source", "render sensors with different bands separately")


# ---------------------------------------------------------------------------------------------
# Sources and plans
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class Inputs:
    """The opened sources of a request: bands (per source, the source band of each output band),
    params (gsd, mode as settled, overlap, navigation), grounds (ground height per source, m)."""

    sources: tuple
    bands: tuple[tuple[int, ...], ...]
    params: RenderParams
    grounds: tuple[float, ...]
    crs: str | None = None
    max_view_angle: float = DEFAULT_MAX_VIEW_ANGLE
    dem: object = None  #: the :class:`archive.dem.DemSpec` the meshes follow (grounds are then None)
    meshes: tuple | None = None  #: with a DEM: each source's terrain meshes (built here: DEM errors come early)


def _quiet(text: str) -> None:
    pass


def open_inputs(request: RenderRequest, nav: NavigationParams, say=_quiet, mosaic: bool = True) -> Inputs:
    """Open and check the sources of ``request`` (``nav`` from :func:`check_request`).

    mosaic: all sources go into one output (same bands, one ground height); else each source is
    an output of its own. ``say(text)`` tells notes (a source without calibration renders raw DN).
    With a DEM, the sources' terrain meshes are built here (metadata and DEM only, no pixel, no GL),
    so that a DEM that does not cover the flights, or has holes under them, fails before any
    cluster starts.
    """
    from archive.graph.plan import cube_meshes
    from archive.sources import open_source

    # absolute paths: workers (maybe on another machine sharing the file system) open them again
    archive = None if request.archive is None else Path(request.archive).absolute()
    sources = [open_source(Path(src).absolute() if Path(src).is_dir() else src, nav,
                           calibration=request.calibration, archive=archive) for src in request.sources]
    bands = [select_bands(s, request.wavelengths, request.bands) for s in sources]
    if mosaic:
        _check_same_bands(sources, bands)
    if request.white_reference:
        for s in sources:
            s.white_reference = _read_white_reference(request.white_reference, s.wavelengths)
    mode = request.mode or "radiance"
    uncalibrated = [s for s in sources if not s.has_calibration]
    if mode == "radiance" and uncalibrated and not request.calibration:
        say(f"archive render: {uncalibrated[0].label} has no radiometric calibration (*.icp): rendering raw DN")
        mode = "raw"
    for s, b in zip(sources, bands):
        s.radiometry(0, b[:1], mode)  # mode problems (calibration, white reference) surface now
    dem = None
    if request.dem is not None:   # the DEM gives the ground: no flat height to settle
        from archive.dem import DemSpec

        dem = DemSpec.create(request.dem, request.dem_datum)
        grounds = [None] * len(sources)
        opened = dem.open()
        meshes = tuple(cube_meshes(s, nav.fov_deg, math.nan, float(request.max_view_angle), terrain=opened,
                                   gsd=float(request.gsd))
                       for s in sources)
    elif mosaic:
        grounds = [resolve_ground_height(request.ground_height, sources)] * len(sources)
    else:
        grounds = [resolve_ground_height(request.ground_height, [s]) for s in sources]
    params = RenderParams(gsd=float(request.gsd), ground_height=grounds[0], mode=mode,
                          bands=tuple(bands[0]), overlap=request.overlap, navigation=nav)
    return Inputs(tuple(sources), tuple(tuple(b) for b in bands), params, tuple(grounds), request.crs,
                  float(request.max_view_angle), dem, meshes if dem is not None else None)


@dataclass(frozen=True, eq=False)
class OutputPlan:
    """One output, planned (metadata only): its sources, the :class:`~archive.graph.plan.RenderPlan`
    (grid, cube jobs, band groups), the processing parameters, the ground height (m), the
    wavelength (nm) of each output band (None when the cubes have none) and its spectral full width
    at half maximum (``fwhm``, nm; None when the cubes have none)."""

    sources: tuple
    plan: RenderPlan
    params: RenderParams
    ground_height: float
    wavelengths: list[float] | None
    max_view_angle: float = DEFAULT_MAX_VIEW_ANGLE
    left_out: dict | None = None  #: lines left out of the meshes, by reason ('no navigation', 'view angle')
    dem: object = None  #: the :class:`archive.dem.DemSpec` the meshes follow (ground_height is then None)
    fwhm: list[float] | None = None

    @property
    def variable(self) -> str:
        """Name of the data variable ('radiance', 'dn', ...)."""
        return variable_for_mode(self.params.mode)

    @property
    def mesh_spec(self) -> tuple:
        """What the meshes were built from (for graph keys): with a DEM also the DEM (file, datum)
        and the GSD (the segments follow it)."""
        spec = (self.params.navigation, self.ground_height, self.max_view_angle, self.plan.grid.epsg)
        return spec if self.dem is None else (*spec, self.dem, self.params.gsd)

    def layers_spec(self, nadir_only: bool = False):
        """The :class:`~archive.provenance.ProvenanceSpec` of this output: every provenance layer,
        or with ``nadir_only`` only the view zenith the 'nadir' rule compares."""
        from archive.provenance import NADIR_KEY, provenance_spec

        return provenance_spec(self.plan, self.sources, [self.ground_height] * len(self.sources), self.dem,
                               (NADIR_KEY,) if nadir_only else None)

    @property
    def attrs(self) -> dict:
        """The output's attributes (mode, gsd, fov, ground height or DEM, sync offset, overlap, sources)."""
        offsets = list(dict.fromkeys(float(s.params.sync_offset) for s in self.sources))
        ground = ({"ground_height_m": self.ground_height} if self.dem is None else
                  {"dem": self.dem.path, "dem_datum": self.dem.datum or "declared"})
        return {"mode": self.params.mode, "gsd_m": self.params.gsd, "fov_deg": self.params.navigation.fov_deg,
                **ground, "sync_offset_s": offsets[0] if len(offsets) == 1 else offsets,
                "overlap": self.params.overlap, "sources": [str(s.label) for s in self.sources]}


def plan_output(inputs: Inputs, members: Sequence[int] | None = None, *, budget: int | None = None,
                band_group: int | None = None) -> OutputPlan:
    """Plan one output of ``inputs`` (the sources at ``members``, default all): cube meshes, output
    grid, cube windows and band groups (``band_group`` bands per render task, default sized to
    ``budget`` bytes of values per task; see :func:`archive.graph.build.with_task_groups`).
    InputError when the output or a task would be absurdly large."""
    from archive.graph.build import TASK_VALUES_BYTES, with_task_groups
    from archive.graph.plan import band_groups, cube_meshes, plan_render

    idx = list(range(len(inputs.sources))) if members is None else list(members)
    p = inputs.params
    sources = [inputs.sources[i] for i in idx]
    bands = [inputs.bands[i] for i in idx]
    ground = inputs.grounds[idx[0]]
    if inputs.meshes is None:
        meshes = [cube_meshes(s, p.navigation.fov_deg, ground, inputs.max_view_angle) for s in sources]
    else:   # terrain meshes, built by open_inputs
        meshes = [list(inputs.meshes[i]) for i in idx]
    plan = plan_render(sources, meshes, bands, p.gsd, crs=inputs.crs)
    if band_group is None:
        plan = with_task_groups(plan, TASK_VALUES_BYTES if budget is None else budget)
    else:
        if isinstance(band_group, bool) or not isinstance(band_group, (int, np.integer)) or band_group <= 0:
            raise InputError("band_group", f"expected a positive number of bands, got {band_group!r}")
        plan = dataclasses.replace(plan, groups=band_groups(plan.nbands, int(band_group)))
    check_size(plan, p.gsd)
    wavelengths = sources[0].wavelengths
    out_wl = None if wavelengths is None else [wavelengths[b] for b in bands[0]]
    fwhm = getattr(sources[0], "fwhm", None)
    out_fwhm = None if fwhm is None else [fwhm[b] for b in bands[0]]
    left_out: dict[str, int] = {}
    for ms in meshes:
        for m in ms:
            for reason, n in (m.dropped or {}).items():
                left_out[reason] = left_out.get(reason, 0) + int(n)
    return OutputPlan(tuple(sources), plan, p, ground, out_wl, inputs.max_view_angle, left_out, inputs.dem,
                      out_fwhm)


def build_output(output: OutputPlan, target):
    """(sink, graph): create the output of ``output`` (metadata only) and build (never compute) the
    render graph that writes it.

    target: an :class:`~archive.outputs.Output` (its format's sink, under its temporary names), or a
    path where a Zarr store is created.
    """
    from archive.graph.build import build_render_graph
    from archive.outputs import MosaicStore, OutputMeta

    p, plan = output.params, output.plan
    meta = OutputMeta(plan.grid, tuple(plan.bands[0]), None if output.wavelengths is None else tuple(output.wavelengths),
                      output.variable, output.attrs, fwhm=None if output.fwhm is None else tuple(output.fwhm))
    if isinstance(target, Output):
        sink = target.sink(meta)
    else:
        sink = MosaicStore.create(target, plan.grid, meta.wavelengths, meta.band_indices, meta.variable,
                                  meta.attrs, fwhm=meta.fwhm)
    layers = layers_sink = None
    provenance = isinstance(target, Output) and target.provenance
    if provenance or p.overlap in KEYED:
        layers = output.layers_spec(nadir_only=not provenance)
    if provenance:
        layers_sink = target.layers_sink(layers)
    graph = build_render_graph(plan, list(output.sources), sink, mode=p.mode, overlap=p.overlap,
                               mesh_spec=output.mesh_spec, layers=layers, layers_sink=layers_sink)
    return sink, graph


# ---------------------------------------------------------------------------------------------
# Running the graph
# ---------------------------------------------------------------------------------------------
def _check_gpu_workers(client, where: str) -> None:
    """InputError unless some worker of ``client`` offers the 'GPU' resource the GL tasks need."""
    workers = client.scheduler_info().get("workers", {})
    if not any((w.get("resources") or {}).get("GPU", 0) >= 1 for w in workers.values()):
        raise InputError(
            where, "no worker offers the 'GPU' resource the render tasks need",
            "start workers with `dask worker ADDRESS --resources GPU=2` (docs/deploy.md)",
        )


#: Render tasks a local worker admits at once (its 'GPU' resource): one draws on the worker's GL
#: thread while the next reads its bands.
GL_SLOTS = 2
#: glibc's M_MMAP_THRESHOLD for local workers (bytes; 32 MiB, its largest): allocations up to this
#: size come from the heap and are reused, instead of fresh memory-mapped pages for every large
#: temporary (each page faulted and zeroed by the kernel: COG writers spent more CPU in the kernel
#: than in Python; a 300-band COG render went from 38 s to 23-25 s, bench/RESULTS.md).
MALLOC_MMAP_THRESHOLD = 32 * 1024**2


def _positive(value, option: str, what: str) -> int | None:
    if value is not None and (isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value <= 0):
        raise InputError(option, f"expected a positive number of {what}, got {value!r}")
    return None if value is None else int(value)


def _cluster(scheduler: str | None, workers: int | None, say, threads: int | None = None):
    """(client, cluster or None): ``scheduler`` or a local cluster of GPU-resourced workers.

    Local cluster: ``workers`` processes (default 1) of ``threads`` threads each (default: the
    machine's cores divided among the workers, at least 2). Render tasks need the 'GPU' resource
    (GL_SLOTS per worker: one draws on the worker's GL thread while another reads); writer tasks
    need none, so the other threads mosaic, encode and write meanwhile.
    """
    import logging

    from distributed import Client, LocalCluster

    if scheduler:
        try:
            client = Client(scheduler, timeout="20s")
        except OSError as exc:
            raise InputError("--scheduler", f"cannot connect to {scheduler}: {exc}",
                             "start one with `dask scheduler` and workers with `--resources GPU=2`") from None
        say(f"archive render: Dask dashboard at {client.dashboard_link}")
        try:
            _check_gpu_workers(client, f"--scheduler {scheduler}")
        except InputError:
            client.close()
            raise
        return client, None
    workers = _positive(workers, "--workers", "worker processes") or 1
    threads = _positive(threads, "--threads", "threads per worker")
    cores = max(1, (os.cpu_count() or 1) // workers)
    # Spawned worker processes (never forked after GL). GL calls run on each worker's GL thread
    # (archive.graph.tasks.gl_call); llvmpipe draws with the worker's cores (LP_NUM_THREADS). glibc
    # reads MALLOC_* when a process starts: Dask sets its 'pre-spawn' variables before spawning.
    import dask

    environ = dict(dask.config.get("distributed.nanny.pre-spawn-environ", None) or {})
    environ.setdefault("MALLOC_MMAP_THRESHOLD_", str(MALLOC_MMAP_THRESHOLD))
    with dask.config.set({"distributed.nanny.pre-spawn-environ": environ}):
        cluster = LocalCluster(n_workers=workers, threads_per_worker=threads or max(2, cores), processes=True,
                               resources={"GPU": GL_SLOTS}, env={"LP_NUM_THREADS": str(cores)},
                               dashboard_address=":0", silence_logs=logging.CRITICAL)  # errors come back here
    return Client(cluster), cluster


def _wait_for_writers(client, timeout: float = 60.0) -> None:
    """Wait until no worker is still running one of our writer tasks (best effort)."""
    deadline = time.monotonic() + timeout
    try:
        while time.monotonic() < deadline:
            running = [k for stack in client.call_stack().values() for k in stack]
            if not any(str(k).startswith(("write-", "saturated-", "blank-", "overview-")) for k in running):
                return
            time.sleep(0.2)
    except Exception:  # the scheduler may be gone already
        pass


def _execute(client, graph, quiet: bool, shared: bool) -> None:
    """Compute the writer tasks with a progress bar; re-raise the first task error as an ArchiveError.

    shared: the cluster outlives this command (``--scheduler``): on failure, cancel our tasks and
    wait for running writers, so that no chunk lands in the store after it is deleted.
    """
    from distributed import KilledWorker, as_completed
    from tqdm import tqdm

    futures = client.compute(list(graph.writes))
    done = as_completed(futures)
    del futures  # only as_completed holds them: results are released as soon as they are counted
    try:
        with tqdm(total=len(graph), desc="render", unit="task", disable=quiet, file=sys.stderr) as bar:
            for future in done:
                if future.status == "error":
                    future.result()  # raises the task's exception here
                future.release()
                bar.update(1)
    except BaseException as exc:
        if shared:
            client.cancel(list(done.futures), force=True)
            _wait_for_writers(client)
        if isinstance(exc, (ArchiveError, KeyboardInterrupt)) or not isinstance(exc, Exception):
            raise
        if isinstance(exc, KilledWorker):
            raise RenderError(f"a Dask worker died while rendering ({exc}); it may have run out of memory "
                              "or crashed in OpenGL: try a larger --gsd or fewer --wavelengths") from exc
        raise RenderError(f"a render task failed: {type(exc).__name__}: {exc}") from exc


def _task_budget(client) -> int:
    """Bytes of rendered values one render task may hold: TASK_VALUES_BYTES, or a tenth of the
    smallest worker memory limit when that is less (small workers get smaller band groups)."""
    from archive.graph.build import TASK_VALUES_BYTES

    limits = [int(w.get("memory_limit") or 0) for w in client.scheduler_info().get("workers", {}).values()]
    limits = [m for m in limits if m > 0]
    return min([TASK_VALUES_BYTES] + [m // 10 for m in limits])


# ---------------------------------------------------------------------------------------------
# Rendering into files
# ---------------------------------------------------------------------------------------------
def _flight_outputs(sources: Sequence[str], out, format: str, overwrite: bool, quicklook,
                    provenance: bool = False) -> list[Output]:
    """Per-flight batch mode: ``out/<name>.<format>`` for each source (checked now)."""
    directory = Path(out).absolute()
    if directory.exists() and not directory.is_dir():
        raise InputError(directory, "is a file, but a batch job writes one output per flight into a directory",
                         "give --out DIR, or --mosaic for one output")
    if directory.suffix.lower() in (".zarr", ".tif", ".tiff", ".hdr"):
        raise InputError(directory, "looks like one output file, but a batch job writes one output per flight",
                         "give --out DIR (outputs DIR/<id>.<format>), or add --mosaic")
    if quicklook:
        raise InputError("--quicklook", "only one quicklook per command", "add --mosaic, or leave it out")
    outputs = []
    for src in sources:
        name = Path(src).name if Path(src).is_dir() else str(src)
        output = Output(directory / f"{name}.{format}", overwrite=bool(overwrite), provenance=provenance)
        output.check()
        outputs.append(output)
    return outputs


@dataclass
class _Job:
    """One output of a command: its Output, plan, sink and graph."""

    output: Output
    planned: OutputPlan
    sink: object
    graph: object
    request: RenderRequest | None = None  #: what renders this output alone again (its recipe)

    def item(self) -> dict:
        """The output's STAC Item (:func:`archive.catalog.product.product_item`): grid, bands,
        processing attributes, time span of its lines, and the recipe (the command that renders it
        again)."""
        from archive.catalog.product import product_item, render_command
        from archive.formats.lcf import gps_seconds_to_datetime

        planned, output = self.planned, self.output
        plan = planned.plan
        first = min(float(planned.sources[j.source].line_times(j.cube)[0]) for j in plan.jobs)
        last = max(float(planned.sources[j.source].line_times(j.cube)[-1]) for j in plan.jobs)
        command = render_command(self.request, output.path, quicklook=output.quicklook, provenance=output.provenance)
        return product_item(output.path, fmt=output.format, grid=plan.grid, band_indices=plan.bands[0],
                            wavelengths=planned.wavelengths, fwhm=planned.fwhm, variable=planned.variable,
                            attrs=planned.attrs, start=gps_seconds_to_datetime(first),
                            end=gps_seconds_to_datetime(last), sources=list(self.request.sources),
                            command=command, request=self.request,
                            provenance=(output.provenance_path or output.path) if output.provenance else None)


def _say(quiet: bool):
    def say(text: str) -> None:
        if not quiet:
            print(text, file=sys.stderr)

    return say


def render(request: RenderRequest, out: str | os.PathLike, *, quicklook: str | os.PathLike | None = None,
           overwrite: bool = False, scheduler: str | None = None, workers: int | None = None,
           quiet: bool = True, per_flight: bool = False, format: str = "zarr", threads: int | None = None) -> dict:
    """Render ``request`` into ``out`` (.zarr, .tif or .hdr); returns a summary dict. Raises ArchiveError.

    One output at ``out``, or with ``per_flight`` one output per source, ``out/<name>.<format>``:
    then the summary holds ``outputs``, one summary per flight. Every output's tasks run in one
    graph, on ``scheduler`` (an address) or on a local cluster of ``workers`` processes of
    ``threads`` threads each (default: the cores). The graph's tile tasks write every format
    directly; COG and ENVI are finished (layout, header) and renamed into place afterwards.
    """
    from archive.graph.build import RenderGraph

    started = time.perf_counter()
    say = _say(quiet)
    _check_gsd(request.gsd)
    if per_flight:
        nav = check_request(request)
        if format not in ("zarr", "tif", "hdr"):
            raise InputError("--format", f"unknown output format {format!r}", "use zarr, tif or hdr")
        outputs = _flight_outputs(request.sources, out, format, overwrite, quicklook, request.provenance)
    else:
        output = Output(Path(out).absolute(), overwrite=bool(overwrite),
                        quicklook=None if not quicklook else Path(quicklook).absolute(),
                        provenance=request.provenance)
        output.check()
        outputs = [output]
        nav = check_request(request)
    client = cluster = None
    jobs: list[_Job] = []
    graph_seconds = 0.0
    try:
        inputs = open_inputs(request, nav, say, mosaic=not per_flight)
        members = [[i] for i in range(len(inputs.sources))] if per_flight else [list(range(len(inputs.sources)))]
        client, cluster = _cluster(scheduler, workers, say, threads)
        budget = _task_budget(client)
        for output, idx in zip(outputs, members):
            planned = plan_output(inputs, idx, budget=budget)
            sink, graph = build_output(planned, output)
            recipe = request.with_sources([request.sources[i] for i in idx]) if per_flight else request
            jobs.append(_Job(output, planned, sink, graph, recipe))
        graph = RenderGraph(tuple(w for j in jobs for w in j.graph.writes), sum(j.graph.renders for j in jobs),
                            sum(j.graph.assemblies for j in jobs))
        t = time.perf_counter()
        if len(graph):
            _execute(client, graph, quiet, shared=cluster is None)
        graph_seconds = time.perf_counter() - t
        for job in jobs:
            job.output.finalize(job.sink, item=job.item)
    finally:
        if client is not None:
            client.close()
        if cluster is not None:
            cluster.close()  # stops the worker processes, with any task still writing
        for output in outputs:
            output.cleanup()
    seconds = time.perf_counter() - started
    summaries = []
    for job in jobs:
        g, plan = job.planned.plan.grid, job.planned.plan
        summaries.append({
            "out": str(job.output.path) if per_flight else str(out), "width": g.width, "height": g.height,
            "gsd": g.gsd, "epsg": g.epsg, "bands": plan.nbands, "wavelengths": job.planned.wavelengths,
            "mode": job.planned.params.mode, "cubes": len(plan.jobs), "sources": len(job.planned.sources),
            "renders": job.graph.renders, "assemblies": job.graph.assemblies, "seconds": seconds,
            "graph_seconds": graph_seconds, "left_out": dict(job.planned.left_out or {}),
            "provenance": (None if not job.output.provenance else
                           str(job.output.provenance_path or job.output.path)),
        })
    if not per_flight:
        return summaries[0]
    return {"outputs": summaries, "seconds": seconds, "graph_seconds": graph_seconds, "renders": graph.renders}


def describe(s: dict) -> str:
    """One line about an output from its :func:`render` summary."""
    wl = s["wavelengths"]
    span = f" ({min(wl):.1f}-{max(wl):.1f} nm)" if wl else ""
    return (f"{s['out']}: {s['width']} x {s['height']} px at {s['gsd']:g} m, "
            f"EPSG:{s['epsg']}, {s['bands']} band{'s' if s['bands'] != 1 else ''}{span}, {s['mode']}, "
            f"{s['cubes']} cube{'s' if s['cubes'] != 1 else ''} from {s['sources']} source"
            f"{'s' if s['sources'] != 1 else ''}{_left_out_text(s.get('left_out'))}")


def _left_out_text(left_out: dict | None) -> str:
    """'; 12 lines left out (3 without navigation, 9 beyond the view-angle limit)' or ''."""
    left_out = {k: v for k, v in (left_out or {}).items() if v}
    if not left_out:
        return ""
    names = {"no navigation": "without navigation", "view angle": "beyond the view-angle limit"}
    parts = ", ".join(f"{n} {names.get(k, k)}" for k, n in left_out.items())
    total = sum(left_out.values())
    return f"; {total} line{'s' if total != 1 else ''} left out ({parts})"


# ---------------------------------------------------------------------------------------------
# Lazy mosaics
# ---------------------------------------------------------------------------------------------
def _active_client():
    """The default distributed Client, if one is active (distributed is never imported here)."""
    distributed = sys.modules.get("distributed")
    if distributed is None:
        return None
    try:
        return distributed.default_client()
    except ValueError:
        return None


def plan(request: RenderRequest, *, band_group: int | None = None, budget: int | None = None,
         quiet: bool = True) -> OutputPlan:
    """Check, open and plan ``request`` as one mosaic (metadata only: no pixel is read, no GL)."""
    nav = check_request(request)
    inputs = open_inputs(request, nav, _say(quiet), mosaic=True)
    return plan_output(inputs, budget=budget, band_group=band_group)


def mosaic(request: RenderRequest, *, band_group: int | None = None, quiet: bool = True):
    """``request`` as a lazy ``xarray.Dataset`` (nothing rendered until computed).

    The data variable (named by mode: 'dn', 'relative', 'radiance', 'reflectance') is (band, y, x)
    float32, NaN where no line covers a pixel, a dask array chunked (band group, 1024, 1024): one
    block per output tile and band group (``band_group`` bands, default sized to the task memory
    budget, the active distributed Client's workers' when there is one), rendered by the render
    graph's task bodies (:mod:`archive.graph.lazy`). ``saturated`` (y, x) uint8 is lazy too. The
    coordinates are those of the Zarr output (x/y pixel centres in metres, ``band``: source band
    index, ``wavelength`` in nm, indexed for ``.sel(wavelength=..., method="nearest")``), with the
    CRS set (rioxarray ``spatial_ref``).
    """
    from archive.graph.lazy import mosaic_arrays

    client = _active_client()
    budget = None
    if client is not None:
        _check_gpu_workers(client, f"the active Dask client ({client.scheduler.address})")
        budget = _task_budget(client)
    planned = plan(request, band_group=band_group, budget=budget, quiet=quiet)
    p, grid = planned.params, planned.plan.grid
    values, saturated = mosaic_arrays(planned.plan, list(planned.sources), mode=p.mode, overlap=p.overlap,
                                      layers=planned.layers_spec(nadir_only=True) if p.overlap in KEYED else None,
                                      mesh_spec=planned.mesh_spec)
    ds = mosaic_dataset(grid, values, saturated, planned.plan.bands[0], planned.wavelengths, planned.fwhm,
                        planned.variable, planned.attrs)
    if planned.wavelengths is not None and len(set(planned.wavelengths)) == len(planned.wavelengths):
        ds = ds.set_xindex("wavelength")
    return ds
