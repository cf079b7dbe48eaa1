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
The caller decides whether neighbours follow closely enough to be joined (~1 frame interval).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial.transform import Rotation

from archive.errors import InputError, RenderError
from archive.navigation import ground_hits

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
    """

    frame: LocalFrame
    ground: np.ndarray
    depth: np.ndarray
    line: np.ndarray
    lines: int
    fov_deg: float
    ground_height: float

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

    def triangles(self) -> np.ndarray:
        """(2 * (rows - 1), 3) int32 vertex indices, two per quad, in line order.

        Vertex 2k is row k's left end, 2k + 1 its right end. The first triangle of each quad has
        row k's edge, the second row k+1's edge, so each row's segment is a triangle edge.
        """
        k = np.arange(max(self.rows - 1, 0), dtype=np.int32)[:, None]
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


def mid_exposure(time: np.ndarray, position: np.ndarray, attitude: Rotation, shutter_ms: float):
    """Poses at t_i + shutter/2: (position (n, 3), attitude (n,)) by interpolation towards line i+1.

    The last pose is extrapolated from the previous interval. time (n,) s, position (n, 3) m.
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
    half = shutter_ms / 2000.0
    frac = half / dt                               # (n-1,) fractions of the interval i -> i+1
    f = np.append(frac, frac[-1])                  # last: same fraction of the previous interval
    src = np.append(np.arange(n - 1), n - 2)       # interval (src -> dst) used for each pose
    dst = src + 1
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
) -> Mesh:
    """Ground mesh of one cube from its per-line exposure-start poses.

    poses: the cube's lines (time (lines,) s, position (lines, 3) NED m, attitude camera -> NED).
    fov_deg: across-track field of view, degrees. ground_height: metres, lcf altitude datum.
    shutter_ms: exposure, ms (mid-exposure poses, see the module docstring).
    framerate: Hz, only to check the shutter fits in a frame interval.
    closing: poses of the next cube's first line(s) (same frame): adds the row L = lines.
    opening: poses of the previous cube's last line(s) (same frame): adds the row L = -1.
    Raises RenderError when a field-of-view end ray does not point down to the ground.
    """
    if not (0 < fov_deg < 180):
        raise InputError("fov", f"field of view must be in (0, 180) degrees, got {fov_deg!r}")
    if shutter_ms < 0 or not math.isfinite(shutter_ms):
        raise InputError("shutter", f"shutter must be >= 0 ms, got {shutter_ms!r}")
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

    times = [np.asarray(poses.time, dtype=np.float64)]
    pos = [np.asarray(poses.position, dtype=np.float64)]
    att = [poses.attitude]
    first = 0
    if opening is not None:
        times.insert(0, np.asarray(opening.time, dtype=np.float64)[-1:])
        pos.insert(0, np.asarray(opening.position, dtype=np.float64)[-1:])
        att.insert(0, opening.attitude[-1:])
        first = 1
    if closing is not None:
        times.append(np.asarray(closing.time, dtype=np.float64)[:2])
        pos.append(np.asarray(closing.position, dtype=np.float64)[:2])
        att.append(closing.attitude[:2])
    mid_pos, mid_att = mid_exposure(
        np.concatenate(times), np.concatenate(pos), Rotation.concatenate(att), shutter_ms
    )
    stop = first + lines + (1 if closing is not None else 0)
    keep = slice(0, stop)
    mid_pos = mid_pos[keep]
    mid_att = mid_att[keep]
    line = np.arange(stop, dtype=np.float64) - first

    t = math.tan(math.radians(fov_deg) / 2)
    d_ground = float(frame.origin_alt) - float(ground_height)
    ground = np.empty((stop, 2, 2))
    depth = np.empty((stop, 2))
    for end, u in enumerate((-t, t)):
        points, lam, bad = ground_hits(mid_pos, mid_att, u, d_ground)
        if bad.any():
            row = int(np.argmax(bad))
            down = float(mid_att[row].apply(np.array([0.0, u, 1.0]))[2])
            raise RenderError(
                f"line {int(line[row])}: the {'left' if end == 0 else 'right'} field-of-view ray "
                f"does not reach the ground at {ground_height} m (camera at "
                f"{float(frame.origin_alt) - mid_pos[row, 2]:.1f} m, ray down component "
                f"{down:.3f}); check attitude, altitude and ground height"
            )
        ground[:, end] = points
        depth[:, end] = lam
    return Mesh(frame, ground, depth, line, lines, float(fov_deg), float(ground_height))
