"""The viewer's page in real headless Chromium (Debian's ``chromium`` driven by Playwright; issues 13, 22).

``archive view`` (the command, in a subprocess) serves an archive of six small overlapping flights.
The page draws band-value tiles it stretches and composes itself, so:

- one flight drawn alone shows its pixels exactly where ``archive.mosaic`` (a UTM render, another
  grid and CRS) has coverage, and the map's background everywhere else (only a 2-pixel band along
  the coverage's edges may differ); pinned spectra equal the mosaic's pixels float32 bit for bit;
- screenshots taken every ~50 ms during a band change and a ground-height change never show the
  open flight's footprint empty (double buffering; previews while the slider moves);
- a stretch change issues no tile request and changes the picture; editing the URL hash updates the
  view without a reload;
- two overlapping flights are drawn at once (the order decides the overlap), and at the zoom that
  fits the archive every flight shows imagery (anti-aliased overview tiles);
- an invalid cube range shows the server's message next to the cube fields; Reset clears it.

The page's screenshot with two pinned spectra is docs/viewer.png (the README shows it): rewritten by
a run with ARCHIVE_SCREENSHOT=1.
"""

from __future__ import annotations

import io
import os
import re
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from tests.conftest import archive_view
from helpers import FOV, inside_geometry

CHROMIUM = Path("/usr/bin/chromium")
LAUNCH_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--no-first-run", "--disable-background-networking",
               "--disable-component-update", "--disable-sync"]
ROOT = Path(__file__).resolve().parents[1]
BACKGROUND = (255, 0, 255)  # the map's background during pixel checks: no stretched flight pixel is this
HALF_WORLD = np.pi * 6378137.0
FLIGHTS = 6

pytestmark = pytest.mark.skipif(not CHROMIUM.exists(), reason="Debian's chromium is not installed at "
                                "/usr/bin/chromium (./dev.sh test installs it: apt-get install chromium)")
playwright = pytest.importorskip("playwright.sync_api", reason="the playwright package is not installed "
                                 "(pip install -e '.[test]' installs it)")


@pytest.fixture(scope="module")
def archive_of_flights(tmp_path_factory):
    """(archive path, ids by start time): six simulated flights (2 cubes x 150 lines x 64 samples x 6
    bands) on a 3 x 2 grid whose neighbours overlap, ingested at --fov 47.5."""
    from archive.ingest.command import ingest
    from archive.simulator.command import simulate_flight

    root = tmp_path_factory.mktemp("viewer")
    dirs = []
    for i in range(FLIGHTS):
        d = root / f"flight{i}"
        simulate_flight(d, cubes=2, bands=6, samples=64, lines=150, cubes_per_pass=2, seed=i,
                        lat=35.12 + 0.00015 * (i // 3), lon=-89.94 + 0.00025 * (i % 3),
                        start=f"2024-06-0{i + 1}T15:00:00Z")
        dirs.append(d)
    results = ingest(dirs, root / "archive", FOV, progress=False)
    return root / "archive", [r.cid for r in results]


@pytest.fixture(scope="module")
def server(archive_of_flights):
    """``archive view --archive A --port 0`` in a subprocess; yields its URL."""
    command = [sys.executable, "-m", "archive", "view", "--archive", str(archive_of_flights[0]), "--port", "0"]
    with archive_view(command, cwd=ROOT) as (url, proc):
        yield url
    assert proc.returncode == 0, proc.stderr.read()


@pytest.fixture(scope="module")
def browser():
    with playwright.sync_playwright() as pw:
        b = pw.chromium.launch(executable_path=str(CHROMIUM), args=LAUNCH_ARGS)
        try:
            yield b
        finally:
            b.close()


class Page:
    """A page of the viewer with its tile requests and errors recorded."""

    def __init__(self, browser, url: str, hash_: str = "", width: int = 1280, height: int = 900):
        self.page = browser.new_page(viewport={"width": width, "height": height}, device_scale_factor=1)
        self.errors: list[str] = []
        self.values_requests: list[str] = []
        self.page.on("pageerror", lambda exc: self.errors.append(str(exc)))
        self.page.on("request", lambda r: self.values_requests.append(r.url) if "/values/" in r.url else None)
        self.page.goto(url + ("#" + hash_ if hash_ else ""))
        self.settled()

    def settled(self, timeout: float = 60_000) -> None:
        self.page.wait_for_function("() => window.viewer.settled && window.viewer.draws > 0", timeout=timeout)

    def clean(self) -> None:
        """Map background BACKGROUND, no footprints, labels or controls (pixel checks)."""
        self.page.evaluate(f"""() => {{
            for (const s of ['.leaflet-control-container', '.leaflet-footprints-pane', '.leaflet-tooltip-pane'])
                document.querySelector(s).style.display = 'none';
            document.getElementById('map').style.background = 'rgb{BACKGROUND}';
        }}""")

    def shot(self) -> np.ndarray:
        return np.asarray(Image.open(io.BytesIO(self.page.locator("#map").screenshot())).convert("RGB"))

    def drawn(self, shot=None) -> np.ndarray:
        shot = self.shot() if shot is None else shot
        return (shot != np.array(BACKGROUND, np.uint8)).any(axis=-1)

    def geometry(self) -> dict:
        """Zoom and the global pixel (Web-Mercator, zoom z) of the map container's top-left corner."""
        return self.page.evaluate("""() => {
            const m = window.viewer.map;
            const p = m.getPixelOrigin().add(m.containerPointToLayerPoint([0, 0]));
            return {zoom: m.getZoom(), x: p.x, y: p.y};
        }""")

    def close(self) -> None:
        assert not self.errors, self.errors
        self.page.close()


def _screen_lonlat(shape, geo):
    """lon, lat of each screen pixel centre of the map."""
    from pyproj import Transformer

    h, w = shape
    res = 2 * HALF_WORLD / 256 / 2 ** geo["zoom"]
    mx = -HALF_WORLD + (geo["x"] + np.arange(w) + 0.5) * res
    my = HALF_WORLD - (geo["y"] + np.arange(h) + 0.5) * res
    gx, gy = np.meshgrid(mx, my)
    lon, lat = Transformer.from_crs(3857, 4326, always_xy=True).transform(gx, gy)
    return np.asarray(lon), np.asarray(lat)


def _mosaic_pixels(ds, shape, geo):
    """(row, col, inside): the pixel of the UTM mosaic ``ds`` under each screen pixel centre of the map,
    and whether it lies in the mosaic."""
    from pyproj import Transformer

    lon, lat = _screen_lonlat(shape, geo)
    e, n = Transformer.from_crs(4326, ds.rio.crs.to_epsg(), always_xy=True).transform(lon, lat)
    gsd = float(ds.x[1] - ds.x[0])
    col = np.floor((np.asarray(e) - (float(ds.x[0]) - gsd / 2)) / gsd).astype(int)
    row = np.floor(((float(ds.y[0]) + gsd / 2) - np.asarray(n)) / gsd).astype(int)
    return row, col, (col >= 0) & (col < ds.sizes["x"]) & (row >= 0) & (row < ds.sizes["y"])


def _expected_coverage(ds, shape, geo) -> np.ndarray:
    """Whether each screen pixel centre of the map falls on a covered pixel of the UTM mosaic ``ds``."""
    row, col, inside = _mosaic_pixels(ds, shape, geo)
    covered = np.isfinite(ds[[v for v in ds.data_vars if v != "saturated"][0]].values[0])
    out = np.zeros(shape, bool)
    out[inside] = covered[row[inside], col[inside]]
    return out


def _footprint_mask(feature, shape, geo) -> np.ndarray:
    """Boolean (height, width) ``shape`` mask of the screen pixels inside ``feature``'s footprint."""
    return inside_geometry(feature["geometry"], *_screen_lonlat(shape, geo))


def _shots_while(page: Page, start, seconds: float = 8.0) -> list[np.ndarray]:
    """Screenshots of the map: one before ``start()``, then as fast as they come (~every 50 ms)
    until the view has settled again (and at least 0.5 s)."""
    shots = [page.shot()]
    page.page.evaluate("() => { window.viewer.settled = false; }")
    start()
    t0 = time.monotonic()
    while time.monotonic() - t0 < seconds:
        shots.append(page.shot())
        if time.monotonic() - t0 > 0.5 and page.page.evaluate("window.viewer.settled"):
            break
        time.sleep(0.05)
    shots.append(page.shot())
    return shots


def _point_check(point, path):
    """The pinned spectrum equals the pixel of ``archive.mosaic`` at the point's GSD, float32-exact."""
    from pyproj import Transformer

    import archive

    ds = archive.mosaic([point["id"]], archive=path, gsd=point["gsd"])
    values = ds["radiance"].values
    assert ds.rio.crs.to_epsg() == point["epsg"]
    e, n = Transformer.from_crs(4326, point["epsg"], always_xy=True).transform(point["lon"], point["lat"])
    col = round((point["pixel"]["x"] - float(ds.x[0])) / point["gsd"])
    row = round((float(ds.y[0]) - point["pixel"]["y"]) / point["gsd"])
    assert abs(float(ds.x[col]) - point["pixel"]["x"]) < 1e-6 and abs(float(ds.y[row]) - point["pixel"]["y"]) < 1e-6
    assert abs(e - point["pixel"]["x"]) <= point["gsd"] / 2 and abs(n - point["pixel"]["y"]) <= point["gsd"] / 2
    spectrum = np.array(point["values"], np.float32)
    assert np.array_equal(spectrum.view(np.uint32), values[:, row, col].astype(np.float32).view(np.uint32)), \
        (spectrum, values[:, row, col])
    return spectrum


#: The spectrum chart's curves as uPlot holds them (viewer.chart): x, and per curve its values, colour and
#: whether uPlot built its path (drew it).
_CHART = """() => { const u = window.viewer.chart;
    return { x: [...u.data[0]], curves: u.series.slice(1).map((s, i) => ({ y: [...u.data[i + 1]],
             stroke: s.stroke(u, i + 1), drawn: Boolean(s.show && s._paths) })) }; }"""


def test_one_flight_where_the_mosaic_is_and_pinned_spectra(server, browser, archive_of_flights):
    from scipy.ndimage import binary_dilation, binary_erosion

    import archive

    path, ids = archive_of_flights
    cid = ids[0]
    page = Page(browser, server, f"flights={cid}&open={cid}")
    page.page.wait_for_function(f"() => window.viewer.open === '{cid}'")
    page.page.evaluate("() => window.viewer.map.setZoom(window.viewer.map.getZoom() + 1)")
    page.settled()
    assert page.page.evaluate("window.viewer.tileErrors") == 0
    page.clean()
    drawn = page.drawn()
    geo = page.geometry()
    coverage = archive.mosaic([cid], archive=path, gsd=0.03, wavelengths=[650])
    expected = _expected_coverage(coverage, drawn.shape, geo)
    edge = binary_dilation(expected, iterations=2) & ~binary_erosion(expected, iterations=2)
    assert expected.sum() > 20_000, "the flight should fill a good part of the map"
    wrong = (drawn != expected) & ~edge
    assert wrong.sum() == 0, f"{wrong.sum()} pixels drawn where the mosaic has no coverage or the reverse"

    # two clicks: two pinned spectra (own colours), each the pixel archive render writes
    inner = binary_erosion(expected, iterations=12)
    rows, cols = np.nonzero(inner)
    box = page.page.locator("#map").bounding_box()
    points = []
    for k in (len(rows) // 3, 2 * len(rows) // 3):
        page.page.mouse.click(box["x"] + cols[k] + 0.5, box["y"] + rows[k] + 0.5)
        page.page.wait_for_function(f"() => window.viewer.pins.length === {len(points) + 1}", timeout=30_000)
        points.append(page.page.evaluate("window.viewer.lastPoint"))
    spectra = [_point_check(p, path) for p in points]
    assert all(p["covered"] and p["id"] == cid and p["mode"] == "radiance" for p in points)
    # the chart (uPlot, viewer.chart): one curve per pin in the pin's own colour, over the point's
    # wavelengths, its values those of the pixel (drawn: uPlot built the curve's path)
    plot = page.page.evaluate(_CHART)
    assert len(plot["curves"]) == 2 and all(c["drawn"] for c in plot["curves"])
    assert [c["stroke"] for c in plot["curves"]] == page.page.evaluate("window.viewer.pins.map((p) => p.colour)")
    assert len({c["stroke"] for c in plot["curves"]}) == 2
    assert plot["x"] == points[0]["wavelength"] == points[1]["wavelength"]
    for curve, spectrum in zip(plot["curves"], spectra):
        assert np.array_equal(np.array(curve["y"], np.float32).view(np.uint32), spectrum.view(np.uint32))
    assert page.page.locator("#spectrum .band-mark").count() == 3          # R, G, B wavelengths marked
    assert "calibration radiance units" in page.page.locator("#spectrum").inner_html()
    # the y-axis label (mode and units) lies inside the chart, not clipped by its edges
    label = page.page.locator("#spectrum .y-label").bounding_box()
    chart = page.page.locator("#spectrum").bounding_box()
    assert chart["y"] <= label["y"] and label["y"] + label["height"] <= chart["y"] + chart["height"], (label, chart)
    assert chart["x"] <= label["x"], (label, chart)
    info = page.page.locator("#pixel-info").inner_text()
    assert f"{points[1]['cube'] + 1} of 2 ({points[1]['base']})" in info and " UTC" in info
    assert "GPS" not in info and str(points[1]["time"])[:8] not in info
    csv = page.page.evaluate("window.viewer.csv").strip().splitlines()
    assert csv[0].startswith("wavelength_nm,radiance ") and len(csv) == len(spectra[0]) + 1
    for j, spectrum in enumerate(spectra):
        assert np.array_equal(np.array([float(line.split(",")[1 + j]) for line in csv[1:]], np.float32), spectrum)
    # the chart as a PNG: twice the chart's size, both curves' colours in it
    page.page.click("#png")
    page.page.wait_for_function("() => Boolean(window.viewer.png)")
    png = page.page.evaluate("""async () => { const b = await (await fetch(window.viewer.png)).arrayBuffer();
        return Array.from(new Uint8Array(b)); }""")
    image = np.asarray(Image.open(io.BytesIO(bytes(png))).convert("RGB")).astype(int)
    size = page.page.evaluate("[window.viewer.chart.width, window.viewer.chart.height]")
    assert image.shape[:2] == (2 * size[1], 2 * size[0])
    for c in plot["curves"]:
        rgb = np.array([int(c["stroke"][k:k + 2], 16) for k in (1, 3, 5)])
        assert (np.abs(image - rgb).sum(axis=-1) < 40).sum() > 50, c["stroke"]
    page.page.locator("#pins button").first.click()       # remove the first
    plot = page.page.evaluate(_CHART)
    assert len(plot["curves"]) == 1
    assert np.array_equal(np.array(plot["curves"][0]["y"], np.float32).view(np.uint32), spectra[1].view(np.uint32))
    page.close()


def opened(browser, server, cid: str) -> Page:
    """A page showing flight ``cid`` alone, open, its tiles settled and its request logs cleared."""
    page = Page(browser, server, f"flights={cid}&open={cid}")
    page.page.wait_for_function(f"() => window.viewer.open === '{cid}'")
    page.settled()
    page.clean()
    return page


def test_never_blank_during_band_and_ground_changes(server, browser, archive_of_flights):
    from scipy.ndimage import binary_erosion

    _, ids = archive_of_flights
    cid = ids[0]
    page = opened(browser, server, cid)
    interior = binary_erosion(page.drawn(), iterations=8)
    assert interior.sum() > 5_000

    def empty_fraction(shots):
        return max(float((~page.drawn(s) & interior).mean() / interior.mean()) for s in shots)

    before = len(page.values_requests)
    shots = _shots_while(page, lambda: page.page.select_option("#band-r", index=5))
    assert len(page.values_requests) > before, "a new band needs its values"
    assert len(shots) >= 3
    assert empty_fraction(shots) < 0.01, "the footprint went blank during a band change"
    assert (shots[-1] != shots[0]).any(axis=-1).mean() > 0.02

    slider = page.page.locator("#ground")
    slider.focus()

    def lower():
        for _ in range(4):
            page.page.keyboard.press("ArrowLeft")
    shots = _shots_while(page, lower)
    assert empty_fraction(shots) < 0.01, "the footprint went blank during a ground change"
    ground = float(slider.input_value())
    assert f"ground={ground:g}" in page.page.evaluate("location.hash") or page.page.wait_for_function(
        f"() => location.hash.includes('ground={ground:g}')")
    assert (shots[-1] != shots[0]).any(axis=-1).mean() > 0.01, "the ground change did not move the picture"
    page.close()


def test_superseded_requests_are_aborted_and_the_latest_view_goes_first(server, browser, archive_of_flights):
    """Two band changes in a row: every band-value request carries its view's generation
    (X-Generation, which orders the server's queue), the second change's are newer than the
    first's, the first change's requests are aborted, and the page settles on the second band."""
    _, ids = archive_of_flights
    page = opened(browser, server, ids[1])
    asked: list[tuple[str, str | None]] = []
    dropped: list[str] = []
    page.page.on("request", lambda r: asked.append((r.url, r.headers.get("x-generation")))
                 if "/values/" in r.url else None)
    page.page.on("requestfailed", lambda r: dropped.append(r.url) if "/values/" in r.url else None)
    first, second = page.page.evaluate("""() => {
        window.viewer.settled = false;
        const s = document.getElementById('band-r'), n = s.options.length, picked = [];
        for (const k of [n - 2, n - 1]) {   // not among the true colour bands shown at open (400-1000 nm)
            s.selectedIndex = k; picked.push(k); s.dispatchEvent(new Event('change'));
        }
        return picked; }""")
    page.settled()

    def band_of(url: str) -> int:
        return int(re.search(r"[?&]bands=(\d+)", url).group(1))
    gens = {b: [int(g) for u, g in asked if band_of(u) == b] for b in (first, second)}
    assert len(gens[second]) >= 1 and all(g is not None for _, g in asked)
    assert not gens[first] or max(gens[first]) < min(gens[second])
    # the first change's requests were abandoned (in the page, before or after reaching the server)
    assert all(u in dropped for u, _ in asked if band_of(u) == first)
    assert not [u for u in dropped if band_of(u) == second]
    assert f",[{second}," in page.page.evaluate("window.viewer.specId")   # the picture settled on the second band
    page.close()


def test_stretch_needs_no_request_and_hash_drives_the_view(server, browser, archive_of_flights):
    _, ids = archive_of_flights
    cid = ids[0]
    page = opened(browser, server, cid)
    before_shot, before = page.shot(), len(page.values_requests)
    page.page.select_option("#stretch", "view")
    page.settled()
    page.page.locator("#per-channel").uncheck()
    page.settled()
    page.page.select_option("#stretch", "manual")
    page.page.fill("#stretch-low", "0")
    page.page.fill("#stretch-high", "20000")
    page.page.locator("#stretch-high").dispatch_event("change")
    page.settled()
    # R/G/B reassigned among the loaded bands: no request either
    r, b = page.page.input_value("#band-r"), page.page.input_value("#band-b")
    page.page.select_option("#band-r", b)
    page.page.select_option("#band-b", r)
    page.settled()
    after_shot = page.shot()
    assert len(page.values_requests) == before, page.values_requests[before:]
    assert (after_shot != before_shot).any(axis=-1).mean() > 0.02
    page.page.wait_for_function("() => location.hash.includes('stretch=0,20000')")

    # the hash is the state: edit it, the view follows without a reload
    page.page.evaluate("() => { window.marker = 1; location.hash = location.hash.replace(/stretch=[^&]*/, "
                       "'stretch=p2,p98').replace(/bands=[^&]*/, 'bands=760'); }")
    page.page.wait_for_function("() => document.getElementById('display').value === 'grey'")
    page.settled()
    assert page.page.evaluate("window.marker") == 1
    assert page.page.input_value("#stretch") == "flight" and float(page.page.input_value("#band-grey")) == 760
    page.close()


def test_several_flights_on_one_map(server, browser, archive_of_flights):
    from scipy.ndimage import binary_erosion

    _, ids = archive_of_flights
    features = {f["id"]: f for f in __import__("json").loads(
        __import__("urllib.request").request.urlopen(server + "api/collections").read())["features"]}
    page = Page(browser, server)          # every flight, at the zoom that fits them all
    page.clean()
    shot = page.shot()
    drawn = page.drawn(shot)
    geo = page.geometry()
    for cid in ids:
        inside = binary_erosion(_footprint_mask(features[cid], drawn.shape, geo), iterations=2)
        assert inside.sum() > 50, cid
        assert drawn[inside].mean() > 0.8, f"{cid} shows no imagery at the zoom fitting the archive"
    # flights drawn as ingested are asked several tiles per request (/api/values/batch, issue 36)
    batched = [u for u in page.values_requests if "/values/batch?" in u]
    assert batched and all(u.count("%3B") + 1 <= 24 for u in batched)
    assert sum(u.count("%3B") + 1 for u in batched) >= FLIGHTS, "each flight's tiles in a batch"
    # flights 0 and 1 overlap: both drawn at once, and their order decides the overlap
    page.page.evaluate(f"() => {{ location.hash = 'flights={ids[1]},{ids[0]}'; }}")
    page.page.wait_for_function(f"() => window.viewer.hidden.size === {FLIGHTS - 2}")
    page.settled()
    page.page.evaluate(f"() => window.viewer.map.fitBounds(L.geoJSON(window.viewer.features.filter("
                       f"f => ['{ids[0]}', '{ids[1]}'].includes(f.id))).getBounds())")
    page.settled()
    shot = page.shot()
    drawn = page.drawn(shot)
    geo = page.geometry()
    a, b = (_footprint_mask(features[c], drawn.shape, geo) for c in ids[:2])
    assert (a & ~b).sum() > 500 and (b & ~a).sum() > 500 and (a & b).sum() > 500, "the flights should overlap"
    a_only, b_only = (binary_erosion(m, iterations=6) for m in (a & ~b, b & ~a))
    assert drawn[a_only].mean() > 0.8 and drawn[b_only].mean() > 0.8, (drawn[a_only].mean(), drawn[b_only].mean())
    before = len(page.values_requests)
    page.page.locator("#flights li", has_text=ids[1]).locator("button.move[title='draw over']").click()
    page.settled()
    swapped = page.shot()
    assert len(page.values_requests) == before
    changed = (swapped != shot).any(axis=-1)
    assert changed[a & b].mean() > 0.3 and changed[a ^ b].mean() < 0.01
    page.close()


def test_invalid_cube_range_shows_the_server_message(server, browser, archive_of_flights, tmp_path):
    _, ids = archive_of_flights
    cid = ids[2]
    page = opened(browser, server, cid)
    before = page.shot()
    # both values at once: fill() of the second box blurs the first, whose change event would first
    # ask for the valid range 2-2 (its picture may arrive before the refusal: not what is tested)
    page.page.evaluate("() => { document.getElementById('cube-first').value = '2'; "
                       "document.getElementById('cube-last').value = '1'; }")
    page.page.locator("#cube-last").dispatch_event("change")
    page.page.wait_for_function("() => document.getElementById('err-cubes').textContent.length > 0")
    message = page.page.inner_text("#err-cubes")
    assert "cubes: first cube 2 comes after last cube 1" in message, message   # 1-based, as the files
    assert (page.shot() == before).all(), "the picture should stay when a change is refused"
    page.page.click("#reset")
    page.settled()
    # the message goes once the reset view has settled (its requests may still be arriving)
    page.page.wait_for_function("() => document.getElementById('err-cubes').textContent === ''", timeout=30_000)
    assert page.page.inner_text("#err-cubes") == ""

    # docs/viewer.png: several flights, two pinned spectra
    page.page.evaluate("() => { location.hash = ''; }")
    page.page.evaluate(f"() => {{ location.hash = 'open={cid}'; }}")
    page.page.wait_for_function("() => window.viewer.hidden.size === 0")
    page.page.evaluate("""() => {
        for (const s of ['.leaflet-control-container', '.leaflet-footprints-pane', '.leaflet-tooltip-pane'])
            document.querySelector(s).style.display = '';
        document.getElementById('map').style.background = '';
        const m = window.viewer.map; m.fitBounds(window.viewer.footprints.getBounds()); }""")
    page.settled()
    box = page.page.locator("#map").bounding_box()
    feature = page.page.evaluate(f"window.viewer.byId.get('{cid}')")
    lon = [c[0] for c in feature["geometry"]["coordinates"][0]]
    lat = [c[1] for c in feature["geometry"]["coordinates"][0]]
    for f in (0.4, 0.6):
        xy = page.page.evaluate(f"window.viewer.map.latLngToContainerPoint([{np.mean(lat)}, "
                                f"{min(lon) + f * (max(lon) - min(lon))}])")
        page.page.mouse.click(box["x"] + xy["x"], box["y"] + xy["y"])
        page.page.wait_for_timeout(300)
    page.page.wait_for_function("() => window.viewer.pins.length >= 2", timeout=30_000)
    page.settled()
    page.page.evaluate("() => document.getElementById('pixel').scrollIntoView({block: 'end'})")
    # the README's screenshot is rewritten only when asked (a test run leaves the checkout as it was)
    shot = ROOT / "docs" / "viewer.png" if os.environ.get("ARCHIVE_SCREENSHOT") else tmp_path / "viewer.png"
    shot.parent.mkdir(exist_ok=True)
    page.page.screenshot(path=str(shot))
    assert shot.stat().st_size > 10_000
    page.close()


def _tab_to(page, selector: str, presses: int = 80) -> None:
    """Press Tab until the focused element matches ``selector`` (reachable by keyboard alone)."""
    for _ in range(presses):
        page.keyboard.press("Tab")
        if page.evaluate(f"() => document.activeElement && document.activeElement.matches({selector!r})"):
            return
    pytest.fail(f"{selector} is not reachable with Tab")


def test_keyboard_flight_list_wheel_notches_and_narrow_layout(server, browser, archive_of_flights):
    _, ids = archive_of_flights
    page = Page(browser, server)
    p = page.page
    first = p.evaluate("window.viewer.order[0]")
    # keyboard only: Tab to the first flight's checkbox, Space hides and shows it; its name, Enter opens
    # it; its "draw over" button, Enter moves it one place up the drawing order (focus stays on it)
    _tab_to(p, f'#flights li[data-id="{first}"] input[type=checkbox]')
    p.keyboard.press("Space")
    p.wait_for_function(f"() => window.viewer.hidden.has('{first}')")
    p.keyboard.press("Space")
    p.wait_for_function(f"() => !window.viewer.hidden.has('{first}')")
    p.keyboard.press("Tab")
    assert p.evaluate("document.activeElement.classList.contains('flight-open')")
    p.keyboard.press("Enter")
    p.wait_for_function(f"() => window.viewer.open === '{first}'")
    page.settled()
    _tab_to(p, f'#flights li[data-id="{first}"] button.move[title="draw over"]')
    p.keyboard.press("Enter")
    p.wait_for_function(f"() => window.viewer.order[1] === '{first}'")
    assert p.evaluate(f"""() => document.activeElement.closest('li').dataset.id === '{first}'""")
    page.settled()

    # one zoom level per wheel notch (100 px), and one for a burst of small trackpad deltas
    box = p.locator("#map").bounding_box()
    p.mouse.move(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
    z0 = p.evaluate("window.viewer.map.getZoom()")
    p.mouse.wheel(0, -100)
    p.wait_for_timeout(400)
    assert p.evaluate("window.viewer.map.getZoom()") == z0 + 1
    p.mouse.wheel(0, 100)
    p.wait_for_timeout(400)
    assert p.evaluate("window.viewer.map.getZoom()") == z0
    for _ in range(5):
        p.mouse.wheel(0, -20)
    p.wait_for_timeout(400)
    assert p.evaluate("window.viewer.map.getZoom()") == z0 + 1
    page.close()

    # a phone's width: the panel starts collapsed and the map fills the screen; the toggle (by
    # keyboard) shows the panel below a map that keeps more than half the height
    narrow = Page(browser, server, f"flights={ids[0]}&open={ids[0]}", width=390, height=800)
    q = narrow.page
    m = q.locator("#map").bounding_box()
    assert q.evaluate("document.body.classList.contains('collapsed')")
    assert m["width"] >= 389 and m["height"] >= 790, m
    q.focus("#panel-toggle")
    q.keyboard.press("Enter")
    q.wait_for_function("() => !document.body.classList.contains('collapsed')")
    assert q.get_attribute("#panel-toggle", "aria-expanded") == "true"
    m = q.locator("#map").bounding_box()
    panel = q.locator("#panel").bounding_box()
    assert m["height"] >= 0.55 * 800 - 1 and m["width"] >= 389, m
    assert panel["y"] >= m["y"] + m["height"] - 1 and panel["height"] <= 0.45 * 800 + 1, panel
    assert q.evaluate("document.documentElement.scrollWidth") <= 390   # nothing wider than the screen
    narrow.settled()
    narrow.close()


def _boxes_overlap(a: dict, b: dict) -> bool:
    return a["x"] < b["x"] + b["width"] and b["x"] < a["x"] + a["width"] and \
        a["y"] < b["y"] + b["height"] and b["y"] < a["y"] + a["height"]


def test_panel_toggle_is_tapped_not_zoomed_on_a_phone(server, browser, archive_of_flights):
    """A finger on ☰ at 390 x 844 opens the panel: nothing (Leaflet's zoom buttons) lies over it,
    at phone size collapsed and open, and at desktop size (issue 36)."""
    p = browser.new_page(viewport={"width": 390, "height": 844}, has_touch=True, is_mobile=True,
                         device_scale_factor=1)
    errors: list[str] = []
    p.on("pageerror", lambda exc: errors.append(str(exc)))
    p.goto(server)
    p.wait_for_function("() => window.viewer.booted && window.viewer.settled")
    assert p.evaluate("document.body.classList.contains('collapsed')")
    on_top = """() => { const b = document.getElementById('panel-toggle').getBoundingClientRect();
        const e = document.elementFromPoint(b.x + b.width / 2, b.y + b.height / 2);
        return e && e.closest('#panel-toggle') !== null; }"""
    assert p.evaluate(on_top)
    zoom = p.evaluate("window.viewer.map.getZoom()")
    box = p.locator("#panel-toggle").bounding_box()
    p.touchscreen.tap(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
    p.wait_for_function("() => !document.body.classList.contains('collapsed')", timeout=10_000)
    assert p.get_attribute("#panel-toggle", "aria-expanded") == "true"
    assert p.evaluate("window.viewer.map.getZoom()") == zoom   # the tap did not zoom the map
    assert p.locator("#panel").is_visible() and p.evaluate(on_top)
    for control in p.locator(".leaflet-control-zoom a").all():
        assert not _boxes_overlap(control.bounding_box(), box)
    p.touchscreen.tap(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
    p.wait_for_function("() => document.body.classList.contains('collapsed')", timeout=10_000)
    assert not errors, errors
    p.close()
    wide = Page(browser, server, width=1400, height=900)
    assert wide.page.evaluate(on_top)
    wide.page.click("#panel-toggle")
    wide.page.wait_for_function("() => document.body.classList.contains('collapsed')")
    assert wide.page.evaluate(on_top)
    wide.close()


def test_refused_values_stay_out_of_the_hash_and_labels_do_not_collide(server, browser, archive_of_flights):
    """A shared link never carries a refused value; footprint labels never overlap, fewer when zoomed
    out; the flight list uses the panel's height; the spectrum chart is in sight with its axis label
    whole at 1400 x 900 (issue 36)."""
    _, ids = archive_of_flights
    cid = ids[1]
    page = Page(browser, server, f"open={cid}", width=1400, height=900)
    p = page.page
    p.wait_for_function(f"() => window.viewer.open === '{cid}'")
    page.settled()
    p.evaluate(f"() => {{ location.hash = 'open={cid}&stretch=5000,100&cubes=3-9'; }}")   # a link with errors
    p.wait_for_function("() => document.getElementById('err-stretch').textContent.length > 0")
    p.wait_for_function("() => document.getElementById('err-cubes').textContent.length > 0", timeout=30_000)
    p.wait_for_function(f"() => (window.viewer.hash || '').includes('open={cid}')")
    p.wait_for_timeout(300)
    shared = p.evaluate("location.hash")
    assert "stretch=5000" not in shared and "cubes=" not in shared and "stretch=p2,p98" in shared, shared
    # a valid manual stretch is written
    p.fill("#stretch-low", "10")
    p.fill("#stretch-high", "900")
    p.locator("#stretch-high").dispatch_event("change")
    p.wait_for_function("() => location.hash.includes('stretch=10,900')")

    page.close()

    # labels: the six overlapping flights fitted (the page's first view), then zoomed out
    page = Page(browser, server, width=1400, height=900)
    p = page.page
    rects = [e.bounding_box() for e in p.locator(".footprint-label").all()]
    assert 1 <= len(rects) <= len(ids)
    assert not any(_boxes_overlap(a, b) for i, a in enumerate(rects) for b in rects[i + 1:]), rects
    p.evaluate("() => window.viewer.map.setZoom(window.viewer.map.getZoom() - 3)")
    page.settled()
    assert len(p.locator(".footprint-label").all()) < len(ids)
    # the list: more than the old 220 px when the panel has the room
    assert p.evaluate("parseFloat(getComputedStyle(document.getElementById('flights')).maxHeight)") > 220

    page.close()

    # a pinned spectrum: the chart inside the window, the y-axis label inside the chart
    page = Page(browser, server, f"flights={cid}&open={cid}", width=1400, height=900)
    p = page.page
    p.wait_for_function(f"() => window.viewer.open === '{cid}'")
    page.settled()
    feature = p.evaluate(f"window.viewer.byId.get('{cid}')")
    ring = np.asarray(feature["geometry"]["coordinates"][0])
    p.evaluate(f"() => window.viewer.map.setView([{ring[:, 1].mean()}, {ring[:, 0].mean()}], "
               "window.viewer.map.getZoom())")
    page.settled()
    box = p.locator("#map").bounding_box()
    p.mouse.click(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
    p.wait_for_function("() => window.viewer.pins.length === 1", timeout=30_000)
    p.wait_for_timeout(300)
    chart = p.locator("#spectrum").bounding_box()
    assert chart["y"] >= 0 and chart["y"] + chart["height"] <= 900, chart
    label = p.evaluate("""() => { const r = document.querySelector('#spectrum .y-label').getBoundingClientRect();
        return {x: r.x, y: r.y, width: r.width, height: r.height}; }""")
    assert label["x"] >= chart["x"] and label["y"] >= chart["y"] - 0.5
    assert label["y"] + label["height"] <= chart["y"] + chart["height"] + 0.5
    page.close()


def test_page_scripts_are_modules_sharing_no_globals_and_rules_come_from_the_api(server, browser, archive_of_flights):
    """The page's script is ES modules (issue 31): no page script but the vendored Leaflet is a
    classic script (whose top-level names would be globals), and the page adds to ``window`` only
    Leaflet's ``L`` (and its UMD ``leaflet``) and ``viewer`` (the state object the tests read). The
    overlap list is the server's (``/api/collections``), and choosing the rule with a key plane
    changes the picture only where two flights overlap (the one seen closer to nadir wins there)."""
    import json
    import urllib.request

    from scipy.ndimage import binary_erosion

    _, ids = archive_of_flights
    blank = browser.new_page()
    blank.goto(server + "api/status")    # a page of the same origin without scripts: what a window has
    before = set(blank.evaluate("Object.keys(window)"))
    blank.close()
    page = Page(browser, server, f"flights={ids[1]},{ids[0]}")
    p = page.page
    # Leaflet also keeps its listeners of window in window._leaflet_events
    added = set(p.evaluate("Object.keys(window)")) - before - {"_leaflet_events"}
    assert "viewer" in added and added <= {"L", "leaflet", "viewer"}, sorted(added)
    scripts = p.evaluate("[...document.scripts].map((s) => [s.getAttribute('src'), s.type])")
    classic = [src for src, kind in scripts if kind != "module"]
    assert classic == ["/static/vendor/leaflet/leaflet.js"], scripts
    assert len(scripts) >= 2
    # the overlap rules: the server's list, its first the default
    fc = json.loads(urllib.request.urlopen(server + "api/collections").read())
    rules = fc["overlaps"]
    options = p.evaluate("[...document.getElementById('overlap').options].map((o) => [o.value, o.textContent])")
    assert options == [[r["name"], r["label"]] for r in rules]
    assert p.evaluate("document.getElementById('overlap').value") == rules[0]["name"]
    keyed = next(r for r in rules if r["key"] is not None)
    features = {f["id"]: f for f in fc["features"]}
    p.evaluate(f"() => window.viewer.map.fitBounds(L.geoJSON(window.viewer.features.filter("
               f"f => ['{ids[0]}', '{ids[1]}'].includes(f.id))).getBounds())")
    page.settled()
    page.clean()
    shot = page.shot()
    geo = page.geometry()
    a, b = (_footprint_mask(features[c], shot.shape[:2], geo) for c in ids[:2])
    p.evaluate("() => { window.viewer.settled = false; }")
    p.select_option("#overlap", keyed["name"])
    page.settled()
    assert f"overlap={keyed['name']}" in p.evaluate("location.hash") or p.wait_for_function(
        f"() => location.hash.includes('overlap={keyed['name']}')")
    assert any(f"overlap={keyed['name']}" in u for u in page.values_requests)
    changed = (page.shot() != shot).any(axis=-1)
    both, one = binary_erosion(a & b, iterations=3), binary_erosion(a ^ b, iterations=3)
    assert both.sum() > 500 and one.sum() > 500
    assert changed[both].mean() > 0.1 and changed[one].mean() < 0.01, (changed[both].mean(), changed[one].mean())
    page.close()


def test_the_opening_view_is_at_a_zoom_the_previews_serve(browser, archive_of_flights):
    """Issue 49 item 7: a page opened with no hash fits the flights, but not finer than the finest zoom their
    ingest previews serve when that is at most 2 zooms out; its first full screen then comes from the
    previews (no tile drawn from the DN on a new server). 3 zooms out, or with a flight open: the fit."""
    import json
    import urllib.request

    from archive.drawing.preview_layout import read_previews
    from archive.catalog.root import open_root

    path, ids = archive_of_flights
    root = open_root(path)
    finest = min(read_previews(root.store(cid)).finest for cid in ids)
    command = [sys.executable, "-m", "archive", "view", "--archive", str(path), "--port", "0"]
    with archive_view(command, cwd=ROOT) as (url, _):
        features = json.loads(urllib.request.urlopen(url + "api/collections").read())["features"]
        assert sorted(f["properties"]["previews_zoom"] for f in features) == sorted(
            read_previews(root.store(cid)).finest for cid in ids)
        def fitted(page):
            return page.page.evaluate("""() => { const m = window.viewer.map;
                return [m.getZoom(), m.getBoundsZoom(window.viewer.footprints.getBounds(), false, L.point(40, 40))]; }""")

        page = Page(browser, url, width=1280, height=900)   # the fit: 3 zooms finer than the previews
        zoom, fit = fitted(page)
        assert fit == finest + 3 and zoom == fit, (zoom, fit, finest)
        page.close()
        before = json.loads(urllib.request.urlopen(url + "api/status").read())
        page = Page(browser, url, width=640, height=450)    # 2 zooms finer: the previews' zoom
        zoom, fit = fitted(page)
        assert fit == finest + 2 and zoom == finest, (zoom, fit, finest)
        page.clean()
        assert page.drawn().sum() > 1_000
        status = json.loads(urllib.request.urlopen(url + "api/status").read())
        assert status["from_previews"] > before["from_previews"], status
        assert status["render"]["done"] == before["render"]["done"], "a tile of the first screen was drawn from the DN"
        page.close()


def test_an_index_display_shows_the_index_of_the_mosaic_on_its_ramp(server, browser, archive_of_flights):
    """Display 'index' (issue 48 item 4): the NDVI button picks a = the band nearest 830 nm and b = the
    band nearest 654 nm (as archive stats maps NDVI), each pixel is (a - b) / (a + b) of the radiance
    archive.mosaic gives there, on the page's colour ramp, with its legend shown and the stretch hidden;
    the hash keeps it (two bands) and restores it."""
    from scipy.ndimage import binary_erosion

    import archive

    path, ids = archive_of_flights
    cid = ids[0]
    page = opened(browser, server, cid)
    page.page.evaluate("() => window.viewer.map.setZoom(window.viewer.map.getZoom() + 1)")   # from the DN
    page.settled()
    rgb = page.shot()
    page.page.click("#ndvi")
    page.page.wait_for_function("() => document.getElementById('display').value === 'index'")
    page.settled()
    assert page.page.locator("#index-legend").is_visible() and not page.page.locator("#stretch").is_visible()
    a_nm, b_nm = (float(page.page.input_value(s)) for s in ("#index-a", "#index-b"))
    wl = np.array(page.page.evaluate(f"() => window.viewer.byId.get('{cid}').properties.wavelength"))
    assert a_nm == wl[np.argmin(abs(wl - 830))] and b_nm == wl[np.argmin(abs(wl - 654))] and a_nm != b_nm
    page.page.wait_for_function(f"() => location.hash.includes('bands={a_nm:g},{b_nm:g}')")
    stops = page.page.evaluate("() => import('/static/tiles.js').then((m) => m.RAMP_STOPS)")
    page.clean()
    shot = page.shot()
    assert (shot != rgb).any(axis=-1).mean() > 0.05   # the picture changed

    # the truth: the mosaic of the two bands (radiance, the page's mode), its pixel under each screen pixel
    ds = archive.mosaic([cid], archive=path, gsd=0.03, wavelengths=[a_nm, b_nm])
    values = ds["radiance"].values
    row, col, inside = _mosaic_pixels(ds, shot.shape[:2], page.geometry())
    index = np.full(shot.shape[:2], np.nan)
    av, bv = values[0][row[inside], col[inside]], values[1][row[inside], col[inside]]
    index[inside] = (av - bv) / (av + bv)
    inner = binary_erosion(np.isfinite(index), iterations=6)
    assert inner.sum() > 10_000, "the flight should fill a good part of the map"
    xs = np.array([s[0] for s in stops])
    expected = np.stack([np.interp(np.clip(index[inner], -1, 1), xs, [s[1][c] for s in stops]) for c in range(3)], -1)
    error = np.abs(shot[inner].astype(float) - expected).max(axis=-1)
    print(f"index display vs the mosaic: median colour error {np.median(error):.1f}, {(error <= 12).mean():.1%} within 12, "
          f"{inner.sum()} pixels, index {np.nanmin(index[inner]):.3f}..{np.nanmax(index[inner]):.3f}")
    assert np.median(error) <= 3 and (error <= 12).mean() >= 0.9, (np.median(error), (error <= 12).mean())
    assert np.ptp(index[inner]) > 0.05, "a scene of one index value would not test the ramp"

    # the hash restores it after a reload
    page.page.reload()
    page.settled()
    assert page.page.input_value("#display") == "index"
    assert (float(page.page.input_value("#index-a")), float(page.page.input_value("#index-b"))) == (a_nm, b_nm)
    page.close()
