"""The viewer's page in real headless Chromium (Debian's ``chromium`` driven by Playwright; issue 13).

``archive view`` (the command, in a subprocess) serves a demo-sized archive; the page opens the
flight, and once its tiles have loaded:

- a screenshot of the map shows the flight's pixels exactly where ``archive.mosaic`` (a UTM
  render, another grid and CRS) has coverage, and the map's background everywhere else (only a
  2-pixel band along the coverage's edges may differ);
- a click on a covered pixel shows a spectrum (SVG chart, CSV, pixel info) equal, float32 bit for
  bit, to the same pixel of the mosaic at the grid of the nominal GSD;
- moving the ground-height slider with the keyboard re-renders the tiles (they change).

The page's screenshot after the click is saved as docs/viewer.png (the README shows it).
"""

from __future__ import annotations

import io
import os
import queue
import re
import signal
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

CHROMIUM = Path("/usr/bin/chromium")
LAUNCH_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--no-first-run", "--disable-background-networking",
               "--disable-component-update", "--disable-sync"]
ROOT = Path(__file__).resolve().parents[1]
BACKGROUND = (255, 0, 255)  # the map's background during the pixel check: no stretched flight pixel is this
FOV = 47.5
HALF_WORLD = np.pi * 6378137.0

pytestmark = pytest.mark.skipif(not CHROMIUM.exists(), reason="Debian's chromium is not installed at "
                                "/usr/bin/chromium (./dev.sh test installs it: apt-get install chromium)")
playwright = pytest.importorskip("playwright.sync_api", reason="the playwright package is not installed "
                                 "(pip install -e '.[test]' installs it)")


@pytest.fixture(scope="module")
def demo_archive(tmp_path_factory):
    """The demo's archive: ``archive simulate`` defaults (4 cubes x 250 lines x 128 samples x 8 bands)
    ingested at --fov 47.5."""
    from archive.ingest.command import ingest
    from archive.simulator.command import simulate_flight

    root = tmp_path_factory.mktemp("viewer")
    simulate_flight(root / "flight")
    (result,) = ingest([root / "flight"], root / "archive", FOV, progress=False)
    return root / "archive", result.cid


@pytest.fixture(scope="module")
def server(demo_archive):
    """``archive view --archive A --port 0`` in a subprocess; yields its URL."""
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    proc = subprocess.Popen([sys.executable, "-m", "archive", "view", "--archive", str(demo_archive[0]), "--port", "0"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT, env=env)
    lines: queue.Queue = queue.Queue()
    threading.Thread(target=lambda: [lines.put(line) for line in proc.stdout], daemon=True).start()
    try:
        line = lines.get(timeout=60)
    except queue.Empty:
        proc.kill()
        pytest.fail(f"archive view printed nothing: {proc.stderr.read()}")
    found = re.search(r"http://127\.0\.0\.1:\d+/", line)
    assert found, line
    yield found.group(0)
    proc.send_signal(signal.SIGINT)
    try:
        proc.wait(15)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
    assert proc.returncode == 0, proc.stderr.read()


def _screenshot(locator) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(locator.screenshot())).convert("RGB"))


def _map_geometry(page) -> dict:
    """Zoom and the global pixel (Web-Mercator, zoom z) of the map container's top-left corner."""
    return page.evaluate("""() => {
        const m = window.viewer.map;
        const p = m.getPixelOrigin().add(m.containerPointToLayerPoint([0, 0]));
        return {zoom: m.getZoom(), x: p.x, y: p.y};
    }""")


def _expected_coverage(ds, shape, geo) -> np.ndarray:
    """Whether each screen pixel centre of the map falls on a covered pixel of the UTM mosaic ``ds``."""
    from pyproj import Transformer

    h, w = shape
    res = 2 * HALF_WORLD / 256 / 2 ** geo["zoom"]
    mx = -HALF_WORLD + (geo["x"] + np.arange(w) + 0.5) * res
    my = HALF_WORLD - (geo["y"] + np.arange(h) + 0.5) * res
    gx, gy = np.meshgrid(mx, my)
    e, n = Transformer.from_crs(3857, ds.rio.crs.to_epsg(), always_xy=True).transform(gx, gy)
    gsd = float(ds.x[1] - ds.x[0])
    col = np.floor((np.asarray(e) - (float(ds.x[0]) - gsd / 2)) / gsd).astype(int)
    row = np.floor(((float(ds.y[0]) + gsd / 2) - np.asarray(n)) / gsd).astype(int)
    inside = (col >= 0) & (col < ds.sizes["x"]) & (row >= 0) & (row < ds.sizes["y"])
    covered = np.isfinite(ds[[v for v in ds.data_vars if v != "saturated"][0]].values[0])
    out = np.zeros(shape, bool)
    out[inside] = covered[row[inside], col[inside]]
    return out


def _wait_tiles(page, contains: str = "") -> None:
    page.wait_for_function(
        "(part) => window.viewer.ready && window.viewer.tileUrl && window.viewer.tileUrl.includes(part)",
        arg=contains, timeout=60_000)
    # every visible tile has loaded (no grey placeholder left)
    page.wait_for_function("() => !document.querySelector('.flight-tiles img.leaflet-tile:not(.leaflet-tile-loaded)')",
                           timeout=60_000)


def test_viewer_in_headless_chromium(server, demo_archive):
    from pyproj import Transformer
    from scipy.ndimage import binary_dilation, binary_erosion

    import archive

    path, cid = demo_archive
    with playwright.sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=str(CHROMIUM), args=LAUNCH_ARGS)
        try:
            page = browser.new_page(viewport={"width": 1280, "height": 960}, device_scale_factor=1)
            errors: list[str] = []
            page.on("pageerror", lambda exc: errors.append(str(exc)))
            page.goto(server)
            page.locator("#flights li", has_text=cid).click()
            _wait_tiles(page)
            assert page.evaluate("window.viewer.tileErrors") == 0

            # ---- pixels where the flight is, and only there ------------------------------------
            page.evaluate(f"""() => {{
                window.viewer.footprints.remove();
                document.querySelector('.leaflet-control-container').style.display = 'none';
                document.getElementById('map').style.background = 'rgb{BACKGROUND}';
            }}""")
            shot = _screenshot(page.locator("#map"))
            geo = _map_geometry(page)
            drawn = (shot != np.array(BACKGROUND, np.uint8)).any(axis=-1)
            coverage = archive.mosaic([cid], archive=path, gsd=0.03, wavelengths=[650])
            expected = _expected_coverage(coverage, drawn.shape, geo)
            edge = binary_dilation(expected, iterations=2) & ~binary_erosion(expected, iterations=2)
            assert expected.sum() > 20_000, "the flight should fill a good part of the map"
            wrong = (drawn != expected) & ~edge
            assert wrong.sum() == 0, f"{wrong.sum()} pixels drawn where the mosaic has no coverage or the reverse"
            assert (drawn & expected).sum() > 0.95 * expected.sum()

            # ---- a click: the spectrum of that pixel, as archive render has it -----------------
            inner = binary_erosion(expected, iterations=6)
            rows, cols = np.nonzero(inner)
            k = int(np.argmin((rows - rows.mean()) ** 2 + (cols - cols.mean()) ** 2))
            box = page.locator("#map").bounding_box()
            page.evaluate("document.querySelector('.leaflet-control-container').style.display = ''")
            page.mouse.click(box["x"] + cols[k] + 0.5, box["y"] + rows[k] + 0.5)
            page.wait_for_function("() => window.viewer.lastPoint !== null", timeout=30_000)
            point = page.evaluate("window.viewer.lastPoint")
            assert point["covered"] and point["id"] == cid and point["mode"] == "radiance"
            ds = archive.mosaic([cid], archive=path, gsd=point["gsd"])
            values = ds["radiance"].values
            assert ds.rio.crs.to_epsg() == point["epsg"]
            e, n = Transformer.from_crs(4326, point["epsg"], always_xy=True).transform(point["lon"], point["lat"])
            col = round((point["pixel"]["x"] - float(ds.x[0])) / point["gsd"])
            row = round((float(ds.y[0]) - point["pixel"]["y"]) / point["gsd"])
            assert abs(float(ds.x[col]) - point["pixel"]["x"]) < 1e-6
            assert abs(float(ds.y[row]) - point["pixel"]["y"]) < 1e-6
            assert abs(e - point["pixel"]["x"]) <= point["gsd"] / 2 and abs(n - point["pixel"]["y"]) <= point["gsd"] / 2
            spectrum = np.array(point["values"], np.float32)
            assert np.array_equal(spectrum.view(np.uint32), values[:, row, col].astype(np.float32).view(np.uint32)), \
                (spectrum, values[:, row, col])
            # what the page shows: the chart (one point per band), pixel info and the CSV
            assert page.locator("#pixel").is_visible()
            polyline = page.locator("#spectrum polyline").first.get_attribute("points")
            assert len(polyline.split()) == len(spectrum)
            info = page.locator("#pixel-info").inner_text()
            assert f"{point['line']}, {point['sample']}" in info and point["utc"] in info
            csv = page.evaluate("window.viewer.csv").strip().splitlines()
            assert csv[0] == "wavelength_nm,radiance" and len(csv) == len(spectrum) + 1
            assert np.array_equal(np.array([float(line.split(",")[1]) for line in csv[1:]], np.float32), spectrum)
            page.evaluate("() => { window.viewer.footprints.addTo(window.viewer.map); "
                          "document.getElementById('map').style.background = ''; }")
            (ROOT / "docs").mkdir(exist_ok=True)
            page.screenshot(path=str(ROOT / "docs" / "viewer.png"))

            # ---- the ground-height slider re-renders the tiles --------------------------------
            page.evaluate(f"""() => {{
                window.viewer.footprints.remove();
                document.querySelector('.leaflet-control-container').style.display = 'none';
                document.getElementById('map').style.background = 'rgb{BACKGROUND}';
            }}""")
            before = _screenshot(page.locator("#map"))
            slider = page.locator("#ground")
            slider.focus()
            for _ in range(20):  # 0.5 m steps: 10 m lower
                page.keyboard.press("ArrowLeft")
            lowered = float(slider.input_value())
            assert lowered < point["ground_height"] - 5
            _wait_tiles(page, f"ground_height={lowered:g}")
            after = _screenshot(page.locator("#map"))
            moved = (after != before).any(axis=-1)
            assert moved.mean() > 0.02, "the tiles did not change with the ground height"
            # the camera is higher above the lowered ground: its swath, and the drawn area, grow
            drawn_after = (after != np.array(BACKGROUND, np.uint8)).any(axis=-1)
            assert drawn_after.sum() > 1.1 * drawn.sum()
            # tiles dropped by the moves (Leaflet aborts them) were skipped or stopped, never failed
            counts = page.evaluate("fetch('/api/status').then(r => r.json())")["render"]
            assert counts["failed"] == 0
            assert counts["done"] + counts["skipped"] + counts["stopped"] <= counts["submitted"]
            assert not errors, errors
        finally:
            browser.close()
