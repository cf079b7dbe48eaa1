"""The Zarr output's metadata written directly (issue 19: creating the store was most of a batch
flight's planning) is the store ``xarray.Dataset.to_zarr`` of the same dataset writes: every
document and every coordinate chunk byte for byte, Zarr v2 and v3, with and without wavelengths and
fwhm; provenance layers added to it keep the store's root attributes; GDAL, xarray and rioxarray
open a store made so."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest

from archive.grid import Grid
from archive.outputs.base import CHUNK
from archive.outputs.zarr import MosaicStore, add_zarr_layers, geozarr_attrs, mosaic_dataset
from archive.geometry.provenance import ProvenanceSpec

GRID = Grid(epsg=32616, gsd=0.1, x0=232051.0, y0=3890317.0, width=1100, height=1030)   # 2 x 2 chunks
BANDS = [3, 5, 7, 9]
WAVELENGTHS = [400.0, 500.5, 600.25, 1000.0]
FWHM = [5.0, 5.0, 5.5, 6.0]
ATTRS = {"mode": "radiance", "gsd_m": 0.1, "fov_deg": 47.5, "ground_height_m": 80.0, "sync_offset_s": 0.0,
         "overlap": "last", "sources": ["/tmp/flight"]}


def _files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def _to_zarr(path: Path, grid: Grid, wavelengths, fwhm, variable: str, zarr_format: int) -> None:
    """The store as xarray writes it (how MosaicStore.create made it before issue 19)."""
    import dask.array as da
    from zarr.codecs import BloscCodec

    from archive.codecs import numcodecs_blosc

    values = da.full((len(BANDS), grid.height, grid.width), np.nan, dtype=np.float32, chunks=(1, CHUNK, CHUNK))
    saturated = da.zeros(grid.shape, dtype=np.uint8, chunks=(CHUNK, CHUNK))
    ds = mosaic_dataset(grid, values, saturated, BANDS, wavelengths, fwhm, variable, dict(ATTRS))
    ds.attrs["archive_grid"] = json.dumps({"epsg": grid.epsg, "gsd": grid.gsd, "x0": grid.x0, "y0": grid.y0,
                                           "width": grid.width, "height": grid.height})
    compressor = (numcodecs_blosc("lz4", 5, "shuffle") if zarr_format == 2
                  else BloscCodec(cname="lz4", clevel=5, shuffle="shuffle"))
    ds[variable].encoding.update({"chunks": (1, CHUNK, CHUNK), "_FillValue": np.float32(np.nan),
                                  "compressors": (compressor,)})
    ds["saturated"].encoding.update({"chunks": (CHUNK, CHUNK)})
    for name in ("x", "y", "wavelength", "fwhm"):
        if name in ds.coords:
            ds[name].encoding["_FillValue"] = None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ds.to_zarr(str(path), mode="w-", compute=False, zarr_format=zarr_format, consolidated=True)


@pytest.mark.parametrize("zarr_format", [2, 3])
@pytest.mark.parametrize("wavelengths, fwhm, variable", [(WAVELENGTHS, FWHM, "radiance"), (None, None, "dn"),
                                                          (WAVELENGTHS, None, "reflectance")])
def test_store_equals_what_xarray_writes(tmp_path, zarr_format, wavelengths, fwhm, variable):
    MosaicStore.create(tmp_path / "direct.zarr", GRID, wavelengths, BANDS, variable, dict(ATTRS), fwhm=fwhm,
                       zarr_format=zarr_format)
    _to_zarr(tmp_path / "xarray.zarr", GRID, wavelengths, fwhm, variable, zarr_format)
    direct, expected = _files(tmp_path / "direct.zarr"), _files(tmp_path / "xarray.zarr")
    # besides Zarr's documents: GDAL's band names (archive.outputs.pam), no Zarr key, in v2 stores
    pam = {name for name in direct if name.endswith(".aux.xml")}
    assert pam == ({f"{variable}/.zarray.aux.xml"} if zarr_format == 2 else set())
    direct = {name: data for name, data in direct.items() if name not in pam}
    assert sorted(direct) == sorted(expected)
    differ = [name for name in expected if direct[name] != expected[name]]
    assert not differ, f"differ from xarray's: {differ}"


def _spec() -> ProvenanceSpec:
    return ProvenanceSpec(GRID.epsg, 1.4e9, "2024-06-12T16:03:00Z",
                          ({"index": 0, "source": "f", "cube": "c1", "cube_index": 0},))


@pytest.mark.parametrize("zarr_format", [2, 3])
def test_layers_are_xarrays_arrays_and_the_root_keeps_its_attributes(tmp_path, zarr_format):
    import dask.array as da
    import xarray as xr

    from archive.outputs.layers import layer_attrs, layers_metadata

    spec = _spec()
    store = MosaicStore.create(tmp_path / "s.zarr", GRID, WAVELENGTHS, BANDS, "radiance", dict(ATTRS),
                               zarr_format=zarr_format)
    root_before = xr.open_zarr(store.path).attrs
    add_zarr_layers(store.path, GRID, spec, geozarr_attrs(GRID))
    # the layer arrays as xarray appends them
    _to_zarr(tmp_path / "x.zarr", GRID, WAVELENGTHS, None, "radiance", zarr_format)
    x, y = GRID.xy_centres()
    ds = xr.Dataset({n: (("y", "x"), da.full(GRID.shape, np.nan, dtype=np.float32, chunks=(CHUNK, CHUNK)))
                     for n in spec.names}, coords={"y": y, "x": x})
    for n in spec.names:
        ds[n].attrs.update({**layer_attrs(spec, n), **geozarr_attrs(GRID)})
        ds[n].encoding.update({"chunks": (CHUNK, CHUNK), "_FillValue": np.float32(np.nan)})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ds.drop_vars(["x", "y"]).to_zarr(str(tmp_path / "x.zarr"), mode="a", compute=False,
                                         zarr_format=zarr_format, consolidated=True)
    direct, expected = _files(tmp_path / "s.zarr"), _files(tmp_path / "x.zarr")
    for n in spec.names:
        docs = [k for k in expected if k.startswith(f"{n}/")]
        assert docs and all(direct[k] == expected[k] for k in docs), n
    opened = xr.open_zarr(store.path)
    assert set(spec.names) <= set(opened.data_vars)
    # the root keeps what it had (xarray's append replaced it by the layers' items), plus those items
    assert opened.attrs == {**root_before, **layers_metadata(spec)}
    assert opened.attrs["archive_grid"] and store.grid == GRID


@pytest.mark.parametrize("zarr_format", [2, 3])
def test_store_opens_in_xarray_rioxarray_and_gdal(tmp_path, zarr_format):
    import rioxarray  # noqa: F401
    import xarray as xr

    store = MosaicStore.create(tmp_path / "s.zarr", GRID, WAVELENGTHS, BANDS, "radiance", dict(ATTRS), fwhm=FWHM,
                               zarr_format=zarr_format)
    add_zarr_layers(store.path, GRID, _spec(), geozarr_attrs(GRID))
    ds = xr.open_zarr(store.path, decode_coords="all")
    assert ds["radiance"].shape == (len(BANDS), GRID.height, GRID.width)
    assert np.isnan(ds["radiance"][:, :5, :5].values).all() and not ds["saturated"][:5, :5].values.any()
    assert ds.rio.crs.to_epsg() == GRID.epsg and ds.rio.transform() == GRID.transform
    assert np.array_equal(ds["wavelength"].values, WAVELENGTHS) and np.array_equal(ds["band"].values, BANDS)
    assert np.issubdtype(ds["time"].dtype, np.datetime64)   # CF units "seconds since ..." decoded
    if zarr_format == 2:   # GDAL 3.10 (rasterio's wheel) opens Zarr v2 (DESIGN 8)
        import rasterio

        with rasterio.open(f'ZARR:"{store.path}":/radiance') as z:
            assert z.count == len(BANDS) and z.shape == GRID.shape and z.crs.to_epsg() == GRID.epsg
            assert z.transform.almost_equals(GRID.transform, precision=1e-9)
            assert np.isnan(z.read(1, window=((0, 4), (0, 4)))).all()


@pytest.mark.parametrize("epsg", [32616, 32760, 3857, 25832, 2056])
def test_crs_attributes_equal_rioxarrays_without_importing_it(epsg):
    """The Zarr output's ``spatial_ref`` attributes are made without xarray/rioxarray (issue 37:
    their import was a serial second of every Zarr render); they equal rioxarray's ``write_crs``,
    key order included."""
    import rioxarray  # noqa: F401  (registers .rio)
    import xarray as xr

    from archive.outputs.zarr import _crs_attrs

    expected = list(xr.Dataset().rio.write_crs(epsg)["spatial_ref"].attrs.items())
    assert list(_crs_attrs.__wrapped__(epsg)) == expected
