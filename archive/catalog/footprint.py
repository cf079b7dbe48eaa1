"""Ground footprint of a flight from its per-line camera poses (numpy only, no OpenGL).

Each line's swath edges (focal-plane u = -tan(fov/2) and +tan(fov/2), DESIGN 3) are intersected
with the flat ground (or traced to their first hits on a DEM, :func:`terrain_swath_edges`); the
lines are split into strips where time jumps (a turn, a pause: never joined, as in the mesh); each
strip's outline is the convex hull of its edge points grown by a margin. The margin covers what
the start-of-exposure poses leave out (the last line's own span, mid-exposure centring, a few cm;
over a DEM also how far a line's trace can leave the chord of its edge hits) and curved passes are
covered by the hull, so the outline always CONTAINS the true footprint; it is a catalog footprint,
not a coverage mask.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pyproj import Transformer
from scipy.spatial import ConvexHull
from scipy.spatial.transform import Rotation

from archive.errors import InputError
from archive.geometry.navigation import DEFAULT_MAX_VIEW_ANGLE, ground_hits, strip_slices, view_angles

# Outline growth beyond the hull, metres, on top of two along-track line steps.
MARGIN_M = 0.5


@dataclass(frozen=True)
class Footprint:
    """strips_utm: one (k, 2) array of UTM (E, N) vertices per strip, counter-clockwise, not closed.
    epsg: UTM zone of those vertices. gsd: nominal across-track pixel size at nadir, metres.
    """

    strips_utm: tuple[np.ndarray, ...]
    epsg: int
    gsd: float

    def lonlat(self) -> list[np.ndarray]:
        """Strips as (k, 2) lon, lat degree arrays (same vertex order)."""
        tr = Transformer.from_crs(self.epsg, 4326, always_xy=True)
        out = []
        for ring in self.strips_utm:
            lon, lat = tr.transform(ring[:, 0], ring[:, 1])
            out.append(np.stack([np.asarray(lon), np.asarray(lat)], axis=-1))
        return out

    def geometry(self) -> dict:
        """GeoJSON Polygon (one strip) or MultiPolygon, lon/lat degrees, rings closed, CCW."""
        rings = []
        for ring in self.lonlat():
            closed = np.vstack([ring, ring[:1]])
            rings.append([[round(float(x), 9), round(float(y), 9)] for x, y in closed])
        if len(rings) == 1:
            return {"type": "Polygon", "coordinates": [rings[0]]}
        return {"type": "MultiPolygon", "coordinates": [[r] for r in rings]}

    def bbox(self) -> list[float]:
        """[west, south, east, north] degrees of all strips (from the rounded GeoJSON vertices)."""
        geom = self.geometry()
        polys = [geom["coordinates"]] if geom["type"] == "Polygon" else geom["coordinates"]
        pts = np.array([p for poly in polys for p in poly[0]], float)
        return [float(pts[:, 0].min()), float(pts[:, 1].min()), float(pts[:, 0].max()), float(pts[:, 1].max())]


def swath_edges(position: np.ndarray, attitude: Rotation, fov_deg: float, ground_down: float,
                where: str = "") -> tuple[np.ndarray, np.ndarray]:
    """Ground points of the two swath edges of every line.

    position: (lines, 3) camera N, E, D metres; attitude: (lines,) camera -> NED; fov_deg: across-
    track field of view; ground_down: the ground plane's D coordinate in the same frame, metres.
    Returns (left, right), each (lines, 2) N, E metres (left = sample 0 end, u = -tan(fov/2)).
    """
    t = np.tan(np.radians(fov_deg) / 2.0)
    position = np.asarray(position, float)
    out = []
    for u in (-t, t):
        points, _, bad = ground_hits(position, attitude, u, ground_down)
        if bad.any():
            row = int(np.flatnonzero(bad)[0])
            if position[row, 2] >= ground_down:
                raise InputError(where or None, f"line {row}: the camera is at or below the ground "
                                 f"(camera D {position[row, 2]:.2f} m, ground D {ground_down:.2f} m)",
                                 "check the ground height")
            raise InputError(where or None, f"line {row}: the swath edge looks at or above the horizon",
                             "check the attitude (roll/pitch) and --fov")
        out.append(points)
    return out[0], out[1]


def terrain_swath_edges(position: np.ndarray, attitude: Rotation, fov_deg: float, frame, terrain,
                        where: str = "") -> tuple[np.ndarray, np.ndarray, float]:
    """:func:`swath_edges` on the terrain: the first hits of the two edge rays of every line on
    ``terrain`` (an opened :class:`archive.terrain.dem.Dem`; errors name it and the ground it lacks).
    position: (lines, 3) camera N, E, D metres of ``frame``; returns (left, right) (lines, 2) N, E
    and the relief (m) between the highest and lowest of those hits."""
    t = np.tan(np.radians(fov_deg) / 2.0)
    position = np.asarray(position, float)
    origin = np.stack([position[:, 1] + frame.origin_e, position[:, 0] + frame.origin_n,
                       frame.origin_alt - position[:, 2]], axis=1)
    rays = [np.atleast_2d(attitude.apply(np.array([0.0, u, 1.0]))) for u in (-t, t)]
    hits = terrain.intersect(frame.epsg, origin, [np.stack([d[:, 1], d[:, 0], -d[:, 2]], axis=1) for d in rays])
    out = []
    heights = []
    for (lam, under), d in zip(hits, rays):
        if under.any():
            row = int(np.flatnonzero(under)[0])
            raise InputError(where or None, f"line {row}: the camera is at or below the ground of the DEM "
                             f"{getattr(terrain, 'path', '')} (camera {origin[row, 2]:.2f} m)",
                             "check the DEM and its vertical datum (--dem-datum)")
        if not np.all(np.isfinite(lam)):
            row = int(np.flatnonzero(~np.isfinite(lam))[0])
            raise InputError(where or None, f"line {row}: the swath edge looks at or above the horizon",
                             "check the attitude (roll/pitch) and --fov")
        out.append(position[:, :2] + lam[:, None] * d[:, :2])
        heights.append(position[:, 2] + lam * d[:, 2])
    heights = np.concatenate(heights)
    return out[0], out[1], float(heights.max() - heights.min())


def strips(time: np.ndarray) -> list[slice]:
    """Split line indices into strips (the project's one strip rule, :func:`archive.geometry.navigation.strip_slices`)."""
    return strip_slices(time)


def _grown_hull(points: np.ndarray, margin: float) -> np.ndarray:
    # Minkowski sum with a 16-gon circumscribing a circle of radius `margin`: contains the buffer.
    k = 16
    ang = 2 * np.pi * np.arange(k) / k
    r = margin / np.cos(np.pi / k)
    ring = np.stack([np.cos(ang), np.sin(ang)], axis=-1) * r
    pts = (points[:, None, :] + ring[None, :, :]).reshape(-1, 2)
    hull = ConvexHull(pts)
    return pts[hull.vertices]  # counter-clockwise for 2-D input


def flight_footprint(time: np.ndarray, position: np.ndarray, attitude: Rotation, frame, fov_deg: float,
                     ground_height: float, samples: int, where: str = "", terrain=None) -> Footprint:
    """Footprint of a flight: time (lines,) s; position (lines, 3) N, E, D m; attitude (lines,)
    camera -> NED; frame: the navigation LocalFrame; ground_height: m above the ellipsoid; terrain:
    an opened :class:`archive.terrain.dem.Dem` the swath edges are traced to instead (ground_height unused)."""
    ground_down = None if terrain is not None else frame.origin_alt - float(ground_height)
    # Lines the renderer leaves out (turns: too far off nadir) are left out of the footprint too.
    seen = view_angles(attitude, fov_deg) <= DEFAULT_MAX_VIEW_ANGLE
    if not seen.any():
        raise InputError(where or None, f"every line looks more than {DEFAULT_MAX_VIEW_ANGLE:g} degrees off nadir",
                         "check the attitude (roll/pitch) and --fov")
    time, position, attitude = np.asarray(time)[seen], np.asarray(position)[seen], attitude[seen]
    bulge = 0.0
    if terrain is not None:
        left, right, relief = terrain_swath_edges(position, attitude, fov_deg, frame, terrain, where)
        # a line's ground trace leaves the chord of its edge hits by up to relief x tan(tilt of its
        # fan plane from the vertical): added to the margin, so that the outline still contains it
        sin_tilt = float(np.max(np.abs(attitude.as_matrix()[:, 2, 0])))
        bulge = relief * sin_tilt / max(np.sqrt(1.0 - sin_tilt**2), 1e-3)
    else:
        left, right = swath_edges(position, attitude, fov_deg, ground_down, where)
    width = np.linalg.norm(right - left, axis=1)
    gsd = float(np.median(width) / max(int(samples), 1))
    rings = []
    for sl in strips(time):
        pts = np.vstack([left[sl], right[sl]])  # (N, E)
        centre = (left[sl] + right[sl]) / 2.0
        step = float(np.max(np.linalg.norm(np.diff(centre, axis=0), axis=1))) if len(centre) > 1 else 0.0
        margin = MARGIN_M + 2.0 * step + gsd + bulge
        en = pts[:, ::-1] + np.array([frame.origin_e, frame.origin_n])  # (E, N) UTM
        rings.append(_grown_hull(en, margin))
    return Footprint(tuple(rings), frame.epsg, gsd)


def recorded_footprint(rings_lonlat, epsg: int, gsd: float) -> Footprint:
    """A :class:`Footprint` from lon/lat rings (degrees; as :meth:`Footprint.lonlat` gave them)."""
    tr = Transformer.from_crs(4326, int(epsg), always_xy=True)
    strips = []
    for ring in rings_lonlat:
        ring = np.asarray(ring, float)
        e, n = tr.transform(ring[:, 0], ring[:, 1])
        strips.append(np.stack([np.asarray(e), np.asarray(n)], axis=-1))
    return Footprint(tuple(strips), int(epsg), float(gsd))


def points_in_polygon(points: np.ndarray, ring: np.ndarray) -> np.ndarray:
    """Even-odd test: points (m, 2) against a ring (k, 2) (closed or not). Returns (m,) bool."""
    points = np.asarray(points, float)
    ring = np.asarray(ring, float)
    if np.allclose(ring[0], ring[-1]):
        ring = ring[:-1]
    x, y = points[:, 0][:, None], points[:, 1][:, None]
    x0, y0 = ring[:, 0][None, :], ring[:, 1][None, :]
    x1, y1 = np.roll(ring[:, 0], -1)[None, :], np.roll(ring[:, 1], -1)[None, :]
    crosses = (y0 > y) != (y1 > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        xint = x0 + (y - y0) * (x1 - x0) / (y1 - y0)
    return np.count_nonzero(crosses & (x < xint), axis=1) % 2 == 1
