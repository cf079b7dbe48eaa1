"""Terrain meshes are watertight across cube seams (issue 17).

Consecutive cubes of a strip meet inside the quads between the last line of one cube and the first
line of the next; each cube draws its half (render/mesh.py, "Watertight seams"). Over a DEM the
rows are split across track, and if the two cubes split the seam rows differently their meshes
meet along a T-junction and leave sliver cracks that may hold a pixel centre (seen on a held-out
hills flight: one empty pixel between cube 0 line 399 and cube 1 line 0).

Hills flights of 2 passes, several seeds, headings and cube counts (3-6), at the nominal GSD and half
of it, in two ways:

- geometry, float64, no GL: the union of the cubes' meshes covers every pixel centre inside the
  strip's outline (the outer rows and swath edges), with the renderer's fragment rule for lines;
- the GL render (``archive.mosaic --dem``, UTM DEM and the same DEM in EPSG:4326): zero empty
  pixels on the truly visible ground, eroded by 0.5 px (the footprint's outer edge only: seams lie
  inside the visible ground and are never eroded).
"""

from __future__ import annotations

import numpy as np
import pytest

from tests.test_terrain import FOV, mosaic, visible_masks

# (seed, grid heading of the even passes (deg), cubes, cubes per pass): 2 passes each
FLIGHTS = [(2, 20.0, 3, 2), (3, 75.0, 4, 2), (5, -40.0, 6, 3), (6, 130.0, 6, 3)]
SHAPE = dict(bands=2, samples=256, lines=300, terrain="hills")


@pytest.fixture(scope="module", params=FLIGHTS, ids=[f"seed{f[0]}-{f[1]:g}deg-{f[2]}cubes" for f in FLIGHTS])
def flight(request, tmp_path_factory):
    """(directory, truth) of a simulated hills flight, made once per module."""
    from archive.simulator.command import simulate_flight
    from archive.simulator.truth import load_truth

    seed, heading, cubes, per_pass = request.param
    directory = tmp_path_factory.mktemp("seams") / "flight"
    simulate_flight(directory, cubes=cubes, cubes_per_pass=per_pass, seed=seed, heading_deg=heading, **SHAPE)
    return directory, load_truth(directory)


# ---------------------------------------------------------------------------------------------
# float64 coverage of pixel centres by meshes (the renderer's rule, without GL)
# ---------------------------------------------------------------------------------------------
def _pixel_coordinates(mesh, grid, ground):
    """(..., 2) (col, row) of local (N, E) points, in pixel-centre units (centre of pixel (0, 0) = 0)."""
    return np.stack([(ground[..., 1] + (mesh.frame.origin_e - grid.x0)) / grid.gsd - 0.5,
                     (grid.y0 - mesh.frame.origin_n - ground[..., 0]) / grid.gsd - 0.5], axis=-1)


def mesh_cover(mesh, grid) -> np.ndarray:
    """(height, width) bool: pixel centres that a drawn triangle of ``mesh`` covers with line =
    floor(L + 0.5) in [0, lines) (the fragment rule), float64, triangle edges included."""
    cover = np.zeros(grid.shape, bool)
    tris = mesh.triangles()
    if tris.size == 0:
        return cover
    pos, attr = mesh.vertex_attributes()
    xy = _pixel_coordinates(mesh, grid, pos)
    tc, tr, tl = xy[tris, 0], xy[tris, 1], attr[tris, 0]
    c0 = np.clip(np.ceil(tc.min(1)), 0, grid.width).astype(np.int64)
    c1 = np.clip(np.floor(tc.max(1)), -1, grid.width - 1).astype(np.int64)
    r0 = np.clip(np.ceil(tr.min(1)), 0, grid.height).astype(np.int64)
    r1 = np.clip(np.floor(tr.max(1)), -1, grid.height - 1).astype(np.int64)
    w, h = np.maximum(c1 - c0 + 1, 0), np.maximum(r1 - r0 + 1, 0)
    count = w * h                                    # candidate pixel centres per triangle
    t = np.repeat(np.arange(len(tris)), count)
    k = np.arange(t.size) - np.repeat(np.cumsum(count) - count, count)
    c, r = c0[t] + k % w[t], r0[t] + k // w[t]
    x, y = c.astype(float), r.astype(float)
    ax, ay, bx, by, cx, cy = tc[t, 0], tr[t, 0], tc[t, 1], tr[t, 1], tc[t, 2], tr[t, 2]
    area = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
    w0 = (bx - x) * (cy - y) - (by - y) * (cx - x)
    w1 = (cx - x) * (ay - y) - (cy - y) * (ax - x)
    w2 = (ax - x) * (by - y) - (ay - y) * (bx - x)
    sign = np.sign(area)
    inside = (area != 0) & (w0 * sign >= 0) & (w1 * sign >= 0) & (w2 * sign >= 0)
    line = np.floor((w0 * tl[t, 0] + w1 * tl[t, 1] + w2 * tl[t, 2]) / np.where(area != 0, area, 1.0) + 0.5)
    drawn = inside & (line >= 0) & (line < mesh.lines)
    cover[r[drawn], c[drawn]] = True
    return cover


def strip_outline(meshes, grid) -> np.ndarray:
    """(k, 2) (col, row) outline of consecutive cubes' own rows: left ends from the first row to the
    last, the last row's vertices, the right ends back, the first row's vertices (rows are
    polylines over terrain; a row's unused columns repeat used vertices)."""
    rows = [_pixel_coordinates(m, grid, m.ground[(m.line >= 0) & (m.line < m.lines)]) for m in meshes]
    first, last = rows[0][0], rows[-1][-1]
    left = np.concatenate([r[:, 0] for r in rows])
    right = np.concatenate([r[:, -1] for r in rows])
    return np.concatenate([left, last[1:-1], right[::-1], first[::-1][1:-1]])


def cracks(meshes, grid) -> np.ndarray:
    """(height, width) bool: pixel centres inside the strip's outline that no cube's mesh covers."""
    from archive.simulator.scene import points_in_polygon

    cc, rr = np.meshgrid(np.arange(grid.width, dtype=float), np.arange(grid.height, dtype=float))
    inside = points_in_polygon(strip_outline(meshes, grid), cc, rr).reshape(grid.shape)
    cover = np.zeros(grid.shape, bool)
    for m in meshes:
        cover |= mesh_cover(m, grid)
    return inside & ~cover


def strips_of(source, meshes) -> list[list[int]]:
    """Cube indices of each strip (cubes joined by their recorder's cube switch)."""
    from archive.graph.plan import strip_links

    links = strip_links(source, [source.poses(i) for i in range(len(source.cubes))])
    out = [[0]]
    for cube, joined in enumerate(links, start=1):
        if joined:
            out[-1].append(cube)
        else:
            out.append([cube])
    return out


@pytest.mark.parametrize("scale", [1.0, 0.5], ids=["nominal", "half"])
def test_no_pixel_centre_lies_in_a_crack(flight, scale):
    from archive.terrain.dem import open_dem
    from archive.graph.plan import cube_meshes
    from archive.grid import Grid
    from archive.params import NavigationParams
    from archive.sources import RawFlightSource

    directory, truth = flight
    gsd = truth.nominal_gsd * scale
    source = RawFlightSource(directory, NavigationParams())
    meshes = cube_meshes(source, FOV, 0.0, terrain=open_dem(directory / "dem.tif"), gsd=gsd)
    bounds = np.array([m.bounds_utm() for m in meshes])
    grid = Grid.from_bounds(meshes[0].epsg, *bounds[:, :2].min(axis=0), *bounds[:, 2:].max(axis=0), gsd)
    strips = strips_of(source, meshes)
    assert len(strips) == 2 and max(len(s) for s in strips) >= 2
    for strip in strips:
        inside = cracks([meshes[i] for i in strip], grid)
        assert not inside.any(), f"strip {strip}: {int(inside.sum())} pixel centres in cracks at {np.argwhere(inside)[:5]}"
    # the seam rows are shared: the next cube's opening row is this cube's last line, vertex for vertex
    for strip in strips:
        for a, b in zip(strip[:-1], strip[1:]):
            ma, mb = meshes[a], meshes[b]
            for la, lb in ((ma.lines - 1, -1), (ma.lines, 0)):
                ra, rb = int(np.flatnonzero(ma.line == la)[0]), int(np.flatnonzero(mb.line == lb)[0])
                va = ma.ground[ra][ma.active[ra]] if ma.active is not None else ma.ground[ra]
                vb = mb.ground[rb][mb.active[rb]] if mb.active is not None else mb.ground[rb]
                assert va.shape == vb.shape and np.array_equal(va, vb), (a, b, la)


@pytest.mark.parametrize("scale", [1.0, 0.5], ids=["nominal", "half"])
def test_gl_render_has_no_empty_pixel_on_visible_ground(flight, scale):
    directory, truth = flight
    values, grid = mosaic(directory, truth.nominal_gsd * scale, dem=directory / "dem.tif")
    eroded, _, _ = visible_masks(truth, grid, d_px=0.5)
    empty = eroded & np.isnan(values).any(axis=0)
    assert eroded.sum() > 20000
    assert not empty.any(), f"{int(empty.sum())} empty pixels on visible ground at {np.argwhere(empty)[:5]}"


def test_gl_render_over_a_lonlat_dem_has_no_empty_pixel(flight, tmp_path):
    """The same DEM in EPSG:4326 (resampled surfaces: each cube's differs, the seams' do not)."""
    from archive.simulator.command import dem_bounds
    from archive.simulator.terrain import write_dem

    directory, truth = flight
    lonlat = tmp_path / "dem_4326.tif"
    write_dem(lonlat, truth.terrain, truth.epsg, dem_bounds(truth, 10.0), 0.1, crs=4326)
    values, grid = mosaic(directory, truth.nominal_gsd, dem=lonlat)
    eroded, _, _ = visible_masks(truth, grid, d_px=0.5)
    empty = eroded & np.isnan(values).any(axis=0)
    assert not empty.any(), f"{int(empty.sum())} empty pixels on visible ground at {np.argwhere(empty)[:5]}"
