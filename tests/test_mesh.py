"""Ground mesh: vertex positions against analytic swaths, perspective-correct sample coordinate."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from archive.errors import RenderError
from archive.geometry.navigation import LocalFrame, Poses
from archive.render.mesh import build_mesh, mid_exposure
from helpers import FOV

T = math.tan(math.radians(FOV / 2))
FRAME = LocalFrame(32616, 500000.0, 3900000.0, 100.0)


def flight(lines=50, rate=250.0, speed=10.0, alt=150.0, t0=1000.0, n0=0.0, attitude=None):
    """Camera flying due north at ``speed`` m/s, ``alt`` m above the ellipsoid (frame origin 100 m)."""
    t = t0 + np.arange(lines) / rate
    pos = np.zeros((lines, 3))
    pos[:, 0] = n0 + speed * (t - 1000.0)
    pos[:, 2] = FRAME.origin_alt - alt
    att = Rotation.identity(lines) if attitude is None else attitude
    return Poses(t, pos, att, FRAME)


def test_nadir_vertices_are_the_analytic_swath_edges():
    rate, shutter = 250.0, 3.0
    poses = flight(rate=rate)
    mesh = build_mesh(poses, FOV, 110.0, shutter, rate)        # 40 m above the ground
    assert mesh.rows == 50 and mesh.lines == 50
    mid_n = 10.0 * (np.arange(50) / rate + shutter / 2000.0)   # mid-exposure northings
    np.testing.assert_allclose(mesh.ground[:, 0, 0], mid_n, atol=1e-9)
    np.testing.assert_allclose(mesh.ground[:, 1, 0], mid_n, atol=1e-9)
    np.testing.assert_allclose(mesh.ground[:, 0, 1], -40.0 * T, atol=1e-9)   # left end: west
    np.testing.assert_allclose(mesh.ground[:, 1, 1], +40.0 * T, atol=1e-9)
    np.testing.assert_allclose(mesh.depth, 40.0)
    np.testing.assert_array_equal(mesh.line, np.arange(50))
    w, s, e, n = mesh.bounds_utm()
    assert w == pytest.approx(500000.0 - 40 * T) and e == pytest.approx(500000.0 + 40 * T)
    assert s == pytest.approx(3900000.0 + mid_n[0]) and n == pytest.approx(3900000.0 + mid_n[-1])
    tri = mesh.triangles()
    assert tri.shape == (98, 3)
    np.testing.assert_array_equal(tri[:2], [[0, 1, 2], [1, 3, 2]])
    assert tri.max() == 99


def test_opening_and_closing_rows_come_from_the_neighbours():
    rate = 250.0
    whole = flight(lines=30, rate=rate)
    part = lambda a, b: Poses(whole.time[a:b], whole.position[a:b], whole.attitude[a:b], FRAME)  # noqa: E731
    alone = build_mesh(whole, FOV, 110.0, 2.0, rate)
    mesh = build_mesh(part(10, 20), FOV, 110.0, 2.0, rate, closing=part(20, 30), opening=part(0, 10))
    np.testing.assert_array_equal(mesh.line, np.arange(-1, 11))
    assert mesh.lines == 10
    np.testing.assert_allclose(mesh.ground, alone.ground[9:21], atol=1e-9)


def test_rolled_camera_sample_coordinate_is_perspective_correct():
    """Along a line's ground segment, s from lambda-weighted barycentrics = the pinhole sample."""
    roll = Rotation.from_euler("ZYX", [[0.3, 0.05, math.radians(10.0)]] * 20)
    poses = flight(lines=20, attitude=roll)
    mesh = build_mesh(poses, FOV, 110.0, 0.0, 250.0)
    row = 7
    centre = poses.position[row]
    r = poses.attitude[row]
    left, right = mesh.ground[row]
    worst_linear = 0.0
    for w in np.linspace(0, 1, 41):
        ned = np.array([*(1 - w) * left + w * right, FRAME.origin_alt - 110.0])
        q = r.inv().apply(ned - centre)                       # camera frame
        u = q[1] / q[2]
        s_true = (u + T) / (2 * T)
        assert mesh.sample_at(row, w) == pytest.approx(s_true, abs=1e-9)
        worst_linear = max(worst_linear, abs(w - s_true))
    # Linear interpolation in ground space would be wrong by far more than a sample of 1000.
    assert worst_linear > 2e-3
    # Each vertex lies on its ray: position + lambda * R (0, u, 1).
    for end, u in ((0, -T), (1, T)):
        p = centre + mesh.depth[row, end] * r.apply([0.0, u, 1.0])
        np.testing.assert_allclose(p[:2], mesh.ground[row, end], atol=1e-9)
        assert p[2] == pytest.approx(FRAME.origin_alt - 110.0)


def test_mid_exposure_interpolates_and_extrapolates():
    t = np.array([0.0, 0.004, 0.008, 0.0125])
    pos = np.stack([t * 10, np.zeros(4), np.zeros(4)], axis=1)
    yaw = np.array([0.0, 0.01, 0.02, 0.04])
    att = Rotation.from_euler("z", yaw[:, None])
    mpos, matt = mid_exposure(t, pos, att, 2.0)
    np.testing.assert_allclose(mpos[:, 0], (t + 0.001) * 10)
    frac = 0.001 / np.array([0.004, 0.004, 0.0045, 0.0045])
    expected = yaw + frac * np.array([0.01, 0.01, 0.02, 0.02])
    np.testing.assert_allclose(matt.as_euler("ZYX")[:, 0], expected, atol=1e-12)


def test_ray_above_horizon_is_a_render_error_without_a_view_limit():
    att = Rotation.from_euler("x", [[math.radians(80.0)]] * 5)
    with pytest.raises(RenderError, match="does not reach the ground"):
        build_mesh(flight(lines=5, attitude=att), FOV, 110.0, 0.0, 250.0, max_view_angle=None)
    # with the view-angle limit (the default) such lines are left out and counted
    mesh = build_mesh(flight(lines=5, attitude=att), FOV, 110.0, 0.0, 250.0)
    assert mesh.rows == 0 and mesh.dropped["view angle"] == 5
    with pytest.raises(RenderError, match="does not reach the ground"):   # ground above the camera
        build_mesh(flight(lines=5), FOV, 200.0, 0.0, 250.0)
