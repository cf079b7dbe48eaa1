"""``archive calibrate``: the parsed options -> :func:`archive.calibrate.calibrate`, a report (text or
``--json``), and with ``--apply`` the estimates recorded where renders find them
(:mod:`archive.calibrate.apply`)."""

from __future__ import annotations

import argparse
import json
import sys

from archive.errors import InputError
from archive.params import NavigationParams

__all__ = ["run", "open_calibration_sources"]


def open_calibration_sources(names, archive=None, fov=None, navigation=None, navigation_columns=None):
    """Opened sources of ``names`` (raw directories or collection ids of ``archive``) with the
    parameters they record (a collection's as ingested, a raw flight's sidecar), and the field of
    view (``fov``, else the collections'). ``navigation``: their georectification source
    (``--navigation``: a raw flight's SBET/CSV trajectory, or ``lcf`` / a collection's track name;
    default the flight's own default), ``navigation_columns`` a CSV export's column text."""
    from archive.formats.trajectory import parse_columns
    from archive.sources import open_source

    if not names:
        raise InputError("calibrate", "no flight given", "name a raw flight directory or a collection id with --archive")
    opened = []
    for name in names:
        params = NavigationParams(sync_offset=None, boresight_deg=None, lever_arm_m=None)
        opened.append(open_source(name, params, archive=archive, navigation=navigation,
                                  navigation_columns=parse_columns(navigation_columns)))
    fovs = {fov} if fov is not None else {s.fov_deg for s in opened}
    if None in fovs:
        raise InputError("--fov", "raw flights do not record their field of view",
                         "pass --fov DEG (47.5 for a Pika L and for 'archive simulate' flights)")
    if len(fovs) != 1:
        raise InputError("--fov", f"the collections were ingested with different fields of view ({sorted(fovs)})",
                         "calibrate flights of one camera, or pass --fov")
    return opened, float(fovs.pop())


def _ground(args: argparse.Namespace, sources) -> tuple:
    """(dem, dem_label, ground): the DEM (--dem, else the one ``sources`` were ingested with) and
    its start offset 0, or no DEM and the flat ground height (--ground-height, else ``sources``')."""
    from archive.sources.ground import auto_ground_height, sources_dem

    if args.dem is not None and args.ground_height is not None:
        raise InputError("--dem", "a DEM and a numeric --ground-height exclude each other", "give one of them")
    dem, dem_label = None, None
    if args.dem is not None:
        from archive.terrain.dem import open_dem

        dem = open_dem(args.dem, args.dem_datum)
        dem_label = str(args.dem)
    elif args.ground_height is None:
        spec = sources_dem(sources)
        if spec is not None:
            dem, dem_label = spec.open(), str(spec.path)
    if dem is not None:
        return dem, dem_label, 0.0
    if args.ground_height is not None:
        return None, None, float(args.ground_height)
    return None, None, auto_ground_height(sources)


def run(args: argparse.Namespace) -> int:
    from archive.calibrate.estimate import calibrate, parse_estimate

    if getattr(args, "apply", False) and args.archive is not None:   # before any estimate
        from archive.collection import check_updatable

        check_updatable(args.archive)
    if getattr(args, "reference", None):
        return run_reference(args)
    if any(getattr(args, k, None) is not None for k in ("query_bbox", "query_datetime", "query_wavelength")):
        raise InputError("--query-*", "selects the flights to co-register to a reference", "add --reference REF")
    estimate = parse_estimate(args.estimate)
    if any(n in estimate for n in ("east", "north", "up")):
        raise InputError("--estimate", "a position offset is relative to another flight: a flight's own overlaps "
                         "cannot see it", "add --reference REF (a flight over the same ground)")
    sources, fov = open_calibration_sources(args.sources, args.archive, args.fov, args.navigation,
                                            args.navigation_columns)
    dem, dem_label, ground = _ground(args, sources)
    quiet = args.json or args.quiet
    result = calibrate(sources, fov, ground, dem=dem, dem_label=dem_label, estimate=estimate,
                       progress=None if quiet else (lambda text: print(text, file=sys.stderr)))
    applied = None
    if args.apply:
        from archive.calibrate.apply import apply

        applied = [str(p) for p in apply(sources, result, fov, args.archive)]
    if args.json:
        out = result.to_json()
        if applied is not None:
            out["applied"] = applied
        print(json.dumps(out, indent=1))
    else:
        print(describe(result))
        if applied:
            print("recorded: " + ", ".join(applied))
    return 0


def run_reference(args: argparse.Namespace) -> int:
    """``calibrate --reference REF``: every SOURCE (and every flight of the ``--query-*`` filters
    but REF) co-registered to REF on its own; one report (or, for several flights, one line) per
    flight; a flight that fails costs only itself (exit 1 when any failed)."""
    from archive.calibrate.coregister import COREGISTER_ESTIMATE, coregister
    from archive.calibrate.estimate import parse_estimate
    from archive.errors import ArchiveError
    from archive.run.command import query_ids

    estimate = parse_estimate(args.estimate, default=COREGISTER_ESTIMATE)
    names = list(args.sources or [])
    names += [i for i in query_ids(args) or () if i not in names]
    (reference,), fov = open_calibration_sources([args.reference], args.archive, args.fov)
    ref_id = str(reference.id) if hasattr(reference, "store") else str(reference.label)
    names = [n for n in names if n not in (args.reference, ref_id)]
    if not names:
        raise InputError("calibrate", f"no flight to co-register to {ref_id}",
                         "name flights (SOURCE...) or select them with --query-bbox, --query-datetime or "
                         "--query-wavelength")
    dem, dem_label, ground = _ground(args, [reference])
    quiet = args.json or args.quiet
    batch = len(names) > 1
    outputs, failed = [], 0
    for name in names:
        try:
            (source,), _ = open_calibration_sources([name], args.archive, fov, args.navigation,
                                                    args.navigation_columns)
            result = coregister(source, reference, fov, ground, dem=dem, dem_label=dem_label, estimate=estimate,
                                progress=None if quiet or batch else (lambda text: print(text, file=sys.stderr)))
            applied = None
            if args.apply:
                from archive.calibrate.apply import apply

                applied = [str(p) for p in apply([source], result, fov, args.archive)]
        except Exception as exc:  # noqa: BLE001 - in a batch a flight that fails costs only itself
            if not batch:
                raise
            failed += 1
            text = str(exc) if isinstance(exc, ArchiveError) else f"{type(exc).__name__}: {exc}"
            outputs.append({"id": name, "status": "failed", "error": text})
            if not args.json:
                print(f"{name}: failed: {text}", flush=True)
            continue
        out = {"id": name, "status": "done", **result.to_json()}
        if applied is not None:
            out["applied"] = applied
        outputs.append(out)
        if args.json:
            continue
        if batch:
            print(summary_line(name, result) + (" (recorded)" if applied else ""), flush=True)
        else:
            print(describe(result))
            if applied:
                print("recorded: " + ", ".join(applied))
    if args.json:
        print(json.dumps(outputs[0] if not batch else {"reference": ref_id, "flights": outputs}, indent=1))
    return 1 if failed else 0


def summary_line(name: str, result) -> str:
    """One line per flight of a co-registration batch."""
    p, s = result.params, result.sigma
    b, a = result.between_before, result.between_after
    rejected = result.windows.get("unmatched", 0) + result.windows.get("outliers", 0)

    def sig(k, digits):
        return "" if s.get(k) is None else f"+-{s[k]:.{digits}f}"
    return (f"{name}: co-registered to {result.reference}: position offset {p.east:+.3f}{sig('east', 3)}, "
            f"{p.north:+.3f}{sig('north', 3)}, {p.up:+.3f}{sig('up', 3)} m, sync {p.sync:+.4f}{sig('sync', 4)} s; "
            f"between flights median {_num(b['median'])} -> {_num(a['median'])} px, p95 {_num(b['p95'])} -> "
            f"{_num(a['p95'])} px ({a['windows']} windows, {rejected} rejected)")


def describe(result) -> str:
    """The report for people: estimates with 1-sigma, observability, misregistration, overlap."""
    p, s = result.params, result.sigma
    dem = result.dem is not None

    def line(name, label, value, unit, digits):
        if name not in result.estimated:
            return f"  {label:<14} {value:.{digits}f} {unit} (held)"
        sig = s.get(name)
        tag = "" if result.observable.get(name, True) else "   NOT SEPARABLE (see below)"
        held = " (held at its start value)" if name in result.held else ""
        sig_text = "" if sig is None else f" +- {sig:.{digits}f}"
        return f"  {label:<14} {value:.{digits}f}{sig_text} {unit}{held}{tag}"

    rows = [
        "calibration (1-sigma):",
        line("roll", "boresight roll", p.roll, "deg", 4),
        line("pitch", "boresight pitch", p.pitch, "deg", 4),
        line("yaw", "boresight yaw", p.yaw, "deg", 4),
        line("sync", "sync offset", p.sync, "s", 4),
        line("ground", "DEM offset" if dem else "ground height", p.ground, "m", 3),
    ]
    if result.reference is not None or any(p.position_offset):
        rows[0] = ("co-registration to " + result.reference + " (1-sigma):") if result.reference else rows[0]
        rows += [line("east", "position dE", p.east, "m", 3), line("north", "position dN", p.north, "m", 3),
                 line("up", "position dU", p.up, "m", 3)]
    b, a = result.residual_before, result.residual_after
    rows.append(f"misregistration between passes (px of {result.pixel_m:.3f} m): before median "
                f"{_num(b['median'])}, p95 {_num(b['p95'])} ({b['windows']} windows); after median "
                f"{_num(a['median'])}, p95 {_num(a['p95'])} ({a['windows']} windows)")
    pairs = ", ".join(f"{q['passes'][0]}-{q['passes'][1]}: {q['pixels']} px, {q['windows']} windows"
                      for q in result.pairs)
    rows.append(f"overlap used: {pairs or 'none (the passes do not overlap each other)'}")
    if result.reference is not None:
        b, a, w = result.between_before, result.between_after, result.windows
        rows.append(f"misregistration with {result.reference} (px of {result.pixel_m:.3f} m): before median "
                    f"{_num(b['median'])}, p95 {_num(b['p95'])} ({b['windows']} windows); after median "
                    f"{_num(a['median'])}, p95 {_num(a['p95'])} ({a['windows']} windows)")
        cross = ", ".join(f"pass {q['passes'][0]} - reference pass {q['passes'][1]}: {q['pixels']} px, "
                          f"{q['windows']} windows" for q in result.between_pairs)
        rows.append(f"overlap with the reference: {result.overlap_m2:.0f} m2; {cross}")
        rows.append(f"windows between the flights: {w['textured']} textured of {w['tried']}, {w['matched']} used, "
                    f"{w['unmatched']} did not match, {w['outliers']} outliers")
    if result.correlations:
        rows.append("correlations: " + ", ".join(f"{k} {v:+.3f}" for k, v in result.correlations.items()))
    rows += [f"note: {n}" for n in result.notes]
    rows.append(f"render / ingest with: {result.flags()}")
    if result.reference is not None:
        rows.append("the position offset has no render flag: --apply records it (renders, stacks and the viewer "
                    "then use it)")
    return "\n".join(rows)


def _num(v) -> str:
    return "-" if v is None else f"{v:.3f}"
