"""A collection remembers the DEM it was ingested with (issue 17): ``render``, ``archive.mosaic`` and
``info`` of it follow that DEM unless ``--dem`` or a numeric ``--ground-height`` is given; a DEM that
moved or changed is refused with a message naming it."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys

import numpy as np
import pytest

from helpers import FOV

GSD = 0.06


def _archive(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "archive", *map(str, args)], capture_output=True, text=True,
                          timeout=600)


@pytest.fixture(scope="module")
def ingested(hills, tmp_path_factory):
    """(flight directory, its DEM (a copy the archive records), archive, collection id)."""
    directory, _ = hills
    root = tmp_path_factory.mktemp("collection-dem")
    dem = root / "dem.tif"
    for name in ("dem.tif", "dem.tif.aux.xml"):     # the aux file holds the DEM's 3-D CRS
        shutil.copy(directory / name, root / name)
    archive = root / "archive"
    done = _archive("ingest", directory, "--archive", archive, "--fov", FOV, "--dem", dem, "--quiet")
    assert done.returncode == 0, done.stderr
    listed = _archive("catalog", "search", "--archive", archive, "--json")
    cid = json.loads(listed.stdout)["features"][0]["id"]
    return directory, dem, archive, cid


def _read(path) -> np.ndarray:
    import rasterio

    with rasterio.open(path) as f:
        return f.read()


def test_collection_renders_on_its_dem_by_default(ingested, tmp_path):
    import archive as lib

    directory, dem, archive, cid = ingested
    raw = tmp_path / "raw.tif"
    done = _archive("render", directory, "--fov", FOV, "--dem", dem, "--gsd", GSD, "--out", raw, "--quiet")
    assert done.returncode == 0, done.stderr
    coll = tmp_path / "collection.tif"
    done = _archive("render", cid, "--archive", archive, "--gsd", GSD, "--out", coll, "--quiet")
    assert done.returncode == 0, done.stderr
    a, b = _read(raw), _read(coll)
    assert a.shape == b.shape and np.array_equal(a, b, equal_nan=True)
    item = json.loads((tmp_path / "collection.tif.json").read_text())
    assert str(dem) in json.dumps(item)              # the recipe names the DEM that was used
    # archive.mosaic of the collection: the same values
    ds = lib.mosaic([cid], archive=str(archive), gsd=GSD, mode="radiance")
    assert np.array_equal(ds["radiance"].values, a, equal_nan=True)
    # an explicit flat ground height wins: a different picture
    flat = tmp_path / "flat.tif"
    done = _archive("render", cid, "--archive", archive, "--gsd", GSD, "--ground-height", 78, "--out", flat,
                    "--quiet")
    assert done.returncode == 0, done.stderr
    c = _read(flat)
    assert c.shape != a.shape or not np.array_equal(c, a, equal_nan=True)
    # info of the collection reports the terrain under it
    info = _archive("info", cid, "--archive", archive, "--json")
    assert info.returncode == 0, info.stderr
    assert json.loads(info.stdout)["terrain"]["dem"] == str(dem)


def test_moved_or_changed_dem_is_refused(ingested, tmp_path):
    _, dem, archive, cid = ingested
    out = tmp_path / "out.tif"
    moved = dem.with_name("moved.tif")
    dem.rename(moved)
    shutil.copy(dem.with_name("dem.tif.aux.xml"), dem.with_name("moved.tif.aux.xml"))
    try:
        done = _archive("render", cid, "--archive", archive, "--gsd", GSD, "--out", out, "--quiet")
        assert done.returncode != 0 and not out.exists()
        assert str(dem) in done.stderr and "no longer there" in done.stderr, done.stderr
        # --dem given explicitly wins over the recorded one
        done = _archive("render", cid, "--archive", archive, "--gsd", GSD, "--dem", moved, "--out", out, "--quiet")
        assert done.returncode == 0, done.stderr
    finally:
        moved.rename(dem)
    backup = tmp_path / "backup.tif"
    shutil.copy(dem, backup)
    try:
        with open(dem, "r+b") as f:                  # same size, other bytes
            f.seek(-16, 2)
            f.write(b"\x01" * 16)
        done = _archive("render", cid, "--archive", archive, "--gsd", GSD, "--out", tmp_path / "b.tif", "--quiet")
        assert done.returncode != 0
        assert str(dem) in done.stderr and "changed since" in done.stderr, done.stderr
    finally:
        shutil.copy(backup, dem)


def test_viewer_draws_the_collection_on_its_dem(ingested, tmp_path):
    """The viewer's point spectra of a DEM collection equal ``archive render --dem`` at those pixels,
    float32 bit for bit (the same terrain meshes); its ground slider is the DEM's vertical offset."""
    import warnings

    from pyproj import Transformer

    from archive.view.registry import FlightRegistry
    from archive.view.server import create_app

    directory, dem, archive, cid = ingested
    out = tmp_path / "dem.tif"
    done = _archive("render", directory, "--fov", FOV, "--dem", dem, "--gsd", GSD, "--out", out, "--quiet")
    assert done.returncode == 0, done.stderr
    import rasterio

    with rasterio.open(out) as f:
        values, transform, epsg = f.read(), f.transform, f.crs.to_epsg()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        from starlette.testclient import TestClient
    to_ll = Transformer.from_crs(epsg, 4326, always_xy=True)
    rows, cols = np.nonzero(np.isfinite(values).all(axis=0))
    pick = np.random.default_rng(3).choice(len(rows), 12, replace=False)
    with TestClient(create_app(FlightRegistry(archive))) as client:
        info = client.get(f"/api/collections/{cid}").json()
        assert info["terrain"] == {"dem": "dem.tif", "offset": 0.0} and info["ground_height"] == 0.0
        for k in pick:
            r, c = int(rows[k]), int(cols[k])
            x, y = transform * (c + 0.5, r + 0.5)
            lon, lat = to_ll.transform(x, y)
            p = client.get(f"/api/collections/{cid}/point",
                           params={"lon": repr(lon), "lat": repr(lat), "gsd": repr(GSD), "mode": "radiance"}).json()
            assert p["covered"], p
            spectrum = np.array([np.nan if v is None else v for v in p["values"]], np.float32)
            assert np.array_equal(spectrum.view(np.uint32), values[:, r, c].view(np.uint32)), (r, c)
        # a vertical offset of the DEM moves the picture: the same point shows another line or sample
        moved = 0
        for k in pick:
            r, c = int(rows[k]), int(cols[k])
            lon, lat = to_ll.transform(*(transform * (c + 0.5, r + 0.5)))
            a = client.get(f"/api/collections/{cid}/point", params={"lon": repr(lon), "lat": repr(lat),
                                                                   "gsd": repr(GSD)}).json()
            b = client.get(f"/api/collections/{cid}/point", params={"lon": repr(lon), "lat": repr(lat),
                                                                   "gsd": repr(GSD), "ground_height": "3"}).json()
            assert b["ground_height"] == 3.0
            moved += (a["line"], a["sample"]) != (b["line"], b["sample"])
        assert moved >= len(pick) // 2
