"""OpenGL rendering of a cube onto a grid (real headless EGL; no skips: a missing EGL fails here)."""

from __future__ import annotations

import math
import pickle

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from archive.errors import InputError
from archive.grid import Grid
from archive.geometry.navigation import LocalFrame, Poses
from archive.render.context import get_context, gl_info
from archive.render.mesh import build_mesh
from archive.render.reference import reference_lookup, reference_values
from archive.render.renderer import Lookup, rasterize_lookup, render_cube, render_lookup
from archive.sources import Radiometry
from helpers import FOV

T = math.tan(math.radians(FOV / 2))
H = 40.0                     # flying height above ground, m
RATE = 270.0                 # Hz; 10 m/s -> 3.7 cm between lines (not a multiple of the GSD)
SHUTTER = 2.0                # ms
GSD = 0.04
# Origin off the GSD lattice, so that no pixel centre falls exactly on a line or sample boundary.
FRAME = LocalFrame(32616, 500000.0071, 3900000.0133, 100.0)


@pytest.fixture(autouse=True)
def no_gl_errors():
    ctx = get_context()
    assert ctx.error == "GL_NO_ERROR"
    yield
    assert ctx.error == "GL_NO_ERROR"


def flight(lines, attitude=None, speed=10.0):
    t = 5000.0 + np.arange(lines) / RATE
    pos = np.zeros((lines, 3))
    pos[:, 0] = speed * (t - 5000.0)
    pos[:, 2] = FRAME.origin_alt - (110.0 + H)
    return Poses(t, pos, Rotation.identity(lines) if attitude is None else attitude, FRAME)


def pattern(nb, lines, samples):
    """DN = 16 * sample + line + 1000 * band, uint16 (bands, lines, samples)."""
    b, li, s = np.meshgrid(np.arange(nb), np.arange(lines), np.arange(samples), indexing="ij")
    return (16 * s + li + 1000 * b).astype(np.uint16)


def grid_around(mesh, margin=0.3):
    w, s, e, n = mesh.bounds_utm()
    return Grid.from_bounds(FRAME.epsg, w - margin, s - margin, e + margin, n + margin, GSD)


def nadir_cube(nb, lines, samples):
    """(mesh, DN, grid) of the nadir flight's cube: its mesh over ground 110 m below the frame's
    origin, :func:`pattern` DN (bands, lines, samples) and :func:`grid_around` its mesh."""
    mesh = build_mesh(flight(lines), FOV, 110.0, SHUTTER, RATE)
    return mesh, pattern(nb, lines, samples), grid_around(mesh)


def expected_nadir(grid, lines, samples):
    """Analytic (line, sample) of each pixel centre for the nadir flight, -1 outside."""
    x, y = grid.xy_centres()
    e = x[None, :] - FRAME.origin_e
    n = y[:, None] - FRAME.origin_n
    n0 = 10.0 * SHUTTER / 2000.0                      # line 0 at mid-exposure
    spacing = 10.0 / RATE
    line = np.floor((n - n0) / spacing + 0.5) + 0 * e
    s = np.floor((e / H + T) / (2 * T) * samples) + 0 * n
    inside = (n >= n0) & (n <= n0 + (lines - 1) * spacing) & (np.abs(e) < H * T)
    return np.where(inside, line, -1).astype(int), np.where(inside, s, -1).astype(int), inside


def radiometry(nb, lines, samples, saturation=None, seed=1):
    rng = np.random.default_rng(seed)
    return Radiometry(
        dark=rng.uniform(0, 50, (nb, samples)).astype(np.float32),
        gain=rng.uniform(0.5, 2, (nb, samples)).astype(np.float32),
        response=rng.uniform(0.5, 1.5, lines).astype(np.float32),
        saturation=saturation,
    )


def test_gl_info_reports_limits():
    info = gl_info()
    assert info["max_texture_size"] >= 4096
    assert info["version_code"] >= 330
    assert isinstance(info["renderer"], str) and info["renderer"]


def test_nadir_flight_renders_the_expected_pixels_with_radiometry():
    nb, lines, samples = 6, 150, 96
    mesh, dn, grid = nadir_cube(nb, lines, samples)
    rad = radiometry(nb, lines, samples)
    result = render_cube(mesh, dn, rad, grid, bands_per_pass=4)     # 2 passes
    assert result.values.shape == (nb, *grid.shape) and result.values.dtype == np.float32
    line, sample, inside = expected_nadir(grid, lines, samples)

    # Coverage: every pixel centre inside the analytic footprint, none outside it.
    assert (result.covered == inside).mean() > 0.999
    assert np.array_equal(np.isnan(result.values[0]), ~result.covered)
    assert np.isnan(result.values[:, ~inside & ~result.covered]).all()

    both = inside & result.covered
    got = result.values[0][both]
    exp_dn = 16 * sample[both] + line[both]
    raw = (got / rad.gain[0][sample[both]] * rad.response[line[both]] + rad.dark[0][sample[both]])
    exact = np.abs(raw - exp_dn) < 0.05
    assert exact.mean() > 0.999, exact.mean()

    # Radiometry of every band at the exactly matching pixels.
    li, si = line[both][exact], sample[both][exact]
    for b in range(nb):
        want = (dn[b, li, si] - rad.dark[b, si].astype(np.float64)) * rad.gain[b, si] / rad.response[li]
        np.testing.assert_allclose(result.values[b][both][exact], want, rtol=2e-6, atol=1e-4)
    assert not result.saturated.any()


@pytest.mark.parametrize("per_pass", [1, 2, 3])
def test_bands_per_pass_do_not_change_values(per_pass):
    nb, lines, samples = 5, 60, 40
    mesh, dn, grid = nadir_cube(nb, lines, samples)
    rad = radiometry(nb, lines, samples)
    four = render_cube(mesh, dn, rad, grid, bands_per_pass=4)
    other = render_cube(mesh, dn, rad, grid, bands_per_pass=per_pass)
    np.testing.assert_array_equal(other.values, four.values)
    np.testing.assert_array_equal(other.covered, four.covered)


def test_saturation_flag_marks_pixels_of_saturated_samples():
    nb, lines, samples = 6, 80, 64
    mesh = build_mesh(flight(lines), FOV, 110.0, SHUTTER, RATE)
    dn = pattern(nb, lines, samples)
    dn[5, 20:30, 10:20] = 65535                    # band 5: second pass, second component
    grid = grid_around(mesh)
    result = render_cube(mesh, dn, radiometry(nb, lines, samples, saturation=65535), grid)
    line, sample, inside = expected_nadir(grid, lines, samples)
    want = inside & (line >= 20) & (line < 30) & (sample >= 10) & (sample < 20)
    assert want.sum() > 300
    assert (result.saturated == want).mean() > 0.998
    assert result.saturated[want].mean() > 0.97
    assert not (result.saturated & ~result.covered).any()
    none = render_cube(mesh, dn, radiometry(nb, lines, samples, saturation=None), grid)
    assert not none.saturated.any()


def test_windows_and_line_chunks_equal_a_single_render():
    nb, lines, samples = 4, 200, 64
    mesh, dn, grid = nadir_cube(nb, lines, samples)
    rad = radiometry(nb, lines, samples, saturation=3000)
    whole = render_cube(mesh, dn, rad, grid)
    tiled = render_cube(mesh, dn, rad, grid, max_size=70)   # 70-px windows, 70-line textures
    assert grid.width > 70 * 8 and grid.height > 70 * 2
    np.testing.assert_array_equal(tiled.values, whole.values)
    np.testing.assert_array_equal(tiled.covered, whole.covered)
    np.testing.assert_array_equal(tiled.saturated, whole.saturated)
    assert whole.saturated.any()


def test_grid_windows_far_or_partial():
    nb, lines, samples = 2, 40, 32
    mesh = build_mesh(flight(lines), FOV, 110.0, SHUTTER, RATE)
    dn = pattern(nb, lines, samples)
    full = render_cube(mesh, dn, None, grid_around(mesh))
    far = Grid(FRAME.epsg, GSD, FRAME.origin_e + 100.0, FRAME.origin_n + 100.0, 20, 10)
    assert np.isnan(render_cube(mesh, dn, None, far).values).all()
    # A window of the big grid renders exactly the same pixels as the big grid.
    r0, c0 = 5, 400
    win = full.grid.window(r0, c0, 20, 300)
    part = render_cube(mesh, dn, None, win)
    np.testing.assert_array_equal(part.values, full.values[:, r0:r0 + 20, c0:c0 + 300])
    with pytest.raises(InputError, match="lines"):
        render_cube(mesh, dn[:, :-1], None, win)


def test_float_dn_matches_integer_dn():
    nb, lines, samples = 3, 50, 32
    mesh, dn, grid = nadir_cube(nb, lines, samples)
    a = render_cube(mesh, dn, None, grid)
    b = render_cube(mesh, dn.astype(np.float32), None, grid)
    np.testing.assert_array_equal(a.values, b.values)


def test_rolled_pitched_camera_agrees_with_the_cpu_reference():
    nb, lines, samples = 3, 120, 200
    k = np.arange(lines)
    euler = np.stack([0.2 + 0.002 * k, 0.08 * np.sin(k / 15.0), 0.17 + 0.05 * np.cos(k / 20.0)], axis=1)
    att = Rotation.from_euler("ZYX", euler)
    mesh = build_mesh(flight(lines, attitude=att), FOV, 110.0, SHUTTER, RATE)
    dn = pattern(nb, lines, samples)
    rad = radiometry(nb, lines, samples)
    grid = grid_around(mesh)
    result = render_cube(mesh, dn, rad, grid)
    x, y = grid.xy_centres()
    rng = np.random.default_rng(3)
    rows = rng.integers(0, grid.height, 4000)
    cols = rng.integers(0, grid.width, 4000)
    ref_line, ref_sample, ref_cov = reference_lookup(mesh, samples, x[cols], y[rows])
    assert ref_cov.sum() > 1000
    got_cov = result.covered[rows, cols]
    assert (got_cov == ref_cov).mean() > 0.995
    ref = reference_values(mesh, dn, rad, x[cols], y[rows])
    both = got_cov & ref_cov
    got = result.values[:, rows, cols][:, both]
    close = np.isclose(got, ref[:, both], rtol=1e-5, atol=1e-3).all(axis=0)
    assert close.mean() > 0.99, close.mean()


def test_each_thread_gets_its_own_context_and_the_same_pixels():
    import threading

    nb, lines, samples = 2, 40, 32
    mesh, dn, grid = nadir_cube(nb, lines, samples)
    here = render_cube(mesh, dn, None, grid)
    out = {}

    def work():
        ctx = get_context()
        out["same_ctx"] = ctx is get_context()
        out["ctx"] = ctx
        out["result"] = render_cube(mesh, dn, None, grid)
        out["error"] = ctx.error

    thread = threading.Thread(target=work)
    thread.start()
    thread.join()
    assert out["same_ctx"] and out["ctx"] is not get_context()
    assert out["error"] == "GL_NO_ERROR"
    np.testing.assert_array_equal(out["result"].values, here.values)


def rolled_pitched(lines):
    k = np.arange(lines)
    euler = np.stack([0.2 + 0.002 * k, 0.08 * np.sin(k / 15.0), 0.17 + 0.05 * np.cos(k / 20.0)], axis=1)
    return build_mesh(flight(lines, attitude=Rotation.from_euler("ZYX", euler)), FOV, 110.0, SHUTTER, RATE)


@pytest.mark.parametrize("per_pass", [4, 8, 6])
def test_lookup_then_bands_equals_render_cube(per_pass):
    nb, lines, samples = 11, 120, 200
    mesh = rolled_pitched(lines)
    dn = pattern(nb, lines, samples)
    dn[9, 90:110, 50:90] = 65535                   # saturated in band 9 only (second group of 8)
    rad = radiometry(nb, lines, samples, saturation=65535)
    grid = grid_around(mesh)
    whole = render_cube(mesh, dn, rad, grid)
    lookup = rasterize_lookup(mesh, grid, samples)
    assert isinstance(lookup, Lookup) and lookup.line.dtype == np.int32 and lookup.line.shape == grid.shape
    result = render_lookup(lookup, dn, rad, per_pass)
    np.testing.assert_array_equal(result.values, whole.values)
    np.testing.assert_array_equal(result.covered, whole.covered)
    np.testing.assert_array_equal(result.saturated, whole.saturated)
    assert 300 < result.saturated.sum() < result.covered.sum() / 10
    # NaN exactly where not covered, in every band; the lookup's -1 marks the same pixels.
    assert np.array_equal(np.isnan(result.values), np.broadcast_to(~result.covered, result.values.shape))
    np.testing.assert_array_equal(lookup.line >= 0, result.covered)
    np.testing.assert_array_equal(lookup.sample >= 0, result.covered)
    assert lookup.sample.max() == samples - 1 and lookup.line.max() == lines - 1
    # The values are the radiometry of the DN at the lookup's (line, sample).
    li, si = lookup.line[result.covered], lookup.sample[result.covered]
    want = (dn[:, li, si] - rad.dark[:, si].astype(np.float64)) * rad.gain[:, si] / rad.response[li]
    np.testing.assert_allclose(result.values[:, result.covered], want, rtol=2e-6, atol=1e-4)
    assert get_context().error == "GL_NO_ERROR"


def test_lookup_pickles_and_is_reused_for_band_groups():
    nb, lines, samples = 6, 60, 40
    mesh, dn, grid = nadir_cube(nb, lines, samples)
    lookup = pickle.loads(pickle.dumps(rasterize_lookup(mesh, grid, samples)))
    assert lookup.grid == grid and (lookup.lines, lookup.samples) == (lines, samples)
    whole = render_cube(mesh, dn, None, grid)
    first = render_lookup(lookup, dn[:2], None)
    rest = render_lookup(lookup, dn[2:], None, 8)
    np.testing.assert_array_equal(np.concatenate([first.values, rest.values]), whole.values)
    assert lookup.box() is not None and whole.covered.sum() > 1000
    with pytest.raises(InputError, match="lookup"):
        render_lookup(lookup, dn[:, :, :-1], None)
    with pytest.raises(InputError, match="bands_per_pass"):
        render_lookup(lookup, dn, None, 9)


def test_lookup_indices_equal_the_cpu_reference():
    lines, samples = 120, 200
    mesh = rolled_pitched(lines)
    grid = grid_around(mesh)
    lookup = rasterize_lookup(mesh, grid, samples)
    x, y = grid.xy_centres()
    rng = np.random.default_rng(4)
    rows = rng.integers(0, grid.height, 5000)
    cols = rng.integers(0, grid.width, 5000)
    ref_line, ref_sample, ref_cov = reference_lookup(mesh, samples, x[cols], y[rows])
    got_line, got_sample = lookup.line[rows, cols], lookup.sample[rows, cols]
    assert ref_cov.sum() > 1500
    assert ((got_line >= 0) == ref_cov).mean() > 0.995
    both = (got_line >= 0) & ref_cov
    same = (got_line[both] == ref_line[both]) & (got_sample[both] == ref_sample[both])
    assert same.mean() > 0.99, same.mean()
    # Off by at most one line / sample where float rounding at a boundary decides.
    assert np.abs(got_line[both] - ref_line[both]).max() <= 1
    assert np.abs(got_sample[both] - ref_sample[both]).max() <= 1


def test_lookup_windows_and_line_chunks_equal_a_single_pass():
    nb, lines, samples = 7, 200, 64
    mesh, dn, grid = nadir_cube(nb, lines, samples)
    rad = radiometry(nb, lines, samples, saturation=3000)
    whole = rasterize_lookup(mesh, grid, samples)
    tiled = rasterize_lookup(mesh, grid, samples, max_size=70)
    np.testing.assert_array_equal(tiled.line, whole.line)
    np.testing.assert_array_equal(tiled.sample, whole.sample)
    one = render_lookup(whole, dn, rad, 8)
    many = render_lookup(whole, dn, rad, 8, max_size=70)      # 70-px windows, 70-line textures
    np.testing.assert_array_equal(many.values, one.values)
    np.testing.assert_array_equal(many.saturated, one.saturated)
    assert one.saturated.any() and get_context().error == "GL_NO_ERROR"


def test_nothing_covered_gives_an_empty_lookup():
    lines, samples = 40, 32
    mesh = build_mesh(flight(lines), FOV, 110.0, SHUTTER, RATE)
    far = Grid(FRAME.epsg, GSD, FRAME.origin_e + 100.0, FRAME.origin_n + 100.0, 20, 10)
    lookup = rasterize_lookup(mesh, far, samples)
    assert (lookup.line == -1).all() and (lookup.sample == -1).all() and lookup.box() is None
    result = render_lookup(lookup, pattern(3, lines, samples), None)
    assert np.isnan(result.values).all() and not result.covered.any()
