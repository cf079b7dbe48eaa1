"""Zarr outputs that GDAL opens (issue 21): ``--zarr-format 2`` (the default) is what GDAL 3.10 reads
(rasterio 1.4's wheel, QGIS 3.40); v3 stays available. Opened through rasterio's own GDAL and
compared with the COG of the same render: values bit for bit, CRS, transform; band wavelengths
from the store's ``wavelength`` array; xarray reads both versions with the same layout."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from helpers import FOV



def _archive(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "archive", *map(str, args)], capture_output=True, text=True,
                          timeout=600)


@pytest.fixture(scope="module")
def renders(tmp_path_factory):
    from archive.simulator.command import simulate_flight

    root = tmp_path_factory.mktemp("zarr-gdal")
    simulate_flight(root / "flight", cubes=2, bands=4, samples=64, lines=120, seed=3)
    outs = {}
    for name, extra in (("m.zarr", ["--provenance"]), ("m3.zarr", ["--zarr-format", "3"]), ("m.tif", [])):
        done = _archive("render", root / "flight", "--fov", FOV, "--gsd", 0.2, "--out", root / name, "--quiet",
                        *extra)
        assert done.returncode == 0, done.stderr
        outs[name] = root / name
    return outs


def test_gdal_opens_the_default_zarr_like_the_cog(renders):
    import rasterio

    with rasterio.open(renders["m.tif"]) as cog:
        values, crs, transform, names = cog.read(), cog.crs, cog.transform, cog.descriptions
    assert json.loads((renders["m.zarr"] / ".zgroup").read_text())["zarr_format"] == 2
    with rasterio.open(f'ZARR:"{renders["m.zarr"]}":/radiance') as z:
        assert z.count == values.shape[0] and z.shape == values.shape[1:]
        assert z.crs == crs
        # GDAL derives the transform from the x/y pixel-centre coordinates: equal to 1e-9 m
        assert z.transform.almost_equals(transform, precision=1e-9), (z.transform, transform)
        assert np.array_equal(z.read().view(np.uint32), values.view(np.uint32))
    with rasterio.open(f'ZARR:"{renders["m.zarr"]}":/wavelength') as w:
        wavelengths = w.read().ravel()
    assert [f"{v:.1f} nm" in n for v, n in zip(wavelengths, names)] == [True] * len(names)
    with rasterio.open(f'ZARR:"{renders["m.zarr"]}":/line') as line:   # a provenance layer too
        assert line.crs == crs and np.nanmax(line.read(1)) >= 100


def test_zarr_versions_hold_the_same_dataset(renders):
    import rioxarray  # noqa: F401
    import xarray as xr

    a = xr.open_zarr(renders["m.zarr"], decode_coords="all")
    b = xr.open_zarr(renders["m3.zarr"], decode_coords="all")
    assert json.loads((renders["m3.zarr"] / "zarr.json").read_text())["zarr_format"] == 3
    assert a.rio.crs == b.rio.crs and a.rio.transform() == b.rio.transform()
    assert np.array_equal(a["radiance"].values, b["radiance"].values, equal_nan=True)
    assert np.array_equal(a["wavelength"].values, b["wavelength"].values)
    assert a["radiance"].attrs == b["radiance"].attrs


def test_bad_zarr_format_is_refused(tmp_path, renders):
    flight = renders["m.tif"].parent / "flight"
    done = _archive("render", flight, "--fov", FOV, "--gsd", 0.2, "--out", tmp_path / "x.zarr", "--zarr-format", "4")
    assert done.returncode == 2 and "--zarr-format" in done.stderr and not (tmp_path / "x.zarr").exists()
