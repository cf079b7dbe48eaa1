"""The ground mesh of one cube: where each image line's field-of-view ends meet the flat ground
(or, over a DEM, where the ends of the line's across-track segments meet the terrain: see
"Terrain meshes" below).

Row k of the mesh is one image line at its mid-exposure pose. Each row has two vertices, the rays
through the two ends of the line of samples (camera vectors (0, -t, 1) and (0, +t, 1),
t = tan(fov/2)) intersected with the ground plane. Each vertex carries

- its ground position (N, E), metres in the poses' local NED frame (float64 here),
- the line coordinate L (the line index within the cube; -1 for an opening row, ``lines`` for
  a closing row),
- the normalised sample coordinate s (0 at the left end u = -t, 1 at the right end u = +t),
- the ray depth lambda (camera-z distance to the ground: point = C + lambda * R (0, u, 1)).

Perspective-correct sample coordinate: along one row's ground segment, with screen (= ground)
barycentric weights b_k, the ground point is C + R (b0 lambda0 v0 + b1 lambda1 v1) with
v = (0, u, 1), so the true ray is lambda v = sum b_k lambda_k v_k: lambda = sum b_k lambda_k and
u lambda = sum b_k lambda_k u_k. Hence s = sum b_k lambda_k s_k / sum b_k lambda_k (exact along
each row, a smooth blend between rows). The renderer interpolates lambda*s and lambda without
perspective and divides per fragment.

Mid-exposure: line i integrates from its start time t_i for ``shutter_ms``; its pose is taken at
t_i + shutter/2, interpolated between line i's and line i+1's poses at the fraction
(shutter/2) / (t_{i+1} - t_i) (position linearly, attitude by slerp); the last row is extrapolated
from the previous interval at the same rate. Line i's span on the ground is then centred on its
row: L in [i - 0.5, i + 0.5) (see the renderer's fragment rule). To leave neither gap nor overlap
between consecutive cubes of a strip, a cube gets a closing row (the next cube's first line,
L = lines) and an opening row (the previous cube's last line, L = -1): the halves beyond
L = lines - 0.5 and below L = -0.5 belong to the neighbours and are discarded by the renderer.
The caller decides whether neighbours belong to the strip; rows are joined only when they follow
within MAX_JOIN_FRAMES frame intervals (:func:`archive.geometry.navigation.joined`), each row is moved to
mid-exposure with its OWN line's shutter (so that two cubes of different shutters meet exactly),
and lines without navigation or looking further than ``max_view_angle`` off nadir are left out:
the mesh is cut there (no quad spans a gap or a dropped line).

Terrain meshes (``build_mesh(..., terrain=dem, gsd=...)``)
--------------------------------------------------------

Segments: each row (line) is split into the same V - 1 across-track segments, at focal-plane
coordinates u_0 = -t < u_1 < ... < u_{V-1} = +t shared by every row of the cube, and every vertex
ray is intersected with the DEM (first hit, :meth:`archive.terrain.dem.Surface.intersect`). Quads join
consecutive rows and neighbouring columns; the sample coordinate s = (u + t) / 2t is
perspective-correct within a segment (lambda-weighted, as on flat ground).

Straight-edge bound: along a segment the mesh puts ray u on the 3-D chord between the segment's
two ground points (that is what the perspective-correct interpolation does), so its map position is
off by |lambda_true(u) - lambda_chord(u)| x |horizontal part of the ray|. Columns start at most
START_COLUMN (4) DEM pixels or output pixels wide on the ground (the larger), and a column is halved
(for every row of the cube) while that error, measured at the middle ray of any of its segments,
exceeds EDGE_ERROR_PX / 2 output pixels. A chord's deviation from a smoothly curved surface peaks at
the middle, and from a single bend (a DEM cell edge) anywhere along it, it is at least half its peak
at the middle: so the error anywhere along a segment stays under EDGE_ERROR_PX (0.1) output pixel.
(Several bends of opposite sense within one segment could hide more; columns no wider than a few DEM
pixels keep that to DEM detail that is itself below the check. Tests sample 1200 rays per line
densely and find the largest error equal to the midpoint estimate, <= 0.05 pixel.)
``edge_error`` records the largest midpoint error left (metres; columns stop halving after
MAX_LEVELS halvings or MAX_COLUMNS vertices per row).

Occlusion: an edge of the mesh (along a row, between rows, or a quad's diagonal) whose direction
is within GRAZING_DEG of the line of sight and which is longer than half a pixel on the map joins
ground points far apart in range: hidden ground (or ground seen at grazing incidence) lies between
them. Triangles with such an edge are left out (``hidden``), and columns holding such a segment in
any row are halved until its rays are OCCLUSION_PX apart on the ground, so the visible ground left
out beside an occlusion is under half a pixel wide. Where one line's remaining triangles still
fold over each other on the map, the GL depth test keeps the nearest (depth = distance from the
camera, :attr:`Mesh.distance`). Ground no line sees is never drawn: NaN in the output.

Watertight seams (the invariant; :mod:`archive.render.terrain` builds terrain meshes)
----------------------------------------------------------------------------------

**Every edge of a drawn triangle is either on the mesh's outer boundary or shared, vertex for
vertex, by exactly one other drawn triangle (of the same cube or of its strip neighbour); no vertex
lies on another triangle's edge (no T-junction).** Flat meshes have two vertices per row and hold it
trivially. Terrain meshes hold it so:

- Within a cube, every row uses the cube's split, except the two rows of each *seam* (the cube's line
  0 with its opening row, its last line with its closing row).
- The two rows of a seam are the same two image lines, at the same poses, in both cubes that share
  it. Their split and their ray hits are computed from those two rows only (their own DEM surface,
  :meth:`archive.terrain.dem.Dem.surface_under` of just their rays, refined by the same rule as a cube's), so
  both cubes get the same vertices, bit for bit, and the same quads between them: the half each cube
  draws (L below lines - 0.5, or from -0.5) meets the other half along the same line.
- Where consecutive rows use different splits (a seam row next to a row on the cube's split), the
  strip between them is stitched by a zipper (:func:`archive.render.terrain.zipper`): every segment
  of both rows is an edge of exactly one triangle of the strip.

A mesh stores every row on the union of its splits (:attr:`Mesh.active` says which columns a row
uses) and its triangles explicitly (:attr:`Mesh.faces`). tests/test_terrain_seams.py checks, in
float64 without GL, that the cubes of a strip cover every pixel centre inside the strip's outline,
and through GL that a render leaves no empty pixel on visible ground.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial.transform import Rotation

from archive.errors import InputError, RenderError
from archive.geometry.navigation import DEFAULT_MAX_VIEW_ANGLE, frame_interval, ground_hits, joined, view_angles
from archive.render.terrain import (EDGE_ERROR_PX, GRAZING_DEG, MAX_COLUMNS, MAX_LEVELS,  # noqa: F401 (re-exported)
                                    OCCLUSION_PX, START_COLUMN, terrain_mesh)


if TYPE_CHECKING:  # pragma: no cover
    from archive.geometry.navigation import LocalFrame, Poses


@dataclass(frozen=True, eq=False)
class Mesh:
    """Ground mesh of one cube (see module docstring).

    frame: the local NED frame of the poses (epsg, origin_e, origin_n, origin_alt).
    ground: (rows, 2, 2) float64: [row, end (0 = left/sample 0, 1 = right), (N, E)] metres local.
    depth: (rows, 2) float64 ray depth lambda, metres along camera z.
    line: (rows,) float64 line coordinate L of each row (-1 for an opening row, then 0, 1, ...).
    lines: number of image lines of the cube (rows with 0 <= L < lines hold its own lines).
    fov_deg, ground_height: the camera field of view (deg) and ground height (m) used.
    breaks: (rows - 1,) bool, True where rows k and k+1 are not joined (no quad between them:
        a time gap, or lines left out between them); None: every row joined to the next.
    dropped: lines of the cube left out, by reason ('no navigation', 'view angle').

    Terrain meshes (:func:`build_mesh` with ``terrain``) have ``V`` >= 2 vertices per row instead of
    two: ground (rows, V, 2), depth (rows, V), and
    columns: (V,) normalised sample coordinate s of each vertex column (None: [0, 1], the flat mesh);
    distance: (rows, V) metres from the camera to each vertex's ground point (the GL depth), or None;
    hidden: (rows - 1, V - 1, 2) bool, triangles left out because they span an occlusion, or None;
    edge_error: the largest straight-edge deviation measured at segment midpoints, metres (0 flat);
    active: (rows, V) bool, the columns each row uses, or None (every row uses every column): a
        cube's seam rows use the seam's split, its other rows the cube's ("Watertight seams" in the
        module docstring); vertices of unused columns repeat the row's previous used vertex;
    faces: (triangles, 3) int32 vertex indices drawn (stitched meshes), or None: the quads of
        :meth:`triangles`. A stitched mesh has ``hidden`` None (its hidden triangles are not in faces).
    """

    frame: LocalFrame
    ground: np.ndarray
    depth: np.ndarray
    line: np.ndarray
    lines: int
    fov_deg: float
    ground_height: float
    breaks: np.ndarray | None = None
    dropped: dict | None = None
    columns: np.ndarray | None = None
    distance: np.ndarray | None = None
    hidden: np.ndarray | None = None
    edge_error: float = 0.0
    active: np.ndarray | None = None
    faces: np.ndarray | None = None

    @property
    def rows(self) -> int:
        return int(self.line.shape[0])

    @property
    def epsg(self) -> int:
        return int(self.frame.epsg)

    def ground_utm(self) -> np.ndarray:
        """(rows, 2, 2) float64 vertex positions as UTM (E, N), metres."""
        out = np.empty_like(self.ground)
        out[..., 0] = self.ground[..., 1] + self.frame.origin_e
        out[..., 1] = self.ground[..., 0] + self.frame.origin_n
        return out

    def bounds_utm(self) -> tuple[float, float, float, float]:
        """(west, south, east, north) UTM metres of all vertices (opening/closing rows included)."""
        g = self.ground_utm().reshape(-1, 2)
        return (float(g[:, 0].min()), float(g[:, 1].min()), float(g[:, 0].max()), float(g[:, 1].max()))

    def to_epsg(self, epsg: int) -> Mesh:
        """The same mesh with its vertices transformed into the projected CRS ``epsg`` (a local
        frame about the vertices' mean, rounded to 1 m): how a flight of another UTM zone is
        rendered into a job's grid. Depths and line/sample coordinates are unchanged."""
        from archive.geometry.navigation import LocalFrame, reproject

        if int(epsg) == self.epsg:
            return self
        g = self.ground_utm().reshape(-1, 2)
        e, n = reproject(g[:, 0], g[:, 1], self.epsg, int(epsg))
        frame = LocalFrame(int(epsg), float(np.round(np.mean(e))) if e.size else 0.0,
                           float(np.round(np.mean(n))) if n.size else 0.0, self.frame.origin_alt)
        ground = np.stack([n - frame.origin_n, e - frame.origin_e], axis=-1).reshape(self.ground.shape)
        return dataclasses.replace(self, frame=frame, ground=ground)

    @property
    def per_row(self) -> int:
        """Vertices per row: 2 for a flat mesh, V for a terrain mesh."""
        return int(self.ground.shape[1])

    def triangles(self) -> np.ndarray:
        """(2 * quads, 3) int32 vertex indices, two per quad, in line order (then column order).

        Vertex V k + j is row k's vertex j (V = :attr:`per_row`; flat meshes: 2k is row k's left
        end, 2k + 1 its right end). The first triangle of each quad has row k's edge, the second
        row k+1's edge, so each row's segment is a triangle edge. Quads between rows that are not
        joined (``breaks``) and triangles of terrain meshes that span an occlusion (``hidden``) are
        left out. A stitched terrain mesh returns its explicit :attr:`faces` (same order: by row pair).
        """
        if self.faces is not None:
            return self.faces
        v = self.per_row
        k = np.arange(max(self.rows - 1, 0), dtype=np.int32)
        if self.breaks is not None:
            k = k[~np.asarray(self.breaks, bool)]
        j = np.arange(v - 1, dtype=np.int32)
        a = (v * k[:, None] + j[None, :])[..., None]                 # (quads along, across, 1)
        first = a + np.array([0, 1, v], dtype=np.int32)
        second = a + np.array([1, v + 1, v], dtype=np.int32)
        tri = np.stack([first, second], axis=2)                       # (k, j, 2, 3)
        if self.hidden is not None:
            return tri[~np.asarray(self.hidden, bool)[k]].reshape(-1, 3)
        return tri.reshape(-1, 3)

    def vertex_attributes(self) -> tuple[np.ndarray, np.ndarray]:
        """Per vertex (V * rows): (N, E) float64 local metres (rows, 2) and (L, s, lambda) float64."""
        v = self.per_row
        pos = self.ground.reshape(-1, 2)
        attr = np.empty((self.rows * v, 3))
        attr[:, 0] = np.repeat(self.line, v)
        attr[:, 1] = np.tile([0.0, 1.0] if self.columns is None else self.columns, self.rows)
        attr[:, 2] = self.depth.reshape(-1)
        return pos, attr

    def sample_at(self, row: int, weight_right: float) -> float:
        """Normalised sample coordinate s at the ground point (1 - w) P_left + w P_right of a row."""
        lam0, lam1 = self.depth[row]
        return float(weight_right * lam1 / ((1 - weight_right) * lam0 + weight_right * lam1))


def mid_exposure(time: np.ndarray, position: np.ndarray, attitude: Rotation, shutter_ms,
                 link: np.ndarray | None = None):
    """Poses at t_i + shutter_i/2: (position (n, 3), attitude (n,)) by interpolation towards line i+1.

    time (n,) s, position (n, 3) m; shutter_ms: one exposure (ms) or one per line (n,).
    link: (n-1,) bool, False where lines i and i+1 are not joined (a gap, a line without
    navigation): line i is then shifted along its previous interval instead (if joined to it), as
    is the last line; a line joined to neither keeps its start pose.
    """
    n = len(time)
    if n < 2:
        return position.copy(), attitude
    dt = np.diff(time)
    if not np.all(dt > 0):
        bad = int(np.argmin(dt > 0))
        raise InputError(
            "poses", f"line times must increase; line {bad + 1} is {dt[bad]:.6g} s after line {bad}",
            "check the .times file and the lines of the cube",
        )
    half = np.broadcast_to(np.asarray(shutter_ms, float) / 2000.0, (n,))
    link = np.ones(n - 1, bool) if link is None else np.asarray(link, bool)
    forward = np.append(link, False)            # line i may use interval i -> i+1
    backward = np.insert(link, 0, False)        # line i may use interval i-1 -> i
    src = np.where(forward, np.arange(n), np.arange(n) - 1)
    use = forward | backward
    src = np.clip(np.where(use, src, 0), 0, n - 2)
    dst = src + 1
    f = np.where(use, half / dt[src], 0.0)      # fraction of the interval used by each line
    mid_pos = position + f[:, None] * (position[dst] - position[src])
    delta = (attitude[src].inv() * attitude[dst]).as_rotvec()   # body-frame step of the interval
    mid_att = attitude * Rotation.from_rotvec(delta * f[:, None])
    return mid_pos, mid_att


def build_mesh(
    poses: Poses,
    fov_deg: float,
    ground_height: float,
    shutter_ms: float,
    framerate: float,
    closing: Poses | None = None,
    opening: Poses | None = None,
    closing_shutter_ms: float | None = None,
    opening_shutter_ms: float | None = None,
    max_view_angle: float | None = DEFAULT_MAX_VIEW_ANGLE,
    terrain=None,
    gsd: float | None = None,
) -> Mesh:
    """Ground mesh of one cube from its per-line exposure-start poses.

    poses: the cube's lines (time (lines,) s, position (lines, 3) NED m, attitude camera -> NED,
    ``valid``: lines without navigation). fov_deg: across-track field of view, degrees.
    ground_height: metres, lcf altitude datum. shutter_ms: exposure, ms (mid-exposure poses, see
    the module docstring); framerate: Hz (the frame interval of the strip rule, and to check the
    shutter fits in a frame interval; 0: the median line step).
    closing: poses of the next cube's first line(s) (same frame): adds the row L = lines, exposed
    for ``closing_shutter_ms`` (default: ``shutter_ms``). opening: poses of the previous cube's last
    line(s): adds the row L = -1, exposed for ``opening_shutter_ms``. The caller decides that the
    neighbours belong to the strip; rows more than MAX_JOIN_FRAMES intervals apart are never joined.
    max_view_angle: degrees off nadir of a field-of-view edge beyond which a line is left out
    (None: no limit). Lines without navigation, beyond the limit, or whose edge rays miss the
    ground are left out; the mesh is cut there (:attr:`Mesh.breaks`) and ``dropped`` counts them.
    terrain: None (flat ground at ``ground_height``) or a DEM (:class:`archive.terrain.dem.Dem`, anything with
    ``surface_under``): then the mesh follows the terrain (module docstring, "Terrain meshes"), ``gsd`` (the output
    pixel, m) setting how finely; ``ground_height`` is not used (NaN in the mesh).
    """
    if not (0 < fov_deg < 180):
        raise InputError("fov", f"field of view must be in (0, 180) degrees, got {fov_deg!r}")
    for name, value in (("shutter", shutter_ms), ("closing shutter", closing_shutter_ms),
                        ("opening shutter", opening_shutter_ms)):
        if value is not None and (value < 0 or not math.isfinite(value)):
            raise InputError("shutter", f"{name} must be >= 0 ms, got {value!r}")
    if framerate and framerate > 0 and shutter_ms / 1000.0 > 1.05 / framerate:
        raise InputError(
            "shutter", f"shutter {shutter_ms} ms is longer than the frame interval "
            f"{1000.0 / framerate:.4g} ms at {framerate} Hz", "check the header's shutter and framerate",
        )
    frame = poses.frame
    lines = len(poses.time)
    if lines == 0:
        raise InputError("poses", "a cube needs at least one line")
    for name, extra in (("closing", closing), ("opening", opening)):
        if extra is not None and extra.frame != frame:
            raise InputError(name, f"{name} poses are in another local frame than the cube's",
                             "build all poses of a flight in one LocalFrame")

    def valid_of(p: Poses, sl: slice) -> np.ndarray:
        n = len(np.asarray(p.time)[sl])
        return np.ones(n, bool) if p.valid is None else np.asarray(p.valid, bool)[sl]

    times = [np.asarray(poses.time, dtype=np.float64)]
    pos = [np.asarray(poses.position, dtype=np.float64)]
    att = [poses.attitude]
    valid = [valid_of(poses, slice(None))]
    shutters = [np.full(lines, float(shutter_ms))]
    first = 0
    if opening is not None:
        times.insert(0, np.asarray(opening.time, dtype=np.float64)[-1:])
        pos.insert(0, np.asarray(opening.position, dtype=np.float64)[-1:])
        att.insert(0, opening.attitude[-1:])
        valid.insert(0, valid_of(opening, slice(-1, None)))
        shutters.insert(0, np.full(1, float(shutter_ms if opening_shutter_ms is None else opening_shutter_ms)))
        first = 1
    if closing is not None:
        times.append(np.asarray(closing.time, dtype=np.float64)[:2])
        pos.append(np.asarray(closing.position, dtype=np.float64)[:2])
        att.append(closing.attitude[:2])
        valid.append(valid_of(closing, slice(0, 2)))
        shutters.append(np.full(len(times[-1]), float(shutter_ms if closing_shutter_ms is None
                                                      else closing_shutter_ms)))
    time = np.concatenate(times)
    valid_all = np.concatenate(valid)
    interval = frame_interval(framerate if framerate and framerate > 0 else None, np.asarray(poses.time))
    link = joined(np.diff(time), interval) & valid_all[:-1] & valid_all[1:] if len(time) > 1 else np.zeros(0, bool)
    mid_pos, mid_att = mid_exposure(time, np.concatenate(pos), Rotation.concatenate(att),
                                    np.concatenate(shutters), link)
    stop = first + lines + (1 if closing is not None else 0)
    mid_pos = mid_pos[:stop]
    mid_att = mid_att[:stop]
    keep = valid_all[:stop].copy()
    link = link[: stop - 1]
    line = np.arange(stop, dtype=np.float64) - first
    no_navigation = int(np.count_nonzero(~keep[first:first + lines]))

    oblique = 0
    if max_view_angle is not None:
        angles = view_angles(mid_att, fov_deg)
        too_far = keep & (angles > float(max_view_angle))
        oblique = int(np.count_nonzero(too_far[first:first + lines]))
        keep &= ~too_far

    if terrain is not None:
        return Mesh(frame, **terrain_mesh(frame, mid_pos, mid_att, keep, link, line, lines, first,
                                           float(fov_deg), terrain, gsd, no_navigation, oblique))
    t = math.tan(math.radians(fov_deg) / 2)
    d_ground = float(frame.origin_alt) - float(ground_height)
    below = keep & (mid_pos[:, 2] >= d_ground)
    if below.any():
        row = int(np.argmax(below))
        raise RenderError(
            f"line {int(line[row])}: the camera ({float(frame.origin_alt) - mid_pos[row, 2]:.1f} m) is at or below "
            f"the ground at {ground_height} m: a ray does not reach the ground; check the ground height")
    ground = np.zeros((stop, 2, 2))
    depth = np.ones((stop, 2))
    missed = np.zeros(stop, bool)
    for end, u in enumerate((-t, t)):
        points, lam, bad = ground_hits(mid_pos, mid_att, u, d_ground)
        missed |= bad
        ground[:, end] = np.where(bad[:, None], 0.0, points)
        depth[:, end] = np.where(bad, 1.0, lam)
    above = keep & missed
    if max_view_angle is None and above.any():
        row = int(np.argmax(above))
        raise RenderError(
            f"line {int(line[row])}: a field-of-view ray does not reach the ground at {ground_height} m "
            f"(camera at {float(frame.origin_alt) - mid_pos[row, 2]:.1f} m); check attitude, altitude and "
            "ground height")
    oblique += int(np.count_nonzero(above[first:first + lines]))
    keep &= ~missed
    # Rows kept, and where consecutive kept rows are not joined (a gap, or dropped lines between).
    rows = np.flatnonzero(keep)
    joined_rows = np.ones(max(len(rows) - 1, 0), bool)
    if len(rows) > 1:
        consecutive = np.diff(rows) == 1
        joined_rows = consecutive & link[rows[:-1]]
    return Mesh(frame, ground[rows], depth[rows], line[rows], lines, float(fov_deg), float(ground_height),
                breaks=None if joined_rows.all() else ~joined_rows,
                dropped={"no navigation": no_navigation, "view angle": oblique})
