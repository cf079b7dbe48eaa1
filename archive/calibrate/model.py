"""The exact geometric model the calibration solves with: camera rays of a flight's passes under trial
parameters (boresight, sync offset, ground height, position offset), forward (image -> ground) and
inverse (ground -> image).

Conventions are the renderer's (DESIGN 2 and 3, :mod:`archive.render.mesh`): a line's content sits
at its MID-exposure pose (exposure start + shutter / 2); line L (fractional, 0-based within a pass)
is linear in time between its neighbours; the focal-plane coordinate u of a ray (camera vector
(0, u, 1)) maps to the continuous sample coordinate ``(u + t) / 2t * samples - 0.5`` (sample k's
centre at k, t = tan(fov / 2)). Poses come from the flight's merged INS track (position linear in
time, attitude by slerp), lever arm fixed, then the trial boresight (camera -> body).

Coordinates: the source's local NED frame (metres N, E, D), or another flight's frame of the same
UTM zone (``frame=``: a reference flight's rays in the frame of the flight registered to it);
heights above the ellipsoid (m). The position offset (DESIGN 11) is added to the INS track: the
model starts from the track WITHOUT the offset the source records, so that trial parameters are
absolute (a recorded offset is the start value).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Slerp

from archive.errors import InputError
from archive.geometry.navigation import boresight_rotation, frame_interval, joined
from archive.sources.navigation import NAV_GAP

__all__ = ["Params", "Pass", "FlightModel", "PARAM_NAMES"]

#: Order of the parameter vector: roll, pitch, yaw (deg), sync offset (s), ground height or DEM
#: vertical offset (m), position offset east, north, up (m).
PARAM_NAMES = ("roll", "pitch", "yaw", "sync", "ground", "east", "north", "up")


@dataclass(frozen=True)
class Params:
    """Trial parameters: boresight (roll, pitch, yaw) degrees, sync offset s, ground (m): the flat
    ground height above the ellipsoid, or with a DEM its vertical offset; position offset (east,
    north, up) m added to every INS position (DESIGN 11)."""

    roll: float = 0.0
    pitch: float = 0.0
    yaw: float = 0.0
    sync: float = 0.0
    ground: float = 0.0
    east: float = 0.0
    north: float = 0.0
    up: float = 0.0

    def vector(self) -> np.ndarray:
        return np.array([self.roll, self.pitch, self.yaw, self.sync, self.ground, self.east, self.north,
                         self.up], float)

    @property
    def position_offset(self) -> tuple[float, float, float]:
        """(dE, dN, dU) metres."""
        return (self.east, self.north, self.up)

    @classmethod
    def from_vector(cls, x: Sequence[float]) -> Params:
        return cls(*(float(v) for v in x))

    @property
    def boresight_deg(self) -> tuple[float, float, float]:
        return (self.roll, self.pitch, self.yaw)


def _ned(offset) -> np.ndarray:
    """(dE, dN, dU) metres -> the N, E, D vector."""
    e, n, u = (float(v) for v in offset)
    return np.array([n, e, -u])


@dataclass(frozen=True, eq=False)
class Pass:
    """One pass (strip) of a flight: consecutive cubes joined by the project's strip rule.

    cubes: cube indices; mid_time: (lines,) mid-exposure times on the .lcf scale WITHOUT a sync
    offset, s; starts: first pass line of each cube; samples: samples per line.
    """

    index: int
    cubes: tuple[int, ...]
    mid_time: np.ndarray
    starts: tuple[int, ...]
    samples: int

    @property
    def lines(self) -> int:
        return int(self.mid_time.size)


class FlightModel:
    """Rays of every pass of a navigated source (raw or collection) under trial :class:`Params`.

    source: a source with ``navigation`` (:class:`~archive.sources.navigation.FlightNavigation`);
    fov_deg: field of view; surface: None for flat ground, else ``height(n, e)`` -> ellipsoid
    heights (m) of the terrain at local N, E points (the trial ``ground`` adds to it); frame: the
    local frame to work in (default the source's; another one must be of the same UTM zone).
    """

    def __init__(self, source, fov_deg: float, surface=None, frame=None):
        nav = source.navigation
        self.source = source
        own = nav.frame
        self.frame = own if frame is None else frame
        if self.frame.epsg != own.epsg:
            raise InputError(getattr(source, "label", None), f"its navigation is in EPSG:{own.epsg}, the flight it "
                             f"is compared with in EPSG:{self.frame.epsg}",
                             "co-register flights of one UTM zone")
        self.fov_deg = float(fov_deg)
        self.t_half = math.tan(math.radians(self.fov_deg) / 2.0)
        self.surface = surface
        #: where a ray's search for the terrain starts (m above the ellipsoid): the terrain under the track
        self.base_height = 0.0
        self.lever = np.asarray(nav.params.lever_arm_m, float)
        track = nav.track
        self._t0 = float(track.time[0])
        self._time = np.asarray(track.time, float) - self._t0
        recorded = np.asarray(getattr(nav.params, "position_offset", (0.0, 0.0, 0.0)), float)
        shift = np.array([own.origin_n - self.frame.origin_n, own.origin_e - self.frame.origin_e,
                          self.frame.origin_alt - own.origin_alt])
        #: the INS track in ``frame`` without any position offset (the trial one is added in poses)
        self._pos = np.asarray(track.position, float) - _ned(recorded) + shift
        self._slerp = Slerp(self._time, track.attitude)
        cuts = np.flatnonzero(np.diff(self._time) > NAV_GAP) + 1
        self._seg_start = self._time[np.r_[0, cuts]]
        self._seg_end = self._time[np.r_[cuts, len(self._time)] - 1]
        self.passes = self._passes(source)
        if surface is not None:
            under = surface(self._pos[:, 0], self._pos[:, 1])
            self.base_height = float(np.nanmedian(under)) if np.isfinite(under).any() else 0.0

    # --- passes -------------------------------------------------------------------------------
    def _passes(self, source) -> tuple[Pass, ...]:
        nav = source.navigation
        mids, groups = [], []
        for k, c in enumerate(nav.cubes):
            start = np.asarray(c.camera_time, float) - float(c.camera_time[0]) + c.t0 - self._t0
            mid = start + (c.shutter_ms or 0.0) / 2000.0
            if groups:
                prev = mids[-1]
                gap = mid[0] - prev[-1]
                if joined(gap, frame_interval(source.cubes[k - 1].framerate, prev)):
                    groups[-1].append(k)
                    mids.append(mid)
                    continue
            groups.append([k])
            mids.append(mid)
        out, k = [], 0
        for i, g in enumerate(groups):
            parts = mids[k:k + len(g)]
            starts = tuple(int(v) for v in np.cumsum([0] + [p.size for p in parts[:-1]]))
            out.append(Pass(i, tuple(g), np.concatenate(parts), starts, int(source.cubes[g[0]].samples)))
            k += len(g)
        return tuple(out)

    # --- poses --------------------------------------------------------------------------------
    def _valid_time(self, t: np.ndarray) -> np.ndarray:
        inside = (t[:, None] >= self._seg_start[None, :] - 0.02) & (t[:, None] <= self._seg_end[None, :] + 0.02)
        return inside.any(axis=1)

    def poses(self, t: np.ndarray, params: Params) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Camera at times ``t`` (s since the track start, sync offset NOT included: it is added
        here): positions (n, 3) N, E, D; camera -> NED matrices (n, 3, 3); valid (n,) bool."""
        t = np.asarray(t, float) + params.sync
        valid = self._valid_time(t) & np.isfinite(t)
        tc = np.where(np.isfinite(t), t, self._time[0])
        # held at the end of the nearest navigation segment (never interpolated across a turn's gap)
        outside = np.maximum(self._seg_start[None, :] - tc[:, None], 0) + np.maximum(tc[:, None] - self._seg_end[None, :], 0)
        seg = np.argmin(outside, axis=1)
        tc = np.clip(tc, self._seg_start[seg], self._seg_end[seg])
        pos = np.stack([np.interp(tc, self._time, self._pos[:, i]) for i in range(3)], axis=1)
        if params.east or params.north or params.up:
            pos = pos + _ned(params.position_offset)
        body = self._slerp(tc)
        if np.any(self.lever != 0.0):
            pos = pos + body.apply(self.lever)
        att = (body * boresight_rotation(params.boresight_deg)).as_matrix()
        return pos, att, valid

    def ground_down(self, params: Params) -> float:
        """D coordinate of the flat ground at the trial height."""
        return float(self.frame.origin_alt - params.ground)

    # --- forward: image -> ground ------------------------------------------------------------
    def forward(self, p: Pass, line: np.ndarray, u: np.ndarray, params: Params, strict: bool = True) -> np.ndarray:
        """Ground points (n, 2) N, E metres of rays (pass line L (fractional), focal-plane u) under
        ``params``; NaN where a ray misses the ground or, when ``strict``, has no navigation (else
        its pose is held at the navigation's end: residuals stay continuous while a trial sync offset
        moves a line past it, and grow instead of vanishing)."""
        line = np.asarray(line, float)
        t = np.interp(line, np.arange(p.lines), p.mid_time, left=np.nan, right=np.nan)
        pos, att, valid = self.poses(t, params)
        d = att @ np.stack([np.zeros_like(u), u, np.ones_like(u)], axis=1)[:, :, None]
        d = d[:, :, 0]
        down = self.ground_down(params) if self.surface is None else \
            float(self.frame.origin_alt - self.base_height - params.ground)
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = (down - pos[:, 2]) / d[:, 2]
            xy = pos[:, :2] + lam[:, None] * d[:, :2]
            if self.surface is not None:  # fixed point: the ray meets the terrain (+ offset)
                for _ in range(12):
                    h = self.surface(xy[:, 0], xy[:, 1]) + params.ground
                    lam = (self.frame.origin_alt - h - pos[:, 2]) / d[:, 2]
                    xy = pos[:, :2] + lam[:, None] * d[:, :2]
        bad = (~valid if strict else np.zeros(valid.shape, bool)) | ~np.isfinite(lam) | (lam <= 0)
        xy[bad] = np.nan
        return xy

    # --- inverse: ground -> image -------------------------------------------------------------
    def line_poses(self, p: Pass, params: Params) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Mid-exposure camera of every line of ``p``: positions (lines, 3), matrices (lines, 3, 3),
        valid (lines,)."""
        return self.poses(p.mid_time, params)

    def ground_height_at(self, n: np.ndarray, e: np.ndarray, params: Params) -> np.ndarray:
        """Ellipsoid height (m) of the trial ground at local N, E points."""
        if self.surface is None:
            return np.full(np.shape(n), float(params.ground))
        return self.surface(n, e) + params.ground

    def inverse(self, p: Pass, points: np.ndarray, params: Params,
                line_poses: tuple | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Where pass ``p`` sees ground points ``points`` (n, 3) N, E, D under ``params``: fractional
        pass line L and focal-plane u, each (n,), NaN where no line of the pass sees the point
        (outside the pass, or its lines lack navigation). Lines sweep the ground monotonically
        along a straight pass: bisection on the signed along-track distance."""
        pos, att, valid = line_poses if line_poses is not None else self.line_poses(p, params)
        points = np.asarray(points, float)
        n = points.shape[0]
        xaxis = att[:, :, 0]
        ok_lines = np.flatnonzero(valid)
        if ok_lines.size < 2:
            return np.full(n, np.nan), np.full(n, np.nan)
        lo_line, hi_line = int(ok_lines[0]), int(ok_lines[-1])

        def f(i):
            return np.einsum("ij,ij->i", points - pos[i], xaxis[i])

        lo = np.full(n, lo_line)
        hi = np.full(n, hi_line)
        flo, fhi = f(lo), f(hi)
        ok = (flo >= 0) & (fhi < 0)
        for _ in range(int(math.ceil(math.log2(max(hi_line - lo_line, 2)))) + 1):
            mid = (lo + hi) // 2
            fm = f(mid)
            right = fm >= 0
            lo = np.where(right, mid, lo)
            flo = np.where(right, fm, flo)
            hi = np.where(right, hi, mid)
            fhi = np.where(right, fhi, fm)
        ok &= (hi - lo == 1) & valid[lo] & valid[hi]
        frac = np.where(ok, flo / np.where(ok, flo - fhi, 1.0), 0.0)
        line = lo + frac
        c = pos[lo] + frac[:, None] * (pos[hi] - pos[lo])
        m = att[lo] + frac[:, None, None] * (att[hi] - att[lo])
        v = np.einsum("nji,nj->ni", m, points - c)   # camera coordinates (m^T (X - C))
        with np.errstate(divide="ignore", invalid="ignore"):
            u = v[:, 1] / v[:, 2]
        ok &= v[:, 2] > 0
        return np.where(ok, line, np.nan), np.where(ok, u, np.nan)

    def sample_coordinate(self, p: Pass, u: np.ndarray) -> np.ndarray:
        """Continuous sample index (sample k's centre at k) of focal-plane coordinates ``u``."""
        return (np.asarray(u, float) + self.t_half) / (2.0 * self.t_half) * p.samples - 0.5

    def footprint(self, p: Pass, params: Params, step: int = 10):
        """The pass's ground footprint (shapely Polygon, local E, N... as (N, E) pairs) under
        ``params``, from the swath edges of every ``step``-th line; None if too few lines."""
        from shapely.geometry import Polygon

        lines = np.arange(0, p.lines, step, dtype=float)
        if lines[-1] != p.lines - 1:
            lines = np.r_[lines, p.lines - 1]
        left = self.forward(p, lines, np.full(lines.size, -self.t_half), params)
        right = self.forward(p, lines, np.full(lines.size, self.t_half), params)
        ok = np.isfinite(left).all(axis=1) & np.isfinite(right).all(axis=1)
        if ok.sum() < 2:
            return None
        ring = np.concatenate([left[ok], right[ok][::-1]])
        poly = Polygon(ring)
        return poly if poly.is_valid else poly.buffer(0)
