"""Navigation: UTM frame, grid convergence, track from .lcf, pose interpolation (synthetic and simulated)."""

from __future__ import annotations

import numpy as np
import pytest
from pyproj import Proj
from scipy.spatial.transform import Rotation

from archive.errors import NavigationError
from archive.formats.lcf import LcfData
from archive.geometry.navigation import (
    LocalFrame,
    Track,
    boresight_rotation,
    grid_convergence,
    interpolate_poses,
    line_times,
    local_frame_for,
    project,
    track_from_lcf,
    utm_epsg_for,
)

MEMPHIS = (-89.94, 35.12)  # lon, lat: 2.94 deg west of zone 16's central meridian (87 W)
DEG = np.pi / 180


def _lcf(time, lon, lat, alt, roll=0.0, pitch=0.0, yaw=0.0, path=None) -> LcfData:
    time = np.asarray(time, float)
    full = [np.broadcast_to(np.asarray(v, float), time.shape).copy() for v in (roll, pitch, yaw, lon, lat, alt)]
    return LcfData(path=path, time=time, roll=full[0], pitch=full[1], yaw=full[2], lon=full[3], lat=full[4],
                   alt=full[5])


def _ground_point(position: np.ndarray, attitude: Rotation, u: float, ground_d: float) -> np.ndarray:
    """NED point where the ray of focal-plane coordinate u meets the flat ground D = ground_d."""
    ray = attitude.apply([0.0, u, 1.0])
    s = (ground_d - position[2]) / ray[2]
    return position + s * ray


# --- zones and frames -------------------------------------------------------------------------

@pytest.mark.parametrize(
    "lon, lat, epsg",
    [(-89.94, 35.12, 32616), (-87.0, 35.0, 32616), (-93.01, 35.0, 32615), (15.0, 67.2, 32633),
     (-70.6, -33.4, 32719), (5.5, 60.0, 32632), (2.0, 60.0, 32631), (15.0, 78.0, 32633),
     (10.0, 78.0, 32633), (179.99, 10.0, 32660), (-180.0, 10.0, 32601), (0.5, 0.0, 32631)],
)
def test_utm_epsg_for(lon, lat, epsg):
    assert utm_epsg_for(lon, lat) == epsg


def test_local_frame_round_trip_and_origin():
    lcf = _lcf([0.0, 1.0], lon=[MEMPHIS[0], MEMPHIS[0]], lat=[MEMPHIS[1], MEMPHIS[1] + 1e-4], alt=[120.0, 121.0])
    frame = local_frame_for(lcf)
    e, n = project(MEMPHIS[0], MEMPHIS[1], 32616)
    assert frame.epsg == 32616
    assert frame.origin_e == np.round(e) and frame.origin_n == np.round(n) and frame.origin_alt == 0.0
    ned = frame.to_ned(np.array([e, e + 3.0]), np.array([n, n - 2.0]), np.array([120.0, 100.0]))
    np.testing.assert_allclose(ned[1] - ned[0], [-2.0, 3.0, 20.0], atol=1e-9)
    np.testing.assert_allclose(ned[0], [n - frame.origin_n, e - frame.origin_e, -120.0], atol=1e-9)
    back = frame.from_ned(ned)
    np.testing.assert_allclose(back[0], [e, e + 3.0], atol=1e-9)
    np.testing.assert_allclose(back[2], [120.0, 100.0], atol=1e-9)


# --- grid convergence -------------------------------------------------------------------------

def test_grid_convergence_memphis_value_and_sign():
    lon, lat = MEMPHIS
    c = float(grid_convergence(lon, lat, 32616))
    # |gamma| = atan(tan(dlon) sin(lat)) = 1.69 deg; west of the central meridian true north leans
    # east on the grid, so the angle to ADD to a true heading is positive.
    assert np.degrees(c) == pytest.approx(1.6924, abs=2e-3)
    assert np.degrees(c) == pytest.approx(-Proj(32616).get_factors(lon, lat).meridian_convergence, abs=1e-5)
    # A point 1 km due true north lies at grid bearing c.
    e0, n0 = project(lon, lat, 32616)
    e1, n1 = project(lon, lat + 1000.0 / 110_950.0, 32616)
    assert np.arctan2(e1 - e0, n1 - n0) == pytest.approx(c, abs=1e-5)
    # Conformal: a point due true east lies at grid bearing 90 deg + c.
    e2, n2 = project(lon + 1e-4, lat, 32616)
    assert np.arctan2(e2 - e0, n2 - n0) == pytest.approx(np.pi / 2 + c, abs=1e-5)
    # East of the meridian and in the south the sign flips.
    assert grid_convergence(-84.0, 35.12, 32616) < 0
    assert grid_convergence(-89.94, -35.12, 32716) < 0
    assert abs(grid_convergence(-87.0, 35.12, 32616)) < 1e-9
    vec = grid_convergence(np.array([-89.94, -84.0]), np.array([35.12, 35.12]), 32616)
    assert vec.shape == (2,) and vec[0] == pytest.approx(c)


def test_track_heading_is_grid_corrected():
    lon, lat = MEMPHIS
    lcf = _lcf([0.0, 0.005], lon=lon, lat=lat, alt=100.0, yaw=[0.0, np.pi / 2])
    frame = local_frame_for(lcf)
    track = track_from_lcf(lcf, frame)
    c = float(grid_convergence(lon, lat, frame.epsg))
    fwd = track.attitude.apply([1.0, 0.0, 0.0])  # body x in NED
    assert np.arctan2(fwd[0, 1], fwd[0, 0]) == pytest.approx(c, abs=1e-9)
    assert np.arctan2(fwd[1, 1], fwd[1, 0]) == pytest.approx(np.pi / 2 + c, abs=1e-9)


def test_skipping_convergence_moves_the_swath_edge_by_half_a_metre():
    """40 m above ground, 47.5 deg FOV, flying true north at Memphis: the swath edge moves ~0.5 m
    (13 pixels of 4 cm) if the heading is not corrected."""
    lon, lat = MEMPHIS
    lcf = _lcf([0.0, 0.005], lon=lon, lat=lat, alt=140.0)
    frame = local_frame_for(lcf)
    track = track_from_lcf(lcf, frame)
    ground_d = frame.origin_alt - 100.0
    uncorrected = Rotation.from_euler("ZYX", [0.0, 0.0, 0.0])
    u = np.tan(np.radians(47.5 / 2))
    p = track.position[0]
    right = _ground_point(p, track.attitude[0], u, ground_d)
    wrong = _ground_point(p, uncorrected, u, ground_d)
    dist = np.linalg.norm(right - wrong)
    assert dist > 0.04
    c = float(grid_convergence(lon, lat, frame.epsg))
    expected = 2 * 40 * u * np.sin(c / 2)  # chord of the edge point (40 u from nadir) turned by c
    assert dist == pytest.approx(expected, rel=1e-3)
    assert 0.45 < dist < 0.6


# --- tracks and interpolation -----------------------------------------------------------------

def test_straight_flight_north_interpolates_positions():
    """Along the central meridian (no convergence), 10 m/s north at 200 Hz."""
    t = 1_340_119_934.235 + np.arange(200) * 0.005  # real-size GPS seconds
    lat0 = 35.12
    lat = lat0 + np.arange(200) * 0.05 / 110_950.0
    lcf = _lcf(t, lon=-87.0, lat=lat, alt=140.0)
    frame = local_frame_for(lcf)
    track = track_from_lcf(lcf, frame)
    np.testing.assert_allclose(np.diff(track.position[:, 0]), 0.05, atol=1e-4)
    np.testing.assert_allclose(track.position[:, 1], track.position[0, 1], atol=1e-6)
    np.testing.assert_allclose(track.position[:, 2], -140.0)
    assert track.attitude.magnitude() == pytest.approx(np.zeros(200), abs=1e-12)
    q = t[10] + np.array([0.0, 0.00125, 0.0025, 0.9])
    poses = interpolate_poses(track, q, frame)
    i = np.searchsorted(t, q, side="right") - 1
    w = (q - t[i]) / 0.005
    expected = track.position[i] * (1 - w[:, None]) + track.position[i + 1] * w[:, None]
    np.testing.assert_allclose(poses.position, expected, atol=1e-6)
    # against the projection of the interpolated latitude (linear within a 5 cm step)
    e, n = project(-87.0, np.interp(q - t[0], t - t[0], lat), frame.epsg)
    np.testing.assert_allclose(poses.utm()[:, 1], n, atol=1e-6)
    np.testing.assert_allclose(poses.utm()[:, 0], e, atol=1e-6)
    np.testing.assert_allclose(poses.time, q)
    assert poses.frame == frame


def _track(n=201, dt=0.005, yaw=None, roll=None, pitch=None, speed=(10.0, 0.0, 0.0)) -> Track:
    time = 1000.0 + np.arange(n) * dt
    zeros = np.zeros(n)
    euler = np.stack([zeros if yaw is None else yaw, zeros if pitch is None else pitch,
                      zeros if roll is None else roll], axis=-1)
    pos = np.outer(time - time[0], speed) + np.array([0.0, 0.0, -40.0])
    return Track(time=time, position=pos, attitude=Rotation.from_euler("ZYX", euler))


FRAME = LocalFrame(epsg=32616, origin_e=500_000.0, origin_n=3_900_000.0, origin_alt=0.0)


def test_slerp_of_known_rotation():
    # yaw 0 -> 10 deg and roll 0 -> -4 deg between two samples 1 s apart: slerp of a rotation
    # about one axis is linear in angle; the combined one is checked against its rotation vector.
    track = Track(time=np.array([0.0, 1.0]), position=np.zeros((2, 3)),
                  attitude=Rotation.from_euler("ZYX", [[0, 0, 0], [10 * DEG, 0, 0]]))
    poses = interpolate_poses(track, np.array([0.25, 0.5, 1.0]), FRAME)
    np.testing.assert_allclose(poses.attitude.as_euler("ZYX", degrees=True)[:, 0], [2.5, 5.0, 10.0], atol=1e-9)
    end = Rotation.from_euler("ZYX", [10 * DEG, 0, -4 * DEG])
    track = Track(time=np.array([0.0, 1.0]), position=np.zeros((2, 3)),
                  attitude=Rotation.concatenate([Rotation.identity(), end]))
    mid = interpolate_poses(track, np.array([0.3]), FRAME).attitude[0]
    expected = Rotation.from_rotvec(0.3 * end.as_rotvec())
    assert (mid.inv() * expected).magnitude() < 1e-12
    assert mid.magnitude() == pytest.approx(0.3 * end.magnitude(), rel=1e-12)


def test_roll_sign_right_wing_up_looks_right():
    lcf = _lcf([0.0, 0.005], lon=-87.0, lat=35.0, alt=100.0, roll=5 * DEG)
    frame = local_frame_for(lcf)
    poses = interpolate_poses(track_from_lcf(lcf, frame), np.array([0.0]), frame)
    # banking left (right wing up), the belly and the nadir ray turn to the right: east when flying north
    np.testing.assert_allclose(poses.attitude.apply([0, 0, 1])[0], [0, np.sin(5 * DEG), np.cos(5 * DEG)], atol=1e-9)
    # and the right wing tip (camera y) rises
    assert poses.attitude.apply([0, 1, 0])[0, 2] == pytest.approx(-np.sin(5 * DEG))


def test_boresight_and_lever_arm():
    # flying east (yaw 90 deg), level, 40 m above the ground
    track = _track(yaw=np.full(201, 90 * DEG), speed=(0.0, 10.0, 0.0))
    t = np.array([1000.1])
    plain = interpolate_poses(track, t, FRAME)
    np.testing.assert_allclose(plain.position[0], [0.0, 1.0, -40.0], atol=1e-9)
    # the line of samples (camera y) points south when flying east
    np.testing.assert_allclose(plain.attitude.apply([0, 1, 0])[0], [-1, 0, 0], atol=1e-12)
    # lever arm 1 m forward, 0.5 m down in the body -> 1 m east, 0.5 m down in NED
    levered = interpolate_poses(track, t, FRAME, lever_arm=(1.0, 0.0, 0.5))
    np.testing.assert_allclose(levered.position[0], [0.0, 2.0, -39.5], atol=1e-9)
    # boresight pitch +2 deg: the camera looks 2 deg forward -> nadir ground point 40 tan 2 deg east
    b = boresight_rotation((0.0, 2.0, 0.0))
    tilted = interpolate_poses(track, t, FRAME, boresight=b)
    g0 = _ground_point(plain.position[0], plain.attitude[0], 0.0, 0.0)
    g1 = _ground_point(tilted.position[0], tilted.attitude[0], 0.0, 0.0)
    np.testing.assert_allclose(g1 - g0, [0.0, 40 * np.tan(2 * DEG), 0.0], atol=1e-9)
    # boresight yaw 90 deg: camera x (line top) points along body y (right wing) = south
    yawed = interpolate_poses(track, t, FRAME, boresight=boresight_rotation((0.0, 0.0, 90.0)))
    np.testing.assert_allclose(yawed.attitude.apply([1, 0, 0])[0], [-1, 0, 0], atol=1e-12)
    # lever arm on the right wing with the right wing 10 deg up (roll_lcf +10 -> roll_aero -10)
    rolled = _track(roll=np.full(201, -10 * DEG))
    p = interpolate_poses(rolled, t, FRAME, lever_arm=(0.0, 1.0, 0.0)).position[0]
    np.testing.assert_allclose(p, [1.0, np.cos(10 * DEG), -40.0 - np.sin(10 * DEG)], atol=1e-9)


def test_line_times():
    times = np.array([263.873396, 263.877412, 263.881428])
    np.testing.assert_allclose(line_times(times, 1_371_805_399.915), 1_371_805_399.915 + np.array([0, 0.004016, 0.008032]),
                               atol=1e-6)
    np.testing.assert_allclose(line_times(times, 10.0, sync_offset=-0.05), [9.95, 9.954016, 9.958032], atol=1e-9)


def test_out_of_span_names_where_and_spans():
    track = _track()  # 1000.000 - 1001.000 s
    with pytest.raises(NavigationError) as info:
        interpolate_poses(track, np.array([1000.5, 1001.01]), FRAME, where="flight/a.lcf")
    text = str(info.value)
    assert "flight/a.lcf" in text and "1000.000\u20131001.000 s" in text and "1000.500\u20131001.010 s" in text
    assert "\n" not in text
    with pytest.raises(NavigationError, match="start"):
        interpolate_poses(track, np.array([999.9]), FRAME, where="a.lcf")


def test_tolerance_extrapolates_linearly():
    yaw = np.radians(np.linspace(0.0, 2.0, 201))  # 2 deg/s turn
    track = _track(yaw=yaw)
    t = np.array([999.99, 1001.01])
    with pytest.raises(NavigationError):
        interpolate_poses(track, t, FRAME)
    poses = interpolate_poses(track, t, FRAME, tolerance=0.02)
    np.testing.assert_allclose(poses.position[:, 0], [-0.1, 10.1], atol=1e-9)
    np.testing.assert_allclose(poses.attitude.as_euler("ZYX", degrees=True)[:, 0], [-0.02, 2.02], atol=1e-9)


@pytest.mark.parametrize("bad", ["repeat", "back"])
def test_non_increasing_times_are_an_error(bad):
    t = np.arange(10) * 0.005
    t[5] = t[4] if bad == "repeat" else t[3]
    lcf = _lcf(t, lon=-87.0, lat=35.0, alt=100.0, path="x/f.lcf")
    frame = local_frame_for(lcf)
    with pytest.raises(NavigationError, match="row 6") as info:
        track_from_lcf(lcf, frame)
    assert "x/f.lcf" in str(info.value)
    with pytest.raises(NavigationError):
        interpolate_poses(Track(time=t, position=np.zeros((10, 3)), attitude=Rotation.identity(10)), t[:2], frame)


def test_nan_in_lcf_is_an_error():
    lat = np.full(5, 35.0)
    lat[2] = np.nan
    lcf = _lcf(np.arange(5) * 0.005, lon=-87.0, lat=lat, alt=100.0, path="f.lcf")
    with pytest.raises(NavigationError, match="latitude"):
        track_from_lcf(lcf, FRAME)


# --- against the simulator's truth ------------------------------------------------------------

SIM_ARGS = ["--cubes", "3", "--lines", "80", "--samples", "16", "--bands", "2", "--cubes-per-pass", "2", "--quiet"]


@pytest.fixture(scope="module")
def cli_simulated(tmp_path_factory):
    """A small flight made by ``archive simulate`` (3 cubes: a pass of 2, a turn, 1 more) and its truth."""
    import subprocess
    import sys

    from archive.simulator.truth import load_truth

    directory = tmp_path_factory.mktemp("nav") / "flight"
    done = subprocess.run([sys.executable, "-m", "archive", "simulate", str(directory), *SIM_ARGS],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    return directory, load_truth(directory)


def _source(directory, truth, **kw):
    from archive.params import NavigationParams
    from archive.sources import RawFlightSource

    return RawFlightSource(directory, NavigationParams(**kw))


def test_poses_match_simulated_truth(cli_simulated):
    directory, truth = cli_simulated
    source = _source(directory, truth)
    assert source.frame.epsg == truth.epsg
    assert len(source.cubes) == len(truth.cubes) == 3
    for info, cube in zip(source.cubes, truth.cubes, strict=True):
        assert info.base == cube.base
        poses = source.poses(info.index)
        np.testing.assert_allclose(poses.time, cube.line_time, atol=2e-6)
        np.testing.assert_allclose(poses.utm(), cube.position_utm, atol=1e-3)
        angle = np.degrees((cube.attitude.inv() * poses.attitude).magnitude())
        assert angle.max() < 1e-3, f"{cube.base}: attitude off by up to {angle.max():.5f} deg"


@pytest.mark.parametrize("offset", [0.01, -0.013])
def test_sync_offset_matches_shifted_truth(cli_simulated, offset):
    directory, truth = cli_simulated
    source = _source(directory, truth, sync_offset=offset)
    for info, cube in zip(source.cubes, truth.cubes, strict=True):
        poses = source.poses(info.index)
        t = cube.line_time + offset
        np.testing.assert_allclose(poses.time, t, atol=2e-6)
        position, attitude = truth.trajectory(t)
        # lines beyond the cube's own .lcf are extrapolated (<= 13 ms): allow a little more there
        inside = (t >= source.track(info.index).time[0]) & (t <= source.track(info.index).time[-1])
        assert inside.sum() > 0.8 * len(t)
        err = np.linalg.norm(poses.utm() - position, axis=1)
        assert err[inside].max() < 1e-3
        assert err.max() < 5e-3
        angle = np.degrees((attitude.inv() * poses.attitude).magnitude())
        assert angle[inside].max() < 1e-3
        assert angle.max() < 0.02


# --- real Resonon navigation ------------------------------------------------------------------

def test_real_lcf_ends_before_the_last_line(resonon_samples):
    """The Juvika .lcf stops 4.4 ms before the last image line: a strict check would reject it,
    the source's tolerance (NAV_TOLERANCE) extrapolates those lines."""
    from archive.formats.lcf import read_lcf
    from archive.formats.times import read_times
    from archive.sources import NAV_TOLERANCE

    folder = resonon_samples / "mh-skjelvareid__massimal"
    lcf = read_lcf(folder / "Juvika_June2022_Pika_L_12.lcf")
    times = read_times(folder / "Juvika_June2022_Pika_L_12.bil.times")
    frame = local_frame_for(lcf)
    assert frame.epsg == 32633  # Juvika, Norway: 15 E, 67 N
    track = track_from_lcf(lcf, frame)
    t = line_times(times, lcf.time[0])
    assert t[-1] - lcf.time[-1] == pytest.approx(0.0044, abs=2e-4)
    with pytest.raises(NavigationError, match="Juvika_June2022_Pika_L_12.lcf"):
        interpolate_poses(track, t, frame, where=str(lcf.path))
    poses = interpolate_poses(track, t, frame, where=str(lcf.path), tolerance=NAV_TOLERANCE)
    speed = np.linalg.norm(np.diff(poses.position[:, :2], axis=0), axis=1) / np.diff(t)
    assert np.all(np.isfinite(speed)) and 1.0 < np.median(speed) < 30.0
    # extrapolated last line continues the track smoothly (within a few cm of the previous step)
    assert abs(speed[-1] - speed[-2]) < 0.5
