"""Overview previews made at ingest (issue 36, :mod:`archive.drawing.preview_layout`): the levels drawn by the
viewer's renderer are bit for bit the band-value tiles the viewer draws from the DN at that zoom, the
coarser ones the means of 2 x 2 pixels of the level above; the viewer answers zoomed-out tiles and
the whole flight's statistics from them without opening the flight; ``archive verify`` checks their
checksums; stale or missing previews fall back to the DN, and ingesting the flight again adds them.
"""

from __future__ import annotations

import shutil
import warnings

import numpy as np
import pytest

from archive.catalog.root import open_root
from archive.cli import main
from archive.drawing.preview_layout import GROUP, read_previews, verify_previews
from archive.view.registry import FlightRegistry
from archive.view.server import create_app
from helpers import FOV


def _client(app):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        from starlette.testclient import TestClient
    return TestClient(app)


@pytest.fixture
def archive_copy(small_archive, tmp_path):
    """A writable copy of the shared small archive (ingested with its previews)."""
    arc, cid = small_archive
    copy = tmp_path / "arc"
    shutil.copytree(arc, copy)
    return copy, cid


def _tile(client, cid, z, x, y, bands, **params):
    """(k, 256, 256) values of a tile or None (204), and whether they came from the previews."""
    r = client.get(f"/api/collections/{cid}/values/{z}/{x}/{y}", params={"bands": bands, **params})
    assert r.status_code in (200, 204), r.text
    source = r.headers.get("x-source") == "previews"
    if r.status_code == 204:
        return None, source
    return np.frombuffer(r.content, "<f4").reshape(-1, 256, 256), source


def _level_tiles(level):
    return [(x, y) for x in range(level.column // 256, (level.column + level.width - 1) // 256 + 1)
            for y in range(level.row // 256, (level.row + level.height - 1) // 256 + 1)]


def test_previews_are_the_viewers_tiles_without_the_dn(small_archive):
    arc, cid = small_archive
    previews = read_previews(open_root(arc).store(cid))
    assert previews is not None, "ingest made no previews"
    zooms = sorted(previews.levels)
    assert zooms == list(range(zooms[0], zooms[-1] + 1)) and len(zooms) >= 3   # a pyramid of consecutive zooms
    assert previews.mode == "radiance" and len(previews.bands) == 3
    registry = FlightRegistry(arc)
    with _client(create_app(registry)) as client:
        info = client.get(f"/api/collections/{cid}").json()
        assert list(previews.bands) == info["default_bands"]
        bands = ",".join(map(str, info["default_bands"]))
        everything = f"0-{len(info['cubes']) - 1}"   # the same drawing, asked so that the DN path draws it
        rendered = [z for z in zooms if registry_level_rendered(arc, cid, z)]
        assert rendered and rendered[-1] == zooms[-1]
        covered = 0
        for z in rendered:
            for x, y in _level_tiles(previews.levels[z]):
                fast, from_previews = _tile(client, cid, z, x, y, bands)
                slow, from_dn = _tile(client, cid, z, x, y, bands, cubes=everything)
                assert from_previews and not from_dn
                if slow is None:
                    assert fast is None
                    continue
                assert np.array_equal(fast, slow, equal_nan=True), (z, x, y)
                covered += int(np.isfinite(slow).sum())
        assert covered > 500
        # a pyramid level: the mean of the finite values of each 2 x 2 block of the level below
        coarse = [z for z in zooms if z not in rendered]
        for z in coarse[:1]:
            level, stored = previews.levels[z], previews.load(z)
            finer, below = previews.levels[z + 1], previews.load(z + 1)
            grid = np.full((3, 2 * level.height, 2 * level.width), np.nan, np.float32)
            r, c = finer.row - 2 * level.row, finer.column - 2 * level.column
            grid[:, r:r + finer.height, c:c + finer.width] = below
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                mean = np.nanmean(grid.reshape(3, level.height, 2, level.width, 2), axis=(2, 4))
            assert np.allclose(stored, mean, rtol=1e-6, equal_nan=True) and np.isfinite(stored).sum() > 3
        # deeper than the finest level: from the DN; another band, mode or rule too
        z = zooms[-1] + 1
        x, y = _level_tiles(previews.levels[zooms[-1]])[0]
        assert not _tile(client, cid, z, 2 * x, 2 * y, bands)[1]
        other = ",".join(str(b) for b in range(info["bands"]) if b not in previews.bands)
        assert not _tile(client, cid, zooms[-1], x, y, other)[1]
        assert not _tile(client, cid, zooms[-1], x, y, bands, mode="raw")[1]
        assert not _tile(client, cid, zooms[-1], x, y, bands, overlap="nadir")[1]
        assert not _tile(client, cid, zooms[-1], x, y, bands, ground_height=info["ground_height"])[1]
        # far out (above the coarsest level): means of its pixels, a value where the flight is
        world, from_previews = _tile(client, cid, 0, 0, 0, bands)
        assert from_previews and 1 <= np.isfinite(world[0]).sum() <= 4
        # the whole flight's statistics, stored at ingest, equal the DN's
        before = client.get("/api/status").json()["render"]["submitted"]
        stored = client.get(f"/api/collections/{cid}/stats", params={"bands": bands}).json()
        assert client.get("/api/status").json()["render"]["submitted"] == before   # nothing drawn
        assert stored == client.get(f"/api/collections/{cid}/stats", params={"bands": bands, "cubes": everything}).json()


def registry_level_rendered(arc, cid, z) -> bool:
    """Whether level z was drawn by the renderer (as its record says)."""
    import json

    attrs = json.loads((open_root(arc).store(cid) / GROUP / "zarr.json").read_text())["attributes"]
    return [r["made"] for r in attrs["archive:previews"]["levels"] if r["zoom"] == z] == ["rendered"]


def test_verify_checks_the_previews(archive_copy, capsys):
    arc, cid = archive_copy
    store = open_root(arc).store(cid)
    assert verify_previews(store) == []
    assert main(["verify", cid, "--archive", str(arc), "--quiet"]) == 0
    # one level's values changed behind the archive's back (written as zarr would, checksum not)
    import zarr

    group = zarr.open_group(store / GROUP, mode="r+")
    name = sorted(group.array_keys())[0]
    values = group[name][...]
    values[np.isfinite(values)] += 1.0
    group[name][...] = values
    capsys.readouterr()
    assert main(["verify", cid, "--archive", str(arc), "--quiet"]) == 1
    out = capsys.readouterr().out
    assert f"previews/{name}: checksum mismatch" in out and "CORRUPT" in out
    # the viewer checks a level when it reads it: that one is drawn from the DN instead
    previews = read_previews(store)
    zoom = int(name[1:])
    x, y = _level_tiles(previews.levels[zoom])[0]
    with _client(create_app(FlightRegistry(arc))) as client:
        r = client.get(f"/api/collections/{cid}/values/{zoom}/{x}/{y}",
                       params={"bands": ",".join(map(str, previews.bands))})
        assert r.status_code in (200, 204) and "x-source" not in r.headers
        healthy = next(z for z in previews.levels if z != zoom)
        x, y = _level_tiles(previews.levels[healthy])[0]
        assert _tile(client, cid, healthy, x, y, ",".join(map(str, previews.bands)))[1]


def test_stale_or_missing_previews_fall_back_and_ingest_adds_them(archive_copy, small_flight):
    from archive.collection import record_navigation
    from archive.ingest.command import ingest

    arc, cid = archive_copy
    store = open_root(arc).store(cid)
    previews = read_previews(store)
    z = max(previews.levels)
    x, y = _level_tiles(previews.levels[z])[0]
    registry = FlightRegistry(arc)
    with _client(create_app(registry)) as client:
        bands = ",".join(map(str, previews.bands))
        assert _tile(client, cid, z, x, y, bands)[1]
        # a new ground height recorded (as calibrate --apply does): the previews no longer match
        import zarr

        attrs = dict(zarr.open_group(store, mode="r").attrs)
        record_navigation(store, attrs["navigation_params"], {}, ground_height=attrs["ground_height"] + 5.0)
        assert read_previews(store) is None
        assert not _tile(client, cid, z, x, y, bands)[1]
        # an older collection, made before previews existed: viewed from its DN
        shutil.rmtree(store / GROUP)
        assert not _tile(client, cid, z, x, y, bands)[1]
    # ingesting the same flight again adds them (its navigation as ingested again first)
    record_navigation(store, attrs["navigation_params"], {}, ground_height=attrs["ground_height"])
    (result,) = ingest([str(small_flight)], arc, FOV, progress=False)
    assert result.status == "already ingested"
    again = read_previews(store)
    assert again is not None and sorted(again.levels) == sorted(previews.levels)
    for zoom in previews.levels:
        assert np.array_equal(again.load(zoom), previews.load(zoom), equal_nan=True)   # the same values: deterministic


def test_many_tiles_of_many_flights_in_one_request(small_archive):
    """/api/values/batch answers several flights' tiles at once (what the page asks at archive scale):
    each part's bytes, window and status are those of the one-tile request; a bad part costs only
    itself."""
    import json

    arc, cid = small_archive
    previews = read_previews(open_root(arc).store(cid))
    z = max(previews.levels)
    tiles = _level_tiles(previews.levels[z])
    bands = ",".join(map(str, previews.bands))
    with _client(create_app(FlightRegistry(arc))) as client:
        asked = [(cid, z, x, y, bands) for x, y in tiles] + [(cid, z, tiles[0][0] + 50, tiles[0][1], "0"),
                                                            ("no-such-flight", z, 0, 0, "0"), (cid, z, 0, 0, "999")]
        parts = ";".join(f"{c}/{zz}/{x}/{y}/{b}" for c, zz, x, y, b in asked)
        r = client.get("/api/values/batch", params={"parts": parts, "mode": "radiance", "overlap": "last", "window": "1"})
        assert r.status_code == 200, r.text
        index = json.loads(r.headers["x-parts"])
        assert [p[0] for p in index[-3:]] == [204, 404, 400] and "999" in index[-1][5]
        offset = 0
        for (c, zz, x, y, b), (status, size, side, window, key, error) in zip(asked[:-2], index, strict=False):
            one = client.get(f"/api/collections/{c}/values/{zz}/{x}/{y}",
                             params={"bands": b, "mode": "radiance", "overlap": "last", "window": "1"})
            assert status == one.status_code and error is None and not key
            if status == 200:
                assert r.content[offset:offset + size] == one.content and side == int(one.headers["x-side"])
                assert window == [int(v) for v in one.headers["x-window"].split(",")]
            offset += size
        assert offset == len(r.content)
        assert client.get("/api/values/batch", params={"parts": ""}).status_code == 400
