"""Terrain inputs (issue 11): the same DEM in another CRS or vertical datum gives the same mosaic,
bad DEMs fail cleanly through the real CLI (one stderr line, non-zero exit, nothing written), and
``archive ingest`` / ``archive info`` take ``--dem`` too (the catalog footprint follows the terrain).

Flights come from test_terrain.py's session cache (simulated once)."""

from __future__ import annotations

import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from archive.errors import InputError
from tests.test_render_truth import lucas_kanade
from helpers import FOV
from tests.test_terrain import mosaic


def dem_bounds(truth, margin=10.0):
    from archive.simulator.command import dem_bounds as bounds

    return bounds(truth, margin)


def same_geometry(a: np.ndarray, b: np.ndarray, band: int = 2, size: int = 24) -> np.ndarray:
    """Shifts (dy, dx) px of ``b`` against ``a`` on textured windows both cover (Lucas-Kanade)."""
    out = []
    for r in range(0, a.shape[1] - size + 1, size // 2):
        for c in range(0, a.shape[2] - size + 1, size // 2):
            wa, wb = a[band, r:r + size, c:c + size], b[band, r:r + size, c:c + size]
            if np.isnan(wa).any() or np.isnan(wb).any():
                continue
            gy, gx = np.gradient(wa)
            if np.sqrt(np.mean(gx**2 + gy**2)) < 0.02 * np.mean(wa):
                continue
            out.append(lucas_kanade(wa.astype(float), wb.astype(float)))
    return np.array(out)


def assert_same_render(a, grid_a, b, grid_b, tolerance_px=0.05):
    assert grid_a == grid_b
    s = same_geometry(a, b)
    assert len(s) >= 20
    size = np.hypot(s[:, 0], s[:, 1])
    assert size.max() <= tolerance_px, (np.median(size), size.max())
    both = ~np.isnan(a).any(axis=0) & ~np.isnan(b).any(axis=0)
    assert (np.isnan(a).any(axis=0) != np.isnan(b).any(axis=0)).mean() < 0.002   # coverage edges only
    assert (a[:, both] == b[:, both]).all(axis=0).mean() > 0.98


def test_dem_in_lonlat_equals_the_utm_dem(hills, tmp_path):
    from archive.simulator.terrain import write_dem

    directory, truth = hills
    lonlat = tmp_path / "dem_4326.tif"
    write_dem(lonlat, truth.terrain, truth.epsg, dem_bounds(truth), 0.1, crs=4326)
    utm, grid = mosaic(directory, truth.nominal_gsd, dem=directory / "dem.tif")
    other, grid_other = mosaic(directory, truth.nominal_gsd, dem=lonlat)
    assert_same_render(utm, grid, other, grid_other)


def test_geoid_dem_with_dem_datum_equals_its_ellipsoidal_twin(hills, tmp_path):
    from archive.terrain.dem import open_dem
    from archive.simulator.terrain import write_dem

    directory, truth = hills
    geoid = tmp_path / "dem_egm96.tif"
    try:
        write_dem(geoid, truth.terrain, truth.epsg, dem_bounds(truth), 0.1, datum="egm96", declare=False)
    except ValueError as exc:
        pytest.skip(f"no EGM96 grid for the test's DEM: {exc}")
    # the geoid is ~28 m below the ellipsoid here: the heights differ by that, and PROJ converts them
    e, n = np.array([truth.cubes[0].position_utm[0, 0]]), np.array([truth.cubes[0].position_utm[0, 1]])
    ellipsoidal = open_dem(directory / "dem.tif").heights_at(truth.epsg, e, n)
    raw = open_dem(geoid, "ellipsoid").heights_at(truth.epsg, e, n)
    assert 20.0 < float(raw[0] - ellipsoidal[0]) < 40.0
    np.testing.assert_allclose(open_dem(geoid, "egm96").heights_at(truth.epsg, e, n), ellipsoidal, atol=1e-3)
    # a DEM whose compound CRS declares EGM96 needs no --dem-datum
    declared = tmp_path / "dem_egm96_declared.tif"
    write_dem(declared, truth.terrain, truth.epsg, dem_bounds(truth, 2.0), 0.5, datum="egm96")
    assert open_dem(declared).datum == "egm96" and open_dem(declared).declared
    with pytest.raises(InputError, match="declares egm96 heights but --dem-datum is ellipsoid"):
        open_dem(declared, "ellipsoid")
    with pytest.raises(InputError, match=r"archive.mosaic\(dem_datum=...\): .*no dem was given \(add dem=FILE"):
        mosaic(directory, truth.nominal_gsd, dem_datum="egm96")
    twin, grid = mosaic(directory, truth.nominal_gsd, dem=directory / "dem.tif")
    other, grid_other = mosaic(directory, truth.nominal_gsd, dem=geoid, dem_datum="egm96")
    assert_same_render(twin, grid, other, grid_other)


# ---------------------------------------------------------------------------------------------
# bad DEMs through the real CLI
# ---------------------------------------------------------------------------------------------
def _archive(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "archive", *args], capture_output=True, text=True, timeout=300)


def _egm2008_grid_missing() -> bool:
    from pyproj.transformer import TransformerGroup

    from archive.terrain.dem import use_system_grids

    use_system_grids()
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return not TransformerGroup("EPSG:4326+3855", "EPSG:4979").best_available


def test_bad_dems_fail_cleanly_through_the_cli(ridge, tmp_path):
    from archive.simulator.terrain import write_dem

    directory, truth = ridge
    w, s, e, n = dem_bounds(truth)
    half = tmp_path / "west_half.tif"                  # covers the western half of the flight only
    write_dem(half, truth.terrain, truth.epsg, (w, s, (w + e) / 2, n), 0.2)
    holes = tmp_path / "holes.tif"                     # nodata under the middle of the flight
    cx, cy = (w + e) / 2, (s + n) / 2
    write_dem(holes, truth.terrain, truth.epsg, (w, s, e, n), 0.2, hole=(cx - 2, cy - 2, cx + 2, cy + 2))
    text = tmp_path / "notes.tif"
    text.write_text("this is not a raster\n")
    plain = tmp_path / "no_datum.tif"                  # heights without a declared vertical datum
    write_dem(plain, truth.terrain, truth.epsg, (w, s, e, n), 0.2, declare=False)
    render = ["render", str(directory), "--fov", str(FOV), "--gsd", "0.5", "--quiet"]
    cases = {
        "uncovered": (render + ["--dem", str(half)], [str(half), "does not cover the flight", "lon -", "lat 35."]),
        "not a raster": (render + ["--dem", str(text)], [str(text), "not a raster"]),
        "holes": (render + ["--dem", str(holes)], [str(holes), "nodata or NaN", "lon -", "lat 35."]),
        "no datum": (render + ["--dem", str(plain)], [str(plain), "vertical datum", "--dem-datum"]),
        "missing": (render + ["--dem", str(tmp_path / "nowhere.tif")], ["nowhere.tif", "not found"]),
        "exclusive": (render + ["--dem", str(directory / "dem.tif"), "--ground-height", "80"],
                      ["--dem", "--ground-height", "exclusive"]),
        "info uncovered": (["info", str(directory), "--dem", str(half)], [str(half), "does not cover the flight"]),
        "ingest uncovered": (["ingest", str(directory), "--archive", str(tmp_path / "archive"), "--fov", str(FOV),
                              "--quiet", "--dem", str(half)], [str(half), "does not cover the flight"]),
    }
    if _egm2008_grid_missing():
        cases["grid missing"] = (render + ["--dem", str(plain), "--dem-datum", "egm2008"],
                                 ["us_nga_egm08_25.tif", "not installed"])
    outs = {}
    for name, (args, _) in cases.items():
        if args[0] == "render":
            outs[name] = tmp_path / f"out_{name.replace(' ', '_')}.zarr"
            args += ["--out", str(outs[name])]
    before = set(tmp_path.iterdir())
    with ThreadPoolExecutor(3) as pool:
        done = dict(zip(cases, pool.map(lambda c: _archive(*c[0]), cases.values())))
    for name, result in done.items():
        command = cases[name][0][0]
        lines = result.stderr.strip().splitlines()
        assert result.returncode != 0, (name, result.stdout, result.stderr)
        assert len(lines) == 1 and lines[0].startswith(f"archive {command}: error:"), (name, result.stderr)
        for fragment in cases[name][1]:
            assert fragment in lines[0], (name, fragment, lines[0])
    assert set(tmp_path.iterdir()) == before          # no output, no partial output, no archive
    for out in outs.values():
        assert not out.exists()


# ---------------------------------------------------------------------------------------------
# ingest and info
# ---------------------------------------------------------------------------------------------
def test_ingest_footprint_follows_the_terrain(ridge, tmp_path):
    from archive.catalog.describe import item_for_collection
    from archive.catalog.footprint import points_in_polygon
    from archive.catalog.root import open_root
    from archive.ingest.command import ingest
    from archive.simulator.truth import load_truth  # noqa: F401  (truth from the fixture)

    directory, truth = ridge
    [result] = ingest([str(directory)], tmp_path / "archive", FOV, progress=False, dem=directory / "dem.tif")
    root = open_root(tmp_path / "archive")
    item = item_for_collection(root, result.cid)
    assert item["properties"]["archive:dem"] == "dem.tif"
    assert item["properties"]["archive:dem_datum"] == "ellipsoid"
    from pyproj import Transformer

    to_ll = Transformer.from_crs(truth.epsg, 4326, always_xy=True)
    polys = item["geometry"]["coordinates"]
    rings = [np.asarray(p[0]) for p in polys] if item["geometry"]["type"] == "MultiPolygon" else [np.asarray(polys[0])]
    for strip in truth.footprint():                   # the true (terrain) footprint is inside the Item's
        lon, lat = to_ll.transform(strip[:, 0], strip[:, 1])
        pts = np.stack([lon, lat], axis=1)
        assert any(points_in_polygon(pts, ring).all() for ring in rings)
    # ... and hugs it: its area is close to the truth's (a flat footprint at the camera's ground
    # height would be another shape; the outline margin is ~1 m)
    from archive.catalog.footprint import recorded_footprint

    fp = recorded_footprint(item["geometry"]["coordinates"][0] if item["geometry"]["type"] == "Polygon"
                            else [p[0] for p in polys], truth.epsg, 0.3)

    def area(ring):
        x, y = ring[:, 0], ring[:, 1]
        return 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))

    true_area = sum(area(p) for p in truth.footprint())
    item_area = sum(area(r) for r in fp.strips_utm)
    assert true_area < item_area < 1.35 * true_area
    # rebuilding the Item from the store (catalog rebuild --items) keeps the terrain footprint
    assert item_for_collection(root, result.cid)["geometry"] == item["geometry"]


def test_info_reports_the_terrain(hills, capsys):
    from archive.cli import main

    directory, truth = hills
    assert main(["info", str(directory), "--dem", str(directory / "dem.tif")]) == 0
    out = capsys.readouterr().out
    line = next(t for t in out.splitlines() if t.startswith("terrain"))
    assert "dem.tif" in line and "ellipsoid heights" in line
    lo, hi = (float(v) for v in line.split("ground ")[1].split(" m above")[0].split("\u2013"))
    assert hi - lo >= 8.0 and 70.0 < lo < hi < 100.0
