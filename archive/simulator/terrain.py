"""Analytic terrain for the simulator: heights as smooth functions of UTM (E, N), the first hit of a
ray on them, and the DEM GeoTIFFs written from them.

Heights are metres above the WGS-84 ellipsoid: ``base`` plus Gaussian bumps and an optional ridge,
laid out in the flight's pass frame (``a`` along the passes' grid heading, ``c`` to its right, about
the pattern's centre; see :mod:`archive.simulator.trajectory`):

- ``hills``: four bumps of -4 to +8 m (widths 4-8 m, slopes up to ~45 degrees), 12 m of relief:
  every ground point is seen (no slope faces away from the camera more steeply than its rays);
- ``ridge``: a 12 m ridge along the passes, 8 m to the right of the last pass, with a gentle face
  towards it (Gaussian width 6 m) and an 83-degree back (width 1.2 m): the camera looks over its
  crest, and a strip of ground behind it is seen by no line.

Ray hits are traced independently of the renderer (DESIGN 7): a ray is marched by Lipschitz-safe
steps (clearance / (descent rate + L x horizontal rate), L a bound of the slope) that can never
step over terrain, then polished by Newton steps to 1e-6 m: the hit is the FIRST one from the camera.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np

__all__ = ["DEM_NAME", "TERRAINS", "Terrain", "make_terrain", "write_dem"]

TERRAINS = ("hills", "ridge")
DEM_NAME = "dem.tif"   #: the DEM GeoTIFF written into a terrain flight's directory
#: Where Debian's proj-data puts the geoid grids.
_SYSTEM_PROJ = "/usr/share/proj"


@dataclass(frozen=True)
class Terrain:
    """Heights above the ellipsoid (m) at UTM points of the flight's zone.

    kind: 'hills' | 'ridge'; base: m; origin_e, origin_n: the pass frame's origin (UTM m);
    heading_deg: grid heading of its ``a`` axis; bumps: (a, c, height m, width m) Gaussian bumps
    ``height * exp(-r^2 / width^2)``; ridge: None or (c of the crest, height m, width towards -c,
    width towards +c), uniform along ``a``.
    """

    kind: str
    base: float
    origin_e: float
    origin_n: float
    heading_deg: float
    bumps: tuple[tuple[float, float, float, float], ...] = ()
    ridge: tuple[float, float, float, float] | None = None

    def _ac(self, e, n) -> tuple[np.ndarray, np.ndarray]:
        psi = math.radians(self.heading_deg)
        de = np.asarray(e, float) - self.origin_e
        dn = np.asarray(n, float) - self.origin_n
        return de * math.sin(psi) + dn * math.cos(psi), de * math.cos(psi) - dn * math.sin(psi)

    def height(self, e, n) -> np.ndarray:
        """Heights (m above the ellipsoid) at UTM points, any (broadcast) shape."""
        a, c = self._ac(e, n)
        h = np.full(np.broadcast(a, c).shape, float(self.base))
        for a0, c0, height, width in self.bumps:
            h += height * np.exp(-((a - a0) ** 2 + (c - c0) ** 2) / width**2)
        if self.ridge is not None:
            c0, height, near, far = self.ridge
            x = (c - c0) / np.where(c < c0, near, far)
            h += height * np.exp(-x * x)
        return h

    def gradient(self, e, n) -> tuple[np.ndarray, np.ndarray]:
        """(dh/dE, dh/dN) at UTM points."""
        a, c = self._ac(e, n)
        ga = np.zeros(np.broadcast(a, c).shape)
        gc = np.zeros_like(ga)
        for a0, c0, height, width in self.bumps:
            g = height * np.exp(-((a - a0) ** 2 + (c - c0) ** 2) / width**2) * (-2.0 / width**2)
            ga += g * (a - a0)
            gc += g * (c - c0)
        if self.ridge is not None:
            c0, height, near, far = self.ridge
            w = np.where(c < c0, near, far)
            x = (c - c0) / w
            gc += height * np.exp(-x * x) * (-2.0 * x / w)
        psi = math.radians(self.heading_deg)
        return ga * math.sin(psi) + gc * math.cos(psi), ga * math.cos(psi) - gc * math.sin(psi)

    @property
    def lipschitz(self) -> float:
        """An upper bound of the slope |grad h| (m/m): the sum of each term's largest slope."""
        peak = math.sqrt(2.0) * math.exp(-0.5)     # max of 2 x exp(-x^2) over x
        total = sum(abs(h) * peak / w for _, _, h, w in self.bumps)
        if self.ridge is not None:
            _, height, near, far = self.ridge
            total += abs(height) * peak / min(near, far)
        return total * 1.001

    @property
    def relief(self) -> tuple[float, float]:
        """(lowest, highest) height bounds, m."""
        lo = self.base + sum(min(0.0, h) for _, _, h, _ in self.bumps)
        hi = self.base + sum(max(0.0, h) for _, _, h, _ in self.bumps)
        if self.ridge is not None:
            hi += max(0.0, self.ridge[1])
            lo += min(0.0, self.ridge[1])
        return lo, hi

    def intersect(self, position: np.ndarray, direction: np.ndarray) -> np.ndarray:
        """First hits of rays: position (n, 3) E, N, altitude (m); direction (n, 3) N, E, D (the
        camera ray R (0, u, 1), any length). Returns lam (n,) with hit = position + lam *
        direction; NaN for rays that do not go down."""
        p = np.asarray(position, float)
        d = np.asarray(direction, float)
        step_dir = np.stack([d[:, 1], d[:, 0], -d[:, 2]], axis=1)   # east, north, up per unit lam
        dz = step_dir[:, 2] * -1.0
        dh = np.hypot(step_dir[:, 0], step_dir[:, 1])
        lam = np.full(p.shape[0], np.nan)
        idx = np.flatnonzero(dz > 1e-9)
        _, hi = self.relief
        t0 = np.maximum((p[idx, 2] - hi - 1e-6) / dz[idx], 0.0)
        lip = self.lipschitz

        def clearance(i, t):
            q = p[i] + t[:, None] * step_dir[i]
            return q[:, 2] - self.height(q[:, 0], q[:, 1]), q

        def march(i, t, threshold):
            """Lipschitz-safe steps until the clearance is below ``threshold`` (never past a hit)."""
            out = t.copy()
            active = np.arange(i.size)
            for _ in range(100000):
                if active.size == 0:
                    break
                g, _ = clearance(i[active], out[active])
                done = g < threshold
                go = active[~done]
                out[go] += g[~done] / (dz[i[go]] + lip * dh[i[go]])
                active = go
            return out

        t = march(idx, t0, 0.02)
        # Newton from just above the surface: the crossing ahead, to 1e-6 m
        tn = t.copy()
        active = np.arange(idx.size)
        for _ in range(12):
            i = idx[active]
            g, q = clearance(i, tn[active])
            ge, gn = self.gradient(q[:, 0], q[:, 1])
            slope = -dz[i] - ge * step_dir[i, 0] - gn * step_dir[i, 1]   # dg/dlam
            tn[active] -= g / np.where(slope < -1e-12, slope, np.nan)
            active = active[np.isfinite(tn[active]) & (np.abs(g) > 1e-8)]
            if active.size == 0:
                break
        g, q = clearance(idx, tn)
        ge, gn = self.gradient(q[:, 0], q[:, 1])
        slope = -dz[idx] - ge * step_dir[idx, 0] - gn * step_dir[idx, 1]
        ok = np.isfinite(tn) & (np.abs(g) < 1e-6) & (slope < 0) & (tn >= t - 1e-9) & (tn <= t + 0.5)
        # grazing rays (Newton found no crossing near): safe steps to 1e-5 m instead
        if not ok.all():
            bad = np.flatnonzero(~ok)
            tn[bad] = march(idx[bad], t[bad], 1e-5)
        lam[idx] = tn
        return lam

    def to_dict(self) -> dict:
        return {"kind": self.kind, "base": self.base, "origin_e": self.origin_e, "origin_n": self.origin_n,
                "heading_deg": self.heading_deg, "bumps": [list(b) for b in self.bumps],
                "ridge": None if self.ridge is None else list(self.ridge)}

    @classmethod
    def from_dict(cls, d: dict) -> Terrain:
        return cls(str(d["kind"]), float(d["base"]), float(d["origin_e"]), float(d["origin_n"]),
                   float(d["heading_deg"]), tuple(tuple(float(v) for v in b) for b in d.get("bumps", ())),
                   None if d.get("ridge") is None else tuple(float(v) for v in d["ridge"]))


def make_terrain(kind: str, base: float, origin_e: float, origin_n: float, heading_deg: float,
                 pass_c: list[float]) -> Terrain:
    """The terrain ``kind`` ('hills' | 'ridge') about the pattern centre; ``pass_c``: the passes'
    across-track coordinates (m), to put the ridge beside the last one."""
    if kind == "hills":
        bumps = ((-3.0, -14.0, 8.0, 7.0), (5.0, 10.0, 7.0, 6.0), (0.0, 0.0, -4.0, 8.0), (-6.0, 16.0, 4.0, 4.0))
        return Terrain(kind, base, origin_e, origin_n, heading_deg, bumps)
    if kind == "ridge":
        return Terrain(kind, base, origin_e, origin_n, heading_deg, (), (max(pass_c) + 8.0, 12.0, 6.0, 1.2))
    raise ValueError(f"unknown terrain {kind!r}, expected one of {', '.join(TERRAINS)}")


def write_dem(path, terrain: Terrain, epsg: int, bounds: tuple[float, float, float, float],
              resolution: float = 0.1, crs=None, datum: str = "ellipsoid", declare: bool = True,
              hole: tuple[float, float, float, float] | None = None) -> None:
    """Write ``terrain`` as a float32 GeoTIFF DEM of pixel-centre heights.

    bounds: (west, south, east, north) UTM metres of ``epsg`` to cover; resolution: pixel side, m;
    crs: None (the UTM zone ``epsg``) or 4326 (lon/lat pixels of about ``resolution`` metres);
    datum: 'ellipsoid' (heights above WGS 84) or 'egm96' (geoid heights: the ellipsoidal height
    minus the EGM96 separation from PROJ's egm96_15.gtx; ValueError when that grid is missing);
    declare: write the vertical datum into the CRS (a 3-D CRS with ellipsoidal heights, or a
    compound CRS + EPSG:5773), else a plain 2-D CRS; hole: a (west, south, east, north) UTM box of
    nodata (-9999) pixels.
    """
    import rasterio
    from pyproj import CRS, Transformer
    from rasterio.transform import from_origin

    w, s, e, n = (float(v) for v in bounds)
    geographic = crs is not None and CRS.from_user_input(crs).is_geographic
    if geographic:
        to_ll = Transformer.from_crs(epsg, 4326, always_xy=True)
        lon, lat = to_ll.transform(np.array([w, e, e, w]), np.array([s, s, n, n]))
        mid = math.radians(float(np.mean(lat)))
        rx, ry = resolution / (111320.0 * math.cos(mid)), resolution / 110570.0
        x0, y0 = float(np.min(lon)), float(np.max(lat))
        width = int(math.ceil((np.max(lon) - x0) / rx))
        height = int(math.ceil((y0 - np.min(lat)) / ry))
        xs = x0 + (np.arange(width) + 0.5) * rx
        ys = y0 - (np.arange(height) + 0.5) * ry
        xx, yy = np.meshgrid(xs, ys)
        ue, un = Transformer.from_crs(4326, epsg, always_xy=True).transform(xx, yy)
        lons, lats = xx, yy
        horizontal = CRS.from_epsg(4326)
    else:
        rx = ry = resolution
        x0, y0 = w, n
        width = int(math.ceil((e - w) / rx))
        height = int(math.ceil((n - s) / ry))
        ue, un = np.meshgrid(x0 + (np.arange(width) + 0.5) * rx, y0 - (np.arange(height) + 0.5) * ry)
        lons, lats = Transformer.from_crs(epsg, 4326, always_xy=True).transform(ue, un)
        horizontal = CRS.from_epsg(epsg)
    h = terrain.height(ue, un)
    if datum == "egm96":
        import pyproj.datadir

        if os.path.isdir(_SYSTEM_PROJ) and _SYSTEM_PROJ not in pyproj.datadir.get_data_dir():
            pyproj.datadir.append_data_dir(_SYSTEM_PROJ)
        from pyproj.transformer import TransformerGroup

        group = TransformerGroup(CRS.from_epsg(4979), CRS.from_user_input("EPSG:4326+5773"), always_xy=True)
        if not group.best_available:
            raise ValueError("the EGM96 grid (egm96_15.gtx) is not installed: apt-get install proj-data")
        _, _, geoid = group.transformers[0].transform(lons, lats, h)
        h = np.asarray(geoid, float)
    elif datum != "ellipsoid":
        raise ValueError(f"datum {datum!r}, expected 'ellipsoid' or 'egm96'")
    if hole is not None:
        hw, hs, he, hn = hole
        h = np.where((ue >= hw) & (ue <= he) & (un >= hs) & (un <= hn), -9999.0, h)
    if not declare:
        out_crs = horizontal
    elif datum == "ellipsoid":
        out_crs = CRS.from_epsg(4979) if geographic else horizontal.to_3d()
    else:
        out_crs = CRS.from_user_input(f"EPSG:{horizontal.to_epsg()}+5773")
    profile = dict(driver="GTiff", width=width, height=height, count=1, dtype="float32", nodata=-9999.0,
                   crs=rasterio.crs.CRS.from_wkt(out_crs.to_wkt()), transform=from_origin(x0, y0, rx, ry),
                   compress="deflate", tiled=True, blockxsize=256, blockysize=256)
    with rasterio.open(path, "w", **profile) as ds:
        ds.write(h.astype(np.float32)[None])
