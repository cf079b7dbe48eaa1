"""Output writers on a small synthetic tiled mosaic: reopened with xarray and rasterio."""

from __future__ import annotations

import numpy as np
import pytest
import rasterio
import xarray as xr
from PIL import Image

from archive.errors import InputError, OutputExistsError
from archive.grid import Grid
from archive.outputs.base import CHUNK
from archive.outputs.publish import Output
from archive.outputs.quicklook import quicklook_bands
from archive.outputs.registry import output_format
from archive.outputs.zarr import MosaicStore
from mosaic_writing import Tile, write_mosaic, write_quicklook, write_tile, write_values

# 1300 x 1100 px: 2 x 2 chunks with ragged edges; big enough for COG overviews (512 px blocks).
GRID = Grid(epsg=32616, gsd=0.5, x0=771000.0, y0=3891500.0, width=1100, height=1300)
# For tests of file handling only: one small ragged tile.
SMALL = Grid(epsg=32616, gsd=0.5, x0=771000.0, y0=3891500.0, width=300, height=200)
WAVELENGTHS = [452.5, 548.25, 641.0]
BANDS = [3, 10, 17]


def _mosaic(grid: Grid = GRID) -> tuple[np.ndarray, np.ndarray]:
    """(3, height, width) float32 with NaN corners and values encoding (band, row, col); saturation mask."""
    b, r, c = np.meshgrid(np.arange(3), np.arange(grid.height), np.arange(grid.width), indexing="ij")
    values = (1000.0 * b + r + c / 2048.0).astype(np.float32)
    values[:, : grid.height // 6, : grid.width // 4] = np.nan
    values[:, r[0] + c[0] > 0.95 * (grid.height + grid.width)] = np.nan
    saturated = np.zeros(grid.shape, bool)
    saturated[grid.height // 3:grid.height // 3 + 10, grid.width // 2:grid.width // 2 + 50] = True
    return values, saturated


def _tiles(values, saturated, fail_after: int | None = None):
    """Tiles of one band each (chunk-aligned), optionally raising after some of them."""
    n = 0
    grid = GRID if values.shape[1:] == GRID.shape else SMALL
    for row0, col0, g in grid.tiles(CHUNK):
        for band in range(values.shape[0]):
            if fail_after is not None and n == fail_after:
                raise RuntimeError("injected failure")
            sl = np.s_[row0:row0 + g.height, col0:col0 + g.width]
            yield Tile(band, row0, col0, values[band:band + 1][(slice(None),) + sl], saturated[sl])
            n += 1


def _write(path, grid: Grid = GRID, **kw):
    values, saturated = _mosaic(grid)
    write_mosaic(path, grid, _tiles(values, saturated), wavelengths=WAVELENGTHS, band_indices=BANDS, **kw)
    return values, saturated


def _same(a, b) -> None:
    np.testing.assert_array_equal(np.isnan(a), np.isnan(b))
    np.testing.assert_array_equal(np.nan_to_num(a, nan=-1), np.nan_to_num(b, nan=-1))


def test_output_format_by_suffix(tmp_path):
    assert output_format("a.zarr").name == "zarr" and output_format("a.TIF").name == "cog"
    assert output_format("a.tiff").name == "cog" and output_format("a.hdr").name == "envi"
    with pytest.raises(InputError, match=r"\.png"):
        output_format(tmp_path / "a.png")


def test_zarr_roundtrip_with_crs_transform_wavelengths(tmp_path):
    out = tmp_path / "m.zarr"
    values, saturated = _write(out)
    ds = xr.open_zarr(out, decode_coords="all")
    assert ds.rio.crs.to_epsg() == 32616
    assert tuple(ds.rio.transform())[:6] == tuple(GRID.transform)[:6]
    assert ds["radiance"].dims == ("band", "y", "x")
    assert ds["radiance"].dtype == np.float32
    assert ds["radiance"].encoding["chunks"] == (1, CHUNK, CHUNK)
    np.testing.assert_allclose(ds["wavelength"].values, WAVELENGTHS)
    assert list(ds["band"].values) == BANDS
    # pixel centres
    assert ds.x.values[0] == GRID.x0 + 0.25 and ds.y.values[0] == GRID.y0 - 0.25
    _same(ds["radiance"].values, values)
    np.testing.assert_array_equal(ds["saturated"].values, saturated.astype(np.uint8))
    assert ds["saturated"].dtype == np.uint8
    assert not list(tmp_path.glob(".*"))  # no temporaries left


def test_unwritten_chunks_read_as_nan(tmp_path):
    store = MosaicStore.create(tmp_path / "s.zarr", GRID, WAVELENGTHS, BANDS, "dn")
    write_values(store, 1, 1024, 0, np.ones((1, GRID.height - 1024, CHUNK), np.float32))
    ds = xr.open_zarr(tmp_path / "s.zarr", decode_coords="all")
    assert np.isnan(ds["dn"].values[0]).all()
    assert np.nansum(ds["dn"].values[1]) == (GRID.height - 1024) * CHUNK
    assert int(ds["saturated"].values.sum()) == 0
    with pytest.raises(ValueError, match="not aligned"):
        write_values(store, 0, 512, 0, np.ones((1, 512, CHUNK), np.float32))


def test_cog_is_tiled_with_overviews_and_metadata(tmp_path):
    out = tmp_path / "m.tif"
    values, _ = _write(out)
    with rasterio.open(out) as ds:
        assert ds.crs.to_epsg() == 32616
        assert tuple(ds.transform)[:6] == tuple(GRID.transform)[:6]
        assert ds.count == 3 and ds.dtypes == ("float32",) * 3
        assert np.isnan(ds.nodata)
        assert ds.block_shapes == [(512, 512)] * 3
        assert ds.overviews(1) == [2, 4]
        structure = ds.tags(ns="IMAGE_STRUCTURE")
        assert structure["LAYOUT"] == "COG" and structure["INTERLEAVE"] == "BAND"
        assert structure["COMPRESSION"] == "ZSTD" and structure["PREDICTOR"] == "3"
        assert ds.descriptions == ("452.5 nm", "548.2 nm", "641.0 nm")
        assert float(ds.tags(2)["wavelength"]) == 548.25
        assert ds.tags()["wavelength"] == "{452.5000, 548.2500, 641.0000}"
        _same(ds.read(), values)
        ov = ds.read(1, out_shape=(GRID.height // 2, GRID.width // 2))  # from the first overview
        assert np.isnan(ov[0, 0]) and np.isfinite(ov[-100, 300])
    # GDAL's COG ghost header (IFDs before data) sits at the start of the file.
    head = out.read_bytes()[:400]
    assert b"GDAL_STRUCTURAL_METADATA" in head and b"LAYOUT=IFDS_BEFORE_DATA" in head
    assert not list(tmp_path.glob(".*"))


def test_envi_bsq_map_info_and_values(tmp_path):
    out = tmp_path / "m.hdr"
    values, _ = _write(out)
    data = tmp_path / "m"
    assert data.stat().st_size == values.size * 4
    text = out.read_text()
    assert "interleave = bsq" in text and "data type = 4" in text
    assert "map info = {UTM, 1, 1, 771000.0, 3891500.0, 0.5, 0.5, 16, North, WGS-84, units=Meters}" in text
    assert "wavelength = {452.5000, 548.2500, 641.0000}" in text
    assert "coordinate system string = {PROJCS[" in text
    raw = np.fromfile(data, dtype="<f4").reshape(values.shape)
    _same(raw, values)
    with rasterio.open(data) as ds:  # GDAL's ENVI driver finds m.hdr
        assert ds.driver == "ENVI"
        assert ds.crs.to_epsg() == 32616
        assert tuple(ds.transform)[:6] == tuple(GRID.transform)[:6]
        assert np.isnan(ds.nodata)
        _same(ds.read(2), values[1])


def test_quicklook_rgb_stretch(tmp_path):
    ql = tmp_path / "q.png"
    values, _ = _write(tmp_path / "m.zarr", quicklook=ql)
    img = np.asarray(Image.open(ql))
    assert img.shape == (GRID.height, GRID.width, 4)
    covered = np.isfinite(values[0])
    np.testing.assert_array_equal(img[..., 3] == 255, covered)
    assert (img[~covered, :3] == 0).all()
    # red = band nearest 640 nm = the last; values grow with row: top dark, bottom bright (stretched)
    red = img[..., 0][covered]
    assert 0.015 < np.mean(red == 0) < 0.03 and 0.015 < np.mean(red == 255) < 0.03
    assert img[300, 500, 0] < img[700, 500, 0] < img[1000, 500, 0]
    assert quicklook_bands(WAVELENGTHS, 3) == (2, 1, 0)
    assert quicklook_bands([900.0, 950.0, 1000.0, 1050.0], 4) == (3, 2, 0)
    assert quicklook_bands(None, 1) == (0, 0, 0)


def test_quicklook_is_decimated(tmp_path):
    ql = tmp_path / "q.png"
    values, saturated = _mosaic()
    store = MosaicStore.create(tmp_path / "s.zarr", GRID, WAVELENGTHS, BANDS)
    for t in _tiles(values, saturated):
        write_tile(store, t)

    write_quicklook(store, ql, max_size=512)
    assert Image.open(ql).size == (367, 434)  # every 3rd pixel of 1100 x 1300


@pytest.mark.parametrize("name", ["m.zarr", "m.tif", "m.hdr"])
def test_existing_output_is_refused_then_replaced_with_overwrite(tmp_path, name):
    out = tmp_path / name
    _write(out, SMALL)
    before = sorted(p.name for p in tmp_path.iterdir())
    with pytest.raises(OutputExistsError, match="--overwrite"):
        _write(out, SMALL)
    _write(out, SMALL, overwrite=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == before


@pytest.mark.parametrize("name", ["m.zarr", "m.tif", "m.hdr"])
def test_failure_midway_leaves_nothing(tmp_path, name):
    values, saturated = _mosaic()  # 2 x 2 chunks x 3 bands: fails after 5 of 12 tiles
    with pytest.raises(RuntimeError, match="injected"):
        write_mosaic(tmp_path / "new" / name, GRID, _tiles(values, saturated, fail_after=5),
                     wavelengths=WAVELENGTHS, band_indices=BANDS, quicklook=tmp_path / "q.png")
    assert list(tmp_path.iterdir()) == []  # not even the directory it made


def test_failure_with_overwrite_keeps_the_old_output(tmp_path):
    out = tmp_path / "m.tif"
    values, _ = _write(out, SMALL)
    with pytest.raises(RuntimeError, match="injected"):
        write_mosaic(out, SMALL, _tiles(values * 0, values[0] > 0, fail_after=2), wavelengths=WAVELENGTHS,
                     band_indices=BANDS, overwrite=True)
    assert [p.name for p in tmp_path.iterdir()] == ["m.tif"]
    with rasterio.open(out) as ds:
        _same(ds.read(), values)


def test_bad_quicklook_name(tmp_path):
    with pytest.raises(InputError, match="png"):
        Output(tmp_path / "m.tif", quicklook=tmp_path / "q.jpg")


def test_format_objects_and_their_spellings(tmp_path):
    """Issue 31: one object per format, found by suffix (:func:`output_format`) or by any word a user
    types after --format (:func:`format_named`); each says its files, sidecars, provenance sibling, sink."""
    import pickle
    from pathlib import Path

    from archive.outputs.cog import CogSink
    from archive.outputs.envi import EnviSink
    from archive.outputs.registry import FORMATS, format_named

    assert [f.name for f in FORMATS] == ["zarr", "cog", "envi"]
    for word, name, suffix in [("zarr", "zarr", ".zarr"), ("tif", "cog", ".tif"), ("TIFF", "cog", ".tif"),
                               ("cog", "cog", ".tif"), ("hdr", "envi", ".hdr"), ("envi", "envi", ".hdr")]:
        fmt = format_named(word)
        assert (fmt.name, fmt.suffix) == (name, suffix) and output_format(f"a{suffix}") is fmt
        assert format_named(fmt) is fmt and pickle.loads(pickle.dumps(fmt)) == fmt
    with pytest.raises(InputError, match=r"--format: unknown output format 'gtiff' \(use one of zarr, cog, tif"):
        format_named("gtiff")
    zarr_, cog, envi = FORMATS
    assert (zarr_.sink, cog.sink, envi.sink) == (MosaicStore, CogSink, EnviSink)
    d = Path("d")
    assert envi.files(d / "m.hdr") == [d / "m", d / "m.hdr"] and envi.sidecars(d / "m.hdr") == [d / "m"]
    assert envi.sibling(d / "m.hdr") == d / "m_provenance.hdr" and cog.sibling(d / "m.tif") == d / "m_provenance.tif"
    assert cog.files(d / "m.tif") == [d / "m.tif"] and zarr_.sibling(d / "m.zarr") is None
    assert (zarr_.media_type, envi.media_type) == ("application/vnd+zarr", "image/x-envi")


@pytest.mark.parametrize("zarr_format", [2, 3])
def test_zarr_item_says_the_version_written(tmp_path, zarr_format):
    """The STAC Item of a Zarr output names the Zarr version of the store (v2 by default; the title
    said v3 for every store before issue 31)."""
    from datetime import UTC, datetime

    from archive.catalog.product import product_item

    from archive.outputs.base import OutputMeta

    out = tmp_path / "m.zarr"
    output = Output(out, zarr_format=zarr_format)
    try:
        output.sink(OutputMeta(SMALL, (3,), zarr_format=zarr_format))   # no tile written: all NaN
        output.finalize()
    finally:
        output.cleanup()
    when = datetime(2024, 6, 12, 16, tzinfo=UTC)
    item = product_item(out, fmt=output_format(out), grid=SMALL, band_indices=[3], wavelengths=None, fwhm=None,
                        variable="radiance", attrs={}, start=when, end=when, sources=["f"], command="archive render",
                        request={})
    title = item["assets"]["data"]["title"]
    assert title.startswith(f"radiance (Zarr v{zarr_format}, variable 'radiance'"), title
    assert item["properties"]["archive:format"] == "zarr"
