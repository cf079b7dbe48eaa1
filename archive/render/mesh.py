"""The ground mesh of one cube: where each image line's field-of-view ends meet the flat ground.

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
within MAX_JOIN_FRAMES frame intervals (:func:`archive.navigation.joined`), each row is moved to
mid-exposure with its OWN line's shutter (so that two cubes of different shutters meet exactly),
and lines without navigation or looking further than ``max_view_angle`` off nadir are left out:
the mesh is cut there (no quad spans a gap or a dropped line).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial.transform import Rotation

from archive.errors import InputError, RenderError
from archive.navigation import DEFAULT_MAX_VIEW_ANGLE, frame_interval, ground_hits, joined, view_angles

if TYPE_CHECKING:  # pragma: no cover
    from archive.navigation import LocalFrame, Poses


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
        from archive.navigation import LocalFrame, reproject

        if int(epsg) == self.epsg:
            return self
        g = self.ground_utm().reshape(-1, 2)
        e, n = reproject(g[:, 0], g[:, 1], self.epsg, int(epsg))
        frame = LocalFrame(int(epsg), float(np.round(np.mean(e))) if e.size else 0.0,
                           float(np.round(np.mean(n))) if n.size else 0.0, self.frame.origin_alt)
        ground = np.stack([n - frame.origin_n, e - frame.origin_e], axis=-1).reshape(self.ground.shape)
        return dataclasses.replace(self, frame=frame, ground=ground)

    def triangles(self) -> np.ndarray:
        """(2 * (rows - 1), 3) int32 vertex indices, two per quad, in line order.

        Vertex 2k is row k's left end, 2k + 1 its right end. The first triangle of each quad has
        row k's edge, the second row k+1's edge, so each row's segment is a triangle edge.
        """
        k = np.arange(max(self.rows - 1, 0), dtype=np.int32)
        if self.breaks is not None:
            k = k[~np.asarray(self.breaks, bool)]
        k = k[:, None]
        first = 2 * k + np.array([0, 1, 2], dtype=np.int32)
        second = 2 * k + np.array([1, 3, 2], dtype=np.int32)
        return np.stack([first, second], axis=1).reshape(-1, 3)

    def vertex_attributes(self) -> tuple[np.ndarray, np.ndarray]:
        """Per vertex (2 * rows): (N, E) float64 local metres (rows, 2) and (L, s, lambda) float64."""
        pos = self.ground.reshape(-1, 2)
        attr = np.empty((self.rows * 2, 3))
        attr[:, 0] = np.repeat(self.line, 2)
        attr[:, 1] = np.tile([0.0, 1.0], self.rows)
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
