"""Zones in the viewer (issue 48 item 4): ``archive view --zones FIELDS`` draws the fields and a click
on one plots its time series, one point per flight, computed by ``archive stats``' own code.

Two small flights of one field a week apart (``scene_seed`` 0: the same ground; 2 cubes x 100 lines x
64 samples x 8 bands, 400-1000 nm), ingested with their sky spectra: the zones are the simulator's
homogeneous patches both flights see whole (as tests/test_stats.py builds them, its helpers reused),
and one far away. The endpoint against ``archive.zonal_stats`` on the same flights and zone and the
true NDVI; the page (real Chromium) against the endpoint; a bad zones file refused in one line.
"""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
import pytest
from shapely.geometry import Polygon, box

from helpers import FOV
from test_stats import _covered, _feature, _ndvi
from tests.conftest import archive_view, serve_loopback

ROOT = Path(__file__).resolve().parents[1]
CHROMIUM = Path("/usr/bin/chromium")
GSD = 0.25
DAYS = ("2024-06-12", "2024-06-19")
STATS = ("count", "coverage", "saturated", "mean", "std", "p10", "median", "p90")


@pytest.fixture(scope="module")
def field(tmp_path_factory):
    """(archive, zones path, {zone: true NDVI}): two flights a week apart and the patches they both see."""
    from archive.ingest.command import ingest
    from archive.simulator.command import simulate_flight

    root = tmp_path_factory.mktemp("viewzones")
    truths = []
    for k, day in enumerate(DAYS):
        truths.append(simulate_flight(root / f"day{k}", seed=k, scene_seed=0, clouds=True, start=f"{day}T16:00:00Z",
                                      cubes=2, bands=8, samples=64, lines=100, cubes_per_pass=2))
        ingest([str(root / f"day{k}")], root / "archive", FOV, progress=False)
    t0 = truths[0]
    features, ndvi = [], {}
    for p in t0.homogeneous_patches():
        w, s, e, n = p["interior"]
        zone = box(w + 0.6, s + 0.6, e - 0.6, n - 0.6)
        if all(_covered(t, zone, 0.1) == 1.0 for t in truths):
            features.append(_feature(t0, p["name"], zone))
            ndvi[p["name"]] = _ndvi(t0, *zone.centroid.coords[0])
    assert len(ndvi) >= 2 and max(ndvi.values()) - min(ndvi.values()) > 0.3, ndvi
    cx, cy = Polygon(t0.footprint()[0]).centroid.coords[0]
    features.append(_feature(t0, "far", box(cx + 1000, cy + 1000, cx + 1010, cy + 1010)))
    zones = root / "fields.geojson"
    zones.write_text(json.dumps({"type": "FeatureCollection", "features": features}))
    return root / "archive", zones, ndvi


def _app(field, stack):
    from archive.view.registry import FlightRegistry
    from archive.view.server import create_app
    from archive.view.stacks import open_stacks
    from archive.view.zones import open_zones, zone_routes

    stacks = open_stacks([stack])
    zones = open_zones(field[1], None, FlightRegistry(str(field[0]), [], None), stacks)
    return create_app(zones.registry, stacks=stacks, extra_routes=zone_routes(zones)), zones


def _get(url: str) -> dict:
    with urllib.request.urlopen(url, timeout=120) as r:
        return json.loads(r.read())


def test_series_are_archive_stats_numbers_and_the_truth(field, scheduler):
    """The endpoint's rows: archive.zonal_stats's, number for number, on the same flights, zone, index and
    grid; the patches' mean NDVI within 0.005 of the truth on both dates; the index display's two bands
    (a, b) NDVI's; a served stack's flights on its grid the same; a zone far from every flight: no flight
    images it; a GeoJSON file the page sends replaces the zones (refused as --zones refuses it). While a
    series is computed the server answers other requests (its event loop is free)."""
    import archive

    archive_path, zones_path, ndvi = field
    table = archive.zonal_stats({"datetime": "2024-06-01/2024-07-01"}, zones_path, ["NDVI"], archive=archive_path,
                                gsd=GSD, scheduler=scheduler)
    stack = zones_path.parent / "field.zarr"
    subprocess.run([sys.executable, "-m", "archive", "render", "--archive", str(archive_path), "--query-datetime",
                    "2024-06", "--stack", "--gsd", str(GSD), "--out", str(stack), "--quiet"], check=True,
                   capture_output=True, timeout=300)
    app, zones = _app(field, stack)
    try:
        with serve_loopback(app) as url:
            listed = _get(f"{url}/api/zones")
            assert [f["id"] for f in listed["features"]] == [*ndvi, "far"]
            lon, lat = np.array(listed["features"][0]["geometry"]["coordinates"][0]).T
            assert -90 < lon.mean() < -89 and 35 < lat.mean() < 36   # lon/lat, as drawn on the map

            # the first series starts the zones' cluster: meanwhile /api/status answers at once
            first = next(iter(ndvi))
            got, waits = {}, []
            asking = threading.Thread(target=lambda: got.update(
                _get(f"{url}/api/zones/series?zone={first}&gsd={GSD}&mode=reflectance")))
            asking.start()
            while asking.is_alive():
                t0 = time.perf_counter()
                _get(f"{url}/api/status")
                waits.append(time.perf_counter() - t0)
                time.sleep(0.05)
            asking.join()
            assert len(waits) >= 5 and max(waits) < 0.5, waits

            for zid, true in ndvi.items():
                series = got if zid == first else _get(f"{url}/api/zones/series?zone={zid}&gsd={GSD}&mode=reflectance")
                rows = table[table["zone"] == zid].sort_values("datetime")
                assert series["index"] == "NDVI" and series["bands"] == "N=828.6nm,R=657.1nm" and series["gsd"] == GSD
                assert [r["flight"] for r in series["rows"]] == list(rows["flight"]) and len(rows) == 2
                assert [r["datetime"][:10] for r in series["rows"]] == list(DAYS)
                for column in STATS:
                    np.testing.assert_allclose([r[column] for r in series["rows"]], rows[column].to_numpy(),
                                               rtol=1e-9, err_msg=f"{zid} {column}")
                for r in series["rows"]:
                    assert abs(r["mean"] - true) < 0.005, (zid, r, true)
                    assert r["coverage"] == pytest.approx(1.0, abs=1e-6) and r["p10"] <= r["median"] <= r["p90"]
                # the index display's bands: (a - b) / (a + b) of the bands NDVI reads, the same numbers
                nd = _get(f"{url}/api/zones/series?zone={zid}&gsd={GSD}&mode=reflectance&a=828.6&b=657.1")
                assert nd["index"] == "ND829_657" and nd["bands"] == "R829=828.6nm,R657=657.1nm"
                np.testing.assert_allclose([r["mean"] for r in nd["rows"]], [r["mean"] for r in series["rows"]], rtol=1e-6)
            far = _get(f"{url}/api/zones/series?zone=far&gsd={GSD}")
            assert far["rows"] == [] and far["message"] == "no flight images zone far"
            for query, status in (("zone=nope", 404), (f"zone={first}&a=800", 400), (f"zone={first}&index=EVI", 400)):
                with pytest.raises(urllib.error.HTTPError) as refused:
                    _get(f"{url}/api/zones/series?{query}")
                assert refused.value.code == status and "error" in json.loads(refused.value.read())
            # the stack's flights, on its grid: the same numbers (that grid is the time stack's at GSD)
            on_stack = _get(f"{url}/api/zones/series?zone={first}&stack=field")
            assert on_stack["gsd"] == GSD and on_stack["flights"] == [r["flight"] for r in got["rows"]]
            assert [r["mean"] for r in on_stack["rows"]] == [r["mean"] for r in got["rows"]]
            # a file loaded in the page replaces the zones, read (and refused) as --zones reads one
            def post(body: bytes, name: str) -> dict:
                ask = urllib.request.Request(f"{url}/api/zones?name={name}", data=body, method="POST")
                with urllib.request.urlopen(ask, timeout=60) as r:
                    return json.loads(r.read())

            one = json.loads(zones_path.read_text())
            one["features"] = one["features"][-1:]
            assert [f["id"] for f in post(json.dumps(one).encode(), "far.geojson")["features"]] == ["far"]
            assert _get(f"{url}/api/zones")["path"] == "far.geojson"
            with pytest.raises(urllib.error.HTTPError) as refused:
                post(b'{"type": "FeatureCollection", "features": []}', "empty.geojson")
            assert refused.value.code == 400
            assert json.loads(refused.value.read())["error"].startswith("empty.geojson: holds no zone (")
    finally:
        zones.close()


def test_bad_zones_are_refused_in_one_line(field, tmp_path):
    bad = tmp_path / "bad.geojson"
    bad.write_text(json.dumps({"type": "FeatureCollection", "features": [
        {"type": "Feature", "properties": {}, "geometry": {"type": "Point", "coordinates": [-89.94, 35.12]}}]}))
    base = [sys.executable, "-m", "archive", "view", "--archive", str(field[0]), "--port", "0"]
    for extra, words in (([ "--zones", str(bad)], "zone 0 is a Point, not a polygon"),
                         (["--zones", str(tmp_path / "none.geojson")], "none.geojson"),
                         (["--zones", str(field[1]), "--zone-id", "owner"], "'owner' is not a property"),
                         (["--zone-id", "name"], "--zone-id")):
        done = subprocess.run(base + extra, capture_output=True, text=True, timeout=60, cwd=ROOT)
        lines = done.stderr.strip().splitlines()
        assert done.returncode != 0 and len(lines) == 1 and words in lines[0], (extra, done.stderr)
        assert "http://" not in done.stdout


@pytest.mark.skipif(not CHROMIUM.exists(), reason="Debian's chromium is not installed at /usr/bin/chromium")
def test_a_click_on_a_zone_plots_its_series(field):
    """The page draws the zones; a click inside one plots the endpoint's rows (one point per flight, in
    time order: x the flights' times, y mean, p10, p90) in uPlot, the zone's id in the title; a file
    loaded in the page replaces the zones, and a zone no flight images says so."""
    sync_api = pytest.importorskip("playwright.sync_api", reason="the playwright package is not installed")
    archive_path, zones_path, ndvi = field
    zid = next(iter(ndvi))
    command = [sys.executable, "-m", "archive", "view", "--archive", str(archive_path), "--zones", str(zones_path),
               "--port", "0"]
    with archive_view(command, cwd=ROOT) as (url, _):
        with sync_api.sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=str(CHROMIUM), args=["--headless", "--no-sandbox"])
            page = browser.new_page(viewport={"width": 1280, "height": 900})
            errors = []
            page.on("pageerror", lambda exc: errors.append(str(exc)))
            page.goto(url)
            page.wait_for_function("() => window.viewer.zones && window.viewer.zones.length === 3")
            page.wait_for_function("() => window.viewer.settled && window.viewer.draws > 0")
            assert page.locator(".leaflet-zones-pane path").count() == 3   # the outlines
            feature = page.evaluate(f"window.viewer.zones.find((f) => f.id === '{zid}')")
            lon, lat = np.array(feature["geometry"]["coordinates"][0]).T
            page.evaluate(f"() => window.viewer.map.setView([{lat.mean()}, {lon.mean()}], 21)")
            page.wait_for_function("() => window.viewer.settled")
            page.evaluate("() => { document.getElementById('ndvi').click(); }")   # the index display: NDVI
            at = page.evaluate(f"(() => {{ const p = window.viewer.map.latLngToContainerPoint([{lat.mean()}, "
                               f"{lon.mean()}]); return [p.x, p.y]; }})()")
            where = page.locator("#map").bounding_box()
            with page.expect_response(lambda r: "/api/zones/series" in r.url, timeout=120_000) as answer:
                page.mouse.click(where["x"] + at[0], where["y"] + at[1])
            series = answer.value.json()
            page.wait_for_function("() => window.viewer.zoneChart", timeout=30_000)
            plot = page.evaluate("""() => { const u = window.viewer.zoneChart;
                return { x: [...u.data[0]], series: u.series.map((s) => s.label), data: u.data.slice(1).map((d) => [...d]),
                         title: document.querySelector('#zone-series .u-title').textContent,
                         ms: window.viewer.zonePlotted - window.viewer.zoneAsked }; }""")
            # a GeoJSON file loaded in the page replaces the zones (the map goes to them); a click on a
            # zone no flight images says so
            far = json.loads(zones_path.read_text())
            far["features"] = far["features"][-1:]
            page.set_input_files("#zone-file", files=[{"name": "far.geojson", "mimeType": "application/geo+json",
                                                       "buffer": json.dumps(far).encode()}])
            page.wait_for_function("() => window.viewer.zones.length === 1 && window.viewer.zones[0].id === 'far'")
            page.wait_for_timeout(300)   # the map at the zone
            at = page.evaluate("""(() => { const c = L.geoJSON(window.viewer.zones[0]).getBounds().getCenter();
                const p = window.viewer.map.latLngToContainerPoint(c); return [p.x, p.y]; })()""")
            page.mouse.click(where["x"] + at[0], where["y"] + at[1])
            page.wait_for_function("() => document.getElementById('zone-message').textContent === "
                                   "'no flight images zone far'", timeout=30_000)
            assert page.locator("#zone-series .uplot").count() == 0
            browser.close()
        assert not errors, errors
    assert series["zone"] == zid and series["index"] == "NDVI" and series["mode"] == "reflectance"
    rows = series["rows"]
    assert len(rows) == 2 and [r["datetime"][:10] for r in rows] == list(DAYS)
    assert plot["series"] == ["UTC", "p10", "mean", "p90"] and zid in plot["title"]
    assert plot["x"] == [np.datetime64(r["datetime"][:-1]).astype("datetime64[us]").astype(float) / 1e6 for r in rows]
    assert plot["data"] == [[r[k] for r in rows] for k in ("p10", "mean", "p90")]
    assert all(abs(r["mean"] - ndvi[zid]) < 0.005 for r in rows)
    print(f"click to plotted series: {plot['ms']:.0f} ms (the server's cluster started by it)")
