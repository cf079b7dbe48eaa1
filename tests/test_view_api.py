"""``archive view``'s HTTP API (issue 13) on a small simulated flight ingested into an archive.

Tiles are checked against the catalog footprint (which contains every covered pixel by
construction); point spectra against ``archive.mosaic`` (bit for bit the values ``archive render``
writes) at the pixel holding the point; bad ids, paths and parameters give 4xx JSON messages
without stack traces; non-loopback binds are refused without ``--allow-remote``; an abandoned
tile request never reaches the renderer (real uvicorn, a raw socket closed early).
"""

from __future__ import annotations

import io
import json
import socket
import threading
import time
import warnings

import numpy as np
import pytest
from PIL import Image
from pyproj import Transformer

import archive
from archive.cli import main
from archive.errors import InputError
from archive.drawing.cache import ByteLRU
from archive.view.registry import FlightRegistry
from archive.view.server import LOOPBACK_NAMES, check_host, create_app
from archive.grid import HALF_WORLD, tile_grid
from helpers import FOV, inside_geometry

Z = 20  # ~0.12 m pixels here: the flight spans a few tiles


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    """(archive path, collection id, its STAC Item) of a 4-cube, 6-band simulated flight."""
    from archive.ingest.command import ingest
    from archive.simulator.command import simulate_flight

    root = tmp_path_factory.mktemp("view")
    simulate_flight(root / "flight", cubes=4, bands=6, samples=64, lines=150, cubes_per_pass=2, seed=5)
    (result,) = ingest([root / "flight"], root / "archive", FOV, progress=False)
    item = json.loads((root / "archive" / "catalog" / "items" / f"{result.cid}.json").read_text())
    return root / "archive", result.cid, item


def _client(app):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # starlette's note about which httpx it found
        from starlette.testclient import TestClient
    return TestClient(app)


@pytest.fixture(scope="module")
def client(demo):
    with _client(create_app(FlightRegistry(demo[0]))) as c:
        yield c


def _tiles_over(bbox, z):
    """XYZ tiles (x, y) of zoom z covering a W, S, E, N degree box."""
    to_merc = Transformer.from_crs(4326, 3857, always_xy=True)
    (x0, x1), (y0, y1) = to_merc.transform([bbox[0], bbox[2]], [bbox[1], bbox[3]])
    side = 2 * HALF_WORLD / 2**z
    cols = range(int((x0 + HALF_WORLD) // side), int((x1 + HALF_WORLD) // side) + 1)
    rows = range(int((HALF_WORLD - y1) // side), int((HALF_WORLD - y0) // side) + 1)
    return [(x, y) for x in cols for y in rows]


def _rgba(response) -> np.ndarray:
    assert response.status_code == 200, response.text
    assert response.headers["content-type"] == "image/png"
    image = Image.open(io.BytesIO(response.content))
    assert image.size == (256, 256)
    return np.asarray(image.convert("RGBA"))


def _pixel_lonlat(z, x, y):
    """lon, lat (256, 256) of the pixel centres of tile z/x/y."""
    grid = tile_grid(z, x, y)
    xs, ys = grid.xy_centres()
    mx, my = np.meshgrid(xs, ys)
    lon, lat = Transformer.from_crs(3857, 4326, always_xy=True).transform(mx, my)
    return np.asarray(lon), np.asarray(lat)


def test_collections_geojson_and_filters(client, demo):
    _, cid, item = demo
    fc = client.get("/api/collections").json()
    assert fc["type"] == "FeatureCollection"
    (f,) = fc["features"]
    p = f["properties"]
    assert f["id"] == cid and f["geometry"] == item["geometry"] and f["bbox"] == item["bbox"]
    assert p["bands"] == 6 and p["min_wavelength"] == 400.0 and p["max_wavelength"] == 1000.0
    assert p["start_datetime"] == item["properties"]["start_datetime"] and p["cubes"] == 4
    w, s, e, n = item["bbox"]
    day = p["start_datetime"][:10]
    for query, hits in [({"bbox": f"{w},{s},{e},{n}"}, 1), ({"bbox": "10,10,11,11"}, 0),
                        ({"datetime": day}, 1), ({"datetime": "2001-01-01/2001-02-01"}, 0),
                        ({"wavelength": "650"}, 1), ({"wavelength": "1500"}, 0),
                        ({"bbox": f"{w},{s},{e},{n}", "datetime": f"{day}/..", "wavelength": "500"}, 1)]:
        got = client.get("/api/collections", params=query)
        assert got.status_code == 200, got.text
        assert len(got.json()["features"]) == hits, query


def test_describe(client, demo):
    _, cid, item = demo
    info = client.get(f"/api/collections/{cid}").json()
    assert info["bands"] == 6 and len(info["cubes"]) == 4 and info["default_mode"] == "radiance"
    assert info["ground_height"] == item["properties"]["archive:ground_height"]
    assert info["lowest_camera"] > info["ground_height"] + 1
    assert len(info["default_bands"]) == 3


def test_tiles_cover_the_footprint_and_nothing_else(client, demo):
    _, cid, item = demo
    tiles = _tiles_over(item["bbox"], Z)
    assert 2 <= len(tiles) <= 40
    opaque_total = inside_total = covered_inside = 0
    for x, y in tiles:
        rgba = _rgba(client.get(f"/api/collections/{cid}/tiles/{Z}/{x}/{y}.png"))
        opaque = rgba[..., 3] > 0
        assert set(np.unique(rgba[..., 3])) <= {0, 255}
        inside = inside_geometry(item["geometry"], *_pixel_lonlat(Z, x, y))
        assert not (opaque & ~inside).any(), f"tile {x}/{y}: pixels drawn outside the footprint"
        opaque_total += int(opaque.sum())
        inside_total += int(inside.sum())
        covered_inside += int((opaque & inside).sum())
    assert opaque_total > 10_000
    # the footprint is each strip's hull grown by a margin: most of it is covered
    assert covered_inside / inside_total > 0.7
    # far from the flight: transparent, and nothing rendered for it
    x, y = tiles[0]
    far = _rgba(client.get(f"/api/collections/{cid}/tiles/{Z}/{x + 40}/{y}.png"))
    assert (far[..., 3] == 0).all()


def test_tile_options_and_cache(client, demo):
    _, cid, item = demo
    def drawn(t):
        return (_rgba(client.get(f"/api/collections/{cid}/tiles/{Z}/{t[0]}/{t[1]}.png"))[..., 3] > 0).sum()

    x, y = max(_tiles_over(item["bbox"], Z), key=drawn)
    url = f"/api/collections/{cid}/tiles/{Z}/{x}/{y}.png"
    base = _rgba(client.get(url))
    before = client.get("/api/status").json()
    again = _rgba(client.get(url))
    after = client.get("/api/status").json()
    assert np.array_equal(base, again)
    assert after["render"]["submitted"] == before["render"]["submitted"]  # from the tile cache
    assert after["caches"]["tiles"]["hits"] == before["caches"]["tiles"]["hits"] + 1
    grey = np.asarray(Image.open(io.BytesIO(client.get(url, params={"band": 2}).content)))
    assert grey.ndim == 3 and grey.shape[2] == 2  # grey + alpha
    assert np.array_equal(grey[..., 1] > 0, base[..., 3] > 0)
    lower = _rgba(client.get(url, params={"ground_height": item["properties"]["archive:ground_height"] - 15}))
    assert (lower[..., 3] != base[..., 3]).mean() > 0.01  # another ground: other coverage
    fixed = _rgba(client.get(url, params={"wavelengths": "650,550,450", "stretch": "0,1e9"}))
    assert fixed[..., :3][fixed[..., 3] > 0].max() <= 1  # radiance is far below 1e9 / 255
    one_cube = _rgba(client.get(url, params={"cubes": "3-3"}))
    assert (one_cube[..., 3] > 0).sum() < (base[..., 3] > 0).sum()


@pytest.mark.parametrize("options", [
    {},
    {"ground_height": 75.5, "sync_offset": 0.004, "mode": "relative", "cubes": (1, 3)},
    {"overlap": "nadir"},
])
def test_point_equals_the_rendered_mosaic(client, demo, options):
    """The spectrum of /point at a pixel centre of ``archive.mosaic``'s grid is that pixel's values,
    float32 bit for bit, whatever the parameters (same meshes, same two GL passes)."""
    path, cid, item = demo
    gsd = item["properties"]["gsd"]  # the page's default: the nominal gsd
    cubes = options.get("cubes")
    params = {k: v for k, v in options.items() if k != "cubes"}
    ds = archive.mosaic([cid], archive=path, gsd=gsd, **params)
    values = ds[[v for v in ds.data_vars if v != "saturated"][0]].values
    epsg = ds.rio.crs.to_epsg()
    to_ll = Transformer.from_crs(epsg, 4326, always_xy=True)
    rows, cols = np.nonzero(np.isfinite(values).all(axis=0))
    pick = np.random.default_rng(7).choice(len(rows), 25, replace=False)
    if options.get("overlap") == "nadir":
        # half of them where the rule matters: pixels the 'last' rule shows from another cube
        last = archive.mosaic([cid], archive=path, gsd=gsd)
        last = last[[v for v in last.data_vars if v != "saturated"][0]].values
        differs = np.flatnonzero(np.any(last[:, rows, cols] != values[:, rows, cols], axis=0))
        assert differs.size > 20, "the flight's passes should overlap"
        pick = np.r_[pick[:13], np.random.default_rng(8).choice(differs, 12, replace=False)]
    query = {k: str(v) for k, v in params.items()}
    if cubes is not None:
        # later cubes win in the mosaic: wherever cubes first..last (last = the flight's last cube)
        # cover a pixel, the whole mosaic shows the same cube as the point of those cubes
        query["cubes"] = f"{cubes[0]}-{cubes[1]}"
    compared = 0
    for k in pick:
        r, c = rows[k], cols[k]
        lon, lat = to_ll.transform(float(ds.x[c]), float(ds.y[r]))
        got = client.get(f"/api/collections/{cid}/point", params={"lon": repr(lon), "lat": repr(lat), **query})
        assert got.status_code == 200, got.text
        p = got.json()
        assert p["gsd"] == gsd and p["epsg"] == epsg
        assert abs(p["pixel"]["x"] - float(ds.x[c])) < 1e-6 and abs(p["pixel"]["y"] - float(ds.y[r])) < 1e-6
        if cubes is not None and not p["covered"]:
            continue
        assert p["covered"] and p["line"] >= 0 and p["sample"] >= 0
        if cubes is not None:
            assert cubes[0] <= p["cube"] <= cubes[1]
        spectrum = np.array([np.nan if v is None else v for v in p["values"]], np.float32)
        assert len(spectrum) == 6 and p["wavelength"] == item["properties"]["archive:wavelengths"]
        assert np.array_equal(spectrum.view(np.uint32), values[:, r, c].astype(np.float32).view(np.uint32)), \
            (r, c, spectrum, values[:, r, c])
        compared += 1
    assert compared >= 10


def test_stats_of_the_view(client, demo):
    _, cid, item = demo
    w, s, e, n = item["bbox"]
    whole = client.get(f"/api/collections/{cid}/stats", params={"wavelengths": "650,550,450"}).json()
    # the whole flight: every 4th line and sample of each of the 4 cubes (150 lines x 64 samples)
    assert whole["sample"] == 4 and whole["count"] == 4 * 38 * 16 and len(whole["low"]) == 3
    assert all(lo < hi for lo, hi in zip(whole["low"], whole["high"]))
    # ... close to the percentiles of the flight as drawn (its bbox on a 512 px grid)
    drawn = client.get(f"/api/collections/{cid}/stats", params={"wavelengths": "650,550,450",
                                                                  "bbox": f"{w},{s},{e},{n}"}).json()
    assert drawn["count"] > 10_000
    for lo, hi, dlo, dhi in zip(whole["low"], whole["high"], drawn["low"], drawn["high"], strict=True):
        assert abs(lo - dlo) < 0.1 * (dhi - dlo) and abs(hi - dhi) < 0.1 * (dhi - dlo)
    # ... and the same whatever the ground height or sync offset (where pixels land, not their values)
    moved = client.get(f"/api/collections/{cid}/stats", params={
        "wavelengths": "650,550,450", "ground_height": item["properties"]["archive:ground_height"] - 7,
        "sync_offset": "0.01"}).json()
    assert (moved["low"], moved["high"]) == (whole["low"], whole["high"])
    half = client.get(f"/api/collections/{cid}/stats",
                      params={"bbox": f"{w},{s},{(w + e) / 2},{n}", "band": 1, "percentiles": "10,90"}).json()
    assert half["band"] == [1] and half["percentiles"] == [10.0, 90.0] and half["count"] > 1000
    away = client.get(f"/api/collections/{cid}/stats", params={"bbox": "10,10,10.1,10.1"}).json()
    assert away["count"] == 0 and away["low"] == [None] * 3


BAD = [
    # (path, params, status, words the message must hold)
    ("/api/collections/Nope_123/tiles/20/0/0.png", {}, 404, "Nope_123"),
    ("/api/collections/..%2F..%2Fetc%2Fpasswd/point", {"lon": 0, "lat": 0}, 404, ""),
    ("/api/collections/%2E%2E/stats", {}, 404, ".."),
    ("/api/collections/../../etc/passwd", {}, 404, ""),
    ("/static/..%2F..%2Fcli.py", {}, 404, ""),
    ("/static/../server.py", {}, 404, ""),
    ("/api/nothing", {}, 404, "/api/nothing"),
    ("{tile}", {"z": 31}, 400, "zoom 31"),
    ("/api/collections/{cid}/tiles/20/99999999/0.png", {}, 400, "does not exist at zoom 20"),
    ("{tile}", {"wavelengths": ",".join(["700"] * 10_000)}, 400, "10000"),
    ("{tile}", {"wavelengths": "500,600"}, 400, "1 (grey) or 3"),
    ("{tile}", {"wavelengths": "5000,600,500"}, 400, "no band near 5000"),
    ("{tile}", {"band": 6}, 400, "band 6 out of range"),
    ("{tile}", {"band": 1, "wavelengths": 500}, 400, "either band"),
    ("{tile}", {"mode": "magic"}, 400, "magic"),
    ("{tile}", {"mode": "reflectance"}, 400, "white reference"),
    ("{tile}", {"stretch": "p90,p10"}, 400, "percentiles"),
    ("{tile}", {"stretch": "1,2,3"}, 400, "stretch"),
    ("{tile}", {"cubes": "3-1"}, 400, "first cube 4 comes after last cube 2"),
    ("{tile}", {"cubes": "0-9"}, 400, "cube 10 out of range: the flight has cubes 1..4"),
    ("{tile}", {"ground_height": 1e7}, 400, "ground_height"),
    ("{tile}", {"ground_height": 500}, 400, "not below the camera"),
    ("{tile}", {"sync_offset": "nan"}, 400, "finite"),
    ("{tile}", {"sync_offset": 3600}, 400, "out of range"),
    ("/api/collections/{cid}/point", {"lon": 1}, 400, "lon and lat"),
    ("/api/collections/{cid}/point", {"lon": 500, "lat": 0}, 400, "lon"),
    ("/api/collections/{cid}/point", {"lon": 0, "lat": 0, "gsd": 0}, 400, "gsd"),
    ("/api/collections/{cid}/stats", {"percentiles": "50"}, 400, "percentiles"),
    ("/api/collections", {"bbox": "1,2,3"}, 400, "4 numbers"),
    ("/api/collections", {"bbox": "10,0,0,10"}, 400, "W <= E"),
    ("/api/collections", {"datetime": "yesterday"}, 400, "yesterday"),
    ("/api/collections", {"wavelength": "x"}, 400, "number"),
]


@pytest.mark.parametrize("path, params, status, words", BAD, ids=[f"{b[0][-24:]}-{b[3]}" for b in BAD])
def test_bad_requests_give_json_4xx_without_trace(client, demo, path, params, status, words):
    _, cid, _ = demo
    params = dict(params)
    if path == "{tile}":
        path = f"/api/collections/{cid}/tiles/{params.pop('z', 20)}/0/0.png"
    got = client.get(path.format(cid=cid), params=params)
    assert got.status_code == status, got.text
    assert got.headers["content-type"].startswith("application/json")
    body = got.json()
    assert words in body["error"] and body["status"] == status
    assert "Traceback" not in got.text and 'File "' not in got.text


def test_host_checks(demo, capsys):
    for host in ("127.0.0.1", "::1", "localhost", "127.0.0.2"):
        check_host(host, allow_remote=False)
    for host in ("0.0.0.0", "192.168.1.20", "::", "example.org"):
        with pytest.raises(InputError, match="--allow-remote"):
            check_host(host, allow_remote=False)
        check_host(host, allow_remote=True)
    assert main(["view", "--archive", str(demo[0]), "--host", "0.0.0.0", "--port", "0"]) == 2
    err = capsys.readouterr().err
    assert "refusing to serve on '0.0.0.0'" in err and "--allow-remote" in err and "Traceback" not in err
    # bound to loopback, the server answers only requests naming a loopback host (DNS rebinding)
    app = create_app(FlightRegistry(demo[0]), allowed_hosts=LOOPBACK_NAMES)
    with _client(app) as c:
        assert c.get("http://127.0.0.1:8000/api/collections").status_code == 200
        assert c.get("http://[::1]:8000/api/status").status_code == 200
        evil = c.get("http://evil.example:8000/api/collections")
        assert evil.status_code == 400 and "evil.example" in evil.json()["error"]


def test_byte_lru_keeps_its_limit():
    cache = ByteLRU(100)
    for i in range(10):
        cache.put(i, bytes(30), 30)
    assert len(cache) == 3 and cache.stats().bytes == 90 and cache.get(0) is None and cache.get(9) is not None
    cache.get(7)
    cache.put("new", b"", 30)   # evicts the least recently used: 8
    assert cache.get(8) is None and cache.get(7) is not None
    cache.put("huge", b"", 101)  # larger than the limit: not kept
    assert cache.get("huge") is None and cache.stats().bytes <= 100 and cache.stats().evictions == 8


def test_server_memory_stays_within_cache_mb(demo):
    """--cache-mb bounds every cache the server keeps, the open flights included (issue 36): many
    tiles at several zooms and ground heights through a server of 2 MiB of cache; after each, every
XX; the open flight is
    charged the arrays its meshes hold (counted here independently); too small a share for a flight
    reopens it instead of keeping it."""
    from archive.view.server import CACHE_SHARES, cache_bytes

    arc, cid, item = demo
    limits = cache_bytes(2)
    assert sum(limits.values()) <= 2 << 20 and set(limits) == set(CACHE_SHARES)
    registry = FlightRegistry(arc, bands_cache=ByteLRU(limits["bands"]), lookup_cache=ByteLRU(limits["lookups"]),
                              flights_cache=ByteLRU(limits["flights"]))
    with _client(create_app(registry, tile_cache_bytes=limits["tiles"])) as c:
        asked = 0
        for z in (Z - 3, Z - 1, Z):
            for ground in ("", "&ground_height=80", "&ground_height=95"):
                for x, y in _tiles_over(item["bbox"], z)[:12]:
                    r = c.get(f"/api/collections/{cid}/values/{z}/{x}/{y}?bands=0,3,5&cubes=0-3{ground}")
                    assert r.status_code in (200, 204) and "x-source" not in r.headers   # drawn from the DN
                    asked += 1
                    caches = c.get("/api/status").json()["caches"]
                    for name, limit in limits.items():
                        assert caches[name]["bytes"] <= caches[name]["limit"] == limit, (name, caches[name])
                    assert sum(v["bytes"] for v in caches.values()) <= 2 << 20
        assert asked >= 30
        evicted = {name: v["evictions"] for name, v in caches.items()}
        assert evicted["tiles"] > 0 and evicted["bands"] > 0 and evicted["lookups"] > 0, evicted
    registry.close()
    # an open flight's charge: the arrays of its meshes (3 ground heights, UTM and EPSG:3857) and little more
    registry = FlightRegistry(arc)
    flight = registry.flight(cid)
    for ground in (None, 80.0, 95.0):
        flight.geometry(ground, None)
    registry.settle()
    meshes = sum(a.nbytes for g in flight._geometries.values() for m in (*g.utm, *g.mercator)
                 for a in (m.ground, m.depth, m.line) if a is not None)
    assert len(flight._geometries) == 3 and meshes > 20_000
    charged = registry.flights_cache.stats().bytes
    assert meshes < charged == flight.nbytes() < meshes + (2 << 20)
    # a flights share smaller than a flight: not kept (reopened per job), the accounting still holds
    tight = FlightRegistry(arc, flights_cache=ByteLRU(64 << 10))
    first = tight.flight(cid)
    first.geometry(None, None)
    tight.settle()
    assert tight.flights_cache.stats().bytes == 0 and tight.flight(cid) is not first
    tight.close()
    registry.close()


@pytest.fixture
def live(demo):
    """A real uvicorn server on a free loopback port, in a thread; yields (base URL, Viewer)."""
    from tests.conftest import serve_loopback

    app = create_app(FlightRegistry(demo[0]))
    with serve_loopback(app) as url:
        yield url, app.state.viewer


def _get_json(url):
    import urllib.request

    with urllib.request.urlopen(url, timeout=10) as r:
        return json.loads(r.read())


def test_abandoned_tile_requests_are_not_rendered(live, demo):
    base, viewer = live
    _, cid, item = demo
    x, y = _tiles_over(item["bbox"], Z)[0]
    path = f"/api/collections/{cid}/tiles/{Z}/{x}/{y}.png?stretch=0,1000"
    gate = threading.Event()
    viewer.render.submit(lambda check: gate.wait(20))  # the render thread is busy
    port = int(base.rsplit(":", 1)[1])
    with socket.create_connection(("127.0.0.1", port)) as s:
        s.sendall(f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n".encode())
        deadline = time.monotonic() + 10
        while viewer.render.queued < 2:  # the tile job waits behind the gate
            assert time.monotonic() < deadline
            time.sleep(0.01)
    # the client has gone: the server notices while the job waits, and cancels it
    deadline = time.monotonic() + 10
    while _get_json(base + "/api/status")["abandoned"] < 1:
        assert time.monotonic() < deadline, "the abandoned request was not noticed"
        time.sleep(0.02)
    gate.set()
    while viewer.render.queued:
        assert time.monotonic() < deadline
        time.sleep(0.01)
    counts = _get_json(base + "/api/status")["render"]
    assert counts["skipped"] == 1 and counts["done"] == 1 and counts["failed"] == 0  # the gate only
    # asked again by a client that stays: rendered
    import urllib.request

    with urllib.request.urlopen(base + path, timeout=20) as r:
        assert r.status == 200 and r.headers["content-type"] == "image/png"
    assert _get_json(base + "/api/status")["render"]["done"] == 2


def test_the_latest_view_is_drawn_first(live, demo):
    """Two tile requests wait while the render thread is busy: the one of the newer view
    (X-Generation) is drawn first although it came second."""
    import select

    base, viewer = live
    _, cid, _ = demo
    viewer.render.call(lambda: viewer.registry.flight(cid).describe())   # the flight open, its meshes made
    (xa, ya), (xb, yb), *_ = _tiles_over(demo[2]["bbox"], Z)
    gate, started = threading.Event(), threading.Event()
    viewer.render.submit(lambda check: (started.set(), gate.wait(20)))
    assert started.wait(10)
    port = int(base.rsplit(":", 1)[1])
    socks = {}
    for name, (x, y), gen in (("old", (xa, ya), "1000"), ("new", (xb, yb), "2000")):
        s = socket.create_connection(("127.0.0.1", port))
        s.sendall(f"GET /api/collections/{cid}/values/{Z}/{x}/{y}?bands=0 HTTP/1.1\r\nHost: 127.0.0.1\r\n"
                  f"X-Generation: {gen}\r\n\r\n".encode())
        socks[name] = s
        deadline = time.monotonic() + 10
        while viewer.render.queued < len(socks) + 1:   # queued in this order
            assert time.monotonic() < deadline
            time.sleep(0.01)
    try:
        overtaken = viewer.render.counts["overtaken"]
        gate.set()
        readable, _, _ = select.select(list(socks.values()), [], [], 20)
        assert socks["new"] in readable
        for s in socks.values():
            s.settimeout(20)
            assert s.recv(12).startswith(b"HTTP/1.1 20")
        assert viewer.render.counts["overtaken"] == overtaken + 1   # the old view's tile, drawn after
    finally:
        for s in socks.values():
            s.close()


def test_raw_flight_directories(demo):
    """``archive view FLIGHT_DIR --fov DEG``: a raw flight served like a collection (its footprint
    computed as the catalog does; tiles and points drawn from the raw files)."""
    path, cid, item = demo
    flight_dir = path.parent / "flight"
    with pytest.raises(InputError, match="--fov"):
        FlightRegistry(None, [flight_dir])
    with _client(create_app(FlightRegistry(None, [flight_dir], FOV))) as c:
        (f,) = c.get("/api/collections").json()["features"]
        # named as ingest names it (issue 49 item 6: one name for a flight, raw or ingested)
        assert f["properties"]["kind"] == "raw" and f["id"] == cid
        assert np.allclose(f["bbox"], item["bbox"], atol=1e-6)
        assert c.get("/api/collections", params={"bbox": "10,10,11,11"}).json()["features"] == []
        described = c.get(f"/api/collections/{cid}")   # the raw folder's (the archive is not served)
        assert described.status_code == 200 and described.json()["id"] == cid
        tiles = _tiles_over(f["bbox"], Z)
        drawn = sum(int((_rgba(c.get(f"/api/collections/{f['id']}/tiles/{Z}/{x}/{y}.png"))[..., 3] > 0).sum())
                    for x, y in tiles)
        assert drawn > 10_000
        lon, lat = (f["bbox"][0] + f["bbox"][2]) / 2, (f["bbox"][1] + f["bbox"][3]) / 2
        p = c.get(f"/api/collections/{f['id']}/point", params={"lon": lon, "lat": lat}).json()
        assert p["gsd"] == f["properties"]["gsd"] and len(p["values"]) == 6
    # beside its own collection, the raw folder keeps the raw source's name: both are served
    with _client(create_app(FlightRegistry(path, [flight_dir], FOV))) as c:
        features = {f["id"]: f for f in c.get("/api/collections").json()["features"]}
        assert features[cid]["properties"]["kind"] != "raw"
        (raw,) = [f for f in features.values() if f["properties"]["kind"] == "raw"]
        assert raw["id"].startswith("flight-") and raw["id"] != cid
        assert c.get(f"/api/collections/{raw['id']}").json()["id"] == raw["id"]


def _values(response, count: int, side: int = 256) -> np.ndarray:
    assert response.status_code == 200, response.text
    assert response.headers["content-type"] == "application/octet-stream"
    planes = np.frombuffer(response.content, "<f4")
    assert planes.size == count * side * side
    return planes.reshape(count, side, side)


def test_band_values_are_what_the_png_tiles_stretch(client, demo):
    """The band-value tile (issue 22) holds the very values the PNG tile encodes: stretched with
    the flight's 2/98 % (the stats endpoint), they give the PNG's bytes; per band, cached per band."""
    from archive.drawing.png import encode_png

    _, cid, item = demo
    x, y = max(_tiles_over(item["bbox"], Z), key=lambda t: (_rgba(client.get(
        f"/api/collections/{cid}/tiles/{Z}/{t[0]}/{t[1]}.png"))[..., 3] > 0).sum())
    info = client.get(f"/api/collections/{cid}").json()
    bands = ",".join(map(str, info["default_bands"]))
    values = _values(client.get(f"/api/collections/{cid}/values/{Z}/{x}/{y}", params={"bands": bands}), 3)
    stats = client.get(f"/api/collections/{cid}/stats", params={"bands": bands}).json()
    png = _rgba(client.get(f"/api/collections/{cid}/tiles/{Z}/{x}/{y}.png"))
    again = np.asarray(Image.open(io.BytesIO(encode_png(values, list(zip(stats["low"], stats["high"], strict=True))))))
    assert np.array_equal(png, again)
    # one band of the three again: from the cache, equal
    before = client.get("/api/status").json()["render"]["submitted"]
    one = _values(client.get(f"/api/collections/{cid}/values/{Z}/{x}/{y}",
                             params={"bands": str(info["default_bands"][1])}), 1)
    assert client.get("/api/status").json()["render"]["submitted"] == before
    assert np.array_equal(one[0], values[1], equal_nan=True)
    # nadir: values and the winners' view zenith (degrees, NaN exactly where nothing covers)
    nadir = _values(client.get(f"/api/collections/{cid}/values/{Z}/{x}/{y}",
                               params={"bands": bands, "overlap": "nadir"}), 4)
    assert nadir.shape[0] == 4 and np.array_equal(np.isfinite(nadir[3]), np.isfinite(nadir[0]))
    assert 0 <= np.nanmin(nadir[3]) and np.nanmax(nadir[3]) < 30
    # a coarse preview (scale 4): 64 x 64
    _values(client.get(f"/api/collections/{cid}/values/{Z}/{x}/{y}", params={"bands": bands, "scale": 4}), 3, 64)
    # away from the flight: 204, nothing to draw
    assert client.get(f"/api/collections/{cid}/values/{Z}/{x + 40}/{y}", params={"bands": "0"}).status_code == 204


def test_values_window_holds_every_value_of_the_tile(client, demo):
    """window=1 (what the page asks): only the rows and columns of the tile that hold values, with
    their place (X-Window: column, row, width, height); everything outside it is NaN in the whole
    tile, the window's values are the whole tile's; the same window for a later band of the tile."""
    _, cid, item = demo
    z = Z - 4   # the flight covers part of a tile
    url = f"/api/collections/{cid}/values/{z}/{{}}/{{}}"
    x, y = max(_tiles_over(item["bbox"], z), key=lambda t: np.isfinite(_values(client.get(
        url.format(*t), params={"bands": "2"}), 1)).sum())
    whole = _values(client.get(url.format(x, y), params={"bands": "2,4", "overlap": "nadir"}), 3)
    r = client.get(url.format(x, y), params={"bands": "2,4", "overlap": "nadir", "window": "1"})
    assert r.status_code == 200
    c0, r0, w, h = map(int, r.headers["X-Window"].split(","))
    assert 0 < w * h < 256 * 256
    part = np.frombuffer(r.content, "<f4").reshape(3, h, w)
    assert np.array_equal(part, whole[:, r0:r0 + h, c0:c0 + w], equal_nan=True)
    outside = whole.copy()
    outside[:, r0:r0 + h, c0:c0 + w] = np.nan
    assert np.isnan(outside).all()
    finite = np.isfinite(part).any(axis=0)
    assert finite[0].any() and finite[-1].any() and finite[:, 0].any() and finite[:, -1].any()   # the smallest
    later = client.get(url.format(x, y), params={"bands": "5", "window": "1"})
    assert later.headers["X-Window"] == r.headers["X-Window"] and len(later.content) == w * h * 4
    # without window=1: the whole tile, as before
    assert "X-Window" not in client.get(url.format(x, y), params={"bands": "2"}).headers


def test_overview_values_are_means_over_the_pixel_footprint(client, demo):
    """At a zoom whose pixels span several of the flight's, a band-value pixel is a mean over its
    footprint (the f x f block of the flight's pixels, lines x samples, around the one it sees), not
    a point sample: it is much closer to the mean of the finer tiles' pixels under it than one of
    those pixels is."""
    _, cid, item = demo
    z = Z - 4
    (x, y), *_ = sorted(_tiles_over(item["bbox"], z), key=lambda t: -np.isfinite(_values(client.get(
        f"/api/collections/{cid}/values/{z}/{t[0]}/{t[1]}", params={"bands": "2"}), 1)).sum())
    coarse = _values(client.get(f"/api/collections/{cid}/values/{z}/{x}/{y}", params={"bands": "2"}), 1)[0]
    assert np.isfinite(coarse).sum() > 50
    # f the power of two nearest the ratio of the pixel sizes: the tiles of zoom z + log2(f) have
    # the flight's pixel size; their f x f blocks' means are the footprints' means
    from archive.grid import zoom_gsd

    f = 2 ** round(np.log2(zoom_gsd(z) / item["properties"]["gsd"]))
    assert f >= 2
    k = int(np.log2(f))
    fine = np.full((256 * f, 256 * f), np.nan, np.float32)
    for i in range(f):
        for j in range(f):
            r = client.get(f"/api/collections/{cid}/values/{z + k}/{x * f + j}/{y * f + i}", params={"bands": "2"})
            if r.status_code == 200:
                fine[i * 256:(i + 1) * 256, j * 256:(j + 1) * 256] = _values(r, 1)[0]
    blocks = fine.reshape(256, f, 256, f)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        mean = np.nanmean(blocks, axis=(1, 3))
    point = fine[f // 2::f, f // 2::f]           # what point sampling would show
    both = np.isfinite(mean) & np.isfinite(coarse) & np.isfinite(point)
    assert both.sum() > 50
    assert (np.isfinite(coarse) & ~np.isfinite(mean)).sum() < 0.1 * np.isfinite(coarse).sum()
    mip_error = np.median(np.abs(coarse[both] - mean[both]))
    point_error = np.median(np.abs(point[both] - mean[both]))
    assert mip_error < 0.6 * point_error, (mip_error, point_error)
    # a block mean: of the f x f block of lines x samples centred on the (line, sample), cut at the edges
    flight = FlightRegistry(demo[0]).flight(cid)
    lines, samples = flight.cubes[1].lines, flight.cubes[1].samples
    full = flight.planes.plane(1, 2, "radiance")
    assert np.isnan(full[-1]) and full.size == lines * samples + 1
    full = full[:-1].reshape(lines, samples)
    h = f // 2
    got = flight.planes.block_means(1, 2, "radiance", f, np.array([40, 0, lines - 1, -1]), np.array([30, 0, samples - 1, 5]))
    assert np.allclose(got[:3], [full[40 - h:40 - h + f, 30 - h:30 - h + f].mean(), full[:f - h, :f - h].mean(),
                                 full[lines - 1 - h:, samples - 1 - h:].mean()], rtol=1e-5)
    assert np.isnan(got[3])   # not covered


def test_outline_follows_ground_and_cubes(client, demo):
    _, cid, item = demo
    base = client.get(f"/api/collections/{cid}/outline").json()
    assert base["type"] == "MultiPolygon" and len(base["coordinates"]) == 4
    two = client.get(f"/api/collections/{cid}/outline", params={"cubes": "1-2"}).json()
    assert len(two["coordinates"]) == 2 and two["coordinates"][0] == base["coordinates"][1]
    lower = client.get(f"/api/collections/{cid}/outline",
                       params={"ground_height": item["properties"]["archive:ground_height"] - 15}).json()

    def width(g):
        ring = np.array(g["coordinates"][0][0])
        return np.ptp(ring[:, 0]) * np.ptp(ring[:, 1])
    assert width(lower) > 1.1 * width(base)   # a lower ground: a wider swath
    bad = client.get(f"/api/collections/{cid}/values/{Z}/0/0", params={"bands": "0", "cubes": "2-1"})
    assert bad.status_code == 400 and bad.json()["error"].startswith("cubes: first cube 3 comes after last cube 2")
    past = client.get(f"/api/collections/{cid}/values/{Z}/0/0", params={"bands": "0", "cubes": "1-4"})
    assert past.status_code == 400 and "cube 5 out of range: the flight has cubes 1..4" in past.json()["error"]
    assert client.get(f"/api/collections/{cid}/values/{Z}/0/0", params={"bands": "99"}).status_code == 400


@pytest.mark.parametrize("mode", ["raw", "relative", "radiance"])
def test_band_planes_are_the_renderers_values(demo, mode):
    """A band plane (what every tile gathers from) holds, bit for bit, the values the renderer's CPU
    band pass (``archive render`` on llvmpipe) gives each (line, sample) of the cube."""
    from archive.grid import Grid
    from archive.render.gather import gather_lookup
    from archive.render.renderer import Lookup

    path, cid, _ = demo
    flight = FlightRegistry(path).flight(cid)
    info = flight.cubes[2]
    line, sample = np.meshgrid(np.arange(info.lines, dtype=np.int32), np.arange(info.samples, dtype=np.int32),
                               indexing="ij")
    every = Lookup(Grid(3857, 1.0, 0.0, 0.0, info.samples, info.lines), line, sample, info.lines, info.samples)
    source = flight.source(None)
    for band in (0, 4):
        want = gather_lookup(every, source.read_bands(2, [band]), source.radiometry(2, [band], mode)).values[0]
        got = flight.planes.plane(2, band, mode)
        assert np.isnan(got[-1])
        assert np.array_equal(got[:-1].view(np.uint32), want.reshape(-1).view(np.uint32))


def test_overlap_rules_are_served_and_say_what_they_need(client, demo):
    """/api/collections serves the overlap rules the page offers (issue 31: the page hard-codes no
    rule name): each one's name, label, key plane and winner; a rule with a key plane gets it with its
    band values (X-Key names it), one without does not; the served names are those accepted."""
    from archive.drawing.query import OVERLAPS

    _, cid, item = demo
    rules = client.get("/api/collections").json()["overlaps"]
    assert rules == [c.as_dict() for c in OVERLAPS] and len(rules) >= 2
    assert all(set(r) == {"name", "label", "key", "wins"} and r["label"] for r in rules)
    assert rules[0]["key"] is None and rules[0]["wins"] == "last"     # the default needs no key plane
    assert any(r["key"] == "view_zenith" and r["wins"] == "lowest" for r in rules)
    x, y = max(_tiles_over(item["bbox"], Z), key=lambda t: (_rgba(client.get(
        f"/api/collections/{cid}/tiles/{Z}/{t[0]}/{t[1]}.png"))[..., 3] > 0).sum())
    for rule in rules:
        r = client.get(f"/api/collections/{cid}/values/{Z}/{x}/{y}", params={"bands": "1,3", "overlap": rule["name"]})
        planes = _values(r, 2 + (rule["key"] is not None))
        assert r.headers["X-Key"] == (rule["key"] or "")
        assert np.isfinite(planes[0]).sum() > 1000, rule
        if rule["key"] is not None:   # the key is there exactly where values are
            assert np.array_equal(np.isfinite(planes[-1]), np.isfinite(planes[0]))
    refused = client.get(f"/api/collections/{cid}/values/{Z}/{x}/{y}", params={"bands": "1", "overlap": "first"})
    assert refused.status_code == 400
    assert all(r["name"] in refused.json()["error"] for r in rules), refused.json()
