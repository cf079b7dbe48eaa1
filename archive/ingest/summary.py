"""``archive info DIR [--dem FILE]``: check a raw flight directory completely and print its summary.

Checks (through :class:`archive.sources.RawFlightSource`): every cube's header and data file size,
``.times`` line count and order, ``.lcf`` parse, navigation coverage of every line (with the given
sync offset), and the calibration if there is one (its bands and samples must fit every cube); with
``--dem``, that the DEM covers every line's swath (and the terrain under the flight). ``--navigation``
checks and summarises the flight with another navigation source, opened as ``render --navigation``
opens it (:func:`archive.sources.open_source`'s ``navigation``): a raw flight's post-processed
trajectory (SBET or CSV; one leaving lines without a pose is a NavigationError naming the file, the
gap and the lines), a collection's ``lcf`` or stored track.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from archive.errors import InputError
from archive.formats.lcf import gps_seconds_to_datetime
from archive.geometry.navigation import frame_interval, joined, strip_slices
from archive.params import NavigationParams
from archive.sources import RawFlightSource



def _number(x: float | None, digits: int = 3) -> float | None:
    return None if x is None or not math.isfinite(x) else round(float(x), digits)


def terrain_summary(source: RawFlightSource, fov_deg: float, dem) -> dict[str, Any]:
    """The terrain under a flight from ``dem`` (an opened :class:`archive.terrain.dem.Dem`): every line's
    swath edges and 7 rays between traced to their first hits on it (an error names the DEM and the lon/lat box it does
    not cover, or its holes), the ground under the camera and the camera's height above it (m)."""
    t = math.tan(math.radians(fov_deg) / 2)
    frame = source.frame
    dem.check_flight([source.poses(info.index) for info in source.cubes], fov_deg)
    ground, clearance, edges = [], [], []
    for info in source.cubes:
        poses = source.poses(info.index)
        p = poses.position
        if poses.valid is not None:
            p = p[np.asarray(poses.valid, bool)]
        if len(p) == 0:
            continue
        origin = np.stack([p[:, 1] + frame.origin_e, p[:, 0] + frame.origin_n, frame.origin_alt - p[:, 2]], axis=1)
        att = poses.attitude if poses.valid is None else poses.attitude[np.asarray(poses.valid, bool)]
        rays = []
        for u in np.linspace(-t, t, 9):   # the edges (checked: the DEM must cover them) and 7 rays between
            d = np.atleast_2d(att.apply(np.array([0.0, u, 1.0])))
            rays.append(np.stack([d[:, 1], d[:, 0], -d[:, 2]], axis=1))
        for (lam, under), d in zip(dem.intersect(frame.epsg, origin, rays), rays):
            if under.any():
                raise InputError(source.label, f"cube {info.base}: the camera is at or below the ground of "
                                 f"the DEM {dem.path}", "check the DEM and its vertical datum (--dem-datum)")
            edges.append((origin[:, 2] + lam * d[:, 2])[np.isfinite(lam)])
        h = dem.heights_at(frame.epsg, origin[:, 0], origin[:, 1])
        ground.append(h)
        clearance.append(origin[:, 2] - h)
    heights = np.concatenate(ground + edges)
    above = np.concatenate(clearance)
    return {"dem": str(dem.path), "datum": dem.datum, "datum_declared": dem.declared,
            "ground_min_m": _number(float(np.nanmin(heights)), 2), "ground_max_m": _number(float(np.nanmax(heights)), 2),
            "height_above_ground_mean_m": _number(float(np.nanmean(above)), 2),
            "height_above_ground_min_m": _number(float(np.nanmin(above)), 2)}


def ingest_id(source: RawFlightSource) -> str:
    """The collection id ``archive ingest`` gives a raw flight (``<sensor>_<UTC start>``, e.g.
    ``Pika-L-SIM_20240612T160000``): ``info`` names a flight as the archive will (issue 49 item 6)."""
    from archive.ingest.command import collection_id, sensor_name

    start = gps_seconds_to_datetime(float(source.line_times(0)[0]))   # with the sync offset, as ingest
    return collection_id(sensor_name(source.header(0).metadata), start)


def navigation_summary(source) -> dict[str, Any]:
    """Which navigation source ``source`` was opened with (``navigation``: 'lcf', a raw flight's trajectory
    file, a collection's track name), the one it uses by default and every one it has (``lcf``, then a
    collection's stored tracks, or the trajectory a raw flight was opened with)."""
    used = str(getattr(source, "navigation_source", "lcf"))
    info = getattr(source, "info", None)
    if info is not None and hasattr(info, "attrs"):   # a collection: the tracks ingest stored
        record = info.attrs.get("navigation_tracks") or {}
        names = ["lcf", *sorted(str(n) for n in (record.get("tracks") or {}) if str(n) != "lcf")]
        return {"navigation": used, "navigation_default": str(record.get("default") or "lcf"),
                "navigation_sources": names}
    return {"navigation": used, "navigation_default": "lcf",
            "navigation_sources": ["lcf"] if used == "lcf" else ["lcf", used]}


def _lcf_rows(source, cube: int, track) -> int:
    """Rows of ``cube``'s ``.lcf``: its track's when it is navigated by the ``.lcf``, else as recorded."""
    if getattr(source, "navigation_source", "lcf") == "lcf":
        return int(len(track.time))
    recorded = getattr(source, "recorded_navigation", None)   # a raw flight's own .lcf
    lcf = recorded[cube].lcf if recorded is not None else source.info.cubes[cube].lcf
    return int(len(lcf.time))


def summarize(source: RawFlightSource, fov_deg: float, dem=None) -> dict[str, Any]:
    """Summary of a flight as plain JSON-able values (times s, lengths m, angles deg) from the navigation
    it was opened with (:func:`navigation_summary`: track, altitudes and per cube ``navigation_rows``);
    with ``dem`` (an opened :class:`archive.terrain.dem.Dem`) also ``terrain`` (:func:`terrain_summary`)."""
    cubes = []
    track_length = 0.0
    track_time = 0.0
    altitudes = []
    strips = 1
    previous_end = None
    cal = source.has_calibration
    for info in source.cubes:
        t = source.line_times(info.index)
        track = source.track(info.index)
        lcf_alt = -track.position[:, 2] + source.frame.origin_alt
        altitudes.append(lcf_alt)
        step = np.diff(track.position[:, :2], axis=0)
        length = float(np.hypot(step[:, 0], step[:, 1]).sum())
        track_length += length
        track_time += float(track.time[-1] - track.time[0])
        duration = float(t[-1] - t[0]) if len(t) > 1 else 0.0
        interval = duration / (len(t) - 1) if len(t) > 1 else float("nan")
        if previous_end is not None and not joined(t[0] - previous_end, frame_interval(info.framerate, t)):
            strips += 1
        strips += len(strip_slices(t, frame_interval(info.framerate, t))) - 1  # pauses inside the cube
        previous_end = float(t[-1])
        if cal:
            # check the calibration fits this cube (bands, samples, binning, exposure keys)
            source.radiometry(info.index, [0], "radiance")
        cubes.append({
            "index": info.index, "base": info.base, "lines": info.lines, "samples": info.samples,
            "bands": info.bands, "framerate_hz": _number(info.framerate), "shutter_ms": _number(info.shutter_ms),
            "gain_db": _number(info.gain_db), "bit_depth": info.bit_depth,
            "start_s": round(float(t[0]), 3), "end_s": round(float(t[-1]), 3), "duration_s": round(duration, 3),
            "measured_line_rate_hz": _number(1.0 / interval if interval > 0 else None),
            "track_length_m": round(length, 2), "mean_altitude_m": round(float(np.mean(lcf_alt)), 2),
            "lcf": (str(source.files(info.index).lcf.name) if hasattr(source, "files") else f"{info.base}.lcf"),
            "lcf_rows": _lcf_rows(source, info.index, track), "navigation_rows": int(len(track.time)),
        })
    start = source.cubes[0].first_time
    end = float(source.line_times(len(source.cubes) - 1)[-1])
    alt = np.concatenate(altitudes)
    wl = source.wavelengths
    half = math.tan(math.radians(fov_deg) / 2)
    samples = source.cubes[0].samples
    duration = end - start
    return {
        "directory": str(getattr(source, "directory", None) or getattr(source, "store", source.label)),
        "id": ingest_id(source) if isinstance(source, RawFlightSource) else source.id,
        "cubes": len(source.cubes),
        "strips": strips,
        "lines": int(sum(c.lines for c in source.cubes)),
        "samples": samples,
        "bands": source.cubes[0].bands,
        "wavelength_min_nm": None if not wl else round(min(wl), 3),
        "wavelength_max_nm": None if not wl else round(max(wl), 3),
        "start_gps_s": round(start, 3),
        "end_gps_s": round(end, 3),
        "duration_s": round(duration, 3),
        "start_utc": gps_seconds_to_datetime(start).isoformat(),
        "sync_offset_s": source.params.sync_offset,
        **navigation_summary(source),
        "epsg": source.frame.epsg,
        "track_length_m": round(track_length, 2),
        "mean_speed_m_s": _number(track_length / track_time if track_time > 0 else None, 2),
        "mean_altitude_m": round(float(np.mean(alt)), 2),
        "min_altitude_m": round(float(np.min(alt)), 2),
        "max_altitude_m": round(float(np.max(alt)), 2),
        "fov_deg": fov_deg,
        "swath_per_m_height": round(2 * half, 4),
        "gsd_per_m_height": round(2 * half / samples, 6),
        "calibration": (str(source.calibration_path) if getattr(source, "calibration_path", None) is not None
                        else "stored in the collection" if source.has_calibration else None),
        "downwelling": _downwelling(source),
        **({} if dem is None else {"terrain": terrain_summary(source, fov_deg, dem)}),
        "cube_list": cubes,
    }


def _downwelling(source) -> str | None:
    """The sky spectrometer's files for --mode reflectance (issue 34): what was found, whether they
    read; None when the flight has none."""
    from archive.errors import ArchiveError

    files = getattr(source, "downwelling", None)
    if files is None:   # a collection
        record = getattr(source, "info", None) and source.info.attrs.get("downwelling")
        return f"{len(record['spectra'])} spectra stored in the collection" if record else None
    if not files.present:
        return None
    try:
        sky = source.sky()
    except ArchiveError as exc:
        return f"{sum(files.found)} of {len(files.found)} spectra, unusable for --mode reflectance: {exc}"
    return f"{len(sky.cubes)} spectra, calibration {sky.calibration}"


def _navigation_line(s: dict[str, Any]) -> list[str]:
    """The navigation line of :func:`format_summary`: none for a flight whose only source is its ``.lcf``."""
    sources = s.get("navigation_sources") or ["lcf"]
    used = s.get("navigation", "lcf")
    if used == "lcf" and len(sources) == 1:
        return []
    listed = ", ".join(f"{n} (default)" if n == s.get("navigation_default") else n for n in sources)
    return [f"navigation {used} (track and altitude from it); sources: {listed}"]


def format_summary(s: dict[str, Any]) -> str:
    """Readable multi-line text of :func:`summarize`'s result."""
    wl = ("no wavelengths" if s["wavelength_min_nm"] is None
          else f"{s['wavelength_min_nm']:.1f}\u2013{s['wavelength_max_nm']:.1f} nm")
    lines = [
        f"flight     {s['directory']}  (id {s['id']})",
        f"cubes      {s['cubes']} in {s['strips']} strip(s), {s['lines']} lines x {s['samples']} samples x "
        f"{s['bands']} bands, {wl}",
        f"time       {s['start_utc']}  ({s['start_gps_s']:.3f} s GPS), {s['duration_s']:.1f} s, "
        f"sync offset {s['sync_offset_s']:+.3f} s",
        f"frame      EPSG:{s['epsg']} (WGS 84 / UTM)",
        *_navigation_line(s),
        f"track      {s['track_length_m']:.1f} m"
        + ("" if s["mean_speed_m_s"] is None else f" at {s['mean_speed_m_s']:.2f} m/s mean")
        + f", altitude {s['mean_altitude_m']:.1f} m mean ({s['min_altitude_m']:.1f}\u2013{s['max_altitude_m']:.1f}) "
        "above the ellipsoid",
        f"swath      {s['swath_per_m_height']:.3f} x height above ground (FOV {s['fov_deg']:g} deg); nominal GSD "
        f"{s['gsd_per_m_height'] * 100:.3f} cm per m of height ({s['gsd_per_m_height'] * 40 * 100:.2f} cm at 40 m)",
        f"calibration {s['calibration'] or 'none (only --mode raw and relative)'}",
        *([] if not s.get("downwelling") else [f"downwelling {s['downwelling']}"]),
        *([] if not s.get("terrain") else [
            f"terrain    {s['terrain']['dem']} ({s['terrain']['datum']} heights): ground "
            f"{s['terrain']['ground_min_m']:.1f}\u2013{s['terrain']['ground_max_m']:.1f} m above the ellipsoid under "
            f"the swath, camera {s['terrain']['height_above_ground_mean_m']:.1f} m above it mean "
            f"({s['terrain']['height_above_ground_min_m']:.1f} min)"]),
        "",
        f"{'#':>3}  {'cube':<28} {'lines':>6} {'Hz':>8} {'shutter ms':>10} {'gain dB':>7} {'start s':>16} "
        f"{'dur s':>7} {'track m':>8} {'alt m':>7}",
    ]
    for c in s["cube_list"]:
        def f(v, fmt):
            return "-" if v is None else format(v, fmt)
        lines.append(
            f"{c['index']:>3}  {c['base']:<28} {c['lines']:>6} {f(c['framerate_hz'], '8.3f')} "
            f"{f(c['shutter_ms'], '10.3f')} {f(c['gain_db'], '7.2f')} {c['start_s']:>16.3f} {c['duration_s']:>7.3f} "
            f"{c['track_length_m']:>8.1f} {c['mean_altitude_m']:>7.1f}")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    """``archive info DIR|ID [--archive A] [--fov DEG] [--sync-offset S] [--dem FILE] [--navigation FILE|lcf|NAME
    [--navigation-columns C]] [--json]``; errors propagate as ArchiveError. A collection ingested with a DEM is
    summarised over it (``--dem`` wins), and from its default navigation source unless ``--navigation`` names
    another (``lcf`` or a stored track; a trajectory file is for raw flights, as in ``render``)."""
    from archive.formats.trajectory import parse_columns
    from archive.terrain.dem import open_dem
    from archive.sources import open_source
    from archive.sources.ground import recorded_dem

    archive = getattr(args, "archive", None)
    fov = getattr(args, "fov", None)
    if getattr(args, "dem", None) is None and getattr(args, "dem_datum", None) is not None:
        raise InputError("--dem-datum", "gives the vertical datum of a DEM, but no --dem was given",
                         "add --dem FILE, or leave --dem-datum out")
    navigation = getattr(args, "navigation", None)
    columns = parse_columns(getattr(args, "navigation_columns", None))
    if navigation is None and columns is not None:
        raise InputError("--navigation-columns", "names a CSV trajectory's columns, but no --navigation was given",
                         "add --navigation FILE, or leave --navigation-columns out")
    if archive is None or Path(args.directory).is_dir():
        fov = 47.5 if fov is None else float(fov)   # info's documented default (a Pika L's)
        source = RawFlightSource(args.directory, NavigationParams(sync_offset=float(args.sync_offset)),
                                 navigation=None if navigation in (None, "lcf") else navigation,
                                 navigation_columns=columns)
        spec = None
    else:
        if fov is None:
            from archive.sources.open import collection_fov

            fov = collection_fov(archive, [args.directory])
        source = open_source(args.directory, NavigationParams(sync_offset=None), archive=archive,
                             navigation=navigation, navigation_columns=columns)
        spec = recorded_dem(source.info.attrs.get("terrain"), str(args.directory))
    if getattr(args, "dem", None) is not None:
        dem = open_dem(args.dem, args.dem_datum)
    else:
        dem = None if spec is None else spec.open()
    summary = summarize(source, float(fov), dem)
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        print(format_summary(summary))
    return 0
