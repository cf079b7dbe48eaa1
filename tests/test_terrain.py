"""Terrain (issue 11): inverse rendering over a DEM against the simulator's truth.

Two simulated flights of two passes each, ~40 m above the ground (flights, DEMs and truths made once
per session in conftest.py, shared with test_terrain_inputs.py):

- ``hills``: 12 m of relief (bumps of -4 to +8 m, slopes up to ~45 degrees), everything seen;
- ``ridge``: a 12 m ridge beside the second pass with an 83-degree back: a strip of ground behind it
  is seen by no line (the truth's :meth:`~archive.simulator.truth.Truth.visible`).

Rendered with ``--dem`` (the simulator's ``dem.tif``, 0.1 m, UTM with ellipsoidal heights declared)
through ``archive.mosaic`` and compared with the truth: sub-pixel shifts (Lucas-Kanade, as in
test_render_truth.py), coverage of the truly visible ground, hidden ground left NaN; the mesh's
straight-edge bound and ray hits directly; the depth test on folded triangles.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from helpers import FOV, eroded_dilated
from tests.test_render_truth import textured_shifts

BAND = 2


def mosaic(directory, gsd, **keywords):
    """(radiance (band, y, x), Grid) of ``archive.mosaic`` computed in this process."""
    import archive
    from archive.grid import Grid

    ds = archive.mosaic([str(directory)], gsd=gsd, fov=FOV, mode="radiance", **keywords)
    t = ds.rio.transform()
    grid = Grid(ds.rio.crs.to_epsg(), t.a, t.c, t.f, ds.sizes["x"], ds.sizes["y"])
    return ds["radiance"].values, grid


def visible_masks(truth, grid, d_px=1.5):
    """(eroded, dilated, covered): the truly visible ground on ``grid`` eroded and dilated by d_px
    pixels (every / any of the 9 points at +-d_px), and the footprint (visible or not)."""
    eroded, dilated = eroded_dilated(lambda xx, yy: truth.visible(xx, yy, crs=grid.epsg), grid, d_px)
    xx, yy = np.meshgrid(*grid.xy_centres())
    return eroded, dilated, truth.covered(xx, yy, crs=grid.epsg)


def shifts(values, grid, truth, band=BAND, size=None):
    """Lucas-Kanade shifts (dy, dx) px of textured, fully covered windows against the truth."""
    size = size or (32 if grid.gsd < truth.nominal_gsd * 0.75 else 24)
    return textured_shifts(values[band], grid, lambda xx, yy: truth, band, size)


def shift_stats(s) -> tuple[float, float, np.ndarray]:
    size = np.hypot(s[:, 0], s[:, 1])
    return float(np.median(size)), float(np.percentile(size, 95)), s.mean(axis=0)


def shift_ok(s) -> bool:
    median, p95, mean = shift_stats(s)
    return median <= 0.2 and p95 <= 0.5 and bool(np.all(np.abs(mean) < 0.1))


# ---------------------------------------------------------------------------------------------
# against the truth
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("scale", [1.0, 0.5], ids=["nominal", "half"])
def test_hills_render_with_the_dem_matches_the_truth(hills, scale):
    directory, truth = hills
    lo, hi = truth.terrain.relief
    assert truth.terrain.kind == "hills"
    gsd = truth.nominal_gsd * scale
    values, grid = mosaic(directory, gsd, dem=directory / "dem.tif")
    s = shifts(values, grid, truth)
    assert len(s) >= 25
    median, p95, mean = shift_stats(s)
    assert median <= 0.2 and p95 <= 0.5, (median, p95)
    assert np.all(np.abs(mean) < 0.1), mean
    # coverage: every truly visible pixel has a value, nothing beyond what is seen
    eroded, dilated, _ = visible_masks(truth, grid)
    has_value = ~np.isnan(values).any(axis=0)
    assert eroded.sum() > 5000
    assert not (eroded & ~has_value).any(), f"{(eroded & ~has_value).sum()} empty pixels on visible ground"
    assert not (has_value & ~dilated).any(), f"{(has_value & ~dilated).sum()} values beyond the seen ground"


def test_hills_relief_and_flat_rendering_fails(hills):
    """>= 10 m of relief under a camera ~40 m above the ground; the same flight rendered flat at the
    mean height under it fails the shift test by a clear margin (the test can fail)."""
    directory, truth = hills
    rings = np.concatenate(truth.footprint())
    xx, yy = np.meshgrid(np.linspace(rings[:, 0].min(), rings[:, 0].max(), 200),
                         np.linspace(rings[:, 1].min(), rings[:, 1].max(), 200))
    inside = truth.covered(xx, yy)
    ground = truth.terrain.height(xx[inside], yy[inside])
    assert ground.max() - ground.min() >= 10.0
    camera = np.concatenate([c.position_utm[:, 2] for c in truth.cubes])
    assert 35.0 <= camera.mean() - ground.mean() <= 45.0
    values, grid = mosaic(directory, truth.nominal_gsd, ground_height=float(ground.mean()))
    s = shifts(values, grid, truth)
    assert len(s) >= 20
    median, p95, _ = shift_stats(s)
    assert not shift_ok(s)
    assert p95 > 2.0 and median > 0.4, (median, p95)


def test_ridge_hidden_ground_stays_empty(ridge):
    """Ground behind the ridge that no line sees is NaN (no smear), every visible pixel has a value,
    and the rendered part still matches the truth."""
    directory, truth = ridge
    values, grid = mosaic(directory, truth.nominal_gsd / 2, dem=directory / "dem.tif")
    eroded, dilated, covered = visible_masks(truth, grid)
    has_value = ~np.isnan(values).any(axis=0)
    hidden = covered & ~dilated                       # inside the swath, seen by no line (with margin)
    assert hidden.sum() * grid.gsd**2 > 20.0, hidden.sum()    # real occlusion: a strip ~3 m wide, 12 m long
    assert not (has_value & hidden).any(), f"{(has_value & hidden).sum()} values on hidden ground"
    assert not (has_value & ~dilated).any(), f"{(has_value & ~dilated).sum()} values beyond the seen ground"
    assert not (eroded & ~has_value).any(), f"{(eroded & ~has_value).sum()} empty pixels on visible ground"
    s = shifts(values, grid, truth, band=1)
    assert len(s) >= 20
    assert shift_ok(s), shift_stats(s)


# ---------------------------------------------------------------------------------------------
# the mesh: straight-edge bound, ray hits, occlusion
# ---------------------------------------------------------------------------------------------
def test_terrain_mesh_bound_and_hits(hills, ridge):
    """Along every segment, the mesh's map position of a ray (on the chord, perspective-correct) is
    within EDGE_ERROR_PX of the ray's first hit on the DEM; hits are first hits, to a millimetre; the
    DEM surface is the simulator's terrain to a few millimetres."""
    from archive.terrain.dem import open_dem
    from archive.params import NavigationParams
    from archive.render.mesh import EDGE_ERROR_PX, build_mesh
    from archive.sources import RawFlightSource

    for (directory, truth), cube in ((hills, 0), (ridge, 3)):
        gsd = truth.nominal_gsd / 2
        src = RawFlightSource(directory, NavigationParams())
        poses = src.poses(cube)
        dem = open_dem(directory / "dem.tif")
        # no shutter, no neighbours: row k is line k at its pose
        mesh = build_mesh(poses, FOV, math.nan, 0.0, src.cubes[cube].framerate, terrain=dem, gsd=gsd)
        assert mesh.rows == len(poses) and mesh.per_row >= 30
        assert mesh.edge_error <= 0.5 * EDGE_ERROR_PX * gsd
        t = math.tan(math.radians(FOV) / 2)
        us = -t + 2 * t * mesh.columns
        rows = np.arange(0, mesh.rows, 7)
        line = mesh.line[rows].astype(int)
        pos, att = poses.position[line], poses.attitude[line]
        dense = np.linspace(-t, t, 1201)
        d = att.as_matrix()[:, None, :, 1] * dense[None, :, None] + att.as_matrix()[:, None, :, 2]
        origin = np.stack([pos[:, 1] + poses.frame.origin_e, pos[:, 0] + poses.frame.origin_n,
                           poses.frame.origin_alt - pos[:, 2]], axis=1)
        o = np.repeat(origin, dense.size, axis=0)
        enu = np.stack([d[..., 1], d[..., 0], -d[..., 2]], axis=-1).reshape(-1, 3)
        surface = dem.surface_under(poses.frame.epsg, o, [enu])
        lam, under = surface.intersect(o, enu)
        assert not under.any() and np.all(np.isfinite(lam))
        hit = o + lam[:, None] * enu
        assert np.max(np.abs(hit[:, 2] - surface.height(hit[:, 0], hit[:, 1]))) < 1e-3
        # first hits: the ray stays above the surface before its hit
        k = np.arange(0, len(o), 97)
        f = np.linspace(0.0, 1.0, 300)[:-3]
        q = o[k, None, :] + (lam[k, None, None] * f[None, :, None]) * enu[k, None, :]
        assert np.all(q[..., 2] - surface.height(q[..., 0], q[..., 1]) > -1e-3)
        # the DEM surface against the simulator's analytic terrain, under the hits
        assert np.percentile(np.abs(hit[:, 2] - truth.terrain.height(hit[:, 0], hit[:, 1])), 99) < 0.01
        # the mesh's position of every dense ray: on the chord of its segment
        lam = lam.reshape(len(rows), dense.size)
        j = np.clip(np.searchsorted(us, dense, side="right") - 1, 0, us.size - 2)
        la, lb = mesh.depth[rows][:, j], mesh.depth[rows][:, j + 1]
        ua, ub = us[j], us[j + 1]
        w = la * (dense - ua) / (la * (dense - ua) + lb * (ub - dense))
        chord = (1 - w) * la + w * lb
        error = np.abs(lam - chord) * np.hypot(d[..., 0], d[..., 1]) / gsd
        if mesh.hidden is not None:                    # segments left out (occlusion) hold no ray
            shown = ~mesh.hidden[np.minimum(rows, mesh.rows - 2), :, 0][:, j]
            error = np.where(shown, error, 0.0)
        assert error.max() <= EDGE_ERROR_PX, error.max()
        if truth.terrain.kind == "ridge":
            assert mesh.hidden is not None and mesh.hidden.any()
        else:
            assert mesh.hidden is None or not mesh.hidden.any()


def test_depth_test_keeps_the_nearest_fold():
    """Where one line's triangles fold over each other on the map, the nearer ground wins."""
    from archive.grid import Grid
    from archive.geometry.navigation import LocalFrame
    from archive.render.mesh import Mesh
    from archive.render.renderer import rasterize_lookup

    frame = LocalFrame(32616, 500000.0, 3900000.0, 0.0)
    # two rows (lines 0 and 1, 1 m apart northwards), three columns: s = 0, 0.5, 1 at E = 0, 4, 2 m:
    # the second segment folds back over the first one between E = 2 and 4
    east = np.array([0.0, 4.0, 2.0])
    ground = np.stack([np.stack([np.full(3, n), east], axis=-1) for n in (0.0, 1.0)])
    for far_second in (True, False):
        distance = np.tile([40.0, 40.0, 60.0 if far_second else 20.0], (2, 1))
        mesh = Mesh(frame, ground, np.ones((2, 3)), np.array([0.0, 1.0]), 2, FOV, math.nan,
                    columns=np.array([0.0, 0.5, 1.0]), distance=distance, hidden=np.zeros((1, 2, 2), bool))
        grid = Grid(32616, 0.1, 500000.0, 3900001.0, 40, 10)
        lookup = rasterize_lookup(mesh, grid, 100)
        folded = lookup.sample[:, 25:35]               # E = 2.5-3.5 m: both segments cover it
        seen = folded[lookup.line[:, 25:35] >= 0]
        assert seen.size > 20
        if far_second:   # the first segment (samples 0-49) is nearer
            assert np.all(seen < 50), seen
        else:
            assert np.all(seen >= 50), seen
