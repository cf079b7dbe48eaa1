"""The renderer against the simulator's truth: coverage, radiometry and sub-pixel geometry.

A simulated flight (two strips of two cubes, cubes with different shutter and gain, 20 deg
heading, ~2.9 deg west of the UTM central meridian, attitude wobble) is read back through
RawFlightSource like a real one, rendered cube by cube at the nominal GSD and half of it, mosaicked
"later wins", and compared with the truth the simulator traced independently.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from archive.grid import Grid
from archive.params import NavigationParams
from archive.render.reference import reference_values
from archive.render.renderer import render_cube
from archive.simulator.command import simulate_flight
from archive.sources import RawFlightSource
from helpers import eroded_dilated

BANDS = 6


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    directory = tmp_path_factory.mktemp("truth") / "flight"
    truth = simulate_flight(directory, cubes=4, bands=BANDS, samples=128, lines=200, seed=0)
    source = RawFlightSource(directory, NavigationParams())
    from archive.graph.plan import cube_meshes

    meshes = dict(enumerate(cube_meshes(source, truth.fov_deg, truth.ground_height)))
    bounds = np.array([m.bounds_utm() for m in meshes.values()])
    return truth, source, meshes, (bounds[:, 0].min(), bounds[:, 1].min(), bounds[:, 2].max(), bounds[:, 3].max())


@pytest.fixture(scope="module", params=[1.0, 0.5], ids=["nominal", "half"])
def rendered(request, flight):
    """Per-cube renders (raw and radiance) on one grid, and their "later wins" mosaics."""
    truth, source, meshes, (w, s, e, n) = flight
    gsd = truth.nominal_gsd * request.param
    grid = Grid.from_bounds(truth.epsg, w - 1, s - 1, e + 1, n + 1, gsd)
    out = {"grid": grid, "raw": {}, "radiance": {}}
    bands = list(range(BANDS))
    for k, mesh in meshes.items():
        dn = source.read_bands(k, bands)
        for mode in ("raw", "radiance"):
            out[mode][k] = render_cube(mesh, dn, source.radiometry(k, bands, mode), grid)
    for mode in ("raw", "radiance"):
        mosaic = np.full((BANDS, *grid.shape), np.nan, np.float32)
        for k in sorted(out[mode]):
            r = out[mode][k]
            mosaic[:, r.covered] = r.values[:, r.covered]
        out[mode + "_mosaic"] = mosaic
    return out


def test_coverage_matches_the_true_footprint(flight, rendered):
    truth = flight[0]
    grid = rendered["grid"]
    eroded, dilated = eroded_dilated(truth.covered, grid, 1.5)
    for mode in ("raw", "radiance"):
        has_value = ~np.isnan(rendered[mode + "_mosaic"]).any(axis=0)
        assert eroded.sum() > 5000
        assert not (eroded & ~has_value).any(), f"{(eroded & ~has_value).sum()} NaN pixels inside"
        assert not (has_value & ~dilated).any(), f"{(has_value & ~dilated).sum()} values outside"
    # Consecutive cubes of a strip meet without overlap: at most a pixel row shared by float noise.
    raw = rendered["raw"]
    for strip in truth.strips:
        for a, b in zip(strip, strip[1:]):
            assert (raw[a].covered & raw[b].covered).sum() <= grid.width // 20


def test_raw_values_are_the_file_dn_the_reference_sees(flight, rendered):
    _, source, meshes, _ = flight
    grid = rendered["grid"]
    x, y = grid.xy_centres()
    rng = np.random.default_rng(0)
    for k, mesh in meshes.items():
        result = rendered["raw"][k]
        rows, cols = np.nonzero(result.covered)
        pick = rng.choice(rows.size, 1500, replace=False)
        rows, cols = rows[pick], cols[pick]
        ref = reference_values(mesh, source.read_bands(k, range(BANDS)), None, x[cols], y[rows])
        same = (result.values[:, rows, cols] == ref).all(axis=0)
        assert same.mean() > 0.99, (k, same.mean())


def test_radiance_of_homogeneous_patches(flight, rendered):
    """Median relative error of radiance in homogeneous patches, per band and per cube, < 2 %."""
    truth = flight[0]
    grid = rendered["grid"]
    x, y = grid.xy_centres()
    xx, yy = np.meshgrid(x, y)
    margin = 1.5 * max(grid.gsd, truth.nominal_gsd)   # a sample's footprint stays inside
    expected = np.full((BANDS, *grid.shape), np.nan)
    for patch in truth.homogeneous_patches():
        w, s, e, n = patch["interior"]
        inside = (xx > w + margin) & (xx < e - margin) & (yy > s + margin) & (yy < n - margin)
        value = truth.radiance(np.array([(w + e) / 2]), np.array([(s + n) / 2]))[:, 0]
        expected[:, inside] = value[:, None]
    exposures = set()
    for k, result in rendered["radiance"].items():
        use = result.covered & ~np.isnan(expected[0])
        assert use.sum() >= 40, f"cube {k}: only {use.sum()} patch pixels"
        rel = (result.values[:, use] - expected[:, use]) / expected[:, use]
        median = np.median(rel, axis=1)
        assert np.all(np.abs(median) < 0.02), (k, median)
        cube = truth.cubes[k]
        exposures.add((cube.shutter_ms, cube.gain_db))
    assert len(exposures) >= 3      # the test spans different shutters and gains


def lucas_kanade(reference: np.ndarray, image: np.ndarray, iterations: int = 4) -> np.ndarray:
    """Shift (dy, dx) in pixels such that image(p) ~ a * reference(p - shift) + b."""
    shift = np.zeros(2)
    core = (slice(2, -2), slice(2, -2))
    for _ in range(iterations):
        moved = ndimage.shift(reference, shift, order=3, mode="nearest")
        gy, gx = np.gradient(moved)
        a = np.stack([gy[core].ravel(), gx[core].ravel(), moved[core].ravel(),
                      np.ones(moved[core].size)], axis=1)
        coef, *_ = np.linalg.lstsq(a, image[core].ravel(), rcond=None)
        shift = shift - coef[:2] / coef[2]
    return shift


def test_lucas_kanade_measures_known_shifts():
    rng = np.random.default_rng(5)
    texture = ndimage.gaussian_filter(rng.normal(size=(48, 48)), 1.5)
    for true in [(0.3, -0.2), (-0.45, 0.1)]:
        shifted = 2.0 * ndimage.shift(texture, true, order=3, mode="nearest") + 1.0
        np.testing.assert_allclose(lucas_kanade(texture, shifted)[[0, 1]], true, atol=0.02)


def textured_shifts(image: np.ndarray, grid, truth_of, band: int, size: int) -> np.ndarray:
    """(n, 2) Lucas-Kanade shifts (dy, dx), px, of ``image`` (height, width: one band of a mosaic on
    ``grid``) against the truth's radiance of ``band`` box-averaged over each pixel, on the textured,
    fully covered ``size`` x ``size`` windows (half overlapping). truth_of(xx, yy): the Truth that
    holds those points (None: skip the window)."""
    x, y = grid.xy_centres()
    out = []
    for r in range(0, grid.height - size + 1, size // 2):
        for c in range(0, grid.width - size + 1, size // 2):
            window = image[r:r + size, c:c + size]
            if np.isnan(window).any():
                continue
            gy, gx = np.gradient(window)
            if np.sqrt(np.mean(gx**2 + gy**2)) < 0.02 * np.mean(window):
                continue                                  # too flat to measure a shift
            xx, yy = np.meshgrid(x[c:c + size], y[r:r + size])
            truth = truth_of(xx, yy)
            if truth is None:
                continue
            reference = truth.radiance_box(xx, yy, grid.gsd, supersample=4, crs=grid.epsg)[band]
            out.append(lucas_kanade(reference, window))
    return np.array(out)


def render_shifts(source, truth, ground: float, band: int) -> np.ndarray:
    """Truth shift test of a GL render of ``source`` (its cubes' meshes at ``ground`` m, each on the
    cubes' common grid at the nominal GSD, "later wins"): (n, 2) Lucas-Kanade shifts (px) of ``band``
    of the radiance mosaic against the truth on textured 24 x 24 windows (:func:`textured_shifts`)."""
    from archive.graph.plan import cube_meshes

    meshes = cube_meshes(source, truth.fov_deg, ground)
    bounds = np.array([m.bounds_utm() for m in meshes if m.rows >= 2])
    grid = Grid.from_bounds(truth.epsg, bounds[:, 0].min() - 1, bounds[:, 1].min() - 1, bounds[:, 2].max() + 1,
                            bounds[:, 3].max() + 1, truth.nominal_gsd)
    mosaic = np.full(grid.shape, np.nan, np.float32)
    for k, mesh in enumerate(meshes):
        if mesh.rows < 2:
            continue
        r = render_cube(mesh, source.read_bands(k, [band]), source.radiometry(k, [band], "radiance"), grid)
        mosaic[r.covered] = r.values[0][r.covered]
    return textured_shifts(mosaic, grid, lambda xx, yy: truth, band, 24)


def passes_truth_test(shifts: np.ndarray) -> bool:
    """Whether :func:`render_shifts` passes: at least 15 windows, median shift <= 0.2 px, 95th
    percentile <= 0.5 px."""
    if len(shifts) < 15:
        return False
    size = np.hypot(shifts[:, 0], shifts[:, 1])
    return bool(np.median(size) <= 0.2 and np.percentile(size, 95) <= 0.5)


def test_geometry_has_no_subpixel_shift(flight, rendered):
    """Rendered radiance vs the truth box-averaged over each pixel, on textured 32 x 32 windows."""
    truth = flight[0]
    grid = rendered["grid"]
    size = 32 if grid.gsd < truth.nominal_gsd * 0.75 else 24
    shifts = textured_shifts(rendered["radiance_mosaic"][3], grid, lambda xx, yy: truth, 3, size)
    assert len(shifts) >= 15
    size_px = np.hypot(shifts[:, 0], shifts[:, 1])
    assert np.median(size_px) <= 0.2, np.median(size_px)
    assert np.percentile(size_px, 95) <= 0.5, np.percentile(size_px, 95)
    assert np.all(np.abs(shifts.mean(axis=0)) < 0.1), shifts.mean(axis=0)
