"""Terrain surfaces in a flight's frame, and the first hits of rays on them.

A :class:`Surface` holds heights (m above the ellipsoid) on a north-up grid of nodes of a UTM zone,
bilinear in between; :meth:`archive.terrain.dem.Dem.surface` makes one from a DEM.

Ray hits (:meth:`Surface.intersect`): the FIRST point where a ray meets the terrain, to 0.1 mm. A
ray is marched from where it passes the highest node to where it passes the lowest, by steps that
cannot jump over terrain: clearance / (descent rate + S x horizontal rate), S being the largest
slope of the bilinear surface (a Lipschitz bound), but never shorter than half a node in 3-D (so
that walls do not stall it; a crossing is then bracketed), and the bracket is bisected.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from archive.errors import InputError

__all__ = ["HIT_TOLERANCE", "Surface", "bilinear", "flat_points"]

#: Ray hits are refined until the bracket is shorter than this, metres.
HIT_TOLERANCE = 1e-4


def flat_points(origin: np.ndarray, direction: np.ndarray, level: float) -> np.ndarray:
    """(n, 2) E, N where rays (origin (n, 3) E, N, alt; direction (n, 3) dE, dN, dUp) cross the
    height ``level`` (at their origin when they do not go down to it)."""
    down = np.maximum(-direction[:, 2], 1e-12)
    lam = np.clip((origin[:, 2] - level) / down, 0.0, 1e6)
    return origin[:, :2] + lam[:, None] * direction[:, :2]


def bilinear(grid: np.ndarray, r: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Bilinear interpolation of ``grid`` at fractional (row, col) indices inside it (clamped)."""
    h, w = grid.shape
    r = np.clip(r, 0.0, h - 1.0)
    c = np.clip(c, 0.0, w - 1.0)
    r0 = np.minimum(r.astype(np.intp), max(h - 2, 0))      # r, c >= 0: truncation is floor
    c0 = np.minimum(c.astype(np.intp), max(w - 2, 0))
    fr = r - r0
    fc = c - c0
    flat = grid.reshape(-1)
    k = r0 * w + c0
    dc = 1 if w > 1 else 0
    dr = w if h > 1 else 0
    top = flat.take(k) * (1.0 - fc) + flat.take(k + dc) * fc
    bottom = flat.take(k + dr) * (1.0 - fc) + flat.take(k + dr + dc) * fc
    return top * (1.0 - fr) + bottom * fr


# ---------------------------------------------------------------------------------------------
# The terrain in the flight's frame
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class Surface:
    """Terrain heights (m above the ellipsoid) on north-up nodes of the UTM zone ``epsg``: node
    (i, j) at easting ``west + j res``, northing ``north - i res``; bilinear in between.

    heights: (rows, cols) float64, NaN where the DEM has no value; outside: (rows, cols) bool,
    nodes beyond the DEM's extent; dem: the :class:`Dem` (for messages).
    """

    epsg: int
    west: float
    north: float
    res: float
    heights: np.ndarray
    outside: np.ndarray
    dem: Dem | None = None

    @property
    def hmin(self) -> float:
        return float(np.nanmin(self.heights))

    @property
    def hmax(self) -> float:
        return float(np.nanmax(self.heights))

    @cached_property
    def slope(self) -> float:
        """Largest slope (m/m) of the bilinear surface: a Lipschitz constant of the heights."""
        h = self.heights
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            dx = np.abs(np.diff(h, axis=1))
            dy = np.abs(np.diff(h, axis=0))
            gx = np.fmax(dx[:-1], dx[1:]) if dx.shape[0] > 1 else dx
            gy = np.fmax(dy[:, :-1], dy[:, 1:]) if dy.shape[1] > 1 else dy
            s = np.nanmax(np.hypot(gx, gy)) / self.res if gx.size and gy.size else 0.0
        return float(s) * 1.0001 + 1e-9

    def height(self, e, n) -> np.ndarray:
        """Bilinear heights at UTM points (any shape); NaN beyond the nodes or on holes."""
        e = np.asarray(e, float)
        n = np.asarray(n, float)
        c = (e - self.west) / self.res
        r = (self.north - n) / self.res
        rows, cols = self.heights.shape
        out = bilinear(self.heights, r, c)
        beyond = (c < -1e-9) | (r < -1e-9) | (c > cols - 1 + 1e-9) | (r > rows - 1 + 1e-9)
        return np.where(beyond, np.nan, out)

    def gaps(self, origin: np.ndarray, direction: np.ndarray, failed_at: np.ndarray):
        """(uncovered (m, 2), holes (k, 2), rays) for rays that met ground without heights at the
        points ``failed_at`` (m, 2): where they would meet the ground at the mean height, and where
        they failed, split by whether that lies beyond the DEM or in its holes."""
        level = float(np.nanmean(self.heights)) if np.isfinite(self.heights).any() else 0.0
        flat = flat_points(origin, direction, level)
        outside = bool(self._outside_at(failed_at[:, 0], failed_at[:, 1]).any())
        pts = np.concatenate([failed_at, flat])
        empty = np.zeros((0, 2))
        return (pts, empty, len(origin)) if outside else (empty, pts, len(origin))

    def _outside_at(self, e, n) -> np.ndarray:
        c = np.clip(np.rint((np.asarray(e) - self.west) / self.res), 0, self.heights.shape[1] - 1).astype(np.intp)
        r = np.clip(np.rint((self.north - np.asarray(n)) / self.res), 0, self.heights.shape[0] - 1).astype(np.intp)
        beyond = ((np.asarray(e) < self.west - self.res) | (np.asarray(n) > self.north + self.res)
                  | (c >= self.heights.shape[1]) | (r >= self.heights.shape[0]))
        return self.outside[r, c] | beyond

    def trace(self, origin: np.ndarray, direction: np.ndarray, tolerance: float = HIT_TOLERANCE
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`intersect` without raising: (lam (n,), failed (n,) bool: the ray met ground without
        heights, (m, 2) E, N where they did)."""
        lam, under, failed, at = self._march(origin, direction, tolerance)
        return lam, failed, at

    def intersect(self, origin: np.ndarray, direction: np.ndarray, tolerance: float = HIT_TOLERANCE
                  ) -> tuple[np.ndarray, np.ndarray]:
        """First hits of rays ``origin + lam * direction`` on the terrain.

        origin: (n, 3) E, N (UTM m of ``epsg``), altitude (m, ellipsoid); direction: (n, 3) dE, dN,
        dUp (any length). Returns lam (n,), NaN for rays that do not go down, and under (n,) bool:
        the origin is at or below the terrain (lam NaN). The hit is within ``tolerance`` metres
        (along the ray) of the first crossing. Raises InputError naming the DEM and a lon/lat box
        when rays cross ground the DEM does not cover or has holes in.
        """
        lam, under, failed, at = self._march(origin, direction, tolerance)
        if failed.any():
            o = np.asarray(origin, float)
            d = np.asarray(direction, float)
            gaps = self.gaps(o[failed], d[failed], at)
            if self.dem is None:
                raise InputError(None, f"{int(failed.sum())} rays cross ground without heights")
            self.dem.raise_gaps(self.epsg, *gaps)
        return lam, under

    def _march(self, origin: np.ndarray, direction: np.ndarray, tolerance: float
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The march of :meth:`intersect` (module docstring): (lam, under, failed, failed_at)."""
        o = np.asarray(origin, float)
        d = np.asarray(direction, float)
        n = o.shape[0]
        lam = np.full(n, np.nan)
        under = np.zeros(n, bool)
        if n == 0:
            return lam, under, np.zeros(0, bool), np.zeros((0, 2))
        dz = -d[:, 2]
        dh = np.hypot(d[:, 0], d[:, 1])
        dn = np.sqrt(dh**2 + dz**2)
        down = dz > 1e-12 * np.maximum(dn, 1e-300)
        top, bottom = self.hmax + 1e-6, self.hmin - 1e-3
        slope = self.slope
        safe_dz = np.where(down, dz, 1.0)
        start = np.where(down, np.maximum((o[:, 2] - top) / safe_dz, 0.0), 0.0)
        end = np.where(down, (o[:, 2] - bottom) / safe_dz, 0.0)
        floor = 0.5 * self.res / np.maximum(dn, 1e-300)
        failed = np.zeros(n, bool)
        fail_pts: list[np.ndarray] = []

        def clearance(idx, t):
            """Height of the ray points above the DEM; rays reaching a DEM hole are marked failed."""
            p = o[idx] + t[:, None] * d[idx]
            g = p[:, 2] - self.height(p[:, 0], p[:, 1])
            bad = ~np.isfinite(g)
            if bad.any():
                failed[idx[bad]] = True
                fail_pts.append(p[bad, :2])
            return g

        idx = np.flatnonzero(down)
        t = start[idx]
        g = clearance(idx, t)
        below = np.isfinite(g) & (g <= 0)
        under[idx[below]] = True
        keep = np.isfinite(g) & (g > 0)
        idx, t, g = idx[keep], t[keep], g[keep]
        lo_i, lo_t, hi_t, lo_g, hi_g = [], [], [], [], []     # brackets (g > 0 at lo, <= 0 at hi)
        for _ in range(100000):
            if idx.size == 0:
                break
            step = np.maximum(g / (dz[idx] + slope * dh[idx]), floor[idx])
            t_new = np.minimum(t + step, end[idx])
            g_new = clearance(idx, t_new)
            crossed = np.isfinite(g_new) & (g_new <= 0)
            close = np.isfinite(g_new) & ~crossed & (g_new < tolerance * dz[idx] / np.maximum(dn[idx], 1e-300))
            lam[idx[close]] = t_new[close]
            lo_i.append(idx[crossed])
            lo_t.append(t[crossed])
            hi_t.append(t_new[crossed])
            lo_g.append(g[crossed])
            hi_g.append(g_new[crossed])
            go = np.isfinite(g_new) & ~crossed & ~close
            idx, t, g = idx[go], t_new[go], g_new[go]
        if lo_i:   # refine the brackets: false position with the Illinois rule
            bi, a, b = np.concatenate(lo_i), np.concatenate(lo_t), np.concatenate(hi_t)
            ga, gb = np.concatenate(lo_g), np.concatenate(hi_g)
            side = np.zeros(bi.size, np.int8)             # which end moved last (+1: a, -1: b)
            for it in range(200):
                if bi.size == 0:
                    break
                if it % 8 == 7:                           # a bisection now and then: guaranteed progress
                    m = 0.5 * (a + b)
                else:
                    m = b - gb * (b - a) / np.where(gb != ga, gb - ga, -1.0)
                    m = np.where((m > a) & (m < b), m, 0.5 * (a + b))
                gm = clearance(bi, m)
                bad = ~np.isfinite(gm)
                pos = gm > 0
                ga = np.where(pos, gm, np.where(side == -1, 0.5 * ga, ga))
                gb = np.where(pos, np.where(side == 1, 0.5 * gb, gb), gm)
                a = np.where(pos, m, a)
                b = np.where(pos, b, m)
                side = np.where(pos, 1, -1).astype(np.int8)
                # done: the bracket, or the distance to the crossing along the ray, is under tolerance
                rate = np.abs(gb - ga) / np.maximum(b - a, 1e-300)
                near = np.abs(gm) / np.maximum(rate, 1e-300) * dn[bi] <= 0.5 * tolerance
                done = ((b - a) * dn[bi] <= tolerance) | near | bad
                lam[bi[done & ~bad]] = np.where(near, m, b)[done & ~bad]
                keep = ~done
                bi, a, b, ga, gb, side = bi[keep], a[keep], b[keep], ga[keep], gb[keep], side[keep]
        lam[failed] = np.nan
        at = np.concatenate(fail_pts) if fail_pts else np.zeros((0, 2))
        return lam, under, failed, at
