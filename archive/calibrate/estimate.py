"""``calibrate``: boresight, sync offset and ground height (or a DEM's vertical offset) from a
flight's own overlapping passes (DESIGN 10).

1. Passes are the flight's strips (the project's strip rule); every pair of passes whose footprints
   overlap is measured.
2. Measure: both passes rendered onto a common grid under the current parameters, the shift field
   between them by coarse masked NCC then Lucas-Kanade on textured windows
   (:mod:`archive.calibrate.match`).
3. Solve: the tie rays of every window brought onto one ground point by least squares
   (:mod:`archive.calibrate.solve`); the sync offset is first searched over +-1 s (the others fitted
   at each step), then refined with the rest.
4. Repeat 2-3 under the new parameters (the windows then barely move, where Lucas-Kanade is most
   accurate) until the parameters settle.
5. Report: 1-sigma uncertainties, correlations, what the flight separates, the misregistration
   before and after, the overlap used.

What a flight can separate: opposite passes shift against each other across track by roll and by a
ground height error alike (2 H droll vs baseline dh / H), and along track by pitch, yaw and sync
offset alike; only the geometry's second-order terms (view angle across the overlap, attitude
wobble, height changes) tell them apart. Parameters whose correlation with another exceeds
:data:`SEPARABLE` are reported as not separable (with the correlation); a pair the flight cannot
tell apart at all (correlation above :data:`DEGENERATE`, e.g. pitch and sync on straight passes
flown without attitude changes) keeps the less needed one at its start value (:data:`HOLD_ORDER`)
rather than inventing it.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from archive.calibrate.match import Tie, measure_pair, pair_grid
from archive.calibrate.model import PARAM_NAMES, FlightModel, Params
from archive.calibrate.solve import Fit, fit, observations
from archive.errors import InputError

__all__ = ["Calibration", "calibrate", "PARAMETER_GROUPS", "SEPARABLE", "DEGENERATE"]

#: --estimate groups -> parameters.
PARAMETER_GROUPS = {"boresight": ("roll", "pitch", "yaw"), "roll": ("roll",), "pitch": ("pitch",),
                    "yaw": ("yaw",), "sync": ("sync",), "ground": ("ground",),
                    "position": ("east", "north", "up"), "east": ("east",), "north": ("north",), "up": ("up",)}
#: |correlation| above which two parameters are reported as not separable.
SEPARABLE = 0.99
#: |correlation| above which the flight cannot tell two parameters apart at all: one is held.
DEGENERATE = 0.9999
#: A held parameter is reported with the parameters it correlates with beyond this.
PARTNER = 0.9
#: Which parameter of a degenerate pair keeps its start value (first in this order).
HOLD_ORDER = ("pitch", "yaw", "roll", "ground", "sync", "up", "east", "north")
#: How far from the start the estimates may go: boresight deg, sync offset s, ground m, position
#: offset m (a mounting is off by a degree or two, not ten, a GNSS without RTK by metres: a solution
#: beyond these is a false match, not a camera).
LIMITS = np.array([5.0, 5.0, 5.0, 1.5, 50.0, 15.0, 15.0, 10.0])
#: Misregistration left (median, px) above which the calibration says it did not converge.
CONVERGED_PX = 0.3
#: Sync offsets searched about the start value, s.
SYNC_SEARCH = (-1.0, 1.0, 0.1)
#: The fine search about the best of SYNC_SEARCH (co-registration), s.
SYNC_FINE = (-0.1, 0.1, 0.01)
#: Fewest tie windows a calibration accepts (and under the start parameters, the first measurement).
MIN_TIES = 30
MIN_FIRST_TIES = 12
#: Measurement grid spacing as a fraction of the nominal GSD, but at least the swath / SWATH_PIXELS
#: (the geometry, not the sensor's sample count, sets how finely overlaps need sampling: a 900-sample
#: camera is measured on the grid of a 128-sample one, its lines low-passed first); window side (grid
#: pixels).
SPACING = 0.5
SWATH_PIXELS = 256
WINDOW = 24
MIN_WINDOW = 16     # tried where no WINDOW-sized window fits in an overlap
#: Outer iterations (measure, solve) at most; stop when every parameter moves less than STOP.
ITERATIONS = 6
STOP = np.array([0.001, 0.001, 0.003, 0.0002, 0.005, 0.005, 0.005, 0.005])   # a tenth of the accuracy goals
#: Bands averaged into the matched image: up to this many around the middle of the spectrum.
BANDS = 4
#: Shortest overlap (along track, m) worth measuring: a few windows.
MIN_OVERLAP_WINDOWS = 4


@dataclass
class Calibration:
    """Result of :func:`calibrate`. params: the estimates (ground: height m, or DEM offset m);
    start: the parameters it started from; estimated: names solved for; sigma: 1-sigma per
    estimated parameter (None where held); observable: per estimated parameter; correlations:
    {'a,b': r} for |r| >= 0.5; residual_before / residual_after: misregistration stats (px of the
    nominal GSD); pairs: overlap per pass pair; pixel_m: the nominal GSD; dem: the DEM path or None;
    notes: sentences for people."""

    params: Params
    start: Params
    estimated: tuple[str, ...]
    sigma: dict
    observable: dict
    correlations: dict
    residual_before: dict
    residual_after: dict
    pairs: list
    pixel_m: float
    dem: str | None = None
    notes: list = field(default_factory=list)
    held: dict = field(default_factory=dict)
    #: co-registration (``--reference``): the reference flight, the misregistration between the two
    #: flights before/after (px of the nominal GSD), the pass pairs between them, the windows
    #: (tried, textured, matched, unmatched, outliers) and the overlap area (m2)
    reference: str | None = None
    between_before: dict | None = None
    between_after: dict | None = None
    between_pairs: list = field(default_factory=list)
    windows: dict = field(default_factory=dict)
    overlap_m2: float | None = None

    def flags(self) -> str:
        """The render/ingest options that apply the estimates."""
        r, p, y = self.params.boresight_deg
        out = f"--boresight {r:.4f},{p:.4f},{y:.4f} --sync-offset {self.params.sync:.4f}"
        if self.dem is None:
            out += f" --ground-height {self.params.ground:.3f}"
        return out

    def to_json(self) -> dict:
        names = {"roll": "roll_deg", "pitch": "pitch_deg", "yaw": "yaw_deg", "sync": "sync_offset_s",
                 "ground": "dem_offset_m" if self.dem else "ground_height_m", "east": "east_m", "north": "north_m",
                 "up": "up_m"}
        out = {
            "boresight_deg": [round(v, 6) for v in self.params.boresight_deg],
            "sync_offset_s": round(self.params.sync, 6),
            "ground_height_m": None if self.dem else round(self.params.ground, 4),
            "sigma": {names[k]: (None if v is None else float(f"{v:.3g}")) for k, v in self.sigma.items()},
            "observable": {names[k]: v for k, v in self.observable.items()},
            "correlation": self.correlations,
            "residual_px": {"before": self.residual_before, "after": self.residual_after},
            "overlap": {"pairs": self.pairs, "windows": int(sum(p["windows"] for p in self.pairs)),
                        "pixels": int(sum(p["pixels"] for p in self.pairs)), "pixel_m": round(self.pixel_m, 5)},
            "estimated": [names[k] for k in self.estimated],
            "held": {names[k]: v for k, v in self.held.items()},
            "start": {"boresight_deg": list(self.start.boresight_deg), "sync_offset_s": self.start.sync,
                      names["ground"]: self.start.ground},
            "flags": {"render": self.flags(), "ingest": self.flags()},
            "notes": self.notes,
        }
        if self.dem:
            out["dem_offset_m"] = round(self.params.ground, 4)
            out["dem"] = self.dem
        if self.reference is not None or any(self.params.position_offset):
            out["position_offset_m"] = [round(v, 5) for v in self.params.position_offset]
            out["start"]["position_offset_m"] = list(self.start.position_offset)
        if self.reference is not None:
            out["reference"] = self.reference
            out["residual_between_px"] = {"before": self.between_before, "after": self.between_after}
            out["overlap_between"] = {"pairs": self.between_pairs, "area_m2": self.overlap_m2,
                                      "windows": self.windows}
        return out


def parse_estimate(text: str | Sequence[str] | None, default: Sequence[str] | None = None) -> tuple[str, ...]:
    """'boresight,sync,ground' (any of :data:`PARAMETER_GROUPS`: boresight, roll, pitch, yaw, sync,
    ground, position, east, north, up) -> parameter names in model order; None: ``default``
    (boresight, sync, ground)."""
    items = text if not isinstance(text, str) else [t for t in text.replace(" ", "").split(",") if t]
    items = list(items) if items is not None else list(default or ("boresight", "sync", "ground"))
    names: set[str] = set()
    for item in items:
        if item not in PARAMETER_GROUPS:
            raise InputError("--estimate", f"unknown parameter {item!r}",
                             f"use a comma-separated list of {', '.join(PARAMETER_GROUPS)}")
        names.update(PARAMETER_GROUPS[item])
    if not names:
        raise InputError("--estimate", "nothing to estimate", "name at least one of boresight, sync, ground")
    return tuple(n for n in PARAM_NAMES if n in names)


@dataclass(frozen=True, eq=False)
class FlightImages:
    source: object
    model: FlightModel
    images: tuple[np.ndarray, ...]   # per pass: (lines, samples) float32


def pass_images(source, model: FlightModel) -> tuple[np.ndarray, ...]:
    """Per pass, the mean of up to BANDS middle bands (relative radiometry: DN per exposure, so
    that cubes of one pass with different shutters meet without a step), (lines, samples)."""
    nb = source.cubes[0].bands
    mid = nb // 2
    bands = sorted(set(range(max(0, mid - BANDS // 2), min(nb, mid - BANDS // 2 + BANDS))))
    out = []
    for p in model.passes:
        parts = []
        for k in p.cubes:
            dn = np.asarray(source.read_bands(k, bands), np.float32)
            rad = source.radiometry(k, bands, "relative")
            v = (dn - rad.dark[:, None, :]) * rad.gain[:, None, :] / rad.response[None, :, None]
            parts.append(v.mean(axis=0))
        out.append(np.concatenate(parts).astype(np.float32))
    return tuple(out)


def prefiltered(flight, images, spacing: float, pixel: float) -> tuple[np.ndarray, ...]:
    """Pass images low-passed (Gaussian) along lines and samples where the measurement grid samples
    them more coarsely than 1.5 raw pixels (no aliasing in the point-sampled grid)."""
    from scipy import ndimage

    out = []
    for p, image in zip(flight.model.passes, images, strict=True):
        pos, _, valid = flight.model.line_poses(p, Params())
        step = np.linalg.norm(np.diff(pos[valid][:, :2], axis=0), axis=1)
        along = float(np.median(step)) if step.size else spacing
        sigma = [0.4 * r if r > 1.5 else 0.0 for r in (spacing / max(along, 1e-9), spacing / pixel)]
        out.append(ndimage.gaussian_filter(image, sigma, mode="nearest") if any(sigma) else image)
    return tuple(out)


def nominal_pixel(flights, ground: float, dem) -> float:
    """Across-track sample spacing at nadir at the median camera height above the ground, m."""
    heights, samples, fov = [], [], flights[0].model.fov_deg
    for f in flights:
        alt = f.model.frame.origin_alt - np.asarray(f.source.navigation.track.position)[:, 2]
        heights.append(float(np.median(alt)) - ground)
        samples.append(f.source.cubes[0].samples)
    h = float(np.median(heights))
    return 2.0 * h * math.tan(math.radians(fov) / 2.0) / float(np.median(samples))


def tie_stats(ties: Sequence[Tie], spacing: float, pixel: float) -> dict:
    if not ties:
        return {"median": None, "p95": None, "windows": 0}
    d = np.array([math.hypot(*t.shift) for t in ties]) * spacing / pixel
    return {"median": round(float(np.median(d)), 4), "p95": round(float(np.percentile(d, 95)), 4),
            "windows": len(ties)}


def measure_passes(flights, params: Params, spacing: float, window: int, progress) -> tuple[list, dict, list]:
    """Ties, grids and per-pair overlap of every overlapping pass pair of every flight."""
    sets, pairs, all_ties = [], [], []
    for fi, f in enumerate(flights):
        grids: dict = {}
        ties: list = []
        passes = f.model.passes
        for i in range(len(passes)):
            for j in range(i + 1, len(passes)):
                grid = pair_grid(f.model, passes[i], passes[j], params, spacing)
                if grid is None:
                    continue
                found, stats = measure_pair(f.model, grid, f.images[i], f.images[j], params, window)
                if stats["windows"] == 0 and window > MIN_WINDOW:   # a narrow overlap: smaller windows
                    found, stats = measure_pair(f.model, grid, f.images[i], f.images[j], params, MIN_WINDOW)
                grids[(i, j)] = grid
                ties.extend(found)
                pairs.append({"flight": fi, "passes": [i, j], "pixels": stats["overlap_px"],
                              "windows": stats["matched"], "textured": stats["textured"],
                              "tried": stats["windows"]})
                if progress:
                    progress(f"  passes {i}-{j}: {stats['overlap_px']} px overlap, {stats['textured']} textured "
                             f"windows, {stats['matched']} matched")
        sets.append((f.model, observations(f.model, grids, ties, params)))
        all_ties.extend(ties)
    return sets, pairs, all_ties


def calibrate(sources: Sequence, fov_deg: float, ground: float, *, dem=None, dem_label: str | None = None,
              estimate: Sequence[str] = ("roll", "pitch", "yaw", "sync", "ground"),
              progress=None, window: int = WINDOW) -> Calibration:
    """Estimate ``estimate`` (names of :data:`~archive.calibrate.model.PARAM_NAMES`) for opened
    navigated ``sources`` (raw or collection: their parameters are the start) sharing one camera,
    mounting and sync offset.

    ground: start ground height (m above the ellipsoid), or with ``dem`` (an opened
    :class:`archive.terrain.dem.Dem`) the start vertical offset of the DEM (m). progress: a callable
    taking a line of text, or None. InputError when there is nothing to measure (no overlap, too
    little texture, a flight too short)."""
    estimate = tuple(n for n in PARAM_NAMES if n in set(estimate))
    first = sources[0].params
    start = Params(*first.boresight_deg, float(first.sync_offset), float(ground), *first.position_offset)
    flights = []
    for s in sources:
        surface = None if dem is None else dem_surface(dem, s, fov_deg)
        model = FlightModel(s, fov_deg, surface)
        flights.append(FlightImages(s, model, ()))
    passes = sum(len(f.model.passes) for f in flights)
    if all(len(f.model.passes) < 2 for f in flights):
        names = ", ".join(str(f.source.label) for f in flights)
        raise InputError(names, f"has {passes} pass{'es' if passes != 1 else ''} and no overlap of the flight with "
                         "itself", "calibrate needs two or more overlapping passes (neighbouring lines, "
                         "crossing lines)")
    ground_for_pixel = ground if dem is None else float(np.median(dem.typical_height())) + ground
    pixel = nominal_pixel(flights, ground_for_pixel, dem)
    samples = float(np.median([c.samples for f in flights for c in f.source.cubes]))
    spacing = max(SPACING * pixel, pixel * samples / SWATH_PIXELS)
    flights = [FlightImages(f.source, f.model, prefiltered(f, pass_images(f.source, f.model), spacing, pixel))
               for f in flights]
    _check_overlap(flights, start, spacing, window)

    say = progress or (lambda text: None)
    say(f"measuring under the start parameters ({describe_params(start, dem is not None)})")
    sets, pairs, ties = measure_passes(flights, start, spacing, window, say)
    ties_before = ties
    _check_ties(ties, pairs, estimate, flights, first=True)
    params = start
    if "sync" in estimate:
        params = search_sync(sets, start, estimate, pixel, say)
    held: dict = {}
    result = fit_separable(sets, params, start, list(estimate), held, pixel, say)
    params = result.params
    def measure(trial: Params):
        sets, pairs, ties = measure_passes(flights, trial, spacing, window, say)
        _check_ties(ties, pairs, estimate, flights)
        return sets

    result = refit(result, measure, lambda sets, trial: fit_separable(
        sets, trial, start, [n for n in estimate if n not in held], held, pixel, say),
        lambda trial: describe_params(trial, dem is not None), say)
    params = result.params
    say(f"final: {describe_params(params, dem is not None)}")
    sets_after, pairs, ties_after = measure_passes(flights, params, spacing, window, lambda text: None)
    final_ground = params.ground if dem is None else float(np.median(dem.typical_height())) + params.ground
    pixel_after = nominal_pixel(flights, final_ground, dem)     # the unit: the flight's nominal GSD
    before = tie_stats(ties_before, spacing, pixel_after)
    after = tie_stats(ties_after, spacing, pixel_after)
    pixel = pixel_after
    check_converged(result, start, after, flights)
    return make_report(result, start, estimate, held, before, after, pairs, pixel, dem_label)


def refit(result: Fit, measure: Callable[[Params], list], fit: Callable[[list, Params], Fit],
          describe: Callable[[Params], str], say: Callable[[str], None]) -> Fit:
    """Measure the overlaps again under ``result``'s parameters and fit again, until no parameter
    moves by more than :data:`STOP` (at most :data:`ITERATIONS` times): ``measure(params)`` -> the
    solver's sets, ``fit(sets, params)`` -> the next :class:`Fit`. Returns the last fit. Shared by
    the calibration within a flight and the co-registration to a reference."""
    for it in range(ITERATIONS):
        params = result.params
        say(f"iteration {it + 1}: {describe(params)}")
        result = fit(measure(params), params)
        if np.all(np.abs(result.params.vector() - params.vector()) <= STOP):
            break
    return result


def check_converged(result: Fit, start: Params, after: dict, flights) -> None:
    """InputError when the solution leaves the passes misregistered (median above CONVERGED_PX) or
    sits on a limit (LIMITS): false matches, not a camera."""
    labels = ", ".join(str(f.source.label) for f in flights)
    x, s0 = result.params.vector(), start.vector()
    at_limit = [n for i, n in enumerate(PARAM_NAMES) if n in result.free and abs(x[i] - s0[i]) >= LIMITS[i] * 0.999]
    if after["median"] is None or after["median"] > CONVERGED_PX or at_limit:
        what = (f"{', '.join(at_limit)} reached the search limit" if at_limit else
                f"the passes still misregister by {after['median']} px (median)")
        raise InputError(labels, f"calibration did not converge: {what}",
                         "check --fov and the start parameters (--ground-height, --dem, the recorded mounting); "
                         "the overlaps may hold too few distinct features")


def dem_surface(dem, source, fov_deg: float, margin: float = 40.0, frame=None):
    """heights(n, e) of ``dem`` at local N, E points of ``frame`` (default ``source``'s frame), m
    above the ellipsoid: the DEM read once under the flight (its camera track grown by the swath
    and ``margin`` m), bilinear between nodes."""
    own = source.frame
    frame = own if frame is None else frame
    pos = np.asarray(source.navigation.track.position)
    alt = own.origin_alt - pos[:, 2]
    reach = float(np.max(alt) - dem.typical_height()) * math.tan(math.radians(min(fov_deg / 2 + 15.0, 80.0))) + margin
    e, n = pos[:, 1] + own.origin_e, pos[:, 0] + own.origin_n
    surface = dem.surface(frame.epsg, (float(e.min() - reach), float(n.min() - reach), float(e.max() + reach),
                                       float(n.max() + reach)))

    def height(nn, ee):
        nn = np.asarray(nn, float)
        out = surface.height(np.asarray(ee, float).ravel() + frame.origin_e, nn.ravel() + frame.origin_n)
        return np.asarray(out, float).reshape(nn.shape)
    return height


def describe_params(p: Params, dem: bool) -> str:
    g = f"DEM offset {p.ground:+.3f} m" if dem else f"ground {p.ground:.3f} m"
    return f"boresight {p.roll:.4f},{p.pitch:.4f},{p.yaw:.4f} deg, sync {p.sync:+.4f} s, {g}"


def _check_overlap(flights, params: Params, spacing: float, window: int) -> None:
    """InputError unless some pass pair overlaps over at least a few windows' length."""
    longest = 0.0
    for f in flights:
        passes = f.model.passes
        prints = [f.model.footprint(p, params) for p in passes]
        for i in range(len(passes)):
            for j in range(i + 1, len(passes)):
                if prints[i] is None or prints[j] is None:
                    continue
                inter = prints[i].intersection(prints[j])
                if not inter.is_empty and inter.area > 0:
                    longest = max(longest, max(rect_sides(inter.minimum_rotated_rectangle)))
    need = MIN_OVERLAP_WINDOWS * window * spacing
    if longest <= 0.0:
        labels = ", ".join(str(f.source.label) for f in flights)
        raise InputError(labels, "no two passes of the flight overlap", "calibrate needs neighbouring passes "
                         "whose swaths overlap (or crossing lines); check --fov and the ground height")
    if longest < need:
        labels = ", ".join(str(f.source.label) for f in flights)
        raise InputError(labels, f"flight too short: the passes overlap over {longest:.1f} m, calibrate "
                         f"needs at least {need:.1f} m ({MIN_OVERLAP_WINDOWS} windows)",
                         "calibrate a longer flight (passes of a few seconds at least)")


def rect_sides(rect) -> list[float]:
    xy = np.asarray(rect.exterior.coords)
    return [float(np.hypot(*(xy[k + 1] - xy[k]))) for k in range(len(xy) - 1)]


def _check_ties(ties, pairs, estimate, flights, first: bool = False) -> None:
    """InputError unless enough windows were matched (fewer suffice under the start parameters,
    where large misregistrations defeat many windows: the first solution re-measures them all)."""
    need = max(MIN_TIES, 6 * len(estimate)) if not first else max(MIN_FIRST_TIES, 2 * len(estimate) + 2)
    if len(ties) >= need:
        return
    textured = sum(p["textured"] for p in pairs)
    tried = sum(p["tried"] for p in pairs)
    labels = ", ".join(str(f.source.label) for f in flights)
    if tried == 0:
        raise InputError(labels, "the overlaps between passes are too narrow: no measurement window fits in them",
                         "calibrate passes flown closer together, or with more side overlap")
    if textured < need:
        raise InputError(labels, f"too little texture in the overlaps: {textured} of {tried} windows are "
                         f"textured, calibrate needs {need}", "calibrate over a flight with more ground "
                         "detail in its overlaps")
    raise InputError(labels, f"only {len(ties)} of {textured} textured overlap windows could be matched "
                     f"between passes (calibrate needs {need})",
                     "check --fov and the start parameters (--ground-height, the ingested mounting)")


def search_sync(sets, start: Params, estimate, pixel: float, say, fine: bool = False) -> Params:
    """The sync offset within +-1 s of the start minimising the robust cost, the other estimated
    parameters fitted at each step. fine: then again every SYNC_FINE[2] s within SYNC_FINE of the
    best, the others fitted from their start values (a pitch that absorbed a sync offset between
    two coarse steps does not carry over into the fine steps)."""
    others = tuple(n for n in estimate if n != "sync")
    bounds = (start.vector() - LIMITS, start.vector() + LIMITS)

    def trial_fit(sync: float) -> Fit:
        trial = Params.from_vector(np.where(np.array(PARAM_NAMES) == "sync", sync, start.vector()))
        return fit(sets, trial, others, pixel, max_nfev=6, bounds=bounds) if others else fit(sets, trial, (), pixel)

    lo, hi, step = SYNC_SEARCH
    best = min((trial_fit(start.sync + ds) for ds in np.arange(lo, hi + step / 2, step)), key=lambda f: f.cost)
    if fine:
        lo, hi, step = SYNC_FINE
        centre = best.params.sync
        best = min([best] + [trial_fit(centre + ds) for ds in np.arange(lo, hi + step / 2, step) if abs(ds) > 1e-9],
                   key=lambda f: f.cost)
    say(f"sync offset search (+-1 s{', then every 10 ms' if fine else ''}): {best.params.sync:+.3f} s")
    return best.params


def fit_separable(sets, params: Params, start: Params, free: list, held: dict, pixel: float, say) -> Fit:
    """Fit ``free`` from ``params``; while two free parameters are degenerate (|correlation| above
    DEGENERATE: the flight cannot tell them apart at all), hold one (HOLD_ORDER) at its ``start``
    value, record it in ``held`` and fit again."""
    bounds = (start.vector() - LIMITS, start.vector() + LIMITS)
    result = fit(sets, params, tuple(free), pixel, bounds=bounds)
    while True:
        pair = _degenerate(result)
        if pair is None:
            return result
        hold = min(pair, key=HOLD_ORDER.index)
        c = result.correlation()
        i = result.free.index(hold)
        others = sorted((p for p in result.free if p != hold), key=lambda p: -abs(c[i, result.free.index(p)]))
        partners = [p for p in others if abs(c[i, result.free.index(p)]) >= PARTNER] or others[:1]
        r = float(c[i, result.free.index(partners[0])]) if partners else float("nan")
        w = float(np.linalg.eigvalsh(c)[0])
        held[hold] = {"with": partners, "correlation": round(r, 6), "eigenvalue": float(f"{w:.3g}")}
        say(f"{hold} cannot be told apart from {', '.join(partners) or 'nothing: it has no measurable effect'} "
            f"(correlation {r:+.6f}): held at its start value")
        free.remove(hold)
        params = Params.from_vector(np.where(np.array(PARAM_NAMES) == hold, start.vector(), params.vector()))
        result = fit(sets, params, tuple(free), pixel, bounds=bounds)


def _degenerate(result: Fit) -> tuple[str, ...] | None:
    """The free parameters of the flight's blind direction, when it has one: the correlation matrix's
    smallest eigenvalue below 1 - DEGENERATE (two parameters correlated beyond DEGENERATE, or three
    or more that only together shift the passes alike, e.g. pitch, yaw and sync offset along track);
    the parameters weighing in its eigenvector. None when every direction is measured."""
    if len(result.free) < 2:
        return None
    c = result.correlation()
    if not np.isfinite(c).all():
        return tuple(result.free)
    w, v = np.linalg.eigh(c)
    if w[0] >= 1.0 - DEGENERATE:
        return None
    weight = np.abs(v[:, w < 1.0 - DEGENERATE]).max(axis=1)    # every blind direction at once
    return tuple(n for i, n in enumerate(result.free) if weight[i] >= 0.2)


def make_report(result: Fit, start: Params, estimate, held: dict, before: dict, after: dict, pairs: list,
            pixel: float, dem_label) -> Calibration:
    sigma = {n: None for n in estimate}
    sigma.update(result.sigma())
    corr = result.correlation() if len(result.free) else np.zeros((0, 0))
    correlations, observable, notes = {}, {}, []
    for i, a in enumerate(result.free):
        for j in range(i + 1, len(result.free)):
            r = float(corr[i, j])
            if abs(r) >= 0.5:
                correlations[f"{a},{result.free[j]}"] = round(r, 4)
    for n in estimate:
        if n in held:
            observable[n] = False
            if not held[n]["with"]:
                notes.append(f"{n} has no measurable effect on the overlaps of this flight: held at its start value")
                continue
            w = " and ".join(held[n]["with"])
            notes.append(f"{n} cannot be separated from {w} by this flight (correlation with "
                         f"{held[n]['with'][0]} {held[n]['correlation']:+.4f}, smallest eigenvalue of the "
                         f"correlation matrix {held[n]['eigenvalue']:.2g}): held at its start value, {w} absorb"
                         f"{'s' if len(held[n]['with']) == 1 else ''} it")
            continue
        absorbs = [h for h, v in held.items() if n in v["with"]]
        if absorbs:
            observable[n] = False
            notes.append(f"{n} absorbs {' and '.join(absorbs)} (held): its estimate is their combination on this "
                         f"flight, right for registering it, not {n} alone")
            continue
        i = result.free.index(n)
        others = [(abs(float(corr[i, j])), result.free[j], float(corr[i, j]))
                  for j in range(len(result.free)) if j != i]
        worst = max(others) if others else (0.0, None, 0.0)
        observable[n] = bool(worst[0] < SEPARABLE)
        if not observable[n]:
            notes.append(f"{n} is not separable from {worst[1]} on this flight (correlation {worst[2]:+.4f}): "
                         f"their combination is measured, each alone only to +-{_fmt(n, sigma[n])}")
    if dem_label is not None and "ground" in estimate and sigma.get("ground") is not None \
            and abs(result.params.ground) > max(2.0 * sigma["ground"], 0.01):
        notes.append(f"the DEM {dem_label} is {result.params.ground:+.3f} m off the flight's ground: renders take "
                     "no DEM offset, so correct the DEM's heights (or its datum) by this much")
    if not observable.get("pitch", True) or not observable.get("sync", True):
        notes.append("pitch and sync offset both shift along track: they separate only through speed, height "
                     "or attitude changes during the passes")
    return Calibration(result.params, start, tuple(estimate), sigma, observable, correlations, before, after,
                       pairs, pixel, dem_label, notes, held)


def _fmt(name: str, value: float | None) -> str:
    if value is None:
        return "?"
    unit = {"roll": "deg", "pitch": "deg", "yaw": "deg", "sync": "s"}.get(name, "m")
    return f"{value:.3g} {unit}"
