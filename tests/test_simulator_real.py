"""Recorder realism of the simulator (issue 9): dropped frames, shutter steps, sync offset, banked and
recorded turns, a pause inside a cube, a UTM zone border, boresight and lever arm. Each option is
checked against the simulator's own physics and files."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from pyproj import Transformer
from scipy.spatial.transform import Rotation, Slerp

from archive.cli import main
from archive.errors import InputError
from archive.formats.envi import EnviCube, read_header
from archive.formats.icp import read_icp, response
from archive.formats.lcf import read_lcf
from archive.formats.times import read_times
from archive.simulator.command import simulate_flight
from archive.simulator.truth import FOOTPRINT_MAX_OFF_NADIR_DEG, load_truth

FR = 249.0
SYNC = 0.037
PAUSE = 0.25
BORESIGHT = (-3.0, 2.0, 1.5)
LEVER = (0.3, -0.15, 0.25)
SMALL = dict(samples=48, lines=120, bands=3)


@pytest.fixture(scope="module")
def real(tmp_path_factory):
    """4 cubes in 2 passes with 2 dropped frames per cube switch, shutters 2.5 / 3.9 ms, a sync
    offset, a pause in cube 2, a boresight and a lever arm."""
    directory = tmp_path_factory.mktemp("real") / "flight"
    truth = simulate_flight(directory, cubes=4, cubes_per_pass=2, seed=4, dropped_frames=2,
                            shutters=(2.5, 3.9), sync_offset=SYNC, pause_s=PAUSE, pause_cube=2,
                            boresight_deg=BORESIGHT, lever_arm_m=LEVER, **SMALL)
    return directory, truth


@pytest.fixture(scope="module")
def banked(tmp_path_factory):
    """70 degree banked turns, recorded; a 60 degree field of view sees the sky at full bank."""
    directory = tmp_path_factory.mktemp("bank") / "flight"
    truth = simulate_flight(directory, cubes=4, cubes_per_pass=2, samples=32, lines=150, bands=2,
                            seed=2, bank_deg=70.0, record_turns=True, fov_deg=60.0)
    return directory, truth


def _files(directory, cube):
    return (read_lcf(directory / f"{cube.base}.lcf"), read_times(directory / f"{cube.base}.bil.times"))


def _ins_from_lcf(lcf, epsg, t):
    """INS pose interpolated from .lcf rows (linear / slerp, grid convergence applied) at times t."""
    proj = Transformer.from_crs(4326, epsg, always_xy=True)
    e, n = proj.transform(lcf.lon, lcf.lat)
    e2, n2 = proj.transform(lcf.lon, lcf.lat + 1e-5)
    conv = np.arctan2(e2 - e, n2 - n)
    rot = Rotation.from_euler("ZYX", np.stack([lcf.yaw + conv, lcf.pitch, -lcf.roll], axis=1))
    pos = np.stack([np.interp(t, lcf.time, v) for v in (e, n, lcf.alt)], axis=1)
    return pos, Slerp(lcf.time, rot)(t)


def _mounted(pos, att, boresight, lever):
    """DESIGN 3: camera -> NED = body -> NED * camera -> body; position + body -> NED(lever arm)."""
    roll, pitch, yaw = boresight
    ned = att.apply(np.asarray(lever, float))
    return (pos + np.stack([ned[:, 1], ned[:, 0], -ned[:, 2]], axis=1),
            att * Rotation.from_euler("ZYX", [yaw, pitch, roll], degrees=True))


def _angle_deg(a, b):
    return np.degrees((a * b.inv()).magnitude())


# --- dropped frames --------------------------------------------------------------------------------
def test_dropped_frames_gap_in_truth_and_camera_clock(real):
    directory, truth = real
    assert truth.dropped_frames == 2 and truth.strips == [(0, 1), (2, 3)]
    for a, b in truth.strips:
        ca, cb = truth.cubes[a], truth.cubes[b]
        assert cb.line_time[0] - ca.line_time[-1] == pytest.approx(3 / FR, abs=1e-6)
        ta, tb = _files(directory, ca)[1], _files(directory, cb)[1]
        assert tb[0] - ta[-1] == pytest.approx(3 / FR, abs=2e-6)
    assert truth.cubes[2].line_time[0] - truth.cubes[1].line_time[-1] > 2.0     # a turn


# --- shutter steps ---------------------------------------------------------------------------------
def test_shutter_steps_between_joined_cubes_and_radiometry(real):
    directory, truth = real
    cal = read_icp(directory / "calibration.icp")
    assert [c.shutter_ms for c in truth.cubes] == [2.5, 3.9, 2.5, 3.9]
    assert {c.gain_db for c in truth.cubes} == {0.0}
    assert {(d.gain_db, d.shutter_ms) for d in cal.darks} == {(0.0, 2.5), (0.0, 3.9)}
    checked = {}
    t_half = math.tan(math.radians(truth.fov_deg) / 2)
    u = -t_half + 2 * t_half * (np.arange(truth.samples) + 0.5) / truth.samples
    for cube in truth.cubes:
        header = read_header(directory / f"{cube.base}.bil.hdr")
        assert header.shutter == cube.shutter_ms and header.gain == cube.gain_db
        dark, gain = cal.for_cube(header)
        dn = EnviCube(directory / f"{cube.base}.bil").read().astype(float)
        radiance = (dn - dark[:, None, :]) * gain[:, None, :] / response(header.shutter, header.gain,
                                                                          cal.shutter_cal, cal.gain_cal)
        # where each sample looks at mid-exposure, through the mounted camera
        pos, att = truth.trajectory(cube.line_time + cube.shutter_ms / 2000)
        m = att.as_matrix()
        d = m[:, None, :, 1] * u[None, :, None] + m[:, None, :, 2]
        lam = (pos[:, 2] - truth.ground_height)[:, None] / d[..., 2]
        e, n = pos[:, 0, None] + lam * d[..., 1], pos[:, 1, None] + lam * d[..., 0]
        for patch in truth.homogeneous_patches():
            w, s, ea, no = patch["interior"]
            margin = 0.6 * truth.nominal_gsd + 0.1
            inside = (e > w + margin) & (e < ea - margin) & (n > s + margin) & (n < no - margin)
            if inside.sum() < 8:
                continue
            np.testing.assert_allclose(radiance[:, inside].mean(axis=1), truth.spectra[patch["material"]],
                                       rtol=0.03, err_msg=patch["name"])
            checked[cube.shutter_ms] = checked.get(cube.shutter_ms, 0) + 1
    assert set(checked) == {2.5, 3.9}, checked


# --- sync offset -------------------------------------------------------------------------------------
def test_sync_offset_lcf_times_and_truth(real):
    directory, truth = real
    assert truth.sync_offset == SYNC
    for cube in truth.cubes:
        lcf, times = _files(directory, cube)
        # DESIGN 2: lcf_t0 + (times - times0) + sync_offset is the line's (true) time
        np.testing.assert_allclose(lcf.time[0] + (times - times[0]) + SYNC, cube.line_time, rtol=0, atol=1e-6)
        assert lcf.time[0] == pytest.approx(cube.line_time[0] - SYNC, abs=1e-6)
        # the navigation covers the lines in true time too, continuously at 200 Hz
        assert lcf.time[-1] >= cube.line_time[-1] + 1 / FR
        np.testing.assert_allclose(np.diff(lcf.time), 0.005, atol=1e-6)
        # every .lcf row holds the INS truth at its own time
        proj = Transformer.from_crs(4326, truth.epsg, always_xy=True)
        e, n = proj.transform(lcf.lon, lcf.lat)
        ins = truth.ins_trajectory(lcf.time)[0]
        np.testing.assert_allclose(np.stack([e, n, lcf.alt], axis=1), ins, rtol=0, atol=1e-6)


# --- boresight and lever arm ---------------------------------------------------------------------
def test_truth_camera_pose_is_ins_pose_through_the_mount(real):
    directory, truth = real
    assert truth.boresight_deg == BORESIGHT and truth.lever_arm_m == LEVER
    worst_pos = worst_ang = 0.0
    for cube in truth.cubes:
        # exactly: the continuous INS truth composed with the mount
        ins_pos, ins_att = truth.ins_trajectory(cube.line_time)
        cam_pos, cam_att = _mounted(ins_pos, ins_att, BORESIGHT, LEVER)
        np.testing.assert_allclose(cube.position_utm, cam_pos, rtol=0, atol=1e-9)
        assert _angle_deg(cube.attitude, cam_att).max() < 1e-9
        # as a user does it: the .lcf interpolated at lcf_t0 + (times - times0) + S, then mounted
        lcf, times = _files(directory, cube)
        pos, att = _mounted(*_ins_from_lcf(lcf, truth.epsg, lcf.time[0] + (times - times[0]) + SYNC),
                            BORESIGHT, LEVER)
        worst_pos = max(worst_pos, float(np.abs(pos - cube.position_utm).max()))
        worst_ang = max(worst_ang, float(_angle_deg(att, cube.attitude).max()))
    assert worst_pos < 1e-3 and worst_ang < 1e-3
    # the mount is real: camera and INS differ by the lever arm and the boresight
    cube = truth.cubes[0]
    ins_pos, ins_att = truth.ins_trajectory(cube.line_time)
    offset = np.linalg.norm(cube.position_utm - ins_pos, axis=1)
    np.testing.assert_allclose(offset, np.linalg.norm(LEVER), rtol=1e-9)
    np.testing.assert_allclose(_angle_deg(cube.attitude, ins_att),
                               Rotation.from_euler("ZYX", BORESIGHT[::-1], degrees=True).magnitude() * 180 / np.pi,
                               rtol=1e-9)


# --- pause --------------------------------------------------------------------------------------------
def test_pause_inside_a_cube(real):
    directory, truth = real
    assert (truth.pause_cube, truth.pause_line, truth.pause_s) == (2, 60, PAUSE)
    cube = truth.cubes[2]
    lcf, times = _files(directory, cube)
    dt = np.diff(times)
    np.testing.assert_allclose(dt[59] - 1 / FR, PAUSE, atol=2e-6)          # between lines 59 and 60
    np.testing.assert_allclose(np.delete(dt, 59), 1 / FR, atol=2e-6)
    np.testing.assert_allclose(np.diff(cube.line_time)[59] - 1 / FR, PAUSE, atol=2e-6)
    # the navigation goes on logging through the pause, and covers the lines after it
    np.testing.assert_allclose(np.diff(lcf.time), 0.005, atol=1e-6)
    assert lcf.time[-1] >= cube.line_time[-1]
    # the lines after the pause are real exposures at their true times: the platform moved on
    moved = np.linalg.norm(cube.position_utm[60, :2] - cube.position_utm[59, :2])
    assert moved == pytest.approx(10.0 * (PAUSE + 1 / FR), rel=0.1)
    # the footprint is split at the pause (2 strips + 1), not the strips
    assert truth.strips == [(0, 1), (2, 3)] and len(truth.footprint()) == 3
    # the other cube of that pass follows the pause
    assert truth.cubes[3].line_time[0] - cube.line_time[-1] == pytest.approx(3 / FR, abs=1e-6)


# --- banked, recorded turns -----------------------------------------------------------------------
def test_banked_turns_are_recorded(banked):
    truth = banked[1]
    assert truth.bank_deg == 70.0 and truth.record_turns
    t = np.concatenate([c.line_time for c in truth.cubes])
    in_turn = np.concatenate([truth.in_turn(k) for k in range(len(truth.cubes))])
    assert 50 < in_turn.sum() < t.size / 2
    bank = np.degrees(np.abs(truth.flight.nominal_bank(t)))
    assert bank[~in_turn].max() == 0.0
    assert abs(bank.max() - 70.0) < 1.0                    # the sustained bank is recorded
    roll = np.concatenate([c.attitude.as_euler("ZYX", degrees=True)[:, 2] for c in truth.cubes])
    assert abs(np.abs(roll).max() - 70.0) < 3.5            # plus the multirotor wobble (< 3.3 deg)
    assert np.abs(roll[~in_turn]).max() < 4.0
    # a coordinated turn: bank = atan(v * yaw rate / g)
    turn = truth.flight.turn
    s = np.linspace(0.0, turn.duration, 50)
    _, _, _, rate = turn(s)
    np.testing.assert_allclose(np.tan(turn.bank(s)), 10.0 * rate / 9.80665, rtol=1e-12, atol=1e-12)


def test_banked_turn_geometry_is_continuous(banked):
    truth = banked[1]
    flight = truth.flight
    eps = 1e-4
    for t in (flight.segment_end(0), flight.segment_end(0) + flight.turn_s):
        (p0, p1), (a0, a1) = flight.position([t - eps, t + eps]), flight.attitude([t - eps, t + eps])
        assert np.linalg.norm(p1 - p0) < 10.0 * 2 * eps * 1.01
        assert np.degrees((a1 * a0.inv()).magnitude()) < 0.1
    # the next pass starts one spacing across, flying the other way
    yaw0 = flight.euler([flight.segment_end(0) - 0.1])[0][0]
    yaw1 = flight.euler([flight.segment_end(0) + flight.turn_s + 0.1])[0][0]
    assert abs(np.angle(np.exp(1j * (yaw1 - yaw0 - np.pi)))) < math.radians(5)
    c = flight.pass_c(np.array([0, 1]))
    assert c[1] - c[0] == flight.spacing


def test_banked_lines_files_sky_and_footprint(banked):
    directory, truth = banked
    t_half = math.tan(math.radians(truth.fov_deg) / 2)
    u = -t_half + 2 * t_half * (np.arange(truth.samples) + 0.5) / truth.samples
    worst_pos = worst_ang = 0.0
    sky_checked = 0
    for k, cube in enumerate(truth.cubes):
        lcf, times = _files(directory, cube)
        pos, att = _ins_from_lcf(lcf, truth.epsg, lcf.time[0] + (times - times[0]))
        worst_pos = max(worst_pos, float(np.abs(pos - cube.position_utm).max()))
        worst_ang = max(worst_ang, float(_angle_deg(att, cube.attitude).max()))
        # samples looking above the horizon see the black sky: their DN is the dark frame's
        m = cube.attitude.as_matrix()
        d = m[:, None, :, 1] * u[None, :, None] + m[:, None, :, 2]
        sky = d[..., 2] < -0.05
        if sky.any():
            dn = EnviCube(directory / f"{cube.base}.bil").read().astype(float)
            ground = d[..., 2] > 0.5
            assert np.abs(dn[:, sky].mean(axis=1) - dn[:, ground].mean(axis=1)).min() > 100
            assert dn[:, sky].max() < 200
            sky_checked += int(sky.sum())
        assert not truth.in_turn(k)[:10].any() or k % 2 == 1
    assert sky_checked > 0
    # 200 Hz navigation still follows the turn; slerp between rows misses ~0.03 deg of the roll-in
    # (0 -> 70 degrees in 0.3 s), against < 0.001 deg on straight passes
    assert worst_pos < 1e-3 and worst_ang < 0.05
    # lines seen too far off nadir are left out of the footprint, which stays near the passes
    limit = 40.0 * math.tan(math.radians(FOOTPRINT_MAX_OFF_NADIR_DEG)) + 40.0
    centre = np.array([truth.scene.origin_e, truth.scene.origin_n])
    for poly in truth.footprint():
        assert np.isfinite(poly).all() and np.linalg.norm(poly - centre, axis=1).max() < limit


# --- UTM zone border ------------------------------------------------------------------------------
def _nadir_lonlat(truth, cube):
    pos = cube.position_utm
    return Transformer.from_crs(truth.epsg, 4326, always_xy=True).transform(pos[:, 0], pos[:, 1])


def test_zone_border_passes_and_truth_in_the_other_zone(tmp_path):
    west = simulate_flight(tmp_path / "west", cubes=2, cubes_per_pass=1, lon=-90.00005, seed=1, samples=16,
                           lines=60, bands=2)
    east = simulate_flight(tmp_path / "east", cubes=2, cubes_per_pass=1, lon=-89.9995, seed=2, samples=16,
                           lines=60, bands=2)
    assert west.epsg == 32615 and west.crs == "EPSG:32615" and east.epsg == 32616
    # the west flight straddles the -90 border: its two passes lie in zones 15 and 16
    lon0 = _nadir_lonlat(west, west.cubes[0])[0]
    lon1 = _nadir_lonlat(west, west.cubes[1])[0]
    assert lon0.max() < -90.0 < lon1.min()
    fp = west.footprint(crs=4326)
    assert len(fp) == 2 and fp[0][:, 0].mean() < -90.0 < fp[1][:, 0].mean()
    # together, the two flights cover both zones
    assert all(p[:, 0].mean() > -90.0 for p in east.footprint(crs=4326))
    # the truth evaluates points of the other zone (as a render made in zone 16 would give them)
    rng = np.random.default_rng(0)
    e15 = west.scene.origin_e + rng.uniform(-15, 15, (7, 5))
    n15 = west.scene.origin_n + rng.uniform(-15, 15, (7, 5))
    to16 = Transformer.from_crs(32615, 32616, always_xy=True)
    e16, n16 = to16.transform(e15, n15)
    np.testing.assert_array_equal(west.radiance(e16, n16, crs=32616).shape, (2, 7, 5))
    np.testing.assert_allclose(west.radiance(e16, n16, crs=32616), west.radiance(e15, n15), rtol=1e-9)
    lon, lat = Transformer.from_crs(32615, 4326, always_xy=True).transform(e15, n15)
    np.testing.assert_allclose(west.abundance(lon, lat, crs=4326), west.abundance(e15, n15), rtol=1e-9)
    np.testing.assert_array_equal(west.covered(e16, n16, crs="EPSG:32616"), west.covered(e15, n15))
    # a zone-16 pixel over a homogeneous patch averages to the patch's radiance
    patch = west.homogeneous_patches()[0]
    w, s, ea, no = patch["interior"]
    pe, pn = to16.transform((w + ea) / 2, (s + no) / 2)
    box = west.radiance_box(np.array([pe]), np.array([pn]), 1.5, crs=32616)[:, 0]
    np.testing.assert_allclose(box, west.spectra[patch["material"]], rtol=1e-12)
    fp16 = west.footprint(crs=32616)
    np.testing.assert_allclose(np.stack(to16.transform(*west.footprint()[0].T), axis=1), fp16[0], atol=1e-6)


# --- persistence, CLI, defaults, refusals ---------------------------------------------------------
def test_truth_round_trips_new_fields(real, banked):
    for directory, truth in (real, banked):
        loaded = load_truth(directory)
        for name in ("sync_offset", "boresight_deg", "lever_arm_m", "dropped_frames", "pause_cube",
                     "pause_line", "pause_s", "record_turns", "bank_deg", "epsg"):
            assert getattr(loaded, name) == getattr(truth, name), name
        t = np.concatenate([c.line_time for c in truth.cubes])
        np.testing.assert_array_equal(loaded.trajectory(t)[0], truth.trajectory(t)[0])
        for a, b in zip(loaded.footprint(), truth.footprint(), strict=True):
            np.testing.assert_array_equal(a, b)


def test_default_truth_has_no_new_keys(tmp_path):
    truth = simulate_flight(tmp_path / "d", cubes=1, bands=2, samples=8, lines=12)
    meta = json.loads((tmp_path / "d" / "truth" / "truth.json").read_text())
    new = {"sync_offset", "boresight_deg", "lever_arm_m", "dropped_frames", "pause", "record_turns"}
    assert not new & set(meta) and not {"bank_deg", "record_into_turn_s"} & set(meta["trajectory"])
    loaded = load_truth(tmp_path / "d")
    assert (loaded.sync_offset, loaded.dropped_frames, loaded.pause_cube, loaded.bank_deg) == (0.0, 0, None, 0.0)
    assert loaded.mount.identity and truth.mount.identity


def test_cli_options(tmp_path, capsys):
    target = tmp_path / "cli"
    assert main(["simulate", str(target), "--cubes", "2", "--lines", "20", "--samples", "8", "--bands", "2",
                 "--dropped-frames", "1", "--shutters", "2.5,3.9", "--sync-offset", "-0.02",
                 "--pause", "0.1", "--boresight", "-0.5,1,0", "--lever-arm", "0.1,0,-0.2",
                 "--bank-deg", "45", "--record-turns", "--cubes-per-pass", "1", "--quiet"]) == 0
    assert "sync offset" in capsys.readouterr().out
    truth = load_truth(target)
    assert (truth.dropped_frames, truth.sync_offset, truth.pause_s, truth.bank_deg) == (1, -0.02, 0.1, 45.0)
    assert truth.boresight_deg == (-0.5, 1.0, 0.0) and truth.lever_arm_m == (0.1, 0.0, -0.2)
    assert [c.shutter_ms for c in truth.cubes] == [2.5, 3.9] and truth.record_turns
    with pytest.raises(SystemExit) as exc:
        main(["simulate", str(tmp_path / "bad"), "--boresight", "1,2", "--quiet"])
    assert exc.value.code == 2 and "3 comma-separated numbers" in capsys.readouterr().err


@pytest.mark.parametrize("kw", [dict(bank_deg=80.0), dict(dropped_frames=11), dict(shutters=(5.0,)),
                                dict(pause_s=1.0, pause_cube=3), dict(boresight_deg=(1, 2)),
                                dict(shutters=(3.0,), shutter_steps=True)])
def test_refuses_bad_options(tmp_path, kw):
    with pytest.raises(InputError):
        simulate_flight(tmp_path / "x", cubes=2, bands=2, samples=8, lines=12, **kw)
