"""The viewer's georectification source (issue 46 point 3): a collection ingested with a post-processed
trajectory is drawn from it by default and from its ``.lcf`` on request, the boresight moves the picture,
the point query follows; checked against the simulator's truth (the flight's ``.lcf`` carries an
undeclared real-time bias BIAS, its trajectory file the true INS path)."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
from helpers import FOV

BIAS = (1.5, -1.1, 0.8)


@pytest.fixture(scope="module")
def tracked(tmp_path_factory):
    """(archive, collection id, truth): a 2-cube flight whose .lcf is BIAS off the truth, ingested with its
    SBET (the collection's default source then)."""
    from archive.ingest.command import ingest
    from archive.simulator.command import simulate_flight
    from archive.simulator.postprocessed import write_trajectory

    root = tmp_path_factory.mktemp("viewnav")
    truth = simulate_flight(root / "flight", cubes=2, bands=4, samples=64, lines=120, cubes_per_pass=2, seed=4,
                            gnss_bias_m=BIAS)
    sbet = write_trajectory(truth, root / "flight.out")
    (result,) = ingest([root / "flight"], root / "archive", FOV, progress=False, navigation=sbet)
    return root / "archive", result.cid, truth


@pytest.fixture(scope="module")
def client(tracked):
    from archive.view.registry import FlightRegistry
    from archive.view.server import create_app

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        from starlette.testclient import TestClient
    with TestClient(create_app(FlightRegistry(tracked[0]))) as c:
        yield c


def _outline_utm(client, cid, truth, **params):
    """The viewer's outline (the cubes' ground meshes as drawn) as one shapely polygon in the truth's UTM zone."""
    from shapely.geometry import Polygon
    from shapely.ops import unary_union

    answer = client.get(f"/api/collections/{cid}/outline", params={"ground_height": truth.ground_height, **params})
    assert answer.status_code == 200, answer.text
    parts = []
    for (ring,) in answer.json()["coordinates"]:
        lon, lat = np.array(ring).T
        e, n = truth.to_utm(lon, lat, "EPSG:4326")
        parts.append(Polygon(np.column_stack([e, n])).buffer(0))
    return unary_union(parts)


def _truth_polygon(truth):
    from shapely.geometry import Polygon
    from shapely.ops import unary_union

    return unary_union([Polygon(p).buffer(0) for p in truth.footprint()])


def test_the_sources_listed_and_the_track_drawn_where_the_truth_is(client, tracked):
    _, cid, truth = tracked
    info = client.get(f"/api/collections/{cid}").json()
    assert info["navigation"] == {"sources": ["lcf", "flight"], "default": "flight"}
    assert info["boresight_deg"] == [0.0, 0.0, 0.0]
    true = _truth_polygon(truth)
    ppk = _outline_utm(client, cid, truth)
    lcf = _outline_utm(client, cid, truth, navigation="lcf")
    assert _outline_utm(client, cid, truth, navigation="flight").equals(ppk)
    # the trajectory: where the truth is (centroid within 5 cm, the footprints overlapping all but ~1 %)
    shift = np.subtract(ppk.centroid.coords[0], true.centroid.coords[0])
    assert np.hypot(*shift) < 0.05, shift
    assert ppk.symmetric_difference(true).area / true.area < 0.01
    # the .lcf: moved by its real-time bias (east, north)
    shift = np.subtract(lcf.centroid.coords[0], true.centroid.coords[0])
    np.testing.assert_allclose(shift, BIAS[:2], atol=0.1)


def test_a_boresight_roll_moves_the_picture_across_track(client, tracked):
    _, cid, truth = tracked
    base = _outline_utm(client, cid, truth)
    rolled = _outline_utm(client, cid, truth, boresight="1,0,0")
    shift = np.subtract(rolled.centroid.coords[0], base.centroid.coords[0])
    height = float(np.mean(np.concatenate([c.position_utm[:, 2] for c in truth.cubes]))) - truth.ground_height
    along = np.concatenate([c.position_utm[:, :2] for c in truth.cubes])
    track = along[-1] - along[0]
    # the swath's edges at +-FOV/2 turn by 1 deg: its centre moves by the mean of their moves on the ground
    half = math.radians(FOV / 2)
    expected = height * (math.tan(half + math.radians(1.0)) - math.tan(half - math.radians(1.0))) / 2
    assert abs(np.hypot(*shift) - expected) < 0.05 * expected, (shift, expected)
    cosine = abs(np.dot(shift, track)) / (np.hypot(*shift) * np.hypot(*track))
    assert cosine < math.sin(math.radians(3)), "a roll moves the footprint across the track"
    # + roll, right wing down: the camera's down axis tilts to the left of the track
    assert track[0] * shift[1] - track[1] * shift[0] > 0, "a + roll looks to the left of the track"


def test_values_and_the_point_query_follow_the_source(client, tracked):
    from pyproj import Transformer

    from archive.grid import HALF_WORLD, zoom_gsd

    _, cid, truth = tracked
    true = _truth_polygon(truth)
    e, n = true.centroid.coords[0]
    lon, lat = truth.from_utm(np.array([e]), np.array([n]), "EPSG:4326")
    lon, lat = float(lon[0]), float(lat[0])
    points = {}
    for nav in ("flight", "lcf"):
        p = client.get(f"/api/collections/{cid}/point", params={"lon": lon, "lat": lat, "gsd": 0.05,
                                                                "navigation": nav}).json()
        assert p["covered"] and p["navigation"] == nav, p
        points[nav] = p
    default = client.get(f"/api/collections/{cid}/point", params={"lon": lon, "lat": lat, "gsd": 0.05}).json()
    assert default["navigation"] == "flight" and default["values"] == points["flight"]["values"]
    assert (points["lcf"]["line"], points["lcf"]["sample"]) != (points["flight"]["line"], points["flight"]["sample"])
    # the tile holding the point: other values from the .lcf
    z = 19
    x, y = Transformer.from_crs(4326, 3857, always_xy=True).transform(lon, lat)
    side = 256 * zoom_gsd(z)
    tx, ty = int((x + HALF_WORLD) // side), int((HALF_WORLD - y) // side)
    bodies = {nav: client.get(f"/api/collections/{cid}/values/{z}/{tx}/{ty}", params={"bands": "1", "navigation": nav})
              for nav in ("flight", "lcf")}
    assert all(b.status_code == 200 for b in bodies.values())
    assert bodies["flight"].content != bodies["lcf"].content


def test_unknown_sources_and_bad_boresights_are_one_line(client, tracked):
    _, cid, _ = tracked
    for params, words in [({"navigation": "rtk"}, "has no navigation source 'rtk' (it has: lcf, flight)"),
                          ({"navigation": "../x"}, "is not a navigation source's name"),
                          ({"boresight": "1,2"}, "expected 3 numbers"),
                          ({"boresight": "0,0,90"}, "out of range")]:
        answer = client.get(f"/api/collections/{cid}/outline", params=params)
        assert answer.status_code == 400, (params, answer.text)
        message = answer.json()["error"]
        assert words in message and "\n" not in message and "Traceback" not in message, message


def test_view_navigation_option(tracked):
    """``archive view --navigation lcf``: the collections are drawn from their .lcf unless a request names
    another source; a file is refused in one line."""
    from archive.errors import InputError
    from archive.view.registry import FlightRegistry

    registry = FlightRegistry(tracked[0], navigation="lcf")
    try:
        flight = registry.flight(tracked[1])
        assert flight.navigation == "lcf" and flight.describe()["navigation"]["default"] == "lcf"
        assert registry.previews(tracked[1]) is None   # the previews are drawn from the default source
    finally:
        registry.close()
    with pytest.raises(InputError, match="not a navigation source's name"):
        FlightRegistry(tracked[0], navigation="/tmp/flight.out")


# ---- the page, in real Chromium ------------------------------------------------------------------
@pytest.fixture(scope="module")
def browser():
    from test_view_browser import CHROMIUM, LAUNCH_ARGS

    if not CHROMIUM.exists():
        pytest.skip("Debian's chromium is not installed at /usr/bin/chromium")
    sync_api = pytest.importorskip("playwright.sync_api")
    with sync_api.sync_playwright() as pw:
        b = pw.chromium.launch(executable_path=str(CHROMIUM), args=LAUNCH_ARGS)
        try:
            yield b
        finally:
            b.close()


@pytest.fixture(scope="module")
def server(tracked):
    import sys

    from tests.conftest import archive_view
    from test_view_browser import ROOT

    command = [sys.executable, "-m", "archive", "view", "--archive", str(tracked[0]), "--port", "0"]
    with archive_view(command, cwd=ROOT) as (url, proc):
        yield url
    assert proc.returncode == 0, proc.stderr.read()


def test_the_page_switches_the_source_and_the_boresight_without_blanking(server, browser, tracked):
    from scipy.ndimage import binary_erosion
    from test_view_browser import Page, _shots_while

    _, cid, _ = tracked
    page = Page(browser, server, f"open={cid}")
    page.page.wait_for_function(f"() => window.viewer.open === '{cid}'")
    page.settled()
    page.clean()
    assert page.page.locator("#navigation option").all_inner_texts() == ["lcf (real-time)", "flight"]
    assert page.page.input_value("#navigation") == "flight"

    def changed(start, what: str) -> np.ndarray:
        shots = _shots_while(page, start)
        first, last = page.drawn(shots[0]), page.drawn(shots[-1])
        inside = binary_erosion(first, iterations=6) & binary_erosion(last, iterations=6)
        assert inside.sum() > 5_000
        blank = max(float((~page.drawn(s) & inside).sum() / inside.sum()) for s in shots)
        assert blank < 0.01, f"the flight went blank ({blank:.1%} of it) during a {what} change"
        moved = float((shots[-1] != shots[0]).any(axis=-1).mean())
        assert moved > 0.005, f"the {what} change did not change the picture"
        return shots[-1]

    before = len(page.values_requests)
    changed(lambda: page.page.select_option("#navigation", "lcf"), "navigation source")
    assert len(page.values_requests) > before and all("navigation=lcf" in u for u in page.values_requests[before:])
    page.page.wait_for_function("() => location.hash.includes('nav=lcf')")

    def roll():   # a drag of the roll slider to 1 degree, then its release
        page.page.evaluate("""() => { const el = document.getElementById('bs-roll'); el.value = '1';
            el.dispatchEvent(new Event('input')); el.dispatchEvent(new Event('change')); }""")
    last = changed(roll, "boresight")
    page.page.wait_for_function("() => location.hash.includes('boresight=1,0,0')")
    assert page.page.locator("#bs-roll-out").inner_text() == "1.00°"
    # a click follows the source and the boresight
    box = page.page.locator("#map").bounding_box()
    rows, cols = np.nonzero(binary_erosion(page.drawn(last), iterations=20))
    page.page.mouse.click(box["x"] + cols[len(cols) // 2] + 0.5, box["y"] + rows[len(rows) // 2] + 0.5)
    page.page.wait_for_function("() => window.viewer.lastPoint !== null", timeout=30_000)
    point = page.page.evaluate("window.viewer.lastPoint")
    assert point["navigation"] == "lcf" and point["boresight_deg"] == [1.0, 0.0, 0.0]
    hash_ = page.page.evaluate("location.hash")[1:]
    page.close()

    # the hash restores both: the same picture
    again = Page(browser, server, hash_)
    again.page.wait_for_function(f"() => window.viewer.open === '{cid}'")
    again.settled()
    again.clean()
    assert again.page.input_value("#navigation") == "lcf" and float(again.page.input_value("#bs-roll")) == 1.0
    for pin in again.page.locator(".leaflet-interactive").all():
        pin.evaluate("el => el.remove()")
    shot = again.shot()
    assert float((shot != last).any(axis=-1).mean()) < 0.002
    again.close()
