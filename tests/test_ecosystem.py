"""The outputs in the hands of the tools people use (issue 49, items 2 and 3): plain ``xr.open_zarr``
(no ``decode_coords``) and rioxarray find the CRS of renders and stacks; GDAL (through rasterio)
opens the Zarr values with their band names; ``odc.stac.load`` of the Item of each output (COG,
ENVI, Zarr, a stack) equals the output's values bit for bit; pystac validates every Item; and every
Python recipe of docs/ecosystem.md runs as written, the pystac-client one against a live STAC API.

The values each reader returns are compared with another writer's or reader's: the COG of the same
render read by rasterio (its own TIFF writer), the Zarr read by zarr/xarray; the CRS and grid with
the COG's. One archive of two simulated flights of one field, rendered once (module fixture).
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from helpers import FOV

SHAPE = dict(cubes=2, samples=32, lines=60, bands=4, cubes_per_pass=2)
DAYS = ("2024-06-12", "2024-06-19")
DOC = Path(__file__).resolve().parents[1] / "docs" / "ecosystem.md"
#: odc-geo's warnings (its use of affine's '*', of shapely.ops.transform): not ours
pytestmark = [pytest.mark.filterwarnings("ignore::PendingDeprecationWarning"),
              pytest.mark.filterwarnings("ignore:The 'shapely.ops.transform:DeprecationWarning")]


@pytest.fixture(scope="module")
def outputs(tmp_path_factory, scheduler):
    """(folder, archive, flight ids): two flights of one field a week apart, ingested; in the folder
    the first rendered as mosaic.zarr (Zarr v2, with provenance layers), mosaic3.zarr (v3),
    mosaic.tif, mosaic.hdr, and the stack of both, stack.zarr, each with its Item (``archive.georectify``,
    what ``archive render`` runs, on the session's local cluster)."""
    import archive
    from archive.ingest.command import ingest
    from archive.simulator.command import simulate_flight

    root = tmp_path_factory.mktemp("ecosystem")
    ids = []
    for k, day in enumerate(DAYS):
        simulate_flight(root / f"day{k}", seed=k, scene_seed=0, start=f"{day}T16:00:00Z", **SHAPE)
        (result,) = ingest([str(root / f"day{k}")], root / "archive", FOV, progress=False)
        ids.append(result.cid)
    folder = root / "out"
    folder.mkdir()
    arc = str(root / "archive")
    for name, extra in (("mosaic.zarr", {"provenance": True}), ("mosaic3.zarr", {"zarr_format": 3}),
                        ("mosaic.tif", {}), ("mosaic.hdr", {})):
        archive.georectify([ids[0]], folder / name, archive=arc, gsd=0.25, scheduler=scheduler, **extra)
    archive.georectify(ids, folder / "stack.zarr", archive=arc, gsd=0.5, stack=True, scheduler=scheduler)
    return folder, root / "archive", ids


def _cog(folder: Path):
    import rasterio

    with rasterio.open(folder / "mosaic.tif") as cog:
        return cog.read(), cog.crs, cog.transform, cog.descriptions, [cog.tags(b, ns="IMAGERY") for b in cog.indexes]


def _bits(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, np.float32).view(np.uint32)


def test_plain_open_zarr_gives_the_crs_grid_and_band_coordinates(outputs):
    import rioxarray  # noqa: F401
    import xarray as xr

    folder, _, _ = outputs
    values, crs, transform, _, _ = _cog(folder)
    for name in ("mosaic.zarr", "mosaic3.zarr", "stack.zarr"):
        ds = xr.open_zarr(folder / name)   # no decode_coords: the CF 'coordinates' name spatial_ref
        assert "spatial_ref" in ds.coords, name
        for var in ("radiance", "saturated"):
            assert ds[var].rio.crs == crs and ds[var].attrs["grid_mapping"] == "spatial_ref", (name, var)
        assert ds.rio.crs == crs
        assert ds["x"].attrs["units"] == ds["y"].attrs["units"] == "m"
        assert (ds["x"].attrs["standard_name"], ds["y"].attrs["standard_name"]) == (
            "projection_x_coordinate", "projection_y_coordinate")
        assert ds["wavelength"].dims == ("band",) and ds["wavelength"].attrs["units"] == "nm"
        assert ds["fwhm"].attrs["units"] == "nm" and list(ds["band"].values) == [0, 1, 2, 3]
        assert ds["band"].attrs["units"] == "1" and ds["radiance"].attrs["units"] == "uW cm-2 sr-1 um-1"
        if name != "stack.zarr":   # the render's grid and values: the COG's, bit for bit
            assert ds.rio.transform() == transform
            assert np.array_equal(_bits(ds["radiance"].values), _bits(values))
        full = xr.open_zarr(folder / name, decode_coords="all")
        assert full.rio.crs == crs and np.array_equal(_bits(full["radiance"].values), _bits(ds["radiance"].values))
    mosaic = xr.open_zarr(folder / "mosaic.zarr")
    assert mosaic["line"].rio.crs == crs and "spatial_ref" in mosaic["line"].encoding["coordinates"]   # a layer
    stack = xr.open_zarr(folder / "stack.zarr")
    assert stack["radiance"].dims == ("time", "band", "y", "x") and stack["time"].dtype.kind == "M"


def test_gdal_opens_the_zarr_values_with_band_names(outputs):
    import rasterio
    import xarray as xr

    folder, _, ids = outputs
    values, crs, transform, names, imagery = _cog(folder)
    assert names[0] and imagery[0]["CENTRAL_WAVELENGTH_UM"]
    for source in (f'ZARR:"{folder / "mosaic.zarr"}":/radiance', str(folder / "mosaic.zarr" / "radiance")):
        with rasterio.open(source) as z:
            assert z.crs == crs and z.transform.almost_equals(transform, precision=1e-9), source
            assert z.descriptions == names
            assert [z.tags(b, ns="IMAGERY") for b in z.indexes] == imagery
            assert z.tags(2)["wavelength_units"] == "nm" and z.units[0] == "uW cm-2 sr-1 um-1"
            assert np.array_equal(_bits(z.read()), _bits(values))
    rio = subprocess.run([str(Path(sys.executable).with_name("rio")), "info",   # rasterio's command line
                          f'ZARR:"{folder / "mosaic.zarr"}":/radiance'], capture_output=True, text=True, timeout=60)
    assert rio.returncode == 0, rio.stderr
    info = json.loads(rio.stdout)
    assert tuple(info["descriptions"]) == names and info["crs"] == f"EPSG:{crs.to_epsg()}"
    with pytest.raises(rasterio.errors.RasterioIOError, match="Unsupported codec: bytes"):   # the doc's v3 note
        rasterio.open(f'ZARR:"{folder / "mosaic3.zarr"}":/radiance')
    stack = xr.open_zarr(folder / "stack.zarr")["radiance"].values   # (time, band, y, x)
    with rasterio.open(folder / "stack.zarr" / "radiance") as s:
        assert s.count == stack.shape[0] * stack.shape[1] and s.crs == crs
        for t, flight in enumerate(ids):
            for b in range(stack.shape[1]):
                band = t * stack.shape[1] + b + 1   # time-major
                assert s.descriptions[band - 1] == f"{names[b]}, {flight}"
                assert s.tags(band)["flight"] == flight and s.tags(band)["time_step"] == str(t)
                assert np.array_equal(_bits(s.read(band)), _bits(stack[t, b]))


def _load(path: Path, **kw):
    import odc.stac
    import pystac

    return odc.stac.load([pystac.Item.from_file(str(path))], **kw)


def test_odc_stac_loads_every_items_values(outputs):
    import odc.stac
    import rasterio
    import xarray as xr

    folder, _, _ = outputs
    values, crs, transform, _, _ = _cog(folder)
    odc.stac.configure_rio(GDAL_DISABLE_READDIR_ON_OPEN="FALSE")   # ENVI's header beside its data file
    try:
        for name in ("mosaic.tif", "mosaic.hdr", "mosaic.zarr"):
            item = json.loads((folder / f"{name}.json").read_text())
            data = item["assets"]["radiance" if name.endswith(".zarr") else "data"]
            assert data["proj:code"] == f"EPSG:{crs.to_epsg()}" and data["proj:shape"] == list(values.shape[1:])
            assert data["proj:transform"] == list(transform)[:6]
            href = (folder / data["href"]).resolve()
            with rasterio.open(href) as ds:   # what the Item says of the bands is what the file says
                if name != "mosaic.hdr":   # (GDAL reads no band unit from an ENVI header)
                    assert [b["unit"] for b in data["raster:bands"]] == list(ds.units)
                assert {b["data_type"] for b in data["raster:bands"]} == {ds.dtypes[0]}
                assert all(b["nodata"] == "nan" and np.isnan(ds.nodata) for b in data["raster:bands"])
            loaded = _load(folder / f"{name}.json")
            assert list(loaded.data_vars) == ["b0", "b1", "b2", "b3"], name
            assert loaded.odc.geobox.crs.epsg == crs.to_epsg() and loaded.odc.geobox.shape == values.shape[1:]
            got = np.stack([loaded[b].isel(time=0).values for b in loaded.data_vars])
            assert np.array_equal(_bits(got), _bits(values)), name
    finally:
        odc.stac.configure_rio(GDAL_DISABLE_READDIR_ON_OPEN="EMPTY_DIR")
    stack = xr.open_zarr(folder / "stack.zarr")["radiance"].values
    loaded = _load(folder / "stack.zarr.json")
    steps, bands = stack.shape[:2]
    assert list(loaded.data_vars) == [f"b{b}_t{t}" for t in range(steps) for b in range(bands)]
    for t in range(steps):
        for b in range(bands):
            assert np.array_equal(_bits(loaded[f"b{b}_t{t}"].isel(time=0).values), _bits(stack[t, b]))
    # Zarr v3: GDAL 3.10 does not read it, so its Item has the store asset alone (xarray's)
    v3 = json.loads((folder / "mosaic3.zarr.json").read_text())
    assert set(v3["assets"]) == {"data"} and v3["assets"]["data"]["zarr:zarr_format"] == 3


def test_pystac_validates_every_item(outputs, capsys):
    """Every output's Item, and the archive's catalog with its flights' Items (pystac, offline:
    the vendored schemas), and ``archive catalog validate`` of the outputs' Items."""
    import pystac

    from archive.catalog.pystac_validator import use_with_pystac
    from archive.catalog.validate import CORE_SCHEMAS
    from archive.cli import main

    folder, archive, ids = outputs
    use_with_pystac()
    try:
        catalog = pystac.Catalog.from_file(str(archive / "catalog.json"))   # the archive's STAC tree
        catalog.validate_all()
        assert sorted(item.id for item in catalog.get_items(recursive=True)) == sorted(ids)
        items = sorted(folder.glob("*.json"))
        assert [p.name for p in items] == ["mosaic.hdr.json", "mosaic.tif.json", "mosaic.zarr.json",
                                           "mosaic3.zarr.json", "stack.zarr.json"]
        for path in items:
            item = pystac.Item.from_dict(json.loads(path.read_text()))
            assert all(a.media_type for a in item.assets.values()), path   # loaders go by it (issue 36)
            schemas = item.validate()
            assert schemas[0] == CORE_SCHEMAS["Feature"] and set(schemas[1:]) == set(item.stac_extensions), path
    finally:
        pystac.validation.set_validator(pystac.validation.JsonSchemaSTACValidator())
    assert main(["catalog", "validate", *map(str, items)]) == 0, capsys.readouterr()


def test_the_recipes_of_docs_ecosystem_run_as_written(outputs, monkeypatch, capsys):
    """Each ``python`` block of docs/ecosystem.md, in order, in the outputs' folder; the pystac-client
    block against the archive's STAC API on loopback (its URL the one change), after the stack is
    added to its flights' Items as that block's text says."""
    import odc.stac
    import pystac

    from archive.cli import main
    from archive.view.registry import FlightRegistry
    from archive.view.server import LOOPBACK_NAMES, create_app
    from tests.conftest import serve_loopback

    folder, archive, _ = outputs
    blocks = re.findall(r"```python\n(.*?)```", DOC.read_text(), re.S)
    assert len(blocks) == 5
    assert "archive catalog add stack.zarr.json --archive A" in DOC.read_text()
    assert main(["catalog", "add", str(folder / "stack.zarr.json"), "--archive", str(archive)]) == 0
    monkeypatch.chdir(folder)
    try:
        with serve_loopback(create_app(FlightRegistry(archive), allowed_hosts=LOOPBACK_NAMES)) as url:
            for k, block in enumerate(blocks):
                code = block.replace("http://127.0.0.1:8000", url)
                exec(compile(code, f"{DOC.name} block {k + 1}", "exec"), {"__name__": "recipe"})  # noqa: S102
    finally:
        odc.stac.configure_rio(GDAL_DISABLE_READDIR_ON_OPEN="EMPTY_DIR")
        pystac.validation.set_validator(pystac.validation.JsonSchemaSTACValidator())
    out = capsys.readouterr().out
    assert "b0_t0" in out and (folder / "step1.tif").is_file()
    assert os.path.getsize(folder / "step1.tif") > 0
