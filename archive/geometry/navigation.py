"""Navigation: INS samples (.lcf) -> a local North-East-Down frame -> camera poses per image line.

Conventions (DESIGN 3):

- The local frame is North-East-Down about a UTM point: N = northing - origin_n, E = easting -
  origin_e, D = origin_alt - altitude (metres). "North" is UTM *grid* north.
- Body frame: x forward, y right wing, z down. Body attitude is a scipy ``Rotation`` mapping body ->
  NED, built from aerospace Euler angles (yaw Z, pitch Y, roll X, intrinsic) with
  ``roll_aero = -roll_lcf`` and ``yaw_grid = yaw_true + grid_convergence``.
- Camera frame: x along track, y along the line of samples, z the viewing direction. The boresight
  maps camera -> body, so camera attitude (camera -> NED) is ``body_attitude * boresight``; the lever
  arm is the camera position in the body frame, so camera position is
  ``body_position + body_attitude.apply(lever_arm)``.
- Poses are taken at each line's exposure START: position linear in time, attitude by slerp.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache
from typing import TYPE_CHECKING

import numpy as np
from pyproj import Transformer
from scipy.spatial.transform import Rotation, Slerp

from archive.errors import InputError, NavigationError
from archive.params import DEFAULT_MAX_VIEW_ANGLE  # noqa: F401  (the meshes' and footprints' default)

if TYPE_CHECKING:
    from archive.formats.lcf import LcfData

# Track times must increase by at least this much (s); .lcf files carry 3 decimals (1 ms).
_MIN_STEP = 1e-6
# Float noise allowed at the ends of the span (s): GPS seconds ~1.3e9 carry ~2.4e-7 s of resolution.
_SPAN_EPS = 1e-5


@dataclass(frozen=True)
class LocalFrame:
    """A local North-East-Down frame about a UTM point.

    epsg: the WGS 84 / UTM zone (326xx north, 327xx south).
    origin_e, origin_n: UTM easting and northing of the origin, metres.
    origin_alt: height of the origin above the WGS-84 ellipsoid, metres.
    """

    epsg: int
    origin_e: float
    origin_n: float
    origin_alt: float

    def to_ned(self, e, n, alt) -> np.ndarray:
        """UTM easting, northing (m) and ellipsoid height (m), any broadcastable shapes ->
        (..., 3) local N, E, D metres."""
        e, n, alt = np.broadcast_arrays(np.asarray(e, float), np.asarray(n, float), np.asarray(alt, float))
        return np.stack([n - self.origin_n, e - self.origin_e, self.origin_alt - alt], axis=-1)

    def from_ned(self, ned) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(..., 3) local N, E, D metres -> (easting, northing, ellipsoid height), each (...,) metres."""
        ned = np.asarray(ned, float)
        return ned[..., 1] + self.origin_e, ned[..., 0] + self.origin_n, self.origin_alt - ned[..., 2]

    def __dask_tokenize__(self):
        return ("LocalFrame", self.epsg, self.origin_e, self.origin_n, self.origin_alt)


def utm_epsg_for(lon: float, lat: float) -> int:
    """EPSG code of the WGS 84 / UTM zone holding (lon, lat) degrees: 326xx north of the equator,
    327xx south (the equator itself counts as north). Honours the Norway (32V) and Svalbard
    (31X-37X) exceptions."""
    lon = float(lon)
    lat = float(lat)
    if not (np.isfinite(lon) and np.isfinite(lat)) or abs(lat) > 90:
        raise InputError(None, f"no UTM zone for longitude {lon}, latitude {lat}",
                         "check the .lcf columns: 5 is longitude, 6 latitude, in degrees")
    if lat > 84 or lat < -80:
        raise InputError(None, f"latitude {lat:.4f} is outside UTM (80 S to 84 N)",
                         "polar flights need a polar stereographic frame, which is not supported")
    lon = (lon + 180.0) % 360.0 - 180.0
    zone = int(np.floor((lon + 180.0) / 6.0)) + 1
    zone = min(zone, 60)
    if 56.0 <= lat < 64.0 and 3.0 <= lon < 12.0:
        zone = 32
    elif 72.0 <= lat < 84.0 and 0.0 <= lon < 42.0:
        if lon < 9.0:
            zone = 31
        elif lon < 21.0:
            zone = 33
        elif lon < 33.0:
            zone = 35
        else:
            zone = 37
    return (32600 if lat >= 0 else 32700) + zone


@lru_cache(maxsize=16)
def _transformer(epsg: int) -> Transformer:
    return Transformer.from_crs(4326, epsg, always_xy=True)


def project(lon, lat, epsg: int) -> tuple[np.ndarray, np.ndarray]:
    """Longitude, latitude (degrees, any shape) -> UTM easting, northing (m) in ``epsg``."""
    lon, lat = np.broadcast_arrays(np.asarray(lon, float), np.asarray(lat, float))
    e, n = _transformer(int(epsg)).transform(lon, lat)
    return np.asarray(e, float), np.asarray(n, float)


@lru_cache(maxsize=16)
def _inverse(epsg: int) -> Transformer:
    return Transformer.from_crs(int(epsg), 4326, always_xy=True)


def to_lonlat(e, n, epsg: int) -> tuple[np.ndarray, np.ndarray]:
    """Easting, northing (m, any shape) in ``epsg`` -> longitude, latitude (degrees)."""
    e, n = np.broadcast_arrays(np.asarray(e, float), np.asarray(n, float))
    lon, lat = _inverse(int(epsg)).transform(e, n)
    return np.asarray(lon, float), np.asarray(lat, float)


def reproject(e, n, src_epsg: int, dst_epsg: int) -> tuple[np.ndarray, np.ndarray]:
    """Easting, northing (m) from ``src_epsg`` to ``dst_epsg`` (both projected, metres)."""
    if int(src_epsg) == int(dst_epsg):
        return np.asarray(e, float), np.asarray(n, float)
    lon, lat = to_lonlat(e, n, src_epsg)
    return project(lon, lat, dst_epsg)


def projected_epsg(crs) -> int:
    """The EPSG code of ``crs`` (an int, 'EPSG:XXXX' or any pyproj-readable text), refused with an
    InputError unless it is a projected CRS in metres (the output grid is square metres)."""
    from pyproj import CRS
    from pyproj.exceptions import CRSError

    try:
        c = CRS.from_user_input(crs)
    except CRSError as exc:
        raise InputError("--crs", f"unknown CRS {crs!r} ({exc})", "give e.g. EPSG:32616") from None
    epsg = c.to_epsg()
    unit = c.axis_info[0].unit_name if c.axis_info else ""
    if not c.is_projected or unit not in ("metre", "meter"):
        raise InputError("--crs", f"{crs!r} is not a projected CRS in metres",
                         "give a projected CRS such as a UTM zone, e.g. EPSG:32616")
    if epsg is None:
        raise InputError("--crs", f"{crs!r} has no EPSG code", "give the CRS as EPSG:XXXX")
    return int(epsg)


def grid_convergence(lon, lat, epsg: int) -> np.ndarray:
    """Grid bearing of TRUE north at (lon, lat) degrees in the UTM zone ``epsg``, radians.

    This is the angle to ADD to a true heading to get a grid heading (the projection is conformal,
    so it is the same for every heading). Computed numerically: project the point and a point
    1e-5 degrees due north, and take atan2(dE, dN). West of the central meridian in the northern
    hemisphere it is positive (e.g. +1.69 deg at Memphis in zone 16), i.e. the opposite sign of the
    textbook convergence angle gamma. Same shape as the broadcast inputs.
    """
    lon, lat = np.broadcast_arrays(np.asarray(lon, float), np.asarray(lat, float))
    step = np.where(lat > 89.0, -1e-5, 1e-5)  # step south near the pole, then flip the vector
    e0, n0 = project(lon, lat, epsg)
    e1, n1 = project(lon, lat + step, epsg)
    sign = np.sign(step)
    return np.arctan2((e1 - e0) * sign, (n1 - n0) * sign)


def local_frame_for(lcf: LcfData) -> LocalFrame:
    """Local frame for a flight: the UTM zone of the first used .lcf sample; origin at that sample's
    easting and northing rounded to 1 m, and at height 0 (the ellipsoid)."""
    if len(lcf.time) == 0:
        raise NavigationError(lcf.path, "no navigation samples", "the .lcf file is empty")
    use = lcf.use
    k = 0 if use is None else int(np.argmax(use))  # the first row to use
    epsg = utm_epsg_for(lcf.lon[k], lcf.lat[k])
    e, n = project(lcf.lon[k], lcf.lat[k], epsg)
    return LocalFrame(epsg=epsg, origin_e=float(np.round(e)), origin_n=float(np.round(n)), origin_alt=0.0)


@dataclass(frozen=True, eq=False)
class Track:
    """INS samples in a local frame.

    time: (n,) s, .lcf time scale, strictly increasing.
    position: (n, 3) N, E, D metres of the INS (body origin).
    attitude: (n,) body -> local NED (grid north), convergence-corrected, roll_aero = -roll_lcf.
    """

    time: np.ndarray
    position: np.ndarray
    attitude: Rotation


def _check_times(time: np.ndarray, where: str | None) -> None:
    if time.ndim != 1 or len(time) < 2:
        raise NavigationError(where, f"navigation needs at least 2 samples, found {time.size}",
                              "the .lcf file is empty or truncated")
    if not np.all(np.isfinite(time)):
        raise NavigationError(where, "navigation times contain NaN or infinity", "repair column 1 of the .lcf")
    step = np.diff(time)
    bad = np.flatnonzero(step < _MIN_STEP)
    if bad.size:
        i = int(bad[0])
        kind = "repeats" if step[i] == 0 else "goes back"
        raise NavigationError(
            where,
            f"navigation time {kind} at row {i + 2} ({time[i]:.3f} s then {time[i + 1]:.3f} s; "
            f"{bad.size} such rows)",
            "times must increase strictly: remove duplicated rows",
        )


def track_from_lcf(lcf: LcfData, frame: LocalFrame) -> Track:
    """INS samples of an .lcf in ``frame``: positions projected to the frame's UTM zone, heading
    corrected by the grid convergence, roll sign changed to aerospace; rows flagged 'do not use'
    (``lcf.use``) left out. Raises NavigationError for
    fewer than 2 samples, non-finite values or times that do not strictly increase."""
    where = None if lcf.path is None else str(lcf.path)
    use = lcf.use
    keep = slice(None) if use is None else np.asarray(use, bool)  # column 10: rows not to use
    time = np.asarray(lcf.time, float)[keep]
    _check_times(time, where)
    columns = {"roll": lcf.roll, "pitch": lcf.pitch, "yaw": lcf.yaw, "longitude": lcf.lon,
               "latitude": lcf.lat, "altitude": lcf.alt}
    columns = {name: np.asarray(values, float)[keep] for name, values in columns.items()}
    for name, values in columns.items():
        values = np.asarray(values, float)
        if values.shape != time.shape:
            raise NavigationError(where, f"{name} has {values.size} values for {time.size} times")
        if not np.all(np.isfinite(values)):
            raise NavigationError(where, f"{name} contains NaN or infinity", "repair or remove those rows")
    lon = columns["longitude"]
    lat = columns["latitude"]
    e, n = project(lon, lat, frame.epsg)
    if not (np.all(np.isfinite(e)) and np.all(np.isfinite(n))):
        raise NavigationError(where, f"positions cannot be projected to EPSG:{frame.epsg}",
                              "check longitude (column 5) and latitude (column 6)")
    position = frame.to_ned(e, n, columns["altitude"])
    yaw = columns["yaw"] + grid_convergence(lon, lat, frame.epsg)
    euler = np.stack([yaw, columns["pitch"], -columns["roll"]], axis=-1)
    return Track(time=time, position=position, attitude=Rotation.from_euler("ZYX", euler))


def offset_track(track: Track, offset_m: Sequence[float] | None) -> Track:
    """``track`` with a constant position offset ``offset_m`` = (dE, dN, dU) metres (grid east,
    north of the frame's UTM zone, up) added to every INS position (DESIGN 11: a GNSS bias found by
    ``archive calibrate --reference``; added before the lever arm). The same track when it is None
    or zero."""
    if offset_m is None:
        return track
    d = np.asarray(offset_m, float)
    if d.shape != (3,) or not np.all(np.isfinite(d)):
        raise InputError(None, f"position offset must be 3 finite numbers (dE, dN, dU metres), got {offset_m!r}")
    if not np.any(d):
        return track
    ned = np.array([d[1], d[0], -d[2]])
    return Track(time=track.time, position=np.asarray(track.position, float) + ned, attitude=track.attitude)


@dataclass(frozen=True, eq=False)
class Poses:
    """Camera poses at each line's exposure START.

    time: (lines,) s, .lcf time scale.
    position: (lines, 3) N, E, D metres of the camera (lever arm applied).
    attitude: (lines,) camera -> NED (boresight applied).
    frame: the local frame of ``position``.
    valid: (lines,) bool, False where a line has no navigation (left out of the mesh); None: all valid.
    """

    time: np.ndarray
    position: np.ndarray
    attitude: Rotation
    frame: LocalFrame
    valid: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.time)

    def utm(self) -> np.ndarray:
        """(lines, 3) camera easting, northing, ellipsoid height, metres."""
        e, n, alt = self.frame.from_ned(self.position)
        return np.stack([e, n, alt], axis=-1)


def line_times(times: np.ndarray, lcf_t0: float, sync_offset: float = 0.0) -> np.ndarray:
    """Image line times on the .lcf scale: ``lcf_t0 + (times - times[0]) + sync_offset``.

    times: (lines,) s of the camera clock (.times file); lcf_t0: time of the first .lcf row (s);
    sync_offset: s added to every line. Returns (lines,) s."""
    times = np.asarray(times, float)
    if times.size == 0:
        return times.copy()
    return float(lcf_t0) + (times - times[0]) + float(sync_offset)


def boresight_rotation(boresight_deg: Sequence[float] = (0.0, 0.0, 0.0)) -> Rotation:
    """Camera -> body rotation from (roll, pitch, yaw) degrees, aerospace sign, intrinsic Z-Y-X
    (as NavigationParams.boresight_deg)."""
    roll, pitch, yaw = (float(v) for v in boresight_deg)
    return Rotation.from_euler("ZYX", [yaw, pitch, roll], degrees=True)


def ground_hits(position: np.ndarray, attitude: Rotation, u: float, ground_down: float
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where the ray of focal-plane coordinate ``u`` (camera vector (0, u, 1)) meets the flat ground.

    position: (n, 3) camera N, E, D metres; attitude: (n,) camera -> NED; ground_down: the ground
    plane's D coordinate, metres. Returns the ground points (n, 2) N, E metres, the ray depth lambda
    (n,) (point = position + lambda * R (0, u, 1)) and a bad (n,) bool mask of rays that do not
    reach the ground (pointing at or above the horizon, or a camera at or below the ground).
    """
    position = np.asarray(position, dtype=np.float64)
    d = np.atleast_2d(attitude.apply(np.array([0.0, u, 1.0])))
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = (ground_down - position[:, 2]) / d[:, 2]
    bad = ~(np.isfinite(lam) & (lam > 0) & (d[:, 2] > 1e-6))
    return position[:, :2] + lam[:, None] * d[:, :2], lam, bad


def span_text(t: np.ndarray) -> str:
    return f"{float(np.min(t)):.3f}\u2013{float(np.max(t)):.3f} s"


def check_coverage(track_time: np.ndarray, t: np.ndarray, where: str | None = "", tolerance: float = 0.0,
                   what: str = "lines") -> None:
    """Raise NavigationError naming ``where`` if times ``t`` (s) leave the navigation span by more
    than ``tolerance`` seconds."""
    t = np.asarray(t, float)
    if t.size == 0:
        return
    if not np.all(np.isfinite(t)):
        raise NavigationError(where or None, f"{what} times contain NaN or infinity")
    lo = track_time[0] - tolerance - _SPAN_EPS
    hi = track_time[-1] + tolerance + _SPAN_EPS
    if t.min() < lo or t.max() > hi:
        late = t.max() - track_time[-1]
        early = track_time[0] - t.min()
        gap = f"{late:.3f} s missing at the end" if late > early else f"{early:.3f} s missing at the start"
        raise NavigationError(
            where or None,
            f"navigation covers {span_text(track_time)} but {what} need {span_text(t)}: {gap}",
            "check that the .lcf belongs to this cube, or the sync offset",
        )


def interpolate_poses(track: Track, t: np.ndarray, frame: LocalFrame, boresight: Rotation | None = None,
                      lever_arm=(0.0, 0.0, 0.0), where: str = "", tolerance: float = 0.0) -> Poses:
    """Camera poses at times ``t`` ((lines,) s, .lcf scale): body position linear in time, body
    attitude by slerp between INS samples; then the lever arm (camera position in the body frame, m)
    and the boresight (camera -> body) are applied.

    Times outside the track's span raise NavigationError naming ``where``. Times at most
    ``tolerance`` seconds outside it (default 0) are extrapolated from the first/last INS interval
    (position linearly, attitude at the same angular rate): real .lcf files may end a few ms before
    the last image line.
    """
    t = np.atleast_1d(np.asarray(t, float))
    time = np.asarray(track.time, float)
    _check_times(time, where or None)
    check_coverage(time, t, where, tolerance)
    # Interpolate relative to the first sample: GPS seconds lose precision in the fraction.
    tr = t - time[0]
    ts = time - time[0]
    idx = np.clip(np.searchsorted(ts, tr, side="right") - 1, 0, len(ts) - 2)
    frac = (tr - ts[idx]) / (ts[idx + 1] - ts[idx])  # outside [0, 1] only when extrapolating
    pos = np.asarray(track.position, float)
    position = pos[idx] + frac[:, None] * (pos[idx + 1] - pos[idx])
    inside = (frac >= 0.0) & (frac <= 1.0)
    att = track.attitude
    if np.all(inside):
        attitude = Slerp(ts, att)(np.clip(tr, ts[0], ts[-1]))
    else:
        delta = (att[idx].inv() * att[idx + 1]).as_rotvec()
        attitude = att[idx] * Rotation.from_rotvec(delta * frac[:, None])
    lever = np.asarray(lever_arm, float)
    if lever.shape != (3,):
        raise InputError(where or None, f"lever arm must be 3 numbers (x, y, z metres), got {lever_arm!r}")
    if np.any(lever != 0.0):
        position = position + attitude.apply(lever)
    if boresight is not None:
        attitude = attitude * boresight
    return Poses(time=t, position=position, attitude=attitude, frame=frame)


# ---------------------------------------------------------------------------------------------
# Strips: which consecutive lines are joined, and which lines are seen well enough to use
# ---------------------------------------------------------------------------------------------
#: Consecutive lines further apart than this many frame intervals are not joined (the strip ends):
#: a pause or a turn is a gap, while a recorder's cube switch, which drops a frame or two (the real
#: Juvika pair _12 -> _13: 1.7 intervals on the .lcf scale, 1.9 on the camera clock), is a seam.
#: The one strip rule of the project: meshes, the catalog footprint and 'archive info' use it.
MAX_JOIN_FRAMES = 3.5


def frame_interval(framerate: float | None, times: np.ndarray | None = None) -> float:
    """A cube's frame interval, s: 1 / framerate (Hz) when known, else the median step of its line
    times (s); inf for a single line without a framerate."""
    if framerate:
        return 1.0 / float(framerate)
    times = np.asarray(times if times is not None else [], float)
    return float(np.median(np.diff(times))) if times.size > 1 else float("inf")


def joined(gap_s, interval_s: float):
    """Whether lines ``gap_s`` seconds apart (scalar or array) belong to one strip, for a frame
    interval of ``interval_s`` seconds (see :data:`MAX_JOIN_FRAMES`)."""
    gap = np.asarray(gap_s, float)
    return (gap > 0.0) & (gap <= MAX_JOIN_FRAMES * float(interval_s))


def strip_slices(time: np.ndarray, interval_s: float | None = None) -> list[slice]:
    """Line index ranges of the strips of consecutive lines ``time`` (s), cut wherever two lines are
    not :func:`joined`; ``interval_s`` defaults to the median line step."""
    time = np.asarray(time, float)
    if time.size < 2:
        return [slice(0, time.size)]
    interval = frame_interval(None, time) if interval_s is None else interval_s
    cuts = np.flatnonzero(~joined(np.diff(time), interval)) + 1
    edges = [0, *cuts.tolist(), time.size]
    return [slice(a, b) for a, b in zip(edges[:-1], edges[1:]) if b > a]


def view_angles(attitude: Rotation, fov_deg: float) -> np.ndarray:
    """(n,) degrees off nadir of the more oblique field-of-view edge ray of each line (camera ->
    NED ``attitude``); 90 or more means the ray does not look down."""
    t = np.tan(np.radians(fov_deg) / 2.0)
    worst = np.zeros(len(attitude))
    for u in (-t, t):
        d = np.atleast_2d(attitude.apply(np.array([0.0, u, 1.0])))
        cos = d[:, 2] / np.linalg.norm(d, axis=1)
        worst = np.maximum(worst, np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
    return worst
