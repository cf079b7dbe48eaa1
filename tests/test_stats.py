"""``archive stats`` / ``archive.zonal_stats`` (issue 48): spectral indices per zone x flight on the
time stack's one grid, against the simulator's truth.

Two flights of one field a week apart (``scene_seed`` 0: the same ground, each its own wobble, noise
and changing sky; 2 cubes x 150 lines x 96 samples x 8 bands, 400-1000 nm), ingested with their sky
spectra and computed in reflectance from them. Zones in lon/lat (reprojected onto the UTM grid):
the homogeneous patches both flights see whole (mean NDVI against the true reflectance's NDVI), a
box cut by each flight's swath edge (coverage against the true footprint), one far away (count
0). Weights against exact polygon areas (shapely) on a small synthetic grid; indices and refusals.
Real EGL, real Dask (a local cluster of the command, and the session's LocalCluster as a
``--scheduler``), real exactextract.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pandas as pd
import pytest
import shapely
from helpers import FOV
from shapely.geometry import Polygon, box

from archive.cli import main

GSD = 0.25
DAYS = ("2024-06-12", "2024-06-19")
SHAPE = dict(cubes=2, bands=8, samples=96, lines=150, cubes_per_pass=2)


def _lonlat(truth, ring) -> list[list[float]]:
    ring = np.asarray(ring, float)
    lon, lat = truth.from_utm(ring[:, 0], ring[:, 1], crs=4326)
    return [[float(a), float(b)] for a, b in zip(lon, lat)]


def _feature(truth, zid: str, polygon: Polygon) -> dict:
    return {"type": "Feature", "id": zid, "properties": {"name": f"zone {zid}"},
            "geometry": {"type": "Polygon", "coordinates": [_lonlat(truth, polygon.exterior.coords)]}}


def _covered(truth, polygon: Polygon, step: float = 0.02) -> float:
    """The fraction of ``polygon`` (UTM) the flight of ``truth`` sees (the true footprint), on a ``step`` m lattice."""
    w, s, e, n = polygon.bounds
    xx, yy = np.meshgrid(np.arange(w + step / 2, e, step), np.arange(s + step / 2, n, step))
    inside = shapely.contains_xy(polygon, xx, yy)
    return float(truth.covered(xx[inside], yy[inside]).mean())


def _ndvi(truth, x: float, y: float) -> float:
    """NDVI of the true reflectance at (x, y) on the bands nearest 655 and 830 nm (spyndex's R and N centres)."""
    from archive.simulator.clouds import truth_reflectance

    r = truth_reflectance(truth, np.array([x]), np.array([y]))[:, 0]
    wl = truth.wavelengths
    red, nir = r[np.argmin(abs(wl - 655))], r[np.argmin(abs(wl - 830))]
    return float((nir - red) / (nir + red))


@pytest.fixture(scope="module")
def field(tmp_path_factory):
    """(root, archive, truths, zones path, {zone: truth NDVI or None}, {zone: (polygon, true coverage per flight)})."""
    from archive.ingest.command import ingest
    from archive.simulator.command import simulate_flight

    root = tmp_path_factory.mktemp("stats")
    truths = []
    for k, day in enumerate(DAYS):
        truths.append(simulate_flight(root / f"day{k}", seed=k, scene_seed=0, clouds=True,
                                      start=f"{day}T16:00:00Z", **SHAPE))
        ingest([str(root / f"day{k}")], root / "archive", FOV, progress=False)
    t0 = truths[0]
    features, ndvi, edges = [], {}, {}
    for p in t0.homogeneous_patches():
        w, s, e, n = p["interior"]
        zone = box(w + 0.6, s + 0.6, e - 0.6, n - 0.6)   # 1.8 m: > 1 px of blur inside the patch's edge
        if all(_covered(t, zone, 0.1) == 1.0 for t in truths):
            features.append(_feature(t0, p["name"], zone))
            ndvi[p["name"]] = _ndvi(t0, *zone.centroid.coords[0])
    assert len(ndvi) >= 2, ndvi
    # a 4 m box centred on the first flight's swath edge, north of its footprint's centre
    foot = Polygon(t0.footprint()[0])
    cx, cy = foot.centroid.coords[0]
    edge = foot.exterior.interpolate(foot.exterior.project(shapely.Point(cx, foot.bounds[3])))
    cut = box(edge.x - 2, edge.y - 2, edge.x + 2, edge.y + 2)
    edges["edge"] = (cut, [_covered(t, cut) for t in truths])
    assert 0.2 < edges["edge"][1][0] < 0.8, edges
    features.append(_feature(t0, "edge", cut))
    features.append(_feature(t0, "far", box(cx + 1000, cy + 1000, cx + 1010, cy + 1010)))
    zones = root / "fields.geojson"
    zones.write_text(json.dumps({"type": "FeatureCollection", "features": features}))
    return root, root / "archive", truths, zones, ndvi, edges


def _query(field) -> list[str]:
    return ["--archive", str(field[1]), "--query-datetime", "2024-06-01/2024-07-01"]


def _check_truth(table: pd.DataFrame, field) -> None:
    _, _, truths, _, ndvi, edges = field
    assert list(table.columns[:14]) == ["zone", "flight", "datetime", "index", "count", "coverage", "saturated",
                                        "mean", "std", "min", "p10", "median", "p90", "max"]
    assert (table["saturated"] == 0).all()   # 0 dB: no DN of these flights clips
    got = table[table["index"] == "NDVI"]
    assert got["flight"].nunique() == 2
    assert [str(d)[:10] for d in sorted(got["datetime"].unique())] == list(DAYS)
    for zid, true in ndvi.items():
        rows = got[got["zone"] == zid]
        assert len(rows) == 2
        for _, row in rows.iterrows():   # every flight, within 0.005 of the truth
            assert abs(row["mean"] - true) < 0.005, (zid, row["flight"], row["mean"], true)
            assert row["coverage"] == pytest.approx(1.0, abs=1e-6) and row["count"] > 40
            assert row["min"] <= row["p10"] <= row["median"] <= row["p90"] <= row["max"]
    assert max(ndvi.values()) - min(ndvi.values()) > 0.3   # zones that differ
    # the zone cut by the swath edge: its imaged fraction, against the true footprint's
    cut, true = edges["edge"]
    rows = got[got["zone"] == "edge"].sort_values("datetime")
    for (_, row), fraction in zip(rows.iterrows(), true):
        # half a pixel along the 4 m edge would be 0.03; the pixel-centre rule errs both ways: measured 0.002
        assert abs(row["coverage"] - fraction) < 0.02, (row["coverage"], fraction)
        assert row["count"] == pytest.approx(row["coverage"] * cut.area / GSD**2, rel=1e-6)
    far = got[got["zone"] == "far"]
    assert len(far) == 2 and (far["count"] == 0).all() and (far["coverage"] == 0).all() and far["mean"].isna().all()


def test_zone_means_match_the_truth_for_every_flight(field, tmp_path):
    """The default path: ``archive.zonal_stats`` on a local cluster of its own (GL on its worker)."""
    import archive

    table = archive.zonal_stats({"datetime": "2024-06-01/2024-07-01"}, field[3], ["NDVI"], archive=field[1],
                                gsd=GSD)
    _check_truth(table, field)
    assert set(table["bands"]) == {"N=828.6nm,R=657.1nm"}
    assert len(table) == (len(field[4]) + 2) * 2
    # the lazy index of archive.stack: (time, y, x), the patches' NDVI on both dates
    from archive.analysis.indices import stack_index

    da = archive.stack({"datetime": "2024-06-01/2024-07-01"}, archive=field[1], gsd=GSD, mode="reflectance",
                       wavelengths=[655, 830])
    ndvi = stack_index(da, "NDVI")
    np.testing.assert_array_equal(da.archive.index("NDVI").values, ndvi.values)   # the accessor's
    assert ndvi.dims == ("time", "y", "x") and ndvi.attrs["bands"] == "N=828.6nm,R=657.1nm"
    values = ndvi.values
    xx, yy = np.meshgrid(ndvi["x"].values, ndvi["y"].values)
    zones = {f["id"]: Polygon(f["geometry"]["coordinates"][0]) for f in json.loads(field[3].read_text())["features"]}
    for zid, true in field[4].items():
        lon, lat = field[2][0].from_utm(xx, yy, crs=4326)
        inside = shapely.contains_xy(zones[zid], lon, lat)
        assert inside.sum() > 30
        for t in range(2):
            assert abs(np.nanmean(values[t][inside]) - true) < 0.005, (zid, t)


def test_cli_and_api_on_a_scheduler_give_the_same_table(field, scheduler, tmp_path):
    import archive

    out = tmp_path / "fields.csv"
    expr = "ND=(R830-R655)/(R830+R655)"
    done = subprocess.run([sys.executable, "-m", "archive", "stats", *_query(field), "--zones", str(field[3]),
                           "--index", "NDVI", "--expression", expr, "--gsd", str(GSD), "--out", str(out),
                           "--scheduler", scheduler, "--quiet"], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0 and not done.stderr.strip(), done.stderr
    assert "wrote" in done.stdout and out.exists()
    cli = pd.read_csv(out, parse_dates=["datetime"])
    _check_truth(cli, field)
    api = archive.zonal_stats({"datetime": "2024-06-01/2024-07-01"}, field[3], "NDVI", expression=[expr],
                              archive=field[1], gsd=GSD, scheduler=scheduler)
    assert list(cli["zone"]) == list(api["zone"]) and list(cli["index"]) == list(api["index"])
    for column in ("count", "coverage", "saturated", "mean", "std", "min", "p10", "median", "p90", "max"):
        np.testing.assert_array_equal(cli[column].to_numpy(), api[column].to_numpy(), err_msg=column)
    # the expression on the same bands is NDVI, number for number
    nd, ndvi = api[api["index"] == "ND"], api[api["index"] == "NDVI"]
    np.testing.assert_allclose(nd["mean"].to_numpy(), ndvi["mean"].to_numpy(), rtol=1e-6)
    # the same zones from a GeoPackage in Web Mercator, named by a property: the same numbers
    import geopandas as gpd

    gpkg = tmp_path / "fields.gpkg"
    gpd.read_file(field[3]).to_crs(3857).to_file(gpkg, driver="GPKG")
    merc = archive.zonal_stats({"datetime": "2024-06-01/2024-07-01"}, gpkg, "NDVI", zone_id="name",
                               archive=field[1], gsd=GSD, scheduler=scheduler)
    assert list(merc["zone"]) == [f"zone {z}" for z in ndvi["zone"]]
    for column in ("count", "coverage", "mean"):   # the fractions move by ~1e-9 through another projection
        np.testing.assert_allclose(merc[column].to_numpy(), ndvi[column].to_numpy(), rtol=1e-6, err_msg=column)
    np.testing.assert_allclose(merc["median"].to_numpy(), ndvi["median"].to_numpy(), atol=1e-4)
    # GeoParquet keeps the zones' geometries (their own CRS: lon/lat), and --out is not replaced unasked
    geo = tmp_path / "fields.parquet"
    args = ["stats", *_query(field), "--zones", str(field[3]), "--index", "NDVI", "--gsd", str(GSD), "--out",
            str(geo), "--geometry", "--scheduler", scheduler, "--quiet"]
    assert main(args) == 0
    frame = gpd.read_parquet(geo)
    zones = gpd.read_file(field[3])
    assert frame.crs.to_epsg() == 4326
    first = frame[frame["zone"] == "edge"].geometry.iloc[0]
    assert first.equals_exact(zones[zones["id"] == "edge"].geometry.iloc[0], 1e-12)
    assert main(args) != 0 and geo.exists()


def test_weights_are_exact_polygon_areas_on_a_small_grid():
    """exactextract's weights against shapely's exact pixel-polygon intersections: count, coverage,
    mean, std, min, max; equal weights: the quantiles are numpy's (linear); NaN pixels left out."""
    from archive.analysis.indices import bind_indices, parse_indices
    from archive.analysis.zonal import window_stats

    rng = np.random.default_rng(4)
    gsd, x0, y0, h, w = 0.5, 1000.0, 2003.0, 6, 8
    values = rng.uniform(0, 1, (1, h, w)).astype(np.float32)
    values[0, 2, 3] = np.nan
    (ix,) = bind_indices(parse_indices([], ["V=R500"]), [500.0])
    zones = [Polygon([(1000.3, 2000.2), (1003.1, 2000.9), (1001.2, 2002.7)]),              # a triangle
             shapely.affinity.rotate(box(1002.2, 2000.4, 1004.9, 2002.2), 25),           # rotated, partly off
             box(1000.5, 2000.5, 1002.0, 2001.5),                                         # whole pixels
             box(1000.2, 2000.2, 1003.8, 2002.8).difference(box(1001.1, 2001.1, 1002.4, 2002.1))]  # a hole
    bounds = (x0, y0 - h * gsd, x0 + w * gsd, y0)
    rows = window_stats(values, [500.0], bounds, [z.wkb for z in zones], [z.area for z in zones], [ix])
    assert [r[:2] for r in rows] == [[k, 0] for k in range(len(zones))]
    for zone, (_, _, count, coverage, saturated, mean, std, vmin, p10, median, p90, vmax) in zip(zones, rows):
        weights = np.array([[box(x0 + c * gsd, y0 - (r + 1) * gsd, x0 + (c + 1) * gsd, y0 - r * gsd)
                             .intersection(zone).area / gsd**2 for c in range(w)] for r in range(h)])
        v = values[0]
        use = (weights > 0) & np.isfinite(v)
        wt, vv = weights[use], v[use].astype(float)
        assert count == pytest.approx(wt.sum(), rel=1e-6)   # exactextract sums float32 fractions
        assert coverage == pytest.approx(wt.sum() * gsd**2 / zone.area, rel=1e-6)
        assert mean == pytest.approx(np.sum(wt * vv) / wt.sum(), rel=1e-6)
        assert std == pytest.approx(math.sqrt(np.sum(wt * (vv - np.sum(wt * vv) / wt.sum()) ** 2) / wt.sum()), rel=1e-5)
        assert (vmin, vmax) == (pytest.approx(vv.min()), pytest.approx(vv.max()))
        assert vmin <= p10 <= median <= p90 <= vmax
        if np.allclose(wt, 1):
            np.testing.assert_allclose([p10, median, p90], np.quantile(vv, [0.1, 0.5, 0.9]), rtol=1e-6)
    assert rows[1][3] < 0.9   # the rotated box is partly off the window: its coverage says so
    assert rows[0][3] < 1 and rows[2][3] == pytest.approx(1.0)   # the triangle holds the NaN pixel
    # a flagged (saturated) pixel: out of count and mean, its weight in ``saturated``
    flags = np.zeros((h, w), np.uint8)
    flags[3, 4] = 1
    flagged = window_stats(values, [500.0], bounds, [z.wkb for z in zones], [z.area for z in zones], [ix], flags)
    for zone, before, after in zip(zones, rows, flagged):
        cell = box(x0 + 4 * gsd, y0 - 4 * gsd, x0 + 5 * gsd, y0 - 3 * gsd).intersection(zone).area / gsd**2
        assert after[4] == pytest.approx(cell, abs=1e-6) and before[4] == 0
        assert after[2] == pytest.approx(before[2] - cell, abs=1e-5)
    assert any(r[4] > 0.1 for r in flagged)


def test_indices_map_to_bands_and_refuse_in_one_line():
    from archive.analysis.indices import bind_indices, evaluate, parse_expression, parse_indices
    from archive.errors import InputError

    camera = np.linspace(400, 1000, 8)   # the simulator's 8 bands
    ndvi, evi, band = bind_indices(parse_indices(["ndvi", "EVI"], ["B=R829"]), camera)
    assert ndvi.name == "NDVI" and dict(ndvi.bands) == pytest.approx({"N": 828.571, "R": 657.143}, abs=1e-3)
    assert dict(evi.spec.constants) == {"g": 2.5, "C1": 6.0, "C2": 7.5, "L": 1.0} and "B" in dict(evi.bands)
    red, nir = np.array([0.05, 0.0, np.nan], np.float32), np.array([0.45, 0.0, 0.3], np.float32)
    got = evaluate(ndvi, {657.143: red, 828.571: nir})   # keys: the camera's band centres
    assert got[0] == pytest.approx(0.8) and np.isnan(got[1]) and np.isnan(got[2])
    for names, texts, words in [
        (["NDVX"], [], "unknown spectral index 'NDVX'"),
        (["NDREI"], [], "RE1"),                          # 695-715 nm: no band of an 8-band camera there
        ([], ["X=__import__('os').system('true')"], "not allowed"),
        ([], ["X=R800.real"], "not allowed"),
        ([], ["X=R2000/R800"], "half a band spacing"),
        ([], ["X=foo+R800"], "'foo' is not a band"),
        ([], ["(R800-R670)"], "NAME=EXPR"),
        ([], ["X=" + "(" * 300 + "R800" + ")" * 300], "X"),
        (["NDVI", "NDVI"], [], "twice"),
        ([], [], "no index"),
    ]:
        with pytest.raises(InputError, match=None) as caught:
            bind_indices(parse_indices(names, texts), camera)
        assert words in str(caught.value) and "\n" not in str(caught.value), (names, texts, str(caught.value))
    assert parse_expression("Y = sqrt(abs(R800 - R670)) / max(R800, 1e-3)").symbols == ("R800", "R670")


def test_bad_input_is_refused_in_one_line(field, tmp_path, capsys):
    root, archive, truths, zones, _, _ = field
    t0 = truths[0]
    cx, cy = Polygon(t0.footprint()[0]).centroid.coords[0]

    def write(name: str, geometry: dict, **extra) -> str:
        path = tmp_path / name
        path.write_text(json.dumps({"type": "FeatureCollection", **extra,
                                    "features": [{"type": "Feature", "properties": {}, "geometry": geometry}]}))
        return str(path)

    ring = [[cx, cy], [cx + 3, cy + 3], [cx + 3, cy], [cx, cy + 3], [cx, cy]]   # a bow tie
    bowtie = write("bowtie.geojson", {"type": "Polygon", "coordinates": [_lonlat(t0, ring)]})
    point = write("point.geojson", {"type": "Point", "coordinates": _lonlat(t0, [[cx, cy]])[0]})
    out = tmp_path / "t.csv"
    base = ["stats", *_query(field), "--gsd", str(GSD), "--out", str(out), "--quiet"]
    cases = [
        (["--zones", str(zones), "--index", "NDVX"], "unknown spectral index"),
        (["--zones", str(zones), "--expression", "X=R2000-R800"], "half a band spacing"),
        (["--zones", str(zones), "--index", "NDREI"], "RE1"),
        (["--zones", bowtie, "--index", "NDVI"], "invalid geometry (Self-intersection"),
        (["--zones", point, "--index", "NDVI"], "is a Point, not a polygon"),
        (["--zones", str(tmp_path / "none.geojson"), "--index", "NDVI"], "none.geojson"),
        (["--zones", str(zones), "--index", "NDVI", "--zone-id", "field"], "'field' is not a property"),
        (["--zones", str(zones), "--index", "NDVI", "--geometry"], "GeoParquet"),
    ]
    for extra, words in cases:
        assert main([*base, *extra]) != 0, extra
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and words in err and "Traceback" not in err, (extra, err)
        assert not out.exists()
    # the command as installed: one line, exit code not 0, nothing written
    done = subprocess.run([sys.executable, "-m", "archive", *base, "--zones", bowtie, "--index", "NDVI"],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode != 0 and len(done.stderr.strip().splitlines()) == 1 and "bowtie.geojson" in done.stderr
    assert not out.exists()


def test_saturated_pixels_are_left_out_and_counted(tmp_path):
    """A flight at 9 dB gain (x2.8): the white patch's DN clips at 4095 in the NDVI bands, the grass
    patch's does not. One zone holds both patches' interiors (a MultiPolygon): its NDVI is the grass
    truth's (the saturated white pixels left out, not mixed in), ``count`` the grass interior's
    pixels and ``saturated`` the white interior's (both 1.8 m squares: 51.84 px at 0.25 m; the
    coverage weights are exact); each patch alone as its own zone."""
    import archive
    from archive.simulator.command import simulate_flight
    from shapely.geometry import MultiPolygon

    truth = simulate_flight(tmp_path / "bright", seed=0, scene_seed=0, gains=[9.0], shutters=[3.0],
                            start="2024-06-12T16:00:00Z", **SHAPE)
    patches = {p["material_name"]: p for p in truth.homogeneous_patches()}
    inner = {}
    for name in ("white", "grass"):
        w, s, e, n = patches[name]["interior"]
        inner[name] = box(w + 0.6, s + 0.6, e - 0.6, n - 0.6)
        assert _covered(truth, inner[name], 0.1) == 1.0, name
    rad = truth.radiance(np.array([inner["grass"].centroid.x]), np.array([inner["grass"].centroid.y]))[:, 0]
    wl = truth.wavelengths
    red, nir = rad[np.argmin(abs(wl - 655))], rad[np.argmin(abs(wl - 830))]
    grass_ndvi = float((nir - red) / (nir + red))
    both = MultiPolygon([inner["grass"], inner["white"]])
    features = [_feature(truth, "grass", inner["grass"]), _feature(truth, "white", inner["white"]),
                {"type": "Feature", "id": "both", "properties": {"name": "both"},
                 "geometry": {"type": "MultiPolygon", "coordinates": [[_lonlat(truth, g.exterior.coords)]
                                                                      for g in both.geoms]}}]
    zones = tmp_path / "patches.geojson"
    zones.write_text(json.dumps({"type": "FeatureCollection", "features": features}))
    table = archive.zonal_stats(str(tmp_path / "bright"), zones, "NDVI", gsd=GSD, fov=FOV, mode="radiance")
    assert list(table.columns) == ["zone", "flight", "datetime", "index", "count", "coverage", "saturated", "mean",
                                   "std", "min", "p10", "median", "p90", "max", "bands"]
    rows = {r["zone"]: r for _, r in table.iterrows()}
    px = inner["grass"].area / GSD**2   # 51.84
    assert rows["grass"]["saturated"] == 0 and rows["grass"]["count"] == pytest.approx(px, rel=1e-5)
    assert rows["white"]["count"] == 0 and np.isnan(rows["white"]["mean"])
    assert rows["white"]["saturated"] == pytest.approx(px, rel=1e-5) and rows["white"]["coverage"] == 0
    got = rows["both"]
    assert got["saturated"] == pytest.approx(px, rel=1e-5) and got["count"] == pytest.approx(px, rel=1e-5)
    assert got["coverage"] == pytest.approx(0.5, rel=1e-5)   # half the zone's area counts
    assert abs(got["mean"] - grass_ndvi) < 0.005, (got["mean"], grass_ndvi)
    assert got["mean"] == pytest.approx(rows["grass"]["mean"], abs=1e-6)
    assert got["min"] >= rows["grass"]["min"] - 1e-6 and got["max"] <= rows["grass"]["max"] + 1e-6
