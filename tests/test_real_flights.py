"""Real flights, not ideal ones (issue 9): what real recorders do, checked on the real Resonon
samples (skipped where they are absent) and on flights the simulator makes with each situation."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from archive.formats.lcf import read_lcf
from archive.formats.times import read_times
from archive.geometry.navigation import LocalFrame, Poses, frame_interval, joined, local_frame_for, strip_slices
from archive.params import NavigationParams
from archive.render.mesh import build_mesh
from archive.sources.navigation import CubeNavigation, FlightNavigation
from helpers import FOV, eroded_dilated



# ---------------------------------------------------------------------------------------------
# the real Juvika pair _12 -> _13
# ---------------------------------------------------------------------------------------------
def _juvika(folder, sync: float) -> FlightNavigation:
    cubes = []
    for k in (12, 13):
        base = folder / f"Juvika_June2022_Pika_L_{k}"
        cubes.append(CubeNavigation(read_times(base.with_suffix(".bil.times")), read_lcf(base.with_suffix(".lcf")),
                                    None, str(base.with_suffix(".lcf"))))
    return FlightNavigation(cubes, local_frame_for(cubes[0].lcf), NavigationParams(sync_offset=sync))


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
    from archive.geometry.navigation import interpolate_poses

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


# ---------------------------------------------------------------------------------------------
# simulated flights with what real recorders do, rendered and compared with the truth
# ---------------------------------------------------------------------------------------------
SMALL = dict(bands=4, samples=64, lines=120)


def _simulate(tmp_path_factory, name, **options):
    from archive.simulator.command import simulate_flight

    directory = tmp_path_factory.mktemp(name) / "flight"
    return directory, simulate_flight(directory, **{**SMALL, **options})


def _mosaic(sources, gsd, **keywords):
    """The radiance mosaic (band, y, x), computed in this process, and its Grid."""
    import archive
    from archive.grid import Grid

    ds = archive.mosaic([str(s) for s in sources], gsd=gsd, fov=FOV, mode="radiance", **keywords)
    t = ds.rio.transform()
    grid = Grid(ds.rio.crs.to_epsg(), t.a, t.c, t.f, ds.sizes["x"], ds.sizes["y"])
    return ds["radiance"].values, grid


def _coverage(truths, grid, d_px=1.5):
    """(eroded, dilated) truth coverage on ``grid`` (in its CRS), by d_px pixels."""
    eroded = np.zeros(grid.shape, bool)
    dilated = np.zeros(grid.shape, bool)
    for truth in truths:
        e, d = eroded_dilated(lambda xx, yy: truth.covered(xx, yy, crs=grid.epsg), grid, d_px)
        eroded |= e
        dilated |= d
    return eroded, dilated


@pytest.mark.parametrize("dropped", [1, 2])
def test_no_hole_at_seams_with_dropped_frames_and_shutter_steps(tmp_path_factory, dropped):
    directory, truth = _simulate(tmp_path_factory, f"seam{dropped}", cubes=4, cubes_per_pass=2,
                                 dropped_frames=dropped, shutter_steps=True, seed=11)
    assert len({c.shutter_ms for c in truth.cubes}) > 1
    values, grid = _mosaic([directory], truth.nominal_gsd, ground_height=truth.ground_height)
    eroded, dilated = _coverage([truth], grid)
    has_value = ~np.isnan(values).any(axis=0)
    assert eroded.sum() > 1000
    assert not (eroded & ~has_value).any(), f"{(eroded & ~has_value).sum()} NaN pixels inside the swath"
    assert not (has_value & ~dilated).any(), f"{(has_value & ~dilated).sum()} values outside"


@pytest.mark.parametrize("sync", [-0.5, -0.05, 0.05, 0.5])
def test_poses_at_cube_starts_with_sync_offsets(tmp_path_factory, sync):
    from archive.ingest.command import ingest
    from archive.sources import open_source

    # cubes of 1 s (250 lines), longer than the largest offset: each cube start lies in the previous .lcf
    directory, truth = _simulate(tmp_path_factory, "sync", cubes=4, cubes_per_pass=2, sync_offset=sync, seed=4,
                                 lines=250, samples=32, bands=2)
    params = NavigationParams(sync_offset=sync)
    raw = open_source(directory, params)
    archive_dir = directory.parent / "archive"
    [result] = ingest([str(directory)], archive_dir, FOV, progress=False, sync_offset=sync)
    col = open_source(result.cid, NavigationParams(sync_offset=None), archive=archive_dir)
    checked = 0
    for k, cube in enumerate(truth.cubes):
        p, q = raw.poses(k), col.poses(k)
        np.testing.assert_array_equal(p.position, q.position)          # raw and collection agree
        np.testing.assert_array_equal(p.attitude.as_quat(), q.attitude.as_quat())
        assert (p.valid is None) == (q.valid is None)
        np.testing.assert_allclose(p.time, cube.line_time, atol=1e-6)
        # lines inside the flight's navigation (not extrapolated) are interpolated to the truth
        _, outside = raw.navigation.locate(p.time)
        inside = outside == 0.0
        first_of_strip = k in [s[0] for s in truth.strips]
        if not first_of_strip or sync > 0:
            assert inside[0], (k, outside[0])          # a cube start reaches into the previous .lcf
        if not inside.any():
            continue
        utm = p.utm()
        err = np.linalg.norm(utm[inside] - np.asarray(cube.position_utm)[inside], axis=1)
        assert err.max() < 1e-3, (k, err.max())
        angle = np.degrees((p.attitude[inside].inv() * cube.attitude[inside]).magnitude())
        assert angle.max() < 1e-3, (k, angle.max())
        if inside[0]:
            checked += 1
        if p.valid is not None:                          # left out: only lines of a strip's first cube
            assert first_of_strip and sync < 0
    assert checked >= 2


def test_turns_up_to_70_degrees_keep_the_output_bounded(tmp_path_factory):
    from archive.run import pipeline

    directory, truth = _simulate(tmp_path_factory, "turns", cubes=4, cubes_per_pass=2, lines=160, bank_deg=70.0,
                                 record_turns=True, seed=5)
    assert max(truth.bank_deg for _ in [0]) == 70.0
    out = directory.parent / "out.zarr"
    import archive

    s = archive.georectify([str(directory)], out, gsd=2 * truth.nominal_gsd, fov=FOV, ground_height=truth.ground_height,
                       mode="radiance", quiet=True)
    assert s["left_out"].get("view angle", 0) > 0
    assert "line" in pipeline.describe(s) and "beyond the view-angle limit" in pipeline.describe(s)
    # the straight passes' footprint, grown by what a line at the 40 deg limit can reach (~34 m at 40 m)
    rings = np.concatenate(truth.footprint())
    w, s_, e, n = rings[:, 0].min(), rings[:, 1].min(), rings[:, 0].max(), rings[:, 1].max()
    assert s["width"] * s["gsd"] <= (e - w) + 2 * 40.0 * np.tan(np.radians(40.0)) + 2
    assert s["height"] * s["gsd"] <= (n - s_) + 2 * 40.0 * np.tan(np.radians(40.0)) + 2


def test_no_smear_across_a_pause(tmp_path_factory):
    directory, truth = _simulate(tmp_path_factory, "pause", cubes=2, cubes_per_pass=2, pause_s=0.6, pause_cube=0,
                                 seed=6)
    values, grid = _mosaic([directory], truth.nominal_gsd, ground_height=truth.ground_height)
    eroded, dilated = _coverage([truth], grid)
    has_value = ~np.isnan(values).any(axis=0)
    assert len(truth.footprint()) >= 2                # the pause splits the pass
    assert not (has_value & ~dilated).any(), f"{(has_value & ~dilated).sum()} values on ground flown while paused"
    assert not (eroded & ~has_value).any()


def _shifts(values, grid, truth_of, band=2):
    """Lucas-Kanade shifts (dy, dx) px of textured 16 px windows against the truth radiance."""
    from tests.test_render_truth import textured_shifts

    return textured_shifts(values[band], grid, truth_of, band, 16)


def _shift_ok(shifts) -> bool:
    size = np.hypot(shifts[:, 0], shifts[:, 1])
    return np.median(size) <= 0.2 and np.percentile(size, 95) <= 0.5 and np.all(np.abs(shifts.mean(axis=0)) < 0.1)


def test_two_flights_across_a_zone_border_mosaic_into_one_grid(tmp_path_factory):
    west_dir, west = _simulate(tmp_path_factory, "west", cubes=2, cubes_per_pass=1, lon=-90.00005, seed=7,
                               samples=128, lines=200)
    east_dir, east = _simulate(tmp_path_factory, "east", cubes=2, cubes_per_pass=1, lon=-89.9995, seed=8,
                               samples=128, lines=200)
    assert {west.epsg, east.epsg} == {32615, 32616}
    assert west.ground_height == east.ground_height
    values, grid = _mosaic([west_dir, east_dir], west.nominal_gsd, ground_height=west.ground_height)
    assert grid.epsg in (32615, 32616)
    x, y = grid.xy_centres()

    def truth_of(xx, yy):
        inside = [t for t in (west, east) if t.covered(xx, yy, crs=grid.epsg).all()]
        others = [t for t in (west, east) if t.covered(xx, yy, crs=grid.epsg).any() and t not in inside]
        return inside[0] if len(inside) == 1 and not others else None

    shifts = _shifts(values, grid, truth_of)
    assert len(shifts) >= 10
    assert _shift_ok(shifts), shifts
    # both flights are in the grid
    for truth in (west, east):
        xx, yy = np.meshgrid(x, y)
        assert (truth.covered(xx, yy, crs=grid.epsg) & ~np.isnan(values[0])).sum() > 500


def test_boresight_and_lever_arm_from_the_cli_recover_the_truth(tmp_path_factory):
    import xarray as xr

    from archive.cli import main
    from archive.grid import Grid

    directory, truth = _simulate(tmp_path_factory, "mount", cubes=2, cubes_per_pass=2, seed=9, samples=128,
                                 lines=200, boresight_deg=(1.0, 2.25, 0.5), lever_arm_m=(0.3, 0.1, 0.2))
    results = {}
    for name, extra in (("mounted", ["--boresight", "1,2.25,0.5", "--lever-arm", "0.3,0.1,0.2"]), ("plain", [])):
        out = directory.parent / f"{name}.zarr"
        assert main(["render", str(directory), "--fov", str(FOV), "--gsd", str(truth.nominal_gsd), "--mode",
                     "radiance", "--ground-height", str(truth.ground_height), "--out", str(out), "--quiet",
                     *extra]) == 0
        ds = xr.open_zarr(out, decode_coords="all")
        t = ds.rio.transform()
        grid = Grid(ds.rio.crs.to_epsg(), t.a, t.c, t.f, ds.sizes["x"], ds.sizes["y"])
        results[name] = _shifts(ds["radiance"].values, grid, lambda xx, yy: truth)
    assert len(results["mounted"]) >= 10
    assert _shift_ok(results["mounted"]), results["mounted"]
    assert not _shift_ok(results["plain"])   # the test can fail: the mounting moves the image by pixels


# ---------------------------------------------------------------------------------------------
# smaller defects: ground height auto, signed DN, white reference span, .lcf column 10
# ---------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def small(tmp_path_factory):
    return _simulate(tmp_path_factory, "small", cubes=2, cubes_per_pass=2, seed=12, bands=3, samples=32, lines=60)


def _set_ground_elevation(directory, value: str) -> None:
    for hdr in directory.glob("*.hdr"):
        text = hdr.read_text()
        lines = [ln for ln in text.splitlines() if not ln.startswith("ground elevation")]
        hdr.write_text("\n".join(lines[:-1] + [f"ground elevation = {value}", lines[-1]]) + "\n")


def test_ground_height_auto(small, tmp_path):
    import shutil

    from archive.errors import InputError
    from archive.ingest.command import ingest
    from archive.sources import open_source
    from archive.sources.ground import auto_ground_height

    directory, truth = small
    params = NavigationParams()
    assert auto_ground_height([open_source(directory, params)]) == truth.ground_height
    # a collection keeps the height it was ingested with, whatever its headers say
    copy = tmp_path / "zero"
    shutil.copytree(directory, copy)
    _set_ground_elevation(copy, "0.000")                 # Resonon's unset default
    [r] = ingest([str(copy)], tmp_path / "a", FOV, ground_height=truth.ground_height - 3.0, progress=False)
    col = open_source(r.cid, params, archive=tmp_path / "a")
    assert col.header(0).metadata["ground elevation"] == 0.0
    assert auto_ground_height([col]) == truth.ground_height - 3.0
    # a raw flight whose header holds the unset 0: refused, asking for --ground-height or --dem
    with pytest.raises(InputError, match=r"unset default 0.*--ground-height M.*--dem"):
        auto_ground_height([open_source(copy, params)])
    # ground at or above the camera, or implausibly far below it
    for value, match in (("200", "not below the camera"), ("-9000", "implausibly far below")):
        _set_ground_elevation(copy, value)
        with pytest.raises(InputError, match=match):
            auto_ground_height([open_source(copy, params)])


def test_signed_int16_cubes_render_their_negative_dn(small):
    from archive.graph.plan import cube_meshes
    from archive.grid import Grid
    from archive.render.reference import reference_values
    from archive.render.renderer import render_cube
    from archive.sources import open_source

    directory, truth = small
    src = open_source(directory, NavigationParams())
    mesh = cube_meshes(src, FOV, truth.ground_height)[0]
    dn = src.read_bands(0, [0, 1]).astype(np.int16) - np.int16(500)   # dark-subtracted: negative DN
    assert dn.min() < 0
    w, s, e, n = mesh.bounds_utm()
    grid = Grid.from_bounds(mesh.epsg, w, s, e, n, truth.nominal_gsd)
    result = render_cube(mesh, dn, None, grid)
    rows, cols = np.nonzero(result.covered)
    x, y = grid.xy_centres()
    ref = reference_values(mesh, dn, None, x[cols], y[rows])
    assert (result.values[:, rows, cols] == ref).all(axis=0).mean() > 0.99
    assert np.nanmin(result.values) < 0


def test_white_reference_must_span_the_bands(small, tmp_path):
    import archive
    from archive.errors import InputError

    directory, truth = small
    wl = np.asarray(truth.wavelengths)
    short = tmp_path / "white.txt"
    np.savetxt(short, np.stack([np.linspace(wl.min(), wl.max() - 200, 5), np.full(5, 100.0)], axis=1))
    with pytest.raises(InputError, match="white reference spans"):
        archive.mosaic([str(directory)], gsd=1.0, fov=FOV, mode="reflectance", white_reference=short)


def test_lcf_rows_flagged_do_not_use_are_left_out(small, tmp_path):
    import shutil

    from archive.sources import open_source

    directory, truth = small
    copy = tmp_path / "flagged"
    shutil.copytree(directory, copy)
    lcf = sorted(copy.glob("*.lcf"))[0]
    rows = [r.split("\t") for r in lcf.read_text().splitlines()]
    for r in rows[10:14]:                              # four rows with a broken fix, flagged 'do not use'
        r[4], r[5], r[9] = "200.0", "95.0", "0"
    lcf.write_text("\n".join("\t".join(r) for r in rows) + "\n")
    params = NavigationParams()
    good, flagged = open_source(directory, params), open_source(copy, params)
    assert flagged.navigation.cubes[0].lcf.use is not None and (~flagged.navigation.cubes[0].lcf.use).sum() == 4
    np.testing.assert_allclose(flagged.poses(0).position, good.poses(0).position, atol=2e-3)
