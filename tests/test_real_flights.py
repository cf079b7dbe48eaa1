"""Real flights, not ideal ones (issue 9): what real recorders do, checked on the real Resonon
samples (skipped where they are absent) and on flights the simulator makes with each situation."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from archive.formats.lcf import read_lcf
from archive.formats.times import read_times
from archive.navigation import LocalFrame, Poses, frame_interval, joined, local_frame_for, strip_slices
from archive.params import NavigationParams
from archive.render.mesh import build_mesh
from archive.sources.navigation import CubeNavigation, FlightNavigation

FOV = 47.5


# ---------------------------------------------------------------------------------------------
# the real Juvika pair _12 -> _13
# ---------------------------------------------------------------------------------------------
def _juvika(folder, sync: float) -> FlightNavigation:
    cubes = []
    for k in (12, 13):
        base = folder / f"Juvika_June2022_Pika_L_{k}"
        cubes.append(CubeNavigation(read_times(base.with_suffix(".bil.times")), read_lcf(base.with_suffix(".lcf")),
                                    None, str(base.with_suffix(".lcf"))))
    return FlightNavigation(cubes, local_frame_for(cubes[0].lcf), NavigationParams(fov_deg=FOV, sync_offset=sync))


def test_juvika_pair_is_one_strip(resonon_samples):
    nav = _juvika(resonon_samples / "mh-skjelvareid__massimal", 0.0)
    t12, t13 = nav.line_times(0), nav.line_times(1)
    interval = frame_interval(None, t12)            # the headers are not in the samples: 109 Hz
    gap = float(t13[0] - t12[-1])
    assert 1.5 < gap / interval < 2.0               # 1.7 frame intervals on the .lcf scale
    assert joined(gap, interval)
    assert len(strip_slices(np.concatenate([t12, t13]))) == 1


def test_juvika_sync_offset_interpolates_in_the_previous_lcf(resonon_samples):
    folder = resonon_samples / "mh-skjelvareid__massimal"
    nav = _juvika(folder, -0.05)
    poses = nav.poses(1)
    assert poses.valid is None                      # every line of _13 has navigation
    # the first 50 ms of _13 lie in _12's .lcf: interpolated there, not extrapolated from _13's
    t = nav.line_times(1)
    own = nav.cube_track(1).time
    early = t < own[0]
    assert 5 <= early.sum() <= 6
    # ... and lie inside the merged navigation (_12's rows, then _13's): interpolated, not extrapolated
    assert np.all(nav.track.time[0] <= t) and np.all(t <= nav.track.time[-1])
    from archive.navigation import interpolate_poses

    expected = interpolate_poses(nav.track, t[early], nav.frame)
    np.testing.assert_allclose(poses.position[early], expected.position, atol=1e-9)
    # no jump at the switch: the step between lines stays that of the flight
    steps = np.linalg.norm(np.diff(np.vstack([nav.poses(0).position[-5:], poses.position[:10]]), axis=0), axis=1)
    assert steps.max() < 3.0 * np.median(steps)


# ---------------------------------------------------------------------------------------------
# meshes: pauses and turns cut the strip
# ---------------------------------------------------------------------------------------------
def _poses(times, roll_deg=None, speed=10.0) -> Poses:
    times = np.asarray(times, float)
    n = len(times)
    position = np.stack([speed * (times - times[0]), np.zeros(n), np.full(n, -40.0)], axis=-1)
    roll = np.zeros(n) if roll_deg is None else np.radians(roll_deg)
    attitude = Rotation.from_euler("ZYX", np.stack([np.zeros(n), np.zeros(n), roll], axis=-1))
    return Poses(times, position, attitude, LocalFrame(32616, 500000.0, 3900000.0, 0.0))


def test_pause_inside_a_cube_cuts_the_mesh():
    rate = 249.0
    t = np.arange(100) / rate
    t[50:] += 0.5                                   # the recorder paused 0.5 s after line 49
    mesh = build_mesh(_poses(t), FOV, 0.0, 3.0, rate)
    assert mesh.breaks is not None and np.flatnonzero(mesh.breaks).tolist() == [49]
    tri = mesh.triangles() // 2                     # row of each vertex
    assert not np.any((tri.min(axis=1) <= 49) & (tri.max(axis=1) >= 50))  # no quad bridges the pause
    # one or two dropped frames are a seam, not a gap
    t2 = np.arange(100) / rate
    t2[50:] += 2 / rate
    assert build_mesh(_poses(t2), FOV, 0.0, 3.0, rate).breaks is None


def test_banked_lines_are_left_out_and_the_mesh_stays_small():
    rate = 249.0
    t = np.arange(60) / rate
    roll = np.zeros(60)
    roll[20:40] = 70.0                              # a sustained 70 deg bank
    mesh = build_mesh(_poses(t, roll), FOV, 0.0, 3.0, rate)
    # line 19's mid-exposure pose already leans into the step: 20 or 21 lines left out
    dropped = mesh.dropped["view angle"]
    assert dropped in (20, 21) and mesh.rows == 60 - dropped
    w, s, e, n = mesh.bounds_utm()
    assert e - w < 2 * 40 * np.tan(np.radians(40.0)) + 1   # bounded by the view-angle limit
    assert np.flatnonzero(mesh.breaks).tolist() == [59 - dropped - 20]
