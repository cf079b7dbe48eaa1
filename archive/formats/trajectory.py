"""Post-processed trajectories (PPK): Applanix SBET and CSV/ASCII exports (DESIGN 12).

- **SBET** (``.out``, ``.sbet``): records of 17 little-endian float64: time (GPS seconds of week),
  latitude, longitude (rad), ellipsoidal height (m), velocity north, east, down (m/s), roll (rad,
  + right wing down: aerospace), pitch (rad, + nose up), platform heading (rad, clockwise from north in
  the wander frame), wander angle (rad), body accelerations x, y, z, angular rates x, y, z. The true
  heading is platform heading - wander angle.
- **CSV / ASCII** with a header row (comma-, semicolon-, tab- or space-separated; lines starting with
  ``#`` or ``%`` before it are skipped): Inertial Explorer's names ``GPSTime, Latitude, Longitude, H-Ell,
  Roll, Pitch, Heading`` (degrees, aerospace signs) are found without help; any other export names its
  columns with ``--navigation-columns time=COL,lat=COL,lon=COL,height=COL,roll=COL,pitch=COL,heading=COL``
  (e.g. Qinertia: ``time=GPS Time,lat=Latitude,lon=Longitude,height=Altitude Ellipsoid,roll=Roll,
  pitch=Pitch,heading=Yaw``).

Time is GPS seconds of week (a trajectory that crosses a week boundary is unwrapped) or full GPS
seconds (since 1980-01-06), told apart by size; :func:`on_gps_scale` puts it on the ``.lcf``'s scale
(the week taken from the flight's own clock); a UTC column instead (``--navigation-columns utc=COL,...``)
gets the leap seconds in force at the flight added. A file that is not monotonic in time or holds a NaN is
refused naming the file and the row.
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from archive.errors import FormatError, InputError, MissingInputError

__all__ = ["COLUMNS", "Trajectory", "on_gps_scale", "parse_columns", "read_trajectory"]

WEEK_S = 604800.0
ROLLOVER_S = 1024 * WEEK_S
SBET_FIELDS = 17
#: The columns a trajectory needs, and Inertial Explorer's names of them.
COLUMNS = {"time": "GPSTime", "lat": "Latitude", "lon": "Longitude", "height": "H-Ell", "roll": "Roll",
           "pitch": "Pitch", "heading": "Heading"}


@dataclass(frozen=True, eq=False)
class Trajectory:
    """A post-processed trajectory of the INS; every array (n,), in time order.

    time: s, GPS seconds of week (unwrapped past a week boundary) when ``week_seconds``, else full GPS
    seconds; lat, lon: degrees; height: m above the WGS-84 ellipsoid; roll (+ right wing down), pitch
    (+ nose up), heading (true north, clockwise): radians, aerospace signs.
    """

    path: Path
    time: np.ndarray
    lat: np.ndarray
    lon: np.ndarray
    height: np.ndarray
    roll: np.ndarray
    pitch: np.ndarray
    heading: np.ndarray
    week_seconds: bool
    utc: bool = False   #: ``time`` is UTC (seconds of the UTC week, or since 1980-01-06 UTC): no leap seconds


def parse_columns(text: str | None) -> dict[str, str] | None:
    """``time=COL,lat=COL,...`` -> {name: column} (``utc=COL`` instead of ``time``: a UTC time column, kept
    under the key ``utc``); None for None. InputError naming the option."""
    if text is None:
        return None
    out = {}
    for part in str(text).split(","):
        key, sep, value = part.partition("=")
        key = key.strip().lower()
        if not sep or key not in (*COLUMNS, "utc") or not value.strip():
            raise InputError("--navigation-columns", f"{part.strip()!r} is not NAME=COLUMN with NAME one of "
                             f"{', '.join(COLUMNS)} (or utc)", "e.g. --navigation-columns time=GPS Time,lat=Latitude")
        out[key] = value.strip()
    missing = [k for k in COLUMNS if k not in out and not (k == "time" and "utc" in out)]
    if missing or ("utc" in out and "time" in out):
        raise InputError("--navigation-columns", f"names no column for {', '.join(missing)}" if missing else
                         "names both time= and utc=", "give all of " + ", ".join(f"{k}=COL" for k in COLUMNS))
    return out


def read_trajectory(path: str | os.PathLike, columns: dict[str, str] | None = None) -> Trajectory:
    """Read an SBET (``.out``/``.sbet``) or a CSV/ASCII export (any other name); see the module docstring."""
    path = Path(path)
    if not path.is_file():
        raise MissingInputError(path, "trajectory file", "check the --navigation path")
    if path.suffix.lower() in (".out", ".sbet"):
        if columns is not None:
            raise InputError("--navigation-columns", "an SBET has fixed fields", "leave --navigation-columns out")
        return _sbet(path)
    return _text(path, columns)


def _sbet(path: Path) -> Trajectory:
    size = path.stat().st_size
    if size == 0 or size % (8 * SBET_FIELDS):
        raise FormatError(path, f"{size} bytes is not a whole number of SBET records ({8 * SBET_FIELDS} bytes each)",
                          "give the SBET as exported (17 little-endian float64 per record)")
    rec = np.fromfile(path, "<f8").reshape(-1, SBET_FIELDS)
    heading = rec[:, 9] - rec[:, 10]   # platform heading in the wander frame - wander angle
    return _checked(path, rec[:, 0], np.degrees(rec[:, 1]), np.degrees(rec[:, 2]), rec[:, 3], rec[:, 7], rec[:, 8],
                    np.mod(heading, 2 * np.pi), "record")


def _text(path: Path, columns: dict[str, str] | None) -> Trajectory:
    try:
        lines = path.read_text(errors="replace").splitlines()
    except OSError as exc:
        raise FormatError(path, f"cannot be read ({exc.strerror or exc})") from None
    start = next((i for i, line in enumerate(lines) if line.strip() and not line.lstrip().startswith(("#", "%"))),
                 None)
    if start is None:
        raise FormatError(path, "holds no header row", "a CSV trajectory starts with a row of column names")
    head = lines[start]
    sep = next((s for s in (",", ";", "\t") if s in head), None)
    split = (lambda line: [v.strip() for v in line.split(sep)]) if sep else (lambda line: line.split())
    names = split(head)
    wanted = dict(columns or COLUMNS)
    utc = "utc" in wanted
    if utc:
        wanted = {"time": wanted.pop("utc"), **wanted}
    lower = [n.lower() for n in names]
    index = {}
    for key, name in wanted.items():
        if name.lower() not in lower:
            how = "" if columns else " (Inertial Explorer's names; other exports: --navigation-columns)"
            raise FormatError(path, f"has no column {name!r} for {key}{how}; its columns: {', '.join(names[:12])}",
                              "name the columns with --navigation-columns time=COL,lat=COL,...")
        index[key] = lower.index(name.lower())
    rows = []
    for k, line in enumerate(lines[start + 1:], start + 2):
        if not line.strip() or line.lstrip().startswith(("#", "%")):
            continue
        values = split(line)
        try:
            rows.append([float(values[index[key]]) for key in COLUMNS])
        except (ValueError, IndexError):
            raise FormatError(path, f"line {k}: expected numbers in columns {', '.join(wanted.values())}",
                              "check the export (one header row, then one row per epoch)") from None
    if not rows:
        raise FormatError(path, "holds no epochs after its header row")
    a = np.array(rows)
    out = _checked(path, a[:, 0], a[:, 1], a[:, 2], a[:, 3], np.radians(a[:, 4]), np.radians(a[:, 5]),
                   np.mod(np.radians(a[:, 6]), 2 * np.pi), "line", first=start + 2)
    return dataclasses.replace(out, utc=utc)


def _checked(path: Path, t, lat, lon, h, roll, pitch, heading, unit: str, first: int = 1) -> Trajectory:
    """The trajectory, its time unwrapped past week boundaries; FormatError for a NaN or a time going back."""
    arrays = np.stack([t, lat, lon, h, roll, pitch, heading])
    bad = np.flatnonzero(~np.isfinite(arrays).all(axis=0))
    if bad.size:
        raise FormatError(path, f"{unit} {int(bad[0]) + first}: a value is not a number ({bad.size} such)",
                          "export the trajectory again, without gaps")
    t = np.asarray(t, float).copy()
    week = bool(t.max() < WEEK_S + 1.0)
    if week:   # a flight across a week boundary: seconds of week start again from 0
        t += np.concatenate([[0.0], np.cumsum(np.diff(t) < -WEEK_S / 2)]) * WEEK_S
    back = np.flatnonzero(np.diff(t) <= 0)
    if back.size:
        k = int(back[0]) + 1
        raise FormatError(path, f"{unit} {k + first}: time {t[k]:.3f} s does not follow {t[k - 1]:.3f} s "
                          "(not monotonic)", "give the trajectory in time order, each epoch once")
    if np.any(np.abs(lat) > 90) or np.any(np.abs(lon) > 360):
        raise FormatError(path, "latitudes or longitudes out of range", "SBET angles are radians, CSV degrees")
    return Trajectory(path, t, np.asarray(lat, float), np.asarray(lon, float), np.asarray(h, float),
                      np.asarray(roll, float), np.asarray(pitch, float), np.asarray(heading, float), week)


def on_gps_scale(trajectory: Trajectory, reference: float) -> np.ndarray:
    """(n,) the trajectory's times as full GPS seconds on the scale of ``reference`` (a GPS time of the
    flight, e.g. its first ``.lcf`` row): the GPS week (or, for full seconds, the 1024-week rollover of
    an old recorder's clock) that puts the trajectory's start nearest the reference."""
    t = trajectory.time
    if trajectory.utc:   # UTC -> GPS: the leap seconds in force at the flight (GPS - UTC, 18 s since 2017)
        from datetime import timedelta

        from archive.formats.lcf import GPS_EPOCH, gps_seconds_to_datetime

        ref = float(reference)
        t = t + ((GPS_EPOCH + timedelta(seconds=ref)) - gps_seconds_to_datetime(ref)).total_seconds()
    step = WEEK_S if trajectory.week_seconds else ROLLOVER_S
    return t + np.round((float(reference) - float(t[0])) / step) * step

