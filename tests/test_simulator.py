"""The simulator is the ground truth: check its files, radiometry, navigation and truth in numbers."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pyproj import Transformer
from scipy.spatial.transform import Rotation, Slerp

from archive.cli import main
from archive.errors import InputError, OutputExistsError
from archive.formats.envi import EnviCube, read_header
from archive.formats.flight import discover_flight
from archive.formats.icp import read_icp, response
from archive.formats.lcf import read_lcf
from archive.formats.times import read_times
from archive.simulator.command import simulate_flight
from archive.simulator.scene import MATERIALS
from archive.simulator.truth import load_truth


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    """The default flight (4 cubes x 250 lines x 128 samples x 8 bands) and its truth."""
    directory = tmp_path_factory.mktemp("sim") / "flight"
    truth = simulate_flight(directory)
    return directory, truth


def _to_utm(epsg):
    return Transformer.from_crs(4326, epsg, always_xy=True)


def _pixel_ground(truth, cube, lines, samples):
    """UTM E, N of each (line, sample) centre ray at mid-exposure: (len(lines), len(samples))."""
    t_half = math.tan(math.radians(truth.fov_deg) / 2)
    u = -t_half + 2 * t_half * (np.asarray(samples) + 0.5) / truth.samples
    pos, att = truth.trajectory(cube.line_time[lines] + cube.shutter_ms / 2000)
    m = att.as_matrix()
    d = m[:, None, :, 1] * u[None, :, None] + m[:, None, :, 2]           # N, E, D
    lam = (pos[:, 2] - truth.ground_height)[:, None] / d[..., 2]
    return pos[:, 0, None] + lam * d[..., 1], pos[:, 1, None] + lam * d[..., 0]


def test_files_exist_and_parse(flight):
    directory, truth = flight
    parsed = discover_flight(directory)
    assert [c.base for c in parsed.cubes] == [f"sim_Pika_L_{k}" for k in (1, 2, 3, 4)]
    assert parsed.calibration is not None and parsed.calibration.name == "calibration.icp"
    assert len(truth.cubes) == 4 and truth.strips == [(0, 1), (2, 3)]
    exposures = set()
    for files, cube in zip(parsed.cubes, truth.cubes, strict=True):
        header = read_header(files.header)
        assert (header.bands, header.lines, header.samples) == (8, 250, 128)
        assert header.interleave == "bil" and header.data_type == 12 and header.byte_order == 0
        assert header.framerate == 249 and header.bit_depth == 12
        assert header.shutter == cube.shutter_ms and header.gain == cube.gain_db
        assert header.flip_radiometric_calibration is False
        np.testing.assert_allclose(header.wavelengths, truth.wavelengths)
        assert files.data.stat().st_size == 8 * 250 * 128 * 2
        times = read_times(files.times, expected_lines=250)
        assert 263.0 < times[0] < 300.0           # camera clock, not GPS
        lcf = read_lcf(files.lcf)
        assert lcf.time[0] == cube.line_time[0]     # first lcf row = first line
        assert lcf.time[-1] >= cube.line_time[-1] + 2 / 249
        np.testing.assert_allclose(np.diff(lcf.time), 0.005, atol=1e-6)
        np.testing.assert_array_equal(lcf.time[0] + (times - times[0]), cube.line_time)  # exactly
        exposures.add((cube.gain_db, cube.shutter_ms))
    assert len({c.shutter_ms for c in truth.cubes}) > 1 and len({c.gain_db for c in truth.cubes}) > 1
    cal = read_icp(directory / "calibration.icp")
    assert cal.gain.shape == (8, 128)
    assert {(d.gain_db, d.shutter_ms) for d in cal.darks} == exposures
    for dark in cal.darks:
        assert 60 < dark.data.mean() < 140 and 4 < dark.data.std() < 16


def test_consecutive_cubes_follow_by_one_frame(flight):
    _, truth = flight
    for a, b in ((0, 1), (2, 3)):
        gap = truth.cubes[b].line_time[0] - truth.cubes[a].line_time[-1]
        assert abs(gap - 1 / 249) < 2e-6
    turn = truth.cubes[2].line_time[0] - truth.cubes[1].line_time[-1]
    assert 3.0 < turn < 10.0


def test_dn_within_12_bits_and_some_saturated(flight):
    directory, truth = flight
    saturated = 0
    for cube in truth.cubes:
        dn = EnviCube(directory / f"{cube.base}.bil").read()
        assert dn.dtype == np.uint16 and dn.max() <= 4095 and dn.min() >= 50
        saturated += int((dn == 4095).sum())
        assert (dn == 4095).mean() < 0.01
    assert saturated > 0


def test_saturated_pixels_lie_on_glint_targets(flight):
    """The pose convention (sample 0 at the left wing, body axes) puts the glint where it is."""
    directory, truth = flight
    glints = [s["bounds"] for s in truth.scene.shapes if s["name"].endswith("_glint")]
    found = 0
    for cube in truth.cubes:
        dn = EnviCube(directory / f"{cube.base}.bil").band(len(truth.wavelengths) // 2)
        lines, samples = np.nonzero(dn == 4095)
        if lines.size == 0:
            continue
        e, n = _pixel_ground(truth, cube, lines, samples)
        e, n = np.diagonal(e), np.diagonal(n)
        dist = np.min([np.hypot(e - (g[0] + g[2]) / 2, n - (g[1] + g[3]) / 2) for g in glints], axis=0)
        assert dist.max() < 0.2 + truth.nominal_gsd
        found += lines.size
    assert found > 0


def test_homogeneous_patches_calibrate_back_to_scene_radiance(flight):
    directory, truth = flight
    cal = read_icp(directory / "calibration.icp")
    checked = set()
    for cube in truth.cubes:
        header = read_header(directory / f"{cube.base}.bil.hdr")
        dark, gain = cal.for_cube(header)
        resp = response(header.shutter, header.gain, cal.shutter_cal, cal.gain_cal)
        dn = EnviCube(directory / f"{cube.base}.bil").read().astype(float)
        radiance = (dn - dark[:, None, :]) * gain[:, None, :] / resp
        lines = np.arange(cube.lines)
        e, n = _pixel_ground(truth, cube, lines, np.arange(truth.samples))
        for patch in truth.homogeneous_patches():
            w, s, ea, no = patch["interior"]
            m = 0.2  # stay a pixel half-width plus exposure smear inside the interior
            inside = (e > w + m) & (e < ea - m) & (n > s + m) & (n < no - m)
            if inside.sum() < 50:
                continue
            measured = radiance[:, inside].mean(axis=1)
            expected = truth.spectra[patch["material"]]
            np.testing.assert_allclose(measured, expected, rtol=0.02, err_msg=patch["name"])
            # the truth agrees at the patch centre, point and box
            ce, cn = (w + ea) / 2, (s + no) / 2
            np.testing.assert_allclose(truth.radiance(np.array(ce), np.array(cn)), expected)
            np.testing.assert_allclose(truth.radiance_box(np.array([ce]), np.array([cn]), 2.0)[:, 0], expected)
            checked.add(patch["material_name"])
    assert len(checked) >= 4, checked


def test_lcf_interpolation_reproduces_truth(flight):
    """200 Hz lcf samples, interpolated linearly (position) and by slerp (attitude) at the line
    times, give the continuous truth within 1 mm and 0.001 degrees."""
    directory, truth = flight
    proj = _to_utm(truth.epsg)
    worst_pos = worst_ang = 0.0
    for cube in truth.cubes:
        lcf = read_lcf(directory / f"{cube.base}.lcf")
        times = read_times(directory / f"{cube.base}.bil.times")
        t = lcf.time[0] + (times - times[0])
        e, n = proj.transform(lcf.lon, lcf.lat)
        e2, n2 = proj.transform(lcf.lon, lcf.lat + 1e-5)
        conv = np.arctan2(e2 - e, n2 - n)
        rot = Rotation.from_euler("ZYX", np.stack([lcf.yaw + conv, lcf.pitch, -lcf.roll], axis=1))
        pos = np.stack([np.interp(t, lcf.time, v) for v in (e, n, lcf.alt)], axis=1)
        att = Slerp(lcf.time, rot)(t)
        true_pos, true_att = truth.trajectory(t)
        np.testing.assert_allclose(true_pos, cube.position_utm, rtol=0, atol=1e-6)
        worst_pos = max(worst_pos, float(np.abs(pos - true_pos).max()))
        worst_ang = max(worst_ang, float(np.degrees((att * true_att.inv()).magnitude()).max()))
        ang_cube = np.degrees((cube.attitude * true_att.inv()).magnitude()).max()
        assert ang_cube < 1e-9
    assert worst_pos < 1e-3
    assert worst_ang < 1e-3
    assert worst_ang > 1e-7  # the wobble is real, the check is not vacuous


def test_wobble_is_multirotor_like(flight):
    _, truth = flight
    t = np.concatenate([c.line_time for c in truth.cubes])
    yaw, pitch, roll = truth.flight.euler(t)
    assert 1.0 < np.degrees(np.ptp(roll)) < 8.0
    assert 1.0 < np.degrees(np.ptp(pitch)) < 8.0
    alt = np.concatenate([c.position_utm[:, 2] for c in truth.cubes])
    assert 119.0 < alt.min() and alt.max() < 121.0 and np.ptp(alt) > 0.05
    heading = np.degrees(yaw[: truth.cubes[0].lines])
    assert np.all(np.abs(heading - 20.0) < 3.0)   # grid heading of the first pass, with crab/drift


def test_convergence_and_lcf_heading(flight):
    directory, truth = flight
    # grid bearing of true north (contract sign): +1.69 deg at Memphis; textbook gamma = -1.69 deg
    assert truth.epsg == 32616
    assert 1.6 < math.degrees(truth.convergence) < 1.8
    lcf = read_lcf(directory / f"{truth.cubes[0].base}.lcf")
    proj = _to_utm(truth.epsg)
    e, n = proj.transform(lcf.lon, lcf.lat)
    e2, n2 = proj.transform(lcf.lon, lcf.lat + 1e-5)
    conv = np.arctan2(e2 - e, n2 - n)
    yaw_grid, pitch, roll = truth.flight.euler(lcf.time)
    diff = np.angle(np.exp(1j * (lcf.yaw - (yaw_grid - conv))))
    assert np.abs(diff).max() < 1e-9
    np.testing.assert_allclose(lcf.roll, -roll, atol=1e-12)
    np.testing.assert_allclose(lcf.pitch, pitch, atol=1e-12)
    pos = truth.trajectory(lcf.time)[0]
    np.testing.assert_allclose(np.stack([e, n, lcf.alt], axis=1), pos, rtol=0, atol=1e-6)


def test_truth_round_trips(flight):
    directory, truth = flight
    loaded = load_truth(directory)
    assert loaded.directory == directory
    assert (loaded.epsg, loaded.fov_deg, loaded.ground_height, loaded.samples) == \
        (truth.epsg, truth.fov_deg, truth.ground_height, truth.samples)
    np.testing.assert_array_equal(loaded.wavelengths, truth.wavelengths)
    for a, b in zip(loaded.cubes, truth.cubes, strict=True):
        assert (a.base, a.shutter_ms, a.gain_db, a.framerate) == (b.base, b.shutter_ms, b.gain_db, b.framerate)
        np.testing.assert_array_equal(a.line_time, b.line_time)
        np.testing.assert_array_equal(a.position_utm, b.position_utm)
        np.testing.assert_allclose(a.attitude.as_quat(), b.attitude.as_quat(), rtol=0, atol=1e-15)
    rng = np.random.default_rng(1)
    e = truth.scene.origin_e + rng.uniform(-40, 40, (30, 20))
    n = truth.scene.origin_n + rng.uniform(-40, 40, (30, 20))
    np.testing.assert_array_equal(loaded.radiance(e, n), truth.radiance(e, n))
    assert loaded.radiance(e, n).shape == (8, 30, 20)
    t = np.linspace(truth.cubes[0].line_time[0] - 1, truth.cubes[-1].line_time[-1] + 1, 97)
    np.testing.assert_array_equal(loaded.trajectory(t)[0], truth.trajectory(t)[0])
    for p, q in zip(loaded.footprint(), truth.footprint(), strict=True):
        np.testing.assert_array_equal(p, q)
    assert loaded.nominal_gsd == pytest.approx(2 * 40 * math.tan(math.radians(47.5 / 2)) / 128, rel=0.01)


def test_checkerboard_box_average(flight):
    _, truth = flight
    checker = next(s for s in truth.scene.shapes if s["kind"] == "checker")
    w, s = checker["bounds"][:2]
    white, black = (truth.spectra[MATERIALS.index(m)] for m in ("white", "asphalt"))
    # a 2 m box centred on an inner corner holds two squares of each colour
    np.testing.assert_allclose(truth.radiance_box(np.array(w + 2.0), np.array(s + 2.0), 2.0),
                               (white + black) / 2, rtol=1e-12)
    np.testing.assert_allclose(truth.radiance(np.array(w + 0.5), np.array(s + 0.5)), white)
    np.testing.assert_allclose(truth.radiance(np.array(w + 1.5), np.array(s + 0.5)), black)


def test_footprint_follows_swath_edges(flight):
    _, truth = flight
    polys = truth.footprint()
    assert len(polys) == 2 and all(p.shape == (2 * 500, 2) for p in polys)
    cube = truth.cubes[0]
    t_half = math.tan(math.radians(truth.fov_deg) / 2)
    mid = np.arange(20, 230, 7)
    pos, att = truth.trajectory(cube.line_time[mid] + cube.shutter_ms / 2000)
    m = att.as_matrix()
    for u, expect in ((-0.97 * t_half, True), (-1.03 * t_half, False), (0.0, True)):
        d = m[:, :, 1] * u + m[:, :, 2]
        lam = (pos[:, 2] - truth.ground_height) / d[:, 2]
        covered = truth.covered(pos[:, 0] + lam * d[:, 1], pos[:, 1] + lam * d[:, 0])
        assert covered.all() == expect and covered.any() == expect, u
    far = truth.covered(np.array([truth.scene.origin_e + 200.0]), np.array([truth.scene.origin_n]))
    assert not far.any()


def test_refuses_existing_directory_and_overwrites(tmp_path):
    target = tmp_path / "out"
    target.mkdir()
    (target / "keep.txt").write_text("x")
    small = dict(cubes=1, bands=2, samples=8, lines=12)
    with pytest.raises(OutputExistsError):
        simulate_flight(target, **small)
    assert (target / "keep.txt").exists()
    truth = simulate_flight(target, overwrite=True, **small)
    assert not (target / "keep.txt").exists() and (target / "sim_Pika_L_1.bil").exists()
    assert truth.cubes[0].lines == 12 and [p.name for p in tmp_path.iterdir()] == ["out"]
    with pytest.raises(InputError):
        simulate_flight(tmp_path / "bad", samples=1)


def test_cli(tmp_path, capsys):
    target = tmp_path / "cli"
    args = ["simulate", str(target), "--cubes", "3", "--lines", "10", "--samples", "16", "--bands", "3",
            "--cubes-per-pass", "2", "--seed", "5", "--quiet"]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "EPSG:32616" in out and "cubes 3" in out
    truth = load_truth(target)
    assert len(truth.cubes) == 3 and truth.strips == [(0, 1), (2,)]
    assert main(args) == 2
    assert "exists" in capsys.readouterr().err


def test_start_and_seed_give_the_flight_id(tmp_path, capsys):
    """--start sets the first line's UTC time (hence the collection id <sensor>_<start>); without it
    each seed starts a minute after the previous one (seed 0 at 2024-06-12T16:00:00Z)."""
    from archive.formats.lcf import gps_seconds_to_datetime
    from archive.simulator.command import T_START_GPS, start_gps

    def first(directory):
        # the first line follows the start by the run-in (RUN_S, 0.5 s): ids keep whole seconds
        t = gps_seconds_to_datetime(float(read_lcf(discover_flight(directory).cubes[0].lcf).time[0]))
        return t.replace(microsecond=0)

    small = ["--cubes", "1", "--lines", "10", "--samples", "8", "--bands", "2", "--quiet"]
    assert main(["simulate", str(tmp_path / "a"), *small, "--start", "2023-05-01T09:30:15Z"]) == 0
    assert first(tmp_path / "a").isoformat() == "2023-05-01T09:30:15+00:00"
    assert main(["simulate", str(tmp_path / "b"), *small, "--start", "2023-05-01T11:30:15+02:00"]) == 0
    assert first(tmp_path / "b") == first(tmp_path / "a")
    assert start_gps(None, 0) == T_START_GPS
    assert gps_seconds_to_datetime(start_gps(None, 7)).isoformat() == "2024-06-12T16:07:00+00:00"
    for seed in (0, 3):
        assert main(["simulate", str(tmp_path / f"s{seed}"), *small, "--seed", str(seed)]) == 0
    assert first(tmp_path / "s0").isoformat() == "2024-06-12T16:00:00+00:00"
    assert first(tmp_path / "s3").isoformat() == "2024-06-12T16:03:00+00:00"
    capsys.readouterr()
    assert main(["simulate", str(tmp_path / "c"), *small, "--start", "yesterday"]) == 2
    assert "--start" in capsys.readouterr().err
