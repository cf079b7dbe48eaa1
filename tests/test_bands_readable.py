"""Bands people can read (issue 36, item 3), checked with the tools they use: GDAL (rasterio) and
rioxarray open the COG, the Zarr and archive.mosaic / archive.stack arrays of a small simulated flight.

COG bands are named by wavelength with its unit ("400.0 nm", not GDAL-contradicting 0-based "band 0")
and carry GDAL's unit type; the Zarr data variable has CF ``units``, which GDAL's Zarr driver reports
as the band unit; NaN is declared nodata everywhere, lazy arrays included.
"""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import rasterio
import rioxarray
import xarray as xr

import archive
from helpers import FOV

SIM = ["--cubes", "2", "--lines", "60", "--samples", "32", "--bands", "4", "--quiet"]
RADIANCE_UNITS = "uW cm-2 sr-1 um-1"


@pytest.fixture(scope="module")
def outputs(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("bands")
    for k in (0, 1):
        subprocess.run([sys.executable, "-m", "archive", "simulate", str(d / f"f{k}"), *SIM, "--seed", str(k)],
                       check=True)
    for name in ("m.tif", "m.zarr"):
        subprocess.run([sys.executable, "-m", "archive", "render", str(d / "f0"), "--fov", str(FOV), "--gsd", "0.5",
                        "--out", str(d / name), "--quiet"], check=True)
    return d


def test_cog_bands_named_by_wavelength_with_units(outputs):
    with rasterio.open(outputs / "m.tif") as ds:
        assert ds.descriptions == ("400.0 nm", "600.0 nm", "800.0 nm", "1000.0 nm")
        assert ds.units == (RADIANCE_UNITS,) * 4
        assert math.isnan(ds.nodata)
        assert ds.tags(1)["wavelength"] == "400.0000" and ds.tags(1)["wavelength_units"] == "nm"
    da = rioxarray.open_rasterio(outputs / "m.tif")
    assert da.attrs["long_name"] == ("400.0 nm", "600.0 nm", "800.0 nm", "1000.0 nm")
    assert math.isnan(da.rio.nodata)


def test_zarr_cf_units_seen_by_xarray_and_gdal(outputs):
    ds = xr.open_zarr(outputs / "m.zarr", decode_coords="all")
    assert ds.radiance.attrs["units"] == RADIANCE_UNITS and math.isnan(ds.radiance.rio.nodata)
    with rasterio.open(f'ZARR:"{outputs / "m.zarr"}":/radiance') as z:
        assert z.units == (RADIANCE_UNITS,) * 4 and math.isnan(z.nodata)
        # GDAL's Zarr driver names a band by the indexing variable of its dimension ('band', the
        # source band index), not by wavelength: the wavelengths are their own array (README)
        assert z.tags(2)["DIM_band_VALUE"] == "1"
    with rasterio.open(f'ZARR:"{outputs / "m.zarr"}":/wavelength') as w:
        assert w.read(1).ravel().tolist() == [400.0, 600.0, 800.0, 1000.0]


def test_mosaic_and_stack_declare_nan_nodata(outputs):
    ds = archive.mosaic([str(outputs / "f0")], gsd=0.5, fov=FOV)
    assert math.isnan(ds.radiance.rio.nodata) and ds.radiance.attrs["units"] == RADIANCE_UNITS
    stack = archive.stack([str(outputs / "f0"), str(outputs / "f1")], gsd=0.5, fov=FOV)
    assert stack.dims == ("time", "band", "y", "x") and math.isnan(stack.rio.nodata)
    # metadata only: the values are the COG's, NaN where no line covers a pixel
    with rasterio.open(outputs / "m.tif") as cog:
        np.testing.assert_array_equal(ds.radiance.values, cog.read())
