"""``archive render --index NDVI --expression NAME=EXPR`` (issue 48 point 1): one band per index,
computed per written tile from the rendered bands the indices read.

Real renders of a simulated reflectance flight (the sky-sensor set-up of tests/test_stats.py): the
NDVI output against NDVI computed from a plain render of its two bands, rendered independently
(equal where both have data, NaN where neither); the simulator's true NDVI on a homogeneous patch;
band names read back by rasterio (COG), xarray (Zarr) and the ENVI header; an expression; a
per-flight batch; a time stack of index bands (two flights: equal to ``stack_index`` of the plain
stack, resumed and replaced as stacks are); tiles (equal to the single render of their union);
the refusals in one line.
"""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from helpers import FOV

import archive
from archive.analysis.indices import bind_indices, evaluate, parse_indices

SHAPE = dict(cubes=2, bands=8, samples=96, lines=150, cubes_per_pass=2)
GSD = 0.25


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    from archive.simulator.command import simulate_flight

    root = tmp_path_factory.mktemp("index")
    truth = simulate_flight(root / "day0", seed=0, scene_seed=0, clouds=True, start="2024-06-12T16:00:00Z", **SHAPE)
    return root, root / "day0", truth


def _render(src, out, **kw):
    return archive.georectify([str(src)], str(out), gsd=GSD, fov=FOV, mode="reflectance", **kw)


@pytest.fixture(scope="module")
def plain(flight):
    """The plain reflectance render of the bands NDVI reads (and R800 / R670 for the expression)."""
    import xarray as xr

    root, src, _ = flight
    ds = xr.open_zarr(root / "plain.zarr") if (root / "plain.zarr").exists() else None
    if ds is None:
        _render(src, root / "plain.zarr")
        ds = xr.open_zarr(root / "plain.zarr")
    return ds


def _expected(ds, text: str, named: bool) -> np.ndarray:
    (spec,) = parse_indices([text] if named else [], [] if named else [text])
    wl = ds["wavelength"].values
    (bound,) = bind_indices([spec], wl)
    values = {float(w): ds["reflectance"].isel(band=k).values for k, w in enumerate(wl)}
    return evaluate(bound, values)


def test_zarr_ndvi_equals_the_plain_render_and_the_truth(flight, plain):
    import xarray as xr
    from shapely.geometry import box

    root, src, truth = flight
    s = _render(src, root / "ndvi.zarr", index=["NDVI"], expression=["RATIO=R800/R670"])
    assert s["bands"] == 2
    ds = xr.open_zarr(root / "ndvi.zarr")
    assert list(ds["band_name"].values) == ["NDVI", "RATIO"]
    got = ds["index"].values
    assert got.dtype == np.float32 and got.shape[1:] == plain["reflectance"].shape[1:]
    for k, (text, named) in enumerate((("NDVI", True), ("RATIO=R800/R670", False))):
        want = _expected(plain, text, named)
        both = np.isfinite(want) & np.isfinite(got[k])
        assert both.sum() > 1000
        np.testing.assert_array_equal(np.isnan(got[k]), np.isnan(want))
        np.testing.assert_allclose(got[k][both], want[both], rtol=2e-7, atol=0)
    # the simulator's truth on a homogeneous patch (the true reflectance's NDVI, bands 655 / 830 nm)
    from archive.simulator.clouds import truth_reflectance

    wl = np.asarray(truth.wavelengths if hasattr(truth, "wavelengths") else plain["wavelength"].values, float)
    checked = 0
    x, y = ds["x"].values, ds["y"].values
    for p in truth.homogeneous_patches():
        w, s_, e, n = p["interior"]
        w, s_, e, n = w + 0.6, s_ + 0.6, e - 0.6, n - 0.6   # > 1 px of blur inside the patch's edge
        cx, cy = box(w, s_, e, n).centroid.coords[0]
        refl = truth_reflectance(truth, np.array([cx]), np.array([cy]))[:, 0]
        r, nir = refl[np.argmin(np.abs(wl - 655))], refl[np.argmin(np.abs(wl - 830))]
        win = got[0][np.ix_((y > s_) & (y < n), (x > w) & (x < e))]
        if win.size and np.isfinite(win).all():
            assert abs(float(np.mean(win)) - (nir - r) / (nir + r)) < 0.005, p["name"]
            checked += 1
    assert checked >= 1
    item = json.loads((root / "ndvi.zarr.json").read_text())
    recipe = item["properties"]["archive:recipe"]
    assert [i["name"] for i in recipe["indices"]] == ["NDVI", "RATIO"]
    assert set(recipe["indices"][0]["bands"]) == {"N", "R"}
    assert recipe["request"]["index"] == ["NDVI"] and "--index NDVI" in recipe["command"]
    assert len(item["properties"]["archive:source_bands"]) == 2   # 8 bands: R800 is N's band, R670 R's


def test_cog_and_envi_band_names(flight, plain):
    import rasterio

    root, src, _ = flight
    _render(src, root / "ndvi.tif", index=["NDVI"])
    want = _expected(plain, "NDVI", True)
    with rasterio.open(root / "ndvi.tif") as f:
        assert f.count == 1 and f.descriptions == ("NDVI",)
        got = f.read(1)
    np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
    np.testing.assert_allclose(got[np.isfinite(got)], want[np.isfinite(want)], rtol=2e-7)
    _render(src, root / "ndvi.hdr", index=["NDVI"])
    header = (root / "ndvi.hdr").read_text()
    assert "NDVI" in header.split("band names", 1)[1].split("}", 1)[0]


def test_plain_render_is_unchanged(plain):
    assert "band_name" not in plain.coords and "band_name" not in plain
    assert plain["reflectance"].shape[0] == 8


def test_per_flight_batch(flight, tmp_path):
    import xarray as xr

    root, src, _ = flight
    s = archive.georectify([str(src)], str(tmp_path / "out"), gsd=GSD, fov=FOV, mode="reflectance",
                           per_flight=True, index=["NDVI"])
    assert s["failed"] == 0, s
    (out,) = tmp_path.joinpath("out").glob("*.zarr")
    assert list(xr.open_zarr(out)["band_name"].values) == ["NDVI"]


def _cli(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "archive", "render", *args], capture_output=True, text=True,
                          timeout=120)


@pytest.mark.parametrize("extra, option", [
    (["--index", "NDVX"], "--index"),
    (["--expression", "X=R2000/R670"], "--expression X"),
    (["--index", "NDVI", "--wavelengths", "650"], "--index"),
    (["--index", "NDVI", "--bands", "0,1"], "--index"),
])
def test_refusals(flight, tmp_path, extra, option):
    _, src, _ = flight
    r = _cli(str(src), "--out", str(tmp_path / "x.zarr"), "--gsd", "0.25", "--fov", str(FOV), "--mode",
             "reflectance", "--quiet", *extra)
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and option in lines[0], r.stderr
    assert not (tmp_path / "x.zarr").exists()


@pytest.fixture(scope="module")
def second(flight):
    """The same ground a week later (seed 1, scene seed 0: its own wobble, noise and sky)."""
    from archive.simulator.command import simulate_flight

    root = flight[0]
    simulate_flight(root / "day1", seed=1, scene_seed=0, clouds=True, start="2024-06-19T16:00:00Z", **SHAPE)
    return root / "day1"


def test_stack_of_index_bands_equals_stack_index_of_the_plain_stack(flight, second, tmp_path):
    """``render --stack --index NDVI --expression RATIO=...``: one float32 band per index, named by
    it, each time step the index of the plain stack's bands (``stack_index``); made with the first
    flight, --resumed by the command with both (only the second added), refused with other indices
    unless --overwrite; the Item records the indices."""
    import xarray as xr

    from archive.analysis.indices import stack_index
    from archive.errors import InputError

    _, src, _ = flight
    both = [str(src), str(second)]
    plain = tmp_path / "plain.zarr"
    archive.georectify(both, str(plain), gsd=GSD, fov=FOV, mode="reflectance", stack=True)
    out = tmp_path / "idx.zarr"
    kw = dict(gsd=GSD, fov=FOV, mode="reflectance", stack=True, like=str(plain))
    s = archive.georectify([str(src)], str(out), index=["NDVI"], expression=["RATIO=R800/R670"], **kw)
    assert s["added"] == [src.name] and s["bands"] == 2
    r = _cli(*both, "--out", str(out), "--stack", "--resume", "--like", str(plain), "--gsd", str(GSD),
             "--fov", str(FOV), "--mode", "reflectance", "--index", "NDVI", "--expression", "RATIO=R800/R670", "--quiet")
    assert r.returncode == 0, r.stderr
    assert "1 added, 1 already there" in r.stdout and "2 bands" in r.stdout
    with xr.open_zarr(plain) as p, xr.open_zarr(out) as ds:
        assert list(ds["band_name"].values) == ["NDVI", "RATIO"] and "wavelength" not in ds.coords
        assert ds["index"].dims == ("time", "band", "y", "x") and ds["index"].dtype == np.float32
        assert list(ds["flight"].values) == list(p["flight"].values) == [src.name, second.name]
        got = ds["index"].values
        for k, text in enumerate(("NDVI", "RATIO=R800/R670")):
            want = stack_index(p["reflectance"], text).values
            assert got.shape[0] == want.shape[0] == 2 and got.shape[2:] == want.shape[1:]
            np.testing.assert_array_equal(np.isnan(got[:, k]), np.isnan(want), err_msg=text)
            finite = np.isfinite(want)
            assert finite[0].sum() > 1000 and finite[1].sum() > 1000
            np.testing.assert_allclose(got[:, k][finite], want[finite], rtol=1e-6, atol=0, err_msg=text)
        np.testing.assert_array_equal(ds["saturated"].values, p["saturated"].values)
    item = json.loads(out.with_name(out.name + ".json").read_text())
    props = item["properties"]
    recipe = props["archive:recipe"]
    assert [i["name"] for i in recipe["indices"]] == ["NDVI", "RATIO"]
    assert set(recipe["indices"][0]["bands"]) == {"N", "R"}
    assert recipe["request"]["index"] == ["NDVI"] and recipe["request"]["expression"] == ["RATIO=R800/R670"]
    assert "--index NDVI" in recipe["command"] and "--stack" in recipe["command"]
    assert props["cube:dimensions"]["band"]["values"] == ["NDVI", "RATIO"]
    assert len(props["archive:wavelengths"]) == 2   # only the two camera bands the indices read were rendered
    assert [f["id"] for f in props["archive:stack"]["flights"]] == [src.name, second.name]
    # other indices: a resume is refused (another request); --overwrite makes the stack again
    with pytest.raises(InputError, match="another request"):
        archive.georectify(both, str(out), index=["NDVI"], resume=True, **kw)
    s = archive.georectify(both, str(out), index=["NDVI"], overwrite=True, **kw)
    assert s["bands"] == 1 and s["added"] == [src.name, second.name]
    with xr.open_zarr(out) as ds:
        assert list(ds["band_name"].values) == ["NDVI"]
        np.testing.assert_array_equal(ds["index"].values[:, 0], got[:, 0])


def test_tiles_with_an_index_equal_the_single_render(flight, tmp_path):
    """``render --tiles 10 --index NDVI`` of an ingested flight: each tile's NDVI is the NDVI of the
    single render of the tiles' union (--bounds, --align), pixel for pixel."""
    import rasterio

    from archive.ingest.command import ingest

    _, src, _ = flight
    (r,) = ingest([str(src)], tmp_path / "archive", FOV, progress=False)
    kw = dict(archive=str(tmp_path / "archive"), gsd=GSD, mode="reflectance", index=["NDVI"], format="tif")
    s = archive.georectify([r.cid], str(tmp_path / "tiles"), tiles=10, **kw)
    tiles = sorted((tmp_path / "tiles").glob("*.tif"))
    assert s["failed"] == 0 and len(tiles) >= 2, s
    corners = [tuple(int(v) for v in p.stem.split("_")[1:]) for p in tiles]
    w, s_ = min(c[0] for c in corners), min(c[1] for c in corners)
    e, n = max(c[0] for c in corners) + 10, max(c[1] for c in corners) + 10
    union = tmp_path / "union.tif"
    archive.georectify([r.cid], str(union), bounds=(w, s_, e, n), align=True, **kw)
    with rasterio.open(union) as f:
        assert f.descriptions == ("NDVI",)
        whole = f.read(1)
    side = round(10 / GSD)
    for path, (e0, n0) in zip(tiles, corners):
        r0, c0 = round((n - n0 - 10) / GSD), round((e0 - w) / GSD)
        with rasterio.open(path) as f:
            assert f.descriptions == ("NDVI",)
            np.testing.assert_array_equal(f.read(1), whole[r0:r0 + side, c0:c0 + side], err_msg=path.name)
        item = json.loads(path.with_name(path.name + ".json").read_text())
        assert [i["name"] for i in item["properties"]["archive:recipe"]["indices"]] == ["NDVI"]
    assert np.isfinite(whole).mean() > 0.1
