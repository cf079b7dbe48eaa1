"""Time stacks in the viewer (issue 32, item 5): ``archive view --stack X.zarr`` serves a stack made
by ``archive render --stack``; its tiles and points are the Zarr's values (no rendering), and the
page's time slider steps through the flights (headless Chromium, skipped without it).

Two small flights of one field a week apart (2 cubes x 60 lines x 32 samples x 4 bands).
"""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import archive_view
import xarray as xr
from helpers import FOV

ROOT = Path(__file__).resolve().parents[1]
CHROMIUM = Path("/usr/bin/chromium")


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    """(archive, stack path): two flights of one field and their stack at 0.5 m."""
    from archive.ingest.command import ingest
    from archive.simulator.command import simulate_flight

    root = tmp_path_factory.mktemp("viewstack")
    for k, day in enumerate(("2024-06-12", "2024-06-19")):
        simulate_flight(root / f"day{k}", cubes=2, samples=32, lines=60, bands=4, seed=k, scene_seed=0,
                        start=f"{day}T16:00:00Z")
        ingest([str(root / f"day{k}")], root / "archive", FOV, progress=False)
    out = root / "field.zarr"
    subprocess.run([sys.executable, "-m", "archive", "render", "--archive", str(root / "archive"), "--query-datetime",
                    "2024-06", "--stack", "--gsd", "0.5", "--out", str(out), "--quiet"], check=True,
                   capture_output=True, timeout=300)
    return root / "archive", out


def _tile_of(lon: float, lat: float, z: int) -> tuple[int, int]:
    n = 1 << z
    x = int((lon + 180.0) / 360.0 * n)
    y = int((1.0 - math.asinh(math.tan(math.radians(lat))) / math.pi) / 2.0 * n)
    return x, y


def test_stack_api_serves_the_zarr_values(stack):
    from starlette.testclient import TestClient

    from archive.view.registry import FlightRegistry
    from archive.view.server import create_app
    from archive.view.stacks import open_stacks

    archive, out = stack
    client = TestClient(create_app(FlightRegistry(str(archive), [], None), stacks=open_stacks([out])))
    (info,) = client.get("/api/stacks").json()["stacks"]
    with xr.open_zarr(out) as ds:
        zarr_values = ds.radiance.values
        assert [t["flight"] for t in info["times"]] == list(ds.flight.values)
    w, s, e, n = info["bbox"]
    lon, lat = (w + e) / 2, (s + n) / 2
    x, y = _tile_of(lon, lat, 21)
    for t in (0, 1):
        r = client.get(f"/api/stacks/field/values/21/{x}/{y}?time={t}&bands=0,1,2")
        assert r.status_code == 200
        planes = np.frombuffer(r.content, "<f4").reshape(3, 256, 256)
        shown = planes[np.isfinite(planes)]
        assert shown.size > 1000 and np.isin(shown, zarr_values[t, :3]).all()   # every value is one of the Zarr's
        p = client.get(f"/api/stacks/field/point?lon={lon}&lat={lat}&time={t}").json()
        np.testing.assert_array_equal(np.array(p["values"], np.float32), zarr_values[t, :, p["row"], p["col"]])
    png = client.get(f"/api/stacks/field/tiles/21/{x}/{y}.png?time=1")
    assert png.status_code == 200 and png.headers["content-type"] == "image/png"
    assert client.get("/api/stacks/field/tiles/3/1/1.png").status_code == 204   # nowhere near
    assert client.get(f"/api/stacks/field/point?lon={lon}&lat={lat}&time=5").status_code == 400
    assert client.get("/api/stacks/other/point?lon=0&lat=0").status_code == 404


@pytest.mark.skipif(not CHROMIUM.exists(), reason="Debian's chromium is not installed at /usr/bin/chromium")
def test_the_page_steps_through_the_flights(stack):
    sync_api = pytest.importorskip("playwright.sync_api", reason="the playwright package is not installed")
    from pyproj import Transformer

    from archive.outputs.like import read_grid

    archive, out = stack
    epsg = read_grid(out).epsg
    with xr.open_zarr(out, decode_coords="all") as ds:   # a pixel of the second flight, well inside its coverage
        covered = np.argwhere(np.isfinite(ds.radiance.values[1]).all(axis=0))
        r, c = covered[len(covered) // 2]
        lon, lat = Transformer.from_crs(epsg, 4326, always_xy=True).transform(float(ds.x[c]), float(ds.y[r]))
    command = [sys.executable, "-m", "archive", "view", "--archive", str(archive), "--stack", str(out), "--port", "0"]
    with archive_view(command, cwd=ROOT) as (url, _):
        with sync_api.sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=str(CHROMIUM), args=["--headless", "--no-sandbox"])
            page = browser.new_page(viewport={"width": 900, "height": 700})
            errors, tiles = [], []
            page.on("pageerror", lambda exc: errors.append(str(exc)))
            page.on("request", lambda r: tiles.append(r.url) if "/api/stacks/field/tiles/" in r.url else None)
            page.goto(url)
            page.get_by_role("button", name="field: 2 flights").click()
            page.wait_for_function("document.getElementById('stack-label').textContent.includes('1 / 2')")
            page.wait_for_load_state("networkidle")
            assert tiles and all("time=0" in u for u in tiles)
            page.fill("#stack-time", "1")   # the slider: the next flight, the same grid
            page.wait_for_function("document.getElementById('stack-label').textContent.includes('2 / 2')")
            page.wait_for_load_state("networkidle")
            assert any("time=1" in u for u in tiles)
            box = page.locator("#map").bounding_box()
            at = page.evaluate(f"(() => {{ const p = window.viewer.map.latLngToContainerPoint([{lat}, {lon}]); return [p.x, p.y]; }})()")
            with page.expect_response(lambda r: "/api/stacks/field/point" in r.url) as answer:
                page.mouse.click(box["x"] + at[0], box["y"] + at[1])   # a pixel the second flight covers
            p = answer.value.json()
            page.wait_for_function("document.querySelectorAll('#stack-point td').length >= 8")
            browser.close()
        assert not errors, errors
        with xr.open_zarr(out) as ds:
            assert p["time"] == 1 and p["flight"] == str(ds.flight.values[1])
            assert None not in p["values"] and abs(p["row"] - r) <= 1 and abs(p["col"] - c) <= 1
            np.testing.assert_array_equal(np.array(p["values"], np.float32),
                                          ds.radiance.values[1, :, p["row"], p["col"]])


def _stack_coverage(out, shape, geo) -> list[np.ndarray]:
    """Per time step, whether each screen pixel centre of the map falls on a stack pixel with a value in
    every band (what the page draws of that step)."""
    from pyproj import Transformer

    from archive.grid import HALF_WORLD
    from archive.outputs.like import read_grid

    grid = read_grid(out)
    h, w = shape
    res = 2 * HALF_WORLD / 256 / 2 ** geo["zoom"]
    mx, my = np.meshgrid(-HALF_WORLD + (geo["x"] + np.arange(w) + 0.5) * res,
                         HALF_WORLD - (geo["y"] + np.arange(h) + 0.5) * res)
    e, n = Transformer.from_crs(3857, grid.epsg, always_xy=True).transform(mx, my)
    rows, cols = (np.floor(v).astype(int) for v in grid.rowcol(e, n))
    inside = (rows >= 0) & (cols >= 0) & (rows < grid.height) & (cols < grid.width)
    with xr.open_zarr(out) as ds:
        finite = np.isfinite(ds.radiance.values).all(axis=1)   # (time, y, x)
    out_masks = []
    for t in range(finite.shape[0]):
        m = np.zeros(shape, bool)
        m[inside] = finite[t][rows[inside], cols[inside]]
        out_masks.append(m)
    return out_masks


@pytest.mark.skipif(not CHROMIUM.exists(), reason="Debian's chromium is not installed at /usr/bin/chromium")
def test_the_stack_is_drawn_above_the_flights(stack):
    """Issue 49 item 4: with the archive's flights drawn, the shown stack lies above them (the flights
    dimmed, or hidden), each time step draws exactly the stack's coverage of that step, the slider changes
    the picture, and a click on a stack pixel answers the stack's value without opening the flight under it."""
    import io

    from PIL import Image
    from scipy.ndimage import binary_dilation, binary_erosion

    sync_api = pytest.importorskip("playwright.sync_api", reason="the playwright package is not installed")
    archive, out = stack
    background = (255, 0, 255)
    command = [sys.executable, "-m", "archive", "view", "--archive", str(archive), "--stack", str(out), "--port", "0"]
    with archive_view(command, cwd=ROOT) as (url, _):
        with sync_api.sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=str(CHROMIUM), args=["--headless", "--no-sandbox"])
            page = browser.new_page(viewport={"width": 900, "height": 700}, device_scale_factor=1)
            errors, points = [], []
            page.on("pageerror", lambda exc: errors.append(str(exc)))
            page.on("request", lambda r: points.append(r.url) if "/point?" in r.url else None)
            page.goto(url)
            page.wait_for_function("() => window.viewer.settled && window.viewer.draws > 0")   # the flights, drawn
            page.get_by_role("button", name="field: 2 flights").click()
            page.wait_for_function("document.getElementById('stack-label').textContent.includes('1 / 2')")
            page.wait_for_function("() => window.viewer.settled")
            page.wait_for_load_state("networkidle")
            page.evaluate(f"""() => {{
                for (const s of ['.leaflet-control-container', '.leaflet-footprints-pane', '.leaflet-tooltip-pane',
                                 '.leaflet-overlay-pane'])
                    document.querySelector(s).style.display = 'none';
                document.getElementById('map').style.background = 'rgb{background}';
            }}""")
            opacity = page.evaluate("getComputedStyle(document.querySelector('.flight-tiles')).opacity")
            assert float(opacity) == pytest.approx(0.25), "the flights are dimmed under the stack"
            assert page.evaluate("getComputedStyle(document.querySelector('.leaflet-stack-pane')).zIndex") == "350"

            def shot():
                return np.asarray(Image.open(io.BytesIO(page.locator("#map").screenshot())).convert("RGB"))

            def step(t: int):
                page.fill("#stack-time", str(t))
                page.wait_for_function(f"document.getElementById('stack-label').textContent.includes('{t + 1} / 2')")
                page.wait_for_load_state("networkidle")
                page.wait_for_timeout(200)   # the last tile decoded and composited

            dimmed = [shot()]
            step(1)
            dimmed.append(shot())
            geo = page.evaluate("""() => { const m = window.viewer.map;
                const p = m.getPixelOrigin().add(m.containerPointToLayerPoint([0, 0]));
                return {zoom: m.getZoom(), x: p.x, y: p.y}; }""")
            coverage = _stack_coverage(out, dimmed[0].shape[:2], geo)
            changed = (dimmed[0] != dimmed[1]).any(axis=-1)
            differs = coverage[0] != coverage[1]
            assert differs.sum() > 500, "the two steps cover different pixels"
            core = binary_erosion(differs, iterations=2)
            assert changed[core].mean() > 0.95, "the slider changes the picture where the steps differ"
            # flights hidden: each step draws exactly its own coverage
            page.select_option("#stack-flights", "hidden")
            for t in (1, 0):
                step(t)
                drawn = (shot() != np.array(background, np.uint8)).any(axis=-1)
                edge = binary_dilation(coverage[t], iterations=1) & ~binary_erosion(coverage[t], iterations=1)
                assert coverage[t].sum() > 2000
                wrong = (drawn != coverage[t]) & ~edge
                assert wrong.sum() == 0, f"step {t}: {wrong.sum()} pixels drawn off the stack's coverage"
            # a click on a stack pixel that a flight covers too: the stack's value, no flight opened
            rows, cols = np.nonzero(binary_erosion(coverage[0], iterations=10))
            k = len(rows) // 2
            box = page.locator("#map").bounding_box()
            with page.expect_response(lambda r: "/api/stacks/field/point" in r.url) as answer:
                page.mouse.click(box["x"] + cols[k] + 0.5, box["y"] + rows[k] + 0.5)
            p = answer.value.json()
            page.wait_for_timeout(300)
            assert page.evaluate("window.viewer.open") is None, "the click opened the flight under the stack"
            assert all("/api/stacks/" in u for u in points), points
            page.click("#stack-close")
            assert page.evaluate("getComputedStyle(document.querySelector('.flight-tiles')).opacity") == "1"
            browser.close()
        assert not errors, errors
        with xr.open_zarr(out) as ds:
            assert p["time"] == 0 and None not in p["values"]
            np.testing.assert_array_equal(np.array(p["values"], np.float32), ds.radiance.values[0, :, p["row"], p["col"]])
