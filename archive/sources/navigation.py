"""Per-line camera poses of a flight: the one navigation helper every source uses.

Inputs, per cube in capture order: the camera-clock line times (``.times``), the cube's ``.lcf``
samples and its shutter; plus the flight's local frame and the :class:`NavigationParams` (sync
offset, boresight, lever arm). Raw and collection sources build the same :class:`FlightNavigation`
from the same numbers, so they give the same line times, the same poses and the same errors.

Line times (DESIGN 2): line i of cube k is at ``lcf_t0[k] + (times[i] - times[0]) + sync_offset``
on the ``.lcf`` scale, where ``lcf_t0[k]`` is the first row of cube k's ``.lcf``.

Poses are interpolated in the flight's WHOLE navigation: the ``.lcf`` rows of all cubes merged
(rows repeated by two files are kept once; rows that go back in time are an error naming the file).
With a sync offset, the first lines of a cube lie before its own ``.lcf`` but inside the previous
cube's, on the same GPS time scale. The merged track is cut into *segments* wherever two samples are
more than :data:`NAV_GAP` apart (a turn between passes, a pause of the INS log): poses are never
interpolated across such a gap.

The tolerance rule, one for every source. For each line time t (and the last line's mid-exposure):

- inside a segment: interpolated (position linearly, attitude by slerp);
- at most ``extrapolation = NAV_TOLERANCE + min(|sync offset|, SYNC_TOLERANCE)`` seconds outside
  the nearest segment: extrapolated from that segment's end interval (real ``.lcf`` files stop up to
  ~15 ms before the last image line; a sync offset moves lines past one end by design);
- further, but within ``NAV_TOLERANCE + |sync offset|``: the line has NO navigation — it is
  flagged in :attr:`Poses.valid` and left out of the mesh (what a large sync offset does at the
  ends of a flight); a cube none of whose lines has navigation is an error;
- further still: :class:`NavigationError` naming the cube's ``.lcf`` (it does not belong to the
  cube, or the sync offset is wrong).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from archive.errors import InputError, NavigationError
from archive.formats.lcf import LcfData
from archive.geometry.navigation import (LocalFrame, Poses, Track, boresight_rotation, interpolate_poses, line_times,
                                offset_track, span_text, track_from_lcf)
from archive.params import NavigationParams
from archive.sources.base import check_cube

__all__ = ["NAV_GAP", "NAV_TOLERANCE", "SYNC_TOLERANCE", "CubeNavigation", "FlightNavigation", "NavigatedSource",
           "merge_tracks", "trajectory_cube"]

#: Extrapolation allowed beyond the navigation without a sync offset, s.
NAV_TOLERANCE = 0.02
#: Most of a sync offset that may be extrapolated over, s.
SYNC_TOLERANCE = 0.1
#: Two navigation samples further apart than this (s) are not interpolated between.
NAV_GAP = 0.1
# Float noise allowed at the ends of a span (s): GPS seconds ~1.3e9 carry ~2.4e-7 s of resolution.
_SPAN_EPS = 1e-5


@dataclass(frozen=True, eq=False)
class CubeNavigation:
    """What navigation needs of one cube.

    camera_time: (lines,) s, the camera clock (``.times``); lcf: the cube's ``.lcf`` samples;
    shutter_ms: exposure (ms, None if unknown); where: the name errors give (the ``.lcf`` path, or
    the collection and cube); clock_t0: the ``.lcf`` time of the first line when ``lcf`` holds another
    navigation source's samples (a post-processed trajectory, :func:`trajectory_cube`), else None (the
    first row of ``lcf``).
    """

    camera_time: np.ndarray
    lcf: LcfData
    shutter_ms: float | None
    where: str
    clock_t0: float | None = None

    @property
    def t0(self) -> float:
        """The ``.lcf`` time of the cube's first line (before the sync offset), s."""
        return float(self.lcf.time[0]) if self.clock_t0 is None else float(self.clock_t0)


def trajectory_cube(cube: CubeNavigation, trajectory, gps_time: np.ndarray, sync: float) -> CubeNavigation:
    """``cube`` navigated by a post-processed ``trajectory`` (:class:`~archive.formats.trajectory.Trajectory`,
    its times ``gps_time`` on the ``.lcf`` scale) instead of its ``.lcf``: the trajectory's epochs around
    the cube's lines (one beyond each end), in the ``.lcf``'s signs; the line times still come from the
    ``.lcf``'s first row and the camera clock. NavigationError naming the trajectory, the gap and the
    cube's lines it leaves out when it does not cover every line (``sync``: the sync offset, s)."""
    t = line_times(cube.camera_time, cube.t0, sync)
    half = 0.0 if cube.shutter_ms is None else cube.shutter_ms / 2000.0
    lo, hi = float(t[0]), float(t[-1]) + half
    where = str(trajectory.path)
    inside = (t >= gps_time[0] - _SPAN_EPS) & (t <= gps_time[-1] + _SPAN_EPS)
    gaps = np.flatnonzero(np.diff(gps_time) > NAV_GAP)
    for g in gaps:   # a gap of the trajectory under the cube's lines
        inside &= ~((t > gps_time[g] + _SPAN_EPS) & (t < gps_time[g + 1] - _SPAN_EPS))
    if not inside.all() or hi > gps_time[-1] + NAV_TOLERANCE:
        out = np.flatnonzero(~inside)
        lines = f"lines {out[0]}-{out[-1]}" if out.size else f"line {len(t) - 1}"
        span = f"{span_text(gps_time)}" + (f", with {gaps.size} gaps over {NAV_GAP:g} s" if gaps.size else "")
        raise NavigationError(where, f"covers {span} but {cube.where.rsplit('/', 1)[-1]} needs {lo:.3f}-{hi:.3f} s: "
                              f"{lines} of that cube have no pose", "give the trajectory of the whole flight")
    a = max(int(np.searchsorted(gps_time, lo, "right")) - 2, 0)
    b = min(int(np.searchsorted(gps_time, hi, "left")) + 2, len(gps_time))
    part = slice(a, b)
    lcf = LcfData(trajectory.path, gps_time[part], -trajectory.roll[part], trajectory.pitch[part],
                  trajectory.heading[part], trajectory.lon[part], trajectory.lat[part], trajectory.height[part])
    return CubeNavigation(cube.camera_time, lcf, cube.shutter_ms, where, clock_t0=cube.t0)


def merge_tracks(tracks: Sequence[Track], where: Sequence[str]) -> Track:
    """One track from the tracks of consecutive cubes, in time order. Where a file overlaps the
    previous one (recorders repeat or overlap a few rows at a cube switch) the earlier file's
    samples are kept and the later file continues after them. NavigationError naming the file when
    a file starts before the previous one does (cubes out of capture order)."""
    keep_t, keep_p, keep_a = [], [], []
    start_prev, end = -np.inf, -np.inf
    for track, name in zip(tracks, where, strict=True):
        t = np.asarray(track.time, float)
        if t[0] < start_prev:
            raise NavigationError(name, f"navigation starts at {t[0]:.3f} s, before the previous cube's "
                                  f"({start_prev:.3f} s)", "cubes of a flight must be in capture order")
        start = int(np.searchsorted(t, end + 5e-4)) if t[0] <= end + 5e-4 else 0
        if start < len(t):
            keep_t.append(t[start:])
            keep_p.append(np.asarray(track.position, float)[start:])
            keep_a.append(track.attitude[start:])
            end = float(t[-1])
        start_prev = float(t[0])
    return Track(np.concatenate(keep_t), np.concatenate(keep_p), Rotation.concatenate(keep_a))


class FlightNavigation:
    """Line times and camera poses of every cube of a flight (see the module docstring).

    cubes: per cube in capture order; frame: the flight's local frame; params: sync offset,
    boresight, lever arm. The constructor checks every cube (NavigationError naming its file).
    """

    def __init__(self, cubes: Sequence[CubeNavigation], frame: LocalFrame, params: NavigationParams):
        self.cubes = tuple(cubes)
        self.frame = frame
        self.params = params
        self.sync = float(params.sync_offset)
        if not np.isfinite(self.sync):
            raise InputError("--sync-offset", f"must be a finite number of seconds, got {params.sync_offset!r}")
        self._tracks = [offset_track(track_from_lcf(c.lcf, frame), params.position_offset_m) for c in self.cubes]
        self.track = merge_tracks(self._tracks, [c.where for c in self.cubes])
        t = self.track.time
        cuts = np.flatnonzero(np.diff(t) > NAV_GAP) + 1
        self._segments = [(int(a), int(b)) for a, b in zip(np.r_[0, cuts], np.r_[cuts, len(t)])]
        self._starts = np.array([t[a] for a, _ in self._segments])     # first and last sample time
        self._ends = np.array([t[b - 1] for _, b in self._segments])   # of each segment, s
        self._boresight = boresight_rotation(params.boresight_deg)
        self.extrapolation = NAV_TOLERANCE + min(abs(self.sync), SYNC_TOLERANCE)
        self.limit = NAV_TOLERANCE + abs(self.sync)
        for k in range(len(self.cubes)):
            self.check(k)

    def cube_track(self, cube: int) -> Track:
        """INS samples of ``cube``'s own ``.lcf`` in the flight's frame."""
        return self._tracks[cube]

    def line_times(self, cube: int) -> np.ndarray:
        """(lines,) exposure-start times of ``cube`` on the .lcf scale (sync offset included), s."""
        c = self.cubes[cube]
        return line_times(c.camera_time, c.t0, self.sync)

    def first_time(self, cube: int) -> float:
        """Exposure start of ``cube``'s first line on the .lcf scale (sync offset included), s."""
        return self.cubes[cube].t0 + self.sync

    def locate(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per time ``t`` (s): the navigation segment to interpolate/extrapolate in, and the
        distance (s) outside it (0 inside)."""
        t = np.asarray(t, float)
        before = np.maximum(self._starts[None, :] - t[:, None], 0.0)
        after = np.maximum(t[:, None] - self._ends[None, :], 0.0)
        outside = np.maximum(before, after)
        seg = np.argmin(outside, axis=1)
        return seg, outside[np.arange(len(t)), seg]

    def check(self, cube: int) -> None:
        """NavigationError naming the cube unless navigation covers (by the module's rule) every
        line from exposure start of the first to mid-exposure of the last."""
        c = self.cubes[cube]
        t = self.line_times(cube)
        if t.size == 0:
            return
        if not np.all(np.isfinite(t)):
            raise NavigationError(c.where, "line times contain NaN or infinity")
        half = 0.0 if c.shutter_ms is None else c.shutter_ms / 2000.0
        need = np.array([t[0], t[-1] + half]) if len(t) > 1 else np.array([t[0]])
        _, outside = self.locate(np.concatenate([need, t]))
        if np.all(outside <= self.limit + _SPAN_EPS) and np.any(outside[len(need):] <= self.extrapolation + _SPAN_EPS):
            return
        own = np.asarray(c.lcf.time, float)
        late = float(need[-1] - own[-1])
        early = float(own[0] - need[0])
        gap = f"{late:.3f} s missing at the end" if late > early else f"{early:.3f} s missing at the start"
        raise NavigationError(
            c.where, f"navigation covers {span_text(own)} but lines need {span_text(need)}: {gap}",
            "check that the .lcf belongs to this cube, or the sync offset")

    def poses(self, cube: int, delay: float = 0.0) -> Poses:
        """Camera poses of every line of ``cube`` at exposure start + ``delay`` seconds: (lines, 3)
        NED positions, (lines,) camera -> NED attitudes, and ``valid`` (lines,) False where a line
        has no navigation (see the module docstring)."""
        c = self.cubes[cube]
        t = self.line_times(cube) + float(delay)
        seg, outside = self.locate(t)
        valid = outside <= self.extrapolation + abs(float(delay)) + _SPAN_EPS
        time = self.track.time
        margin = self.extrapolation + abs(float(delay))
        order, pos_parts, att_parts = [], [], []
        for s in np.unique(seg):
            a, b = self._segments[int(s)]
            idx = np.flatnonzero(seg == s)
            if b - a < 2:  # a lone sample: hold it (only lines right next to it use it)
                pos_parts.append(np.repeat(self.track.position[a:a + 1], len(idx), axis=0))
                att_parts.append(Rotation.concatenate([self.track.attitude[a]] * len(idx)))
            else:
                clipped = np.clip(t[idx], time[a] - margin, time[b - 1] + margin)
                piece = Track(time[a:b], self.track.position[a:b], self.track.attitude[a:b])
                p = interpolate_poses(piece, clipped, self.frame, where=c.where, tolerance=np.inf)
                pos_parts.append(p.position)
                att_parts.append(p.attitude)
            order.append(idx)
        if len(order) == 1:
            position, attitude = pos_parts[0], att_parts[0]
        else:
            inverse = np.argsort(np.concatenate(order))
            position = np.concatenate(pos_parts)[inverse]
            attitude = Rotation.concatenate(att_parts)[inverse]
        lever = np.asarray(self.params.lever_arm_m, float)
        if lever.shape != (3,):
            raise InputError("--lever-arm", f"must be 3 numbers (x, y, z metres), got {self.params.lever_arm_m!r}")
        if np.any(lever != 0.0):
            position = position + attitude.apply(lever)
        attitude = attitude * self._boresight
        return Poses(time=t, position=position, attitude=attitude, frame=self.frame,
                     valid=None if np.all(valid) else valid)


class NavigatedSource:
    """The navigation members of a file-backed source (raw or collection), served by its
    :class:`FlightNavigation` ``self.navigation``; cube indices are checked against ``self.cubes``
    (errors name ``self.label``)."""

    navigation: FlightNavigation
    cubes: tuple
    label: str

    def _check(self, cube: int) -> int:
        return check_cube(cube, self.cubes, self.label)

    def line_times(self, cube: int) -> np.ndarray:
        """(lines,) exposure-start times of ``cube`` on the .lcf scale (sync offset included), s."""
        return self.navigation.line_times(self._check(cube))

    def check_navigation(self, cube: int) -> None:
        """NavigationError naming the cube's navigation unless it covers the cube's lines."""
        self.navigation.check(self._check(cube))

    def track(self, cube: int) -> Track:
        """INS samples of ``cube``'s own navigation in the flight's frame."""
        return self.navigation.cube_track(self._check(cube))

    def poses(self, cube: int, delay: float = 0.0) -> Poses:
        """Camera poses of every line of ``cube`` at exposure start + ``delay`` seconds: (lines, 3)
        NED positions, (lines,) camera -> NED attitudes, ``valid`` (see :class:`FlightNavigation`)."""
        return self.navigation.poses(self._check(cube), delay)
