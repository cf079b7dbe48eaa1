"""Provenance layers and the 'nadir' overlap rule (issue 12), checked against the simulator's truth.

A small two-pass simulated flight is rendered with ``--provenance`` (real GL, a real local Dask
cluster, real Zarr/COG/ENVI files). The raw DN gathered through (cube, line, sample) must equal the
``--mode raw`` mosaic bit for bit; view zenith, azimuth and path length must match the true camera
at the true line time; time the true line time within one frame; sun angles NREL's published SPA
example within 0.01 degrees; overlap_count the number of true strip footprints covering the pixel.
"""

from __future__ import annotations

import json
import tempfile
from datetime import UTC, datetime, timedelta
from pathlib import Path

import numpy as np
import pytest
import rasterio
import xarray as xr

from archive.cli import main
from archive.formats.envi import EnviCube
from archive.formats.lcf import gps_seconds_to_datetime
from archive.geometry.provenance import LAYERS, sun_position
from archive.simulator.scene import points_in_polygon
from helpers import FOV

GSD = 0.03
NAMES = [layer.name for layer in LAYERS]


@pytest.fixture(scope="module")
def flight(strips_flight):
    """(directory, Truth) of the shared 4-cube flight in 2 strips, 6 bands (conftest), read only."""
    return strips_flight


def _render(flight_dir: Path, out: Path, *extra: str) -> int:
    return main(["render", str(flight_dir), "--fov", str(FOV), "--gsd", str(GSD), "--ground-height", "auto",
                 "--mode", "raw", "--out", str(out), "--quiet", *extra])


@pytest.fixture(scope="module")
def rendered(flight, tmp_path_factory):
    """Zarr renders with provenance: overlap 'last' and 'nadir'."""
    directory, _ = flight
    base = tmp_path_factory.mktemp("provenance-out")
    out = {}
    for rule in ("last", "nadir"):
        path = base / f"{rule}.zarr"
        assert _render(directory, path, "--provenance", "--overlap", rule) == 0
        out[rule] = path
    return out


def _open(path: Path) -> xr.Dataset:
    return xr.open_zarr(path, decode_coords="all", decode_times=False)


def _covered(ds: xr.Dataset) -> tuple[np.ndarray, np.ndarray]:
    rows, cols = np.nonzero(np.isfinite(ds["line"].values))
    return rows, cols


def _pixel_xy(ds: xr.Dataset, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return ds["x"].values[cols], ds["y"].values[rows]


def _cubes(flight_dir: Path, ds: xr.Dataset) -> list[dict]:
    table = json.loads(ds.attrs["provenance_cubes"])
    for entry in table:
        entry["path"] = flight_dir / f"{entry['cube']}.bil"
    return table


@pytest.mark.parametrize("rule", ["last", "nadir"])
def test_gathering_raw_dn_through_the_glt_gives_the_raw_mosaic_bit_for_bit(flight, rendered, rule):
    directory, _ = flight
    ds = _open(rendered[rule])
    dn = ds["dn"].values
    cube, line, sample = (ds[n].values for n in ("cube", "line", "sample"))
    covered = np.isfinite(line)
    assert covered.mean() > 0.25
    # NaN in the values exactly where the layers say no line covers the pixel
    assert np.array_equal(np.isfinite(dn).all(axis=0), covered)
    assert np.array_equal(np.isnan(dn).all(axis=0), ~covered)
    for name in ("cube", "line", "sample", "time", "view_zenith", "overlap_count"):
        assert np.array_equal(np.isfinite(ds[name].values), covered), name
    gathered = np.full(dn.shape, np.nan, np.float32)
    for entry in _cubes(directory, ds):
        at = covered & (cube == entry["index"])
        raw = EnviCube(entry["path"]).read()           # (bands, lines, samples)
        gathered[:, at] = raw[:, line[at].astype(int), sample[at].astype(int)]
    assert np.array_equal(gathered.view(np.uint32), dn.view(np.uint32))  # bit for bit, NaN included


def _sampled_truth(directory: Path, truth, ds: xr.Dataset, count: int, seed: int):
    """``count`` random covered pixels of ``ds``: (rows, cols, the true camera E, N, alt (n, 3) at
    mid-exposure of the line each came from, that line's true start time (n,))."""
    rows, cols = _covered(ds)
    pick = np.random.default_rng(seed).choice(rows.size, count, replace=False)
    rows, cols = rows[pick], cols[pick]
    table = _cubes(directory, ds)
    cube_index = np.array([table[int(c)]["cube_index"] for c in ds["cube"].values[rows, cols]])
    line = ds["line"].values[rows, cols].astype(int)
    camera = np.empty((rows.size, 3))
    true_time = np.empty(rows.size)
    for c in np.unique(cube_index):
        at = cube_index == c
        cube = truth.cubes[c]
        true_time[at] = cube.line_time[line[at]]
        camera[at] = np.asarray(truth.trajectory(true_time[at] + cube.shutter_ms / 2000.0)[0])
    return rows, cols, camera, true_time


def test_view_geometry_time_and_sun_match_the_truth(flight, rendered):
    directory, truth = flight
    ds = _open(rendered["last"])
    rows, cols, camera, true_time = _sampled_truth(directory, truth, ds, 4000, seed=0)
    x, y = _pixel_xy(ds, rows, cols)
    ground = truth.ground_height_at(x, y)
    d = camera - np.stack([x, y, ground], axis=1)
    horizontal = np.hypot(d[:, 0], d[:, 1])
    zenith = np.degrees(np.arctan2(horizontal, d[:, 2]))
    # grid azimuth turned to true north with the truth's grid convergence (the bearing of true
    # north in the grid, degrees; the simulator's sign: add it to a true heading for a grid one)
    azimuth = (np.degrees(np.arctan2(d[:, 0], d[:, 1]) - truth.convergence)) % 360.0
    length = np.linalg.norm(d, axis=1)

    got = {n: ds[n].values[rows, cols].astype(float) for n in NAMES}
    assert np.max(np.abs(got["view_zenith"] - zenith)) < 0.05
    assert zenith.max() > 15.0     # the check spans the swath, not only nadir
    # azimuth: only meaningful off nadir (at nadir a centimetre turns it all the way round)
    off = zenith > 2.0
    diff = (got["view_azimuth"][off] - azimuth[off] + 180.0) % 360.0 - 180.0
    assert np.max(np.abs(diff)) < 0.5
    assert np.max(np.abs(got["path_length"] - length)) < 0.05

    # time: seconds since the reference instant, UTC; the truth's GPS seconds turned to UTC
    reference = datetime.fromisoformat(ds.attrs["time_reference"].replace("Z", "+00:00"))
    assert ds["time"].attrs["units"] == f"seconds since {ds.attrs['time_reference']}"
    first = gps_seconds_to_datetime(float(true_time.min()))
    true_s = np.array([(gps_seconds_to_datetime(t) - reference).total_seconds() for t in true_time])
    frame = 1.0 / truth.cubes[0].framerate
    assert np.max(np.abs(got["time"] - true_s)) < frame
    assert reference <= first < reference + timedelta(seconds=1)

    # sun: the layers hold SPA at the line's time and the camera's position (the pixel's is within
    # 0.001 degrees over 100 m): recompute at the pixel with the true time
    lon, lat = truth.from_utm(x, y, 4326)
    unix = np.array([(gps_seconds_to_datetime(t)).timestamp() for t in true_time])
    sun_zenith, sun_azimuth = sun_position(unix, lat, lon, ground)
    assert np.max(np.abs(got["sun_zenith"] - sun_zenith)) < 0.01
    assert np.max(np.abs(got["sun_azimuth"] - sun_azimuth)) < 0.01


def test_sun_position_matches_the_published_spa_example():
    """Reda & Andreas (2004), NREL/TP-560-34302, Table A5.1: 2003-10-17 12:30:30 local time (UTC-7),
    39.742476 N, 105.1786 W, 1830.14 m, delta T 67 s: topocentric elevation without refraction
    e0 = 39.872046 deg (zenith 50.127954), azimuth 194.340241 deg."""
    moment = datetime(2003, 10, 17, 19, 30, 30, tzinfo=UTC).timestamp()
    zenith, azimuth = sun_position(np.array([moment]), 39.742476, -105.1786, 1830.14, delta_t=67.0)
    assert abs(zenith[0] - (90.0 - 39.872046)) < 0.01
    assert abs(azimuth[0] - 194.340241) < 0.01
    # with delta T estimated for the date (what renders use) it stays within the tolerance
    zenith, azimuth = sun_position(np.array([moment]), 39.742476, -105.1786, 1830.14)
    assert abs(zenith[0] - (90.0 - 39.872046)) < 0.01
    assert abs(azimuth[0] - 194.340241) < 0.01


def test_overlap_count_is_the_number_of_true_strips_covering_the_pixel(flight, rendered):
    _, truth = flight
    ds = _open(rendered["last"])
    rows, cols = _covered(ds)
    x, y = _pixel_xy(ds, rows, cols)
    e, n = truth.to_utm(x, y)
    inside = np.zeros(x.size, int)
    for poly in truth.footprint():
        inside += points_in_polygon(poly, e, n)
    count = ds["overlap_count"].values[rows, cols]
    # away from the footprint edges (within 2 px of an edge the rasterised and the true footprints
    # may disagree), the counts agree
    interior = _interior(ds, rows, cols)
    assert (inside[interior] == 2).sum() > 1000     # the passes overlap
    assert np.array_equal(count[interior], inside[interior])


def _interior(ds: xr.Dataset, rows: np.ndarray, cols: np.ndarray, margin: int = 2) -> np.ndarray:
    """Pixels whose neighbourhood of ``margin`` px has the same overlap count (off footprint edges)."""
    from scipy.ndimage import maximum_filter, minimum_filter

    count = np.nan_to_num(ds["overlap_count"].values, nan=0.0)
    size = 2 * margin + 1
    same = maximum_filter(count, size) == minimum_filter(count, size)
    return same[rows, cols]


def _true_zenith_from_pass(truth, strip: tuple[int, ...], x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """View zenith (deg) of ground points (x, y) from the strip's camera at the moment its scan
    plane (the camera's y-z plane) sweeps over them; NaN where it never does."""
    times = np.concatenate([truth.cubes[k].line_time + truth.cubes[k].shutter_ms / 2000.0 for k in strip])
    position, attitude = truth.trajectory(times)
    position = np.asarray(position)
    along = attitude.as_matrix()[:, :, 0]            # camera x axis in NED (N, E, D)
    along_enu = np.stack([along[:, 1], along[:, 0], -along[:, 2]], axis=1)
    ground = truth.ground_height_at(x, y)
    point = np.stack([x, y, ground], axis=1)
    signed = np.einsum("pk,lk->pl", point, along_enu) - np.einsum("lk,lk->l", position, along_enu)[None]
    out = np.full(x.size, np.nan)
    flips = np.diff(np.sign(signed), axis=1) != 0
    has = flips.any(axis=1)
    i = np.argmax(flips, axis=1)
    p = np.arange(x.size)
    f = signed[p, i] / (signed[p, i] - signed[p, np.minimum(i + 1, len(times) - 1)])
    camera = position[i] + f[:, None] * (position[np.minimum(i + 1, len(times) - 1)] - position[i])
    d = camera - point
    out[has] = np.degrees(np.arctan2(np.hypot(d[:, 0], d[:, 1]), d[:, 2]))[has]
    return out


def test_nadir_rule_takes_the_pass_seen_closer_to_nadir(flight, rendered):
    _, truth = flight
    last, nadir = _open(rendered["last"]), _open(rendered["nadir"])
    count = nadir["overlap_count"].values
    rows, cols = np.nonzero(count == 2)
    pick = np.random.default_rng(1).choice(rows.size, min(3000, rows.size), replace=False)
    rows, cols = rows[pick], cols[pick]
    x, y = _pixel_xy(nadir, rows, cols)
    strips = truth.strips
    assert len(strips) == 2
    zen = np.stack([_true_zenith_from_pass(truth, s, x, y) for s in strips])    # (2, n)
    ok = np.isfinite(zen).all(axis=0) & (np.abs(zen[0] - zen[1]) > 0.5)       # a clear winner
    assert ok.sum() > 1000
    table = json.loads(nadir.attrs["provenance_cubes"])
    strip_of = {k: s for s, strip in enumerate(strips) for k in strip}
    chosen = np.array([strip_of[table[int(c)]["cube_index"]] for c in nadir["cube"].values[rows, cols]])
    assert np.array_equal(chosen[ok], np.argmin(zen[:, ok], axis=0))
    # the 'last' rule takes the later pass there instead, wherever that one is not the nadir-most
    later = np.array([strip_of[table[int(c)]["cube_index"]] for c in last["cube"].values[rows, cols]])
    assert (later[ok] == 1).all()
    assert (chosen[ok] == 0).sum() > 100
    # and the nadir mosaic's values are those of the chosen pixels (same layers as written)
    assert np.array_equal(nadir["view_zenith"].values[rows, cols][ok],
                          np.minimum.reduce([last["view_zenith"].values[rows, cols][ok],
                                             nadir["view_zenith"].values[rows, cols][ok]]))


def test_cog_and_envi_siblings_hold_the_zarr_layers(flight, rendered, tmp_path):
    directory, _ = flight
    zarr_ds = _open(rendered["last"])
    cog = tmp_path / "m.tif"
    hdr = tmp_path / "m.hdr"
    assert _render(directory, cog, "--provenance") == 0
    assert _render(directory, hdr, "--provenance") == 0
    sibling = tmp_path / "m_provenance.tif"
    with rasterio.open(sibling) as src:
        assert src.count == len(NAMES)
        assert list(src.descriptions) == NAMES
        assert src.crs.to_epsg() == int(zarr_ds.rio.crs.to_epsg())
        tags = src.tags()
        assert tags["time_reference"] == zarr_ds.attrs["time_reference"]
        for b, name in enumerate(NAMES, start=1):
            assert np.array_equal(src.read(b), zarr_ds[name].values, equal_nan=True), name
    with rasterio.open(tmp_path / "m_provenance") as src:
        assert src.count == len(NAMES)
        for b, name in enumerate(NAMES, start=1):
            assert np.array_equal(src.read(b), zarr_ds[name].values, equal_nan=True), name
    assert "band names = {cube, line, sample, time" in (tmp_path / "m_provenance.hdr").read_text()
    from archive.outputs.cog_check import check_cog

    assert check_cog(sibling) == []


def test_provenance_with_the_mean_rule_is_refused_before_any_work(flight, tmp_path, capsys):
    directory, _ = flight
    out = tmp_path / "m.tif"
    assert _render(directory, out, "--provenance", "--overlap", "mean") != 0
    err = capsys.readouterr().err
    assert "--provenance" in err and "--overlap last or nadir" in err
    assert list(tmp_path.iterdir()) == []


def test_an_existing_provenance_sibling_is_not_overwritten(flight, tmp_path, capsys):
    directory, _ = flight
    (tmp_path / "m_provenance.tif").write_bytes(b"mine")
    assert _render(directory, tmp_path / "m.tif", "--provenance") != 0
    assert "m_provenance.tif" in capsys.readouterr().err
    assert (tmp_path / "m_provenance.tif").read_bytes() == b"mine"
    assert not (tmp_path / "m.tif").exists()


def test_the_lazy_mosaic_applies_the_nadir_rule_as_the_render(flight, rendered):
    import archive

    directory, _ = flight
    lazy = archive.mosaic(directory, gsd=GSD, fov=FOV, mode="raw", overlap="nadir")
    written = _open(rendered["nadir"])
    assert np.array_equal(lazy["dn"].values, written["dn"].values, equal_nan=True)


def test_view_zenith_over_terrain_uses_the_dem_heights(tmp_path_factory):
    """Over hills rendered with --dem, the ground point of a pixel is the DEM's: view zenith and
    path length match the true camera and the true terrain height at the pixel."""
    from archive.simulator.command import simulate_flight

    directory = tmp_path_factory.mktemp("provenance-hills") / "flight"
    truth = simulate_flight(directory, terrain="hills", cubes=2, cubes_per_pass=2, bands=3, samples=64,
                            lines=150, seed=21)
    out = directory.parent / "hills.zarr"
    assert main(["render", str(directory), "--fov", str(FOV), "--gsd", str(GSD), "--dem", str(directory / "dem.tif"),
                 "--mode", "raw", "--out", str(out), "--quiet", "--provenance"]) == 0
    ds = _open(out)
    rows, cols, camera, _ = _sampled_truth(directory, truth, ds, 3000, seed=2)
    x, y = _pixel_xy(ds, rows, cols)
    ground = truth.ground_height_at(x, y)
    assert np.ptp(ground) > 2.0                     # real relief under the checked pixels
    d = camera - np.stack([x, y, ground], axis=1)
    zenith = np.degrees(np.arctan2(np.hypot(d[:, 0], d[:, 1]), d[:, 2]))
    assert np.max(np.abs(ds["view_zenith"].values[rows, cols] - zenith)) < 0.05
    assert np.max(np.abs(ds["path_length"].values[rows, cols] - np.linalg.norm(d, axis=1))) < 0.05


def test_nadir_rule_strategy_and_the_writers_fast_path_agree():
    """Smallest key wins, the later part on a tie, NaN keys never win; saturation follows the winner;
    the writer's band-by-band path writes what the strategy object assembles."""
    from archive.graph.tasks import assemble_task, assemble_write_task
    from archive.grid import Grid
    from archive.outputs.zarr import MosaicStore
    from archive.overlap import NADIR

    rng = np.random.default_rng(4)
    boxes = [(0, 0, 6, 5), (2, 1, 6, 6), (1, 3, 4, 4)]
    renders, keys = [], []
    for i, (_, _, h, w) in enumerate(boxes):
        values = rng.normal(size=(3, h, w)).astype(np.float32)
        key = rng.choice([1.0, 2.0, 3.0], size=(h, w)).astype(np.float32)
        key[0, 0] = np.nan
        values[:, 0, 0] = np.nan
        renders.append((values, rng.random((h, w)) < 0.3))
        keys.append(key)
    tile = (0, 0, 9, 8)
    values, saturated = assemble_task(NADIR, tile, 3, boxes, *renders, keys=keys)
    # brute force: per pixel, the last part with the smallest finite key
    for r in range(9):
        for c in range(8):
            best, pick = np.inf, None
            for k, (r0, c0, h, w) in enumerate(boxes):
                if r0 <= r < r0 + h and c0 <= c < c0 + w:
                    key = keys[k][r - r0, c - c0]
                    if key <= best:
                        best, pick = key, (k, r - r0, c - c0)
            if pick is None:
                assert np.isnan(values[:, r, c]).all() and not saturated[r, c]
            else:
                k, i, j = pick
                assert np.array_equal(values[:, r, c], renders[k][0][:, i, j])
                assert saturated[r, c] == renders[k][1][i, j]
    with tempfile.TemporaryDirectory() as folder:
        store = MosaicStore.create(f"{folder}/m.zarr", Grid(32616, 1.0, 0.0, 100.0, 8, 9), None, [0, 1, 2])
        sat = assemble_write_task(store, NADIR, 0, tile, 3, boxes, None, *renders, keys=keys)
        written = store._array(store.variable)[:, :9, :8]
        assert np.array_equal(written, values, equal_nan=True)
        assert np.array_equal(sat, saturated)


def test_view_geometry_in_another_output_crs_is_in_ground_metres(flight, tmp_path):
    """With --crs EPSG:3857 (whose metres are ~1.22 ground metres at 35 degrees N) the layers still
    give the true view zenith and path length: geometry is computed in the flight's UTM zone."""
    directory, truth = flight
    out = tmp_path / "mercator.zarr"
    assert _render(directory, out, "--provenance", "--crs", "EPSG:3857") == 0
    ds = _open(out)
    assert ds.rio.crs.to_epsg() == 3857
    rows, cols, camera, _ = _sampled_truth(directory, truth, ds, 3000, seed=3)
    x, y = truth.to_utm(*_pixel_xy(ds, rows, cols), crs=3857)
    d = camera - np.stack([x, y, truth.ground_height_at(x, y)], axis=1)
    zenith = np.degrees(np.arctan2(np.hypot(d[:, 0], d[:, 1]), d[:, 2]))
    assert zenith.max() > 15.0
    assert np.max(np.abs(ds["view_zenith"].values[rows, cols] - zenith)) < 0.05
    assert np.max(np.abs(ds["path_length"].values[rows, cols] - np.linalg.norm(d, axis=1))) < 0.05
    off = zenith > 2.0
    azimuth = (np.degrees(np.arctan2(d[:, 0], d[:, 1]) - truth.convergence)) % 360.0
    diff = (ds["view_azimuth"].values[rows, cols][off] - azimuth[off] + 180.0) % 360.0 - 180.0
    assert np.max(np.abs(diff)) < 0.5
