"""Terrain meshes: the part of :func:`archive.render.mesh.build_mesh` that follows a DEM.

See :mod:`archive.render.mesh` ("Terrain meshes", "Watertight seams") for the method; this module
traces the rays, chooses each row's across-track split and triangulates the rows:

- :class:`_Tracer` intersects the rays of rows with one DEM :class:`~archive.terrain.dem.Surface`, one
  focal-plane coordinate u at a time (cached);
- :func:`_split` refines a column split for some rows (straight-edge and occlusion checks);
- :func:`terrain_mesh` splits the cube's rows with its own split, the two rows of each cube seam with
  a split of their own (traced on a surface of their own: a function of those two rows only, so the
  neighbouring cube computes the very same vertices), and stitches rows of different splits.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from archive.errors import InputError, RenderError

__all__ = ["EDGE_ERROR_PX", "GRAZING_DEG", "MAX_COLUMNS", "MAX_LEVELS", "OCCLUSION_PX", "START_COLUMN",
           "terrain_mesh", "zipper"]

#: Terrain meshes: the straight-edge error bound, output pixels (checked at segment midpoints
#: against half of it, see :func:`_split`).
EDGE_ERROR_PX = 0.1
#: Terrain meshes: an edge within this angle of the line of sight (the surface between its ends
#: would be seen at more than 90 - GRAZING_DEG degrees of incidence) spans an occlusion.
GRAZING_DEG = 10.0
#: Terrain meshes: segments spanning an occlusion are split until their rays are this close on the
#: ground (output pixels), so that the ground left out beside an occlusion stays below it.
OCCLUSION_PX = 0.5
#: Terrain meshes: columns start at most this many DEM pixels or output pixels wide on the ground
#: (the larger), then are halved where the straight-edge check needs it.
START_COLUMN = 4.0
#: Terrain meshes: most vertices per row, and most halvings of a column.
MAX_COLUMNS = 4097
MAX_LEVELS = 10


def _enu(d: np.ndarray) -> np.ndarray:
    """(n, 3) N, E, D vectors -> E, N, Up."""
    return np.stack([d[:, 1], d[:, 0], -d[:, 2]], axis=1)


def _edge_hidden(pa: np.ndarray, pb: np.ndarray, da: np.ndarray, db: np.ndarray, min_map: float) -> np.ndarray:
    """Edges (..., 3) from ground points pa to pb (N, E, D m) seen along unit rays da, db: True where
    the edge is within GRAZING_DEG of the mean line of sight and longer than ``min_map`` m on the map."""
    v = pb - pa
    length = np.linalg.norm(v, axis=-1)
    m = da + db
    m = m / np.linalg.norm(m, axis=-1, keepdims=True)
    sin = np.linalg.norm(np.cross(v, m), axis=-1) / np.where(length > 0, length, 1.0)
    return (length > 0) & (sin < np.sin(np.radians(GRAZING_DEG))) & (np.hypot(v[..., 0], v[..., 1]) > min_map)


class _Tracer:
    """First hits of the rays of some rows on one surface, per focal-plane coordinate u (cached).

    pos (R, 3) camera N, E, D (local m); origin (R, 3) camera E, N, altitude; matrix (R, 3, 3) camera
    -> NED; row_lines (R,) line coordinate of each row (for messages).
    """

    def __init__(self, pos, origin, matrix, surface, row_lines):
        self.pos, self.origin, self.matrix, self.surface = pos, origin, matrix, surface
        self.row_lines = row_lines
        self.cache: dict[float, tuple[np.ndarray, np.ndarray]] = {}

    def trace(self, us) -> None:
        """Intersect the rays of every coordinate of ``us`` not traced yet (one call)."""
        todo = [float(u) for u in dict.fromkeys(us) if float(u) not in self.cache]
        if not todo:
            return
        u = np.array(todo)
        d = self.matrix[:, None, :, 1] * u[None, :, None] + self.matrix[:, None, :, 2]     # (R, U, 3)
        o = np.broadcast_to(self.origin[:, None, :], d.shape).reshape(-1, 3)
        lam, under = self.surface.intersect(o, _enu(d.reshape(-1, 3)))
        if under.any():
            r = int(np.argmax(under)) // u.size
            raise RenderError(
                f"line {int(self.row_lines[r])}: the camera ({self.origin[r, 2]:.1f} m) is at or below the DEM's "
                f"ground ({self.surface.height(self.origin[r, 0], self.origin[r, 1]):.1f} m); check the DEM, "
                "its vertical datum (--dem-datum) and the altitudes")
        lam = lam.reshape(d.shape[:2])
        for k, key in enumerate(todo):
            self.cache[key] = (lam[:, k], d[:, k])

    def hits(self, u: float) -> tuple[np.ndarray, np.ndarray]:
        """(lam (R,), ray (R, 3) N, E, D) of focal-plane coordinate u."""
        self.trace([u])
        return self.cache[float(u)]

    def ground(self, u: float) -> np.ndarray:
        lam, d = self.hits(u)
        return self.pos + lam[:, None] * d

    def keep(self, good: np.ndarray) -> None:
        """Keep only the rows where ``good``."""
        self.pos, self.origin, self.matrix = self.pos[good], self.origin[good], self.matrix[good]
        self.row_lines = self.row_lines[good]
        for u, (lam, d) in list(self.cache.items()):
            self.cache[u] = (lam[good], d[good])


@dataclass
class _Split:
    """Rows traced at a column split: us (V,) focal-plane coordinates; lam (R, V) ray depths;
    pts (R, V, 3) ground points N, E, D (local m); unit (R, V, 3) unit rays; rng (R, V) distances (m)
    from the camera; occluded (R, V - 1) segments spanning an occlusion; worst: the largest midpoint
    straight-edge error left (m)."""

    us: np.ndarray
    lam: np.ndarray
    pts: np.ndarray
    unit: np.ndarray
    rng: np.ndarray
    occluded: np.ndarray
    worst: float


def _split(tracer: _Tracer, surface, gsd: float, t: float) -> _Split:
    """The across-track split of the tracer's rows (module docstring of :mod:`archive.render.mesh`):
    START_COLUMN-wide columns, halved (for every row) until the straight-edge and occlusion checks
    hold. A function of the rows' rays and the surface only."""
    width = float(np.median(np.hypot(*(tracer.ground(t) - tracer.ground(-t))[:, :2].T)))
    pixel = surface.dem.pixel_m if getattr(surface, "dem", None) is not None else 2.0 * surface.res
    start = START_COLUMN * max(pixel, gsd)
    k0 = int(min(max(math.ceil(width / start), 2), MAX_COLUMNS - 1))
    us = np.linspace(-t, t, k0 + 1)
    us[0], us[-1] = -t, t
    tol = 0.5 * EDGE_ERROR_PX * gsd
    hits = tracer.hits
    for level in range(MAX_LEVELS + 1):
        mids = 0.5 * (us[:-1] + us[1:])
        tracer.trace(np.concatenate([us, mids]))
        lam_v = np.stack([hits(u)[0] for u in us], axis=1)              # (R, V)
        ray_v = np.stack([hits(u)[1] for u in us], axis=1)              # (R, V, 3)
        lam_m = np.stack([hits(u)[0] for u in mids], axis=1)            # (R, V - 1)
        ray_m = np.stack([hits(u)[1] for u in mids], axis=1)
        la, lb = lam_v[:, :-1], lam_v[:, 1:]
        chord = 2.0 * la * lb / (la + lb)                  # lambda of the chord point on the middle ray
        err = np.abs(lam_m - chord) * np.hypot(ray_m[..., 0], ray_m[..., 1])
        pts = tracer.pos[:, None, :] + lam_v[..., None] * ray_v
        unit = ray_v / np.linalg.norm(ray_v, axis=-1, keepdims=True)
        occluded = _edge_hidden(pts[:, :-1], pts[:, 1:], unit[:, :-1], unit[:, 1:], 0.5 * gsd)
        rng = np.linalg.norm(lam_v[..., None] * ray_v, axis=-1)
        angle = np.linalg.norm(np.cross(unit[:, :-1], unit[:, 1:]), axis=-1)
        spread = np.maximum(rng[:, :-1], rng[:, 1:]) * angle
        need = (~occluded & (err > tol)) | (occluded & (spread > OCCLUSION_PX * gsd))
        worst = float(np.max(np.where(occluded, 0.0, err), initial=0.0))
        split = need.any(axis=0)
        if not split.any() or level == MAX_LEVELS or us.size + int(split.sum()) > MAX_COLUMNS:
            break
        us = np.sort(np.concatenate([us, mids[split]]))
    return _Split(us, lam_v, pts, unit, rng, occluded, worst)


def zipper(ua: np.ndarray, ub: np.ndarray) -> np.ndarray:
    """Triangles (n, 3) stitching a row split at ``ua`` (sorted, shared ends) to the next row split at
    ``ub``, as an (n, 3, 2) int array of (row, column) vertices: (0, i) is the first row's column i,
    (1, j) the next row's column j. Columns advance in order of u (the smaller next u first), so every segment of
    both rows is an edge of exactly one triangle and the strip has no T-junction."""
    tris = []
    i = j = 0
    while i < len(ua) - 1 or j < len(ub) - 1:
        if j == len(ub) - 1 or (i < len(ua) - 1 and ua[i + 1] <= ub[j + 1]):
            tris.append(((0, i), (0, i + 1), (1, j)))
            i += 1
        else:
            tris.append(((0, i), (1, j + 1), (1, j)))
            j += 1
    return np.array(tris, dtype=np.int64).reshape(-1, 3, 2)


def _regular_faces(v: int, k: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """(len(k), len(cols) - 1, 2, 3) vertex indices of the quads between rows k and k + 1 on the same
    columns ``cols`` (indices into the row's V vertices), two triangles per quad as in
    :meth:`Mesh.triangles`: the first has row k's edge, the second row k + 1's."""
    a = v * k[:, None] + cols[None, :-1]
    b = v * k[:, None] + cols[None, 1:]
    first = np.stack([a, b, a + v], axis=-1)
    second = np.stack([b, b + v, a + v], axis=-1)
    return np.stack([first, second], axis=2)


def terrain_mesh(frame, mid_pos, mid_att, keep, link, line, lines, first, fov_deg, terrain, gsd,
                 no_navigation, oblique) -> dict:
    """The terrain part of :func:`archive.render.mesh.build_mesh` (its module docstring, "Terrain
    meshes" and "Watertight seams"): rows at mid-exposure ``mid_pos`` / ``mid_att`` where ``keep``,
    joined where ``link``; ``line`` the line coordinate of each row (-1 opening, ``lines`` closing);
    ``first`` the index of the cube's line 0 among the rows. Returns the fields of the
    :class:`~archive.render.mesh.Mesh` (all but its frame)."""
    if gsd is None or not (math.isfinite(gsd) and gsd > 0):
        raise InputError("gsd", f"a terrain mesh needs the output pixel size, got {gsd!r}")
    t = math.tan(math.radians(fov_deg) / 2)
    rows = np.flatnonzero(keep)

    def empty() -> dict:
        return dict(ground=np.zeros((0, 2, 2)), depth=np.ones((0, 2)), line=np.zeros(0), lines=lines,
                    fov_deg=fov_deg, ground_height=math.nan, dropped={"no navigation": no_navigation, "view angle": oblique},
                    columns=np.array([0.0, 1.0]), distance=np.zeros((0, 2)))

    if rows.size == 0:
        return empty()

    def origin_of(pos: np.ndarray) -> np.ndarray:
        return np.stack([pos[:, 1] + frame.origin_e, pos[:, 0] + frame.origin_n,
                         float(frame.origin_alt) - pos[:, 2]], axis=1)

    def surface_of(att, origin):
        return terrain.surface_under(frame.epsg, origin, [_enu(att.apply(np.array([0.0, u, 1.0])))
                                                          for u in (-t, t)])

    pos, att = mid_pos[rows], mid_att[rows]
    origin = origin_of(pos)
    surface = surface_of(att, origin)
    tracer = _Tracer(pos, origin, att.as_matrix(), surface, line[rows])
    # rows whose field-of-view edges miss the terrain (rays at or above the horizon) are left out
    missed = ~(np.isfinite(tracer.hits(-t)[0]) & np.isfinite(tracer.hits(t)[0]))
    if missed.any():
        oblique += int(np.count_nonzero((rows[missed] >= first) & (rows[missed] < first + lines)))
        rows = rows[~missed]
        tracer.keep(~missed)
        if rows.size == 0:
            return empty()
    cube = _split(tracer, surface, gsd, t)
    joined_rows = np.ones(max(len(rows) - 1, 0), bool)
    if len(rows) > 1:
        joined_rows = (np.diff(rows) == 1) & link[rows[:-1]]
    breaks = None if joined_rows.all() else ~joined_rows

    # Seams: the cube's line 0 joined to the opening row, its last line joined to the closing row.
    row_line = line[rows]
    seams: dict[int, _Split] = {}
    for a_line in ((-1, lines - 1) if lines >= 2 else ()):
        p = np.flatnonzero(row_line == a_line)
        if p.size == 0 or p[0] + 1 >= len(rows) or row_line[p[0] + 1] != a_line + 1 or not joined_rows[p[0]]:
            continue
        p = int(p[0])
        sl = slice(p, p + 2)
        s_pos = mid_pos[rows[sl]]
        s_att = mid_att[rows[sl]]
        s_origin = origin_of(s_pos)
        s_surface = surface_of(s_att, s_origin)
        s_tracer = _Tracer(s_pos, s_origin, s_att.as_matrix(), s_surface, row_line[sl])
        if not (np.isfinite(s_tracer.hits(-t)[0]).all() and np.isfinite(s_tracer.hits(t)[0]).all()):
            continue
        seams[p] = _split(s_tracer, s_surface, gsd, t)

    worst = max([cube.worst] + [s.worst for s in seams.values()])
    columns_of = lambda us: np.clip((us + t) / (2.0 * t), 0.0, 1.0)   # noqa: E731
    if not seams:
        return _regular_mesh(frame, cube, row_line, lines, fov_deg, joined_rows, breaks, gsd, no_navigation,
                             oblique, worst, columns_of(cube.us))
    return _stitched_mesh(frame, cube, seams, row_line, lines, fov_deg, joined_rows, breaks, gsd,
                          no_navigation, oblique, worst, columns_of)


def _regular_mesh(frame, cube: _Split, row_line, lines, fov_deg, joined_rows, breaks, gsd, no_navigation,
                  oblique, worst, columns) -> dict:
    """Every row on the cube's split: quads, with ``hidden`` flags per triangle."""
    hidden = None
    if len(row_line) > 1:
        hidden = _quad_hidden(cube, gsd)
    columns[0], columns[-1] = 0.0, 1.0
    return dict(ground=cube.pts[..., :2], depth=cube.lam, line=row_line, lines=lines, fov_deg=fov_deg,
                ground_height=math.nan, breaks=breaks,
                dropped={"no navigation": no_navigation, "view angle": oblique},
                columns=columns, distance=cube.rng, hidden=hidden, edge_error=worst)


def _quad_hidden(split: _Split, gsd: float) -> np.ndarray:
    """(R - 1, V - 1, 2) bool: the triangles of the quads between consecutive rows of ``split`` that
    have an edge spanning an occlusion."""
    pts, unit = split.pts, split.unit
    a, b = pts[:-1], pts[1:]                           # rows k and k + 1
    ua, ub = unit[:-1], unit[1:]
    across = split.occluded                            # (R, V - 1) along each row
    down = _edge_hidden(a, b, ua, ub, 0.5 * gsd)       # (R - 1, V): column edges
    diag = _edge_hidden(a[:, 1:], b[:, :-1], ua[:, 1:], ub[:, :-1], 0.5 * gsd)   # (R - 1, V - 1)
    tri1 = across[:-1] | diag | down[:, :-1]
    tri2 = down[:, 1:] | across[1:] | diag
    return np.stack([tri1, tri2], axis=-1)


def _stitched_mesh(frame, cube: _Split, seams: dict[int, _Split], row_line, lines, fov_deg, joined_rows,
                   breaks, gsd, no_navigation, oblique, worst, columns_of) -> dict:
    """Rows on the cube's split, the two rows of each seam on the seam's split, all vertices on the
    union of the splits (``active`` says which a row uses), and explicit ``faces``: quads between
    rows of one split, zipper strips between rows of different splits."""
    union = np.unique(np.concatenate([cube.us] + [s.us for s in seams.values()]))
    n_rows, v = len(row_line), union.size
    split_of = np.full(n_rows, -1)                     # -1: the cube's split, else the seam's first row
    for p in seams:
        split_of[p:p + 2] = p
    pts = np.zeros((n_rows, v, 3))
    unit = np.zeros((n_rows, v, 3))
    lam = np.ones((n_rows, v))
    rng = np.zeros((n_rows, v))
    active = np.zeros((n_rows, v), bool)
    col_index = {-1: np.searchsorted(union, cube.us)}
    own = split_of == -1
    idx = col_index[-1]
    for dst, src in ((pts, cube.pts), (unit, cube.unit), (lam, cube.lam), (rng, cube.rng)):
        dst[np.ix_(own, idx)] = src[own]
    active[np.ix_(own, idx)] = True
    for p, seam in seams.items():
        col_index[p] = idx = np.searchsorted(union, seam.us)
        for dst, src in ((pts, seam.pts), (unit, seam.unit), (lam, seam.lam), (rng, seam.rng)):
            dst[p:p + 2, idx] = src
        active[p:p + 2, idx] = True
    # columns a row does not use repeat its previous used vertex (never drawn; bounds stay true)
    fill = np.maximum.accumulate(np.where(active, np.arange(v)[None, :], 0), axis=1)
    for arr in (pts, unit, lam, rng):
        arr[...] = np.take_along_axis(arr, fill.reshape(fill.shape + (1,) * (arr.ndim - 2)), axis=1)

    # faces, in row order: quads where both rows use the cube's split (its hidden flags), else the
    # faces of the strip between the two rows' splits (one split: quads; two: a zipper)
    pieces: list[tuple[int, np.ndarray]] = []
    k = np.flatnonzero(joined_rows & own[:-1] & own[1:])
    if k.size:
        quads = _regular_faces(v, k, col_index[-1])
        hidden = _quad_hidden(cube, gsd)[k]
        for kk, f, h in zip(k, quads, hidden):
            pieces.append((int(kk), f[~h]))
    for kk in np.flatnonzero(joined_rows & ~(own[:-1] & own[1:])):
        ca, cb = col_index[split_of[kk]], col_index[split_of[kk + 1]]
        if split_of[kk] == split_of[kk + 1]:
            faces = _regular_faces(v, np.array([kk]), ca).reshape(-1, 3)
        else:
            z = zipper(union[ca], union[cb])
            cols = np.where(z[..., 0] == 0, ca[np.minimum(z[..., 1], ca.size - 1)],
                            cb[np.minimum(z[..., 1], cb.size - 1)])
            faces = v * (kk + z[..., 0]) + cols
        r, c = np.divmod(faces, v)
        p, d = pts[r, c], unit[r, c]
        hide = np.zeros(len(faces), bool)
        for e0, e1 in ((0, 1), (1, 2), (2, 0)):
            hide |= _edge_hidden(p[:, e0], p[:, e1], d[:, e0], d[:, e1], 0.5 * gsd)
        pieces.append((int(kk), faces[~hide].reshape(-1, 3)))
    pieces.sort(key=lambda item: item[0])
    faces = (np.concatenate([f.reshape(-1, 3) for _, f in pieces]) if pieces
             else np.zeros((0, 3), np.int64)).astype(np.int32)
    columns = columns_of(union)
    columns[0], columns[-1] = 0.0, 1.0
    return dict(ground=pts[..., :2], depth=lam, line=row_line, lines=lines, fov_deg=fov_deg,
                ground_height=math.nan, breaks=breaks,
                dropped={"no navigation": no_navigation, "view angle": oblique},
                columns=columns, distance=rng, hidden=None, edge_error=worst, active=active, faces=faces)
