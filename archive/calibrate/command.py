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


def open_calibration_sources(names, archive=None, fov=None):
    """Opened sources of ``names`` (raw directories or collection ids of ``archive``) with the
    parameters they record (a collection's as ingested, a raw flight's sidecar), and the field of
    view (``fov``, else the collections')."""
    from archive.sources import open_source

    if not names:
        raise InputError("calibrate", "no flight given", "name a raw flight directory or a collection id with --archive")
    opened = []
    for name in names:
        params = NavigationParams(fov_deg=fov or 47.5, sync_offset=None, boresight_deg=None, lever_arm_m=None)
        opened.append(open_source(name, params, archive=archive))
    fovs = {fov} if fov is not None else {s.fov_deg for s in opened}
    if None in fovs:
        raise InputError("--fov", "raw flights do not record their field of view",
                         "pass --fov DEG (47.5 for a Pika L and for 'archive simulate' flights)")
    if len(fovs) != 1:
        raise InputError("--fov", f"the collections were ingested with different fields of view ({sorted(fovs)})",
                         "calibrate flights of one camera, or pass --fov")
    return opened, float(fovs.pop())


def run(args: argparse.Namespace) -> int:
    from archive.calibrate.estimate import calibrate, parse_estimate
    from archive.sources.ground import auto_ground_height, sources_dem

    estimate = parse_estimate(args.estimate)
    sources, fov = open_calibration_sources(args.sources, args.archive, args.fov)
    if args.dem is not None and args.ground_height is not None:
        raise InputError("--dem", "a DEM and a numeric --ground-height exclude each other", "give one of them")
    dem, dem_label = None, None
    if args.dem is not None:
        from archive.dem import open_dem

        dem = open_dem(args.dem, args.dem_datum)
        dem_label = str(args.dem)
    elif args.ground_height is None:
        spec = sources_dem(sources)
        if spec is not None:
            dem, dem_label = spec.open(), str(spec.path)
    if dem is not None:
        ground = 0.0
    elif args.ground_height is not None:
        ground = float(args.ground_height)
    else:
        ground = auto_ground_height(sources)
    quiet = args.json or args.quiet
    result = calibrate(sources, fov, ground, dem=dem, dem_label=dem_label, estimate=estimate,
                       progress=None if quiet else (lambda text: print(text, file=sys.stderr)))
    applied = None
    if args.apply:
        from archive.calibrate.apply import apply

        applied = [str(p) for p in apply(sources, result, args.archive)]
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
    b, a = result.residual_before, result.residual_after
    rows.append(f"misregistration between passes (px of {result.pixel_m:.3f} m): before median "
                f"{_num(b['median'])}, p95 {_num(b['p95'])} ({b['windows']} windows); after median "
                f"{_num(a['median'])}, p95 {_num(a['p95'])} ({a['windows']} windows)")
    pairs = ", ".join(f"{q['passes'][0]}-{q['passes'][1]}: {q['pixels']} px, {q['windows']} windows"
                      for q in result.pairs)
    rows.append(f"overlap used: {pairs}")
    if result.correlations:
        rows.append("correlations: " + ", ".join(f"{k} {v:+.3f}" for k, v in result.correlations.items()))
    rows += [f"note: {n}" for n in result.notes]
    rows.append(f"render / ingest with: {result.flags()}")
    return "\n".join(rows)


def _num(v) -> str:
    return "-" if v is None else f"{v:.3f}"
