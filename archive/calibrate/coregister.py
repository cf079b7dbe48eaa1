"""``archive calibrate --reference``: a flight's navigation corrections relative to a reference
flight held fixed, from where the two overlap (DESIGN 11; issue 33).

What is estimated: a constant position offset (dE, dN, dU metres, grid east/north of the flight's
UTM zone and up: a GNSS bias) besides the flight's sync offset and boresight. The reference's
navigation, mounting and ground are held: its passes are rendered under its own recorded
parameters, in the flight's local frame.

1. Measure: every pair (pass of the flight, pass of the reference) whose footprints overlap is
   rendered onto a common grid (:func:`~archive.calibrate.match.pair_grid`) and matched exactly
   like two passes of one flight (coarse masked NCC, then Lucas-Kanade with a gain and offset per
   window: robust to a different day's light); the flight's own pass pairs are measured too and
   keep constraining its sync offset and boresight.
2. Solve: the flight's ray through each cross window must meet the ground where the reference saw
   the same content (:class:`~archive.calibrate.solve.Anchored`), jointly with the flight's own
   tie pairs, by the robust least squares of :mod:`archive.calibrate.solve`; the sync offset is
   searched first as in :func:`~archive.calibrate.estimate.calibrate`.
3. Repeat under the new parameters until they settle; report 1-sigma, what the overlap cannot
   separate (held, said), the misregistration between the two flights before and after, the
   overlap used and the windows rejected (textured windows that did not match: grown, moved or new
   ground; matched windows left off by the fit).

The ground is the reference's: relative to a reference held fixed, a ground height error of the
flight and its vertical offset dU change its rays identically, so only dU is estimated.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np

from archive.calibrate.estimate import (MIN_OVERLAP_WINDOWS, MIN_WINDOW, SPACING, SWATH_PIXELS,
                                        WINDOW, Calibration, FlightImages, check_converged, dem_surface,
                                        describe_params, fit_separable, make_report, measure_passes, nominal_pixel,
                                        pass_images, prefiltered, rect_sides, refit, search_sync, tie_stats)
from archive.calibrate.match import measure_pair, pair_grid
from archive.calibrate.model import PARAM_NAMES, FlightModel, Params
from archive.calibrate.solve import anchored
from archive.errors import InputError

__all__ = ["COREGISTER_ESTIMATE", "MAX_PAIR_WINDOWS", "MIN_CROSS_TIES", "OUTLIER_PX", "coregister"]

#: What ``--reference`` estimates unless ``--estimate`` says otherwise.
COREGISTER_ESTIMATE = ("roll", "pitch", "yaw", "sync", "east", "north", "up")
#: Fewest windows matched between the two flights (under the start parameters: MIN_FIRST_CROSS).
MIN_CROSS_TIES = 30
MIN_FIRST_CROSS = 12
#: Windows measured at most per pair of passes between the flights (spread over the overlap): crossing
#: passes overlap over their whole swath, thousands of windows; a few hundred fix the offset to mm.
MAX_PAIR_WINDOWS = 200
#: A window matched between the flights but still this far off after the solution (px of the
#: nominal GSD) is counted as rejected (changed ground that happened to correlate).
OUTLIER_PX = 1.0


def _label(source) -> str:
    """A collection's id, a raw flight's directory."""
    return str(source.id) if hasattr(source, "store") else str(source.label)


def coregister(source, reference, fov_deg: float, ground: float, *, dem=None, dem_label: str | None = None,
               estimate: Sequence[str] = COREGISTER_ESTIMATE, progress=None, window: int = WINDOW) -> Calibration:
    """Estimate ``estimate`` (names of :data:`~archive.calibrate.model.PARAM_NAMES`; 'ground' is
    held at the reference's) of the opened navigated ``source`` relative to the opened
    ``reference`` (held fixed under the parameters it records), both seen by one camera of field of
    view ``fov_deg``.

    ground: the reference's ground height (m above the ellipsoid), or with ``dem`` (an opened
    :class:`archive.terrain.dem.Dem`) the DEM's vertical offset (m), used for both flights. progress: a
    callable taking a line of text, or None. Returns a :class:`Calibration` whose ``reference``,
    ``between_*`` and ``windows`` fields describe the registration between the two flights.
    InputError (one line, naming both flights) when they do not overlap, the overlap has too little
    texture or too few windows match, or the solution does not converge."""
    say = progress or (lambda text: None)
    name, ref_name = _label(source), _label(reference)
    asked = tuple(n for n in PARAM_NAMES if n in set(estimate))
    estimate = tuple(n for n in asked if n != "ground")
    if not estimate:
        raise InputError("--estimate", "nothing to estimate against a reference but the ground, which is the "
                         "reference's", "estimate position, sync and/or boresight")
    first, rp = source.params, reference.params
    start = Params(*first.boresight_deg, float(first.sync_offset), float(ground), *first.position_offset)
    ref_params = Params(*rp.boresight_deg, float(rp.sync_offset), float(ground), *rp.position_offset)
    fmodel = FlightModel(source, fov_deg, None if dem is None else dem_surface(dem, source, fov_deg))
    rmodel = FlightModel(reference, fov_deg, None if dem is None else dem_surface(dem, reference, fov_deg,
                                                                                 frame=fmodel.frame),
                         frame=fmodel.frame)
    flight, ref = FlightImages(source, fmodel, ()), FlightImages(reference, rmodel, ())
    ground_for_pixel = ground if dem is None else float(np.median(dem.typical_height())) + ground
    pixel = nominal_pixel([flight], ground_for_pixel, dem)
    samples = float(np.median([c.samples for c in source.cubes]))
    spacing = max(SPACING * pixel, pixel * samples / SWATH_PIXELS)
    area, longest = _cross_overlap(flight, ref, start, ref_params)
    need = MIN_OVERLAP_WINDOWS * window * spacing
    if area <= 0.0:
        raise InputError(name, f"does not overlap the reference {ref_name}: overlap found 0 m2 (footprints "
                         f"{_distance(flight, ref, start, ref_params):.0f} m apart)",
                         "choose a reference flown over the same ground (archive catalog search --bbox)")
    if longest < need:
        raise InputError(name, f"overlaps the reference {ref_name} over only {area:.0f} m2 ({longest:.1f} m "
                         f"across), co-registration needs at least {need:.1f} m ({MIN_OVERLAP_WINDOWS} windows)",
                         "choose a reference that covers more of this flight")
    flight = FlightImages(source, fmodel, prefiltered(flight, pass_images(source, fmodel), spacing, pixel))
    ref = FlightImages(reference, rmodel, prefiltered(ref, pass_images(reference, rmodel), spacing, pixel))

    say(f"measuring {name} against {ref_name} under the start parameters ({_text(start, dem)})")
    sets, cross_pairs, cross_ties, own_ties = _measure_both(flight, ref, start, ref_params, spacing, window, say,
                                                            solved=False)
    before, own_before = tie_stats(cross_ties, spacing, pixel), tie_stats(own_ties, spacing, pixel)
    _check_cross(cross_ties, cross_pairs, estimate, name, ref_name, first=True)
    params = start
    held: dict = {}
    if any(n in estimate for n in ("east", "north", "up")):   # the bias first: it dominates the shifts
        offset = [n for n in estimate if n in ("east", "north", "up")]
        params = fit_separable(sets, params, start, offset, {}, pixel, say).params
    if "sync" in estimate:
        params = search_sync(sets, params, estimate, pixel, say, fine=True)
    result = fit_separable(sets, params, start, list(estimate), held, pixel, say)

    def measure(trial: Params):
        sets, cross_pairs, cross_ties, _ = _measure_both(flight, ref, trial, ref_params, spacing, window, say)
        _check_cross(cross_ties, cross_pairs, estimate, name, ref_name)
        return sets

    result = refit(result, measure, lambda sets, trial: fit_separable(
        sets, trial, start, [n for n in estimate if n not in held], held, pixel, say),
        lambda trial: _text(trial, dem), say)
    params = result.params
    say(f"final: {_text(params, dem)}")
    _, cross_pairs, cross_after, own_after = _measure_both(flight, ref, params, ref_params, spacing, window,
                                                           lambda text: None)
    inlying = [t for t in cross_after if math.hypot(*t.shift) * spacing / pixel <= OUTLIER_PX]
    after = tie_stats(inlying, spacing, pixel)
    own = tie_stats(own_after, spacing, pixel)
    try:
        check_converged(result, start, after, [flight])
    except InputError as exc:
        what = exc.problem.removeprefix("calibration did not converge: ").replace("the passes", "the flights")
        raise InputError(name, f"co-registration to {ref_name} did not converge: {what}", exc.fix) from None
    own_pairs = [{k: v for k, v in p.items() if k != "own"} for p in cross_pairs if p.get("own")]
    report = make_report(result, start, estimate, held, own_before, own, own_pairs, pixel, dem_label)
    tried = sum(p["tried"] for p in cross_pairs if not p.get("own"))
    textured = sum(p["textured"] for p in cross_pairs if not p.get("own"))
    matched = len(cross_after)
    windows = {"tried": int(tried), "textured": int(textured), "matched": int(len(inlying)),
               "unmatched": int(textured - matched), "outliers": int(matched - len(inlying))}
    notes = list(report.notes)
    if "ground" in asked or "up" in estimate:
        notes.append(f"the ground is the reference's ({'DEM offset' if dem is not None else 'height'} "
                     f"{ground:.3f} m, held): relative to a reference held fixed, a ground error of the flight "
                     "and its vertical offset dU move its rays alike"
                     + ("; dU is estimated" if "up" in estimate else ""))
    if windows["unmatched"] or windows["outliers"]:
        notes.append(f"{windows['unmatched'] + windows['outliers']} of {textured} textured windows between the "
                     f"flights were rejected ({windows['unmatched']} did not match, {windows['outliers']} "
                     f"matched but stayed more than {OUTLIER_PX:g} px off): ground that changed between the days")
    between = [{k: v for k, v in p.items() if k != "own"} for p in cross_pairs if not p.get("own")]
    return dataclasses.replace(report, notes=notes, reference=ref_name,
                               between_before=before, between_after=after, between_pairs=between,
                               windows=windows, overlap_m2=round(float(area), 1))


def _text(p: Params, dem) -> str:
    return (f"{describe_params(p, dem is not None)}, position offset {p.east:+.3f},{p.north:+.3f},{p.up:+.3f} m")


def _footprints(f: FlightImages, params: Params):
    from shapely.ops import unary_union

    prints = [f.model.footprint(p, params) for p in f.model.passes]
    prints = [p for p in prints if p is not None and not p.is_empty]
    return unary_union(prints) if prints else None


def _cross_overlap(flight: FlightImages, ref: FlightImages, params: Params, ref_params: Params) -> tuple[float, float]:
    """Area (m2) of the overlap of the two flights' footprints, and the longest side (m) of the
    largest overlapping piece's minimum rotated rectangle."""
    a, b = _footprints(flight, params), _footprints(ref, ref_params)
    if a is None or b is None:
        return 0.0, 0.0
    inter = a.intersection(b)
    if inter.is_empty or inter.area <= 0:
        return 0.0, 0.0
    pieces = getattr(inter, "geoms", [inter])
    longest = max((max(rect_sides(g.minimum_rotated_rectangle)) for g in pieces if g.area > 0), default=0.0)
    return float(inter.area), float(longest)


def _distance(flight: FlightImages, ref: FlightImages, params: Params, ref_params: Params) -> float:
    a, b = _footprints(flight, params), _footprints(ref, ref_params)
    return float("nan") if a is None or b is None else float(a.distance(b))


def _measure_both(flight: FlightImages, ref: FlightImages, params: Params, ref_params: Params, spacing: float,
                  window: int, say, solved: bool = True) -> tuple[list, list, list, list]:
    """(sets for the solver: the flight's own pass pairs and its anchored ties to the reference;
    the pairs measured (own pairs flagged 'own'); the ties between the flights; the own ties).
    solved: ``params`` come from a solution, so a pair whose coarse search finds no clear
    correlation (much changed ground) is searched about no shift instead of left out."""
    own_sets, own_pairs, own_ties = measure_passes([flight], params, spacing, window, say)
    grids: dict = {}
    ties: list = []
    pairs = [{**p, "own": True} for p in own_pairs]
    for i, pa in enumerate(flight.model.passes):
        for j, pb in enumerate(ref.model.passes):
            grid = pair_grid(flight.model, pa, pb, params, spacing, model_b=ref.model, params_b=ref_params)
            if grid is None:
                continue
            kw = {"model_b": ref.model, "params_b": ref_params, "fallback": np.zeros(2) if solved else None,
                  "max_windows": MAX_PAIR_WINDOWS}
            found, stats = measure_pair(flight.model, grid, flight.images[i], ref.images[j], params, window, **kw)
            if stats["windows"] == 0 and window > MIN_WINDOW:
                found, stats = measure_pair(flight.model, grid, flight.images[i], ref.images[j], params,
                                            MIN_WINDOW, **kw)
            grids[(i, j)] = grid
            ties.extend(found)
            pairs.append({"passes": [i, j], "pixels": stats["overlap_px"], "windows": stats["matched"],
                          "textured": stats["textured"], "tried": stats["windows"]})
            say(f"  pass {i} - reference pass {j}: {stats['overlap_px']} px overlap, {stats['textured']} textured "
                f"windows, {stats['matched']} matched")
    sets = [s for s in own_sets if len(s[1])] + [(flight.model, anchored(flight.model, grids, ties, params))]
    return sets, pairs, ties, own_ties


def _check_cross(ties, pairs, estimate, name: str, ref_name: str, first: bool = False) -> None:
    """InputError unless enough windows matched between the flights."""
    need = max(MIN_CROSS_TIES, 6 * len(estimate)) if not first else max(MIN_FIRST_CROSS, 2 * len(estimate) + 2)
    if len(ties) >= need:
        return
    cross = [p for p in pairs if not p.get("own")]
    textured = sum(p["textured"] for p in cross)
    tried = sum(p["tried"] for p in cross)
    if tried == 0:
        raise InputError(name, f"its overlap with the reference {ref_name} is too narrow: no measurement window "
                         "fits in it", "choose a reference that covers more of this flight")
    if textured < need:
        raise InputError(name, f"too little texture where it overlaps the reference {ref_name}: {textured} of "
                         f"{tried} windows are textured, co-registration needs {need}",
                         "choose a reference over ground with more detail")
    raise InputError(name, f"only {len(ties)} of {textured} textured windows matched the reference {ref_name} "
                     f"(co-registration needs {need})", "the ground may have changed too much between the flights, "
                     "or the start parameters are far off (--fov, the ground height)")
