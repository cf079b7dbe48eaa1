"""Band metadata everywhere (issue 12, part 4): the spectral full width at half maximum (``fwhm``)
from the raw headers through sources and collections into every output format.

A simulated 301-band flight (2 nm apart, so the simulator's headers give distinct Pika L widths of
2.5-3.0 nm) is rendered with the real pipeline, three bands picked by ``--wavelengths``, as COG,
ENVI and Zarr. Checked: GDAL reports a COG's wavelengths and widths through its standard IMAGERY
metadata (``CENTRAL_WAVELENGTH_UM``, ``FWHM_UM``, micrometres); GDAL's ENVI driver reads the
ENVI output's ``fwhm``; the Zarr store carries a ``fwhm`` coordinate, CF attributes and the GeoZarr
``proj:`` / ``spatial:`` conventions equal to the grid; a flight without ``fwhm`` writes none; an
ingested flight keeps its ``fwhm`` (and stores from before it was recorded read as None).
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import rasterio
import xarray as xr

from archive.cli import main
from archive.errors import FormatError
from archive.formats.envi import read_header
from archive.params import NavigationParams
from helpers import FOV

GSD = 0.1
BANDS = 301
PICK = "450,700,950"  # nm: three bands with different widths
WIDTH_TOL_UM = 5e-4  # GDAL's ENVI driver prints micrometres with 3 decimals


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    """The simulated flight, and a copy of it whose headers have no ``fwhm``."""
    from archive.simulator.command import simulate_flight

    root = tmp_path_factory.mktemp("bandmeta")
    directory = root / "flight"
    simulate_flight(directory, cubes=2, bands=BANDS, samples=64, lines=150, cubes_per_pass=2, seed=3)
    bare = root / "bare"
    shutil.copytree(directory, bare)
    for hdr in bare.glob("*.hdr"):
        hdr.write_text("".join(line for line in hdr.read_text().splitlines(keepends=True)
                               if not line.startswith("fwhm")))
    return directory, bare


def _render(source, out: Path, scheduler: str, *extra: str) -> None:
    args = ["render", str(source), "--fov", str(FOV), "--gsd", str(GSD), "--wavelengths", PICK,
            "--out", str(out), "--quiet", "--scheduler", scheduler, *extra]
    assert main(args) == 0


@pytest.fixture(scope="module")
def rendered(flight, scheduler, tmp_path_factory):
    """m.{zarr,tif,hdr} of the flight, n.{zarr,tif,hdr} of the copy without fwhm."""
    directory, bare = flight
    folder = tmp_path_factory.mktemp("bandmeta-out")
    for name in ("m.zarr", "m.tif", "m.hdr"):
        _render(directory, folder / name, scheduler)
    for name in ("n.zarr", "n.tif", "n.hdr"):
        _render(bare, folder / name, scheduler)
    return folder


@pytest.fixture(scope="module")
def expected(flight, rendered):
    """(wavelengths nm, fwhm nm) of the rendered bands, from the raw header and the Zarr's band index."""
    directory, _ = flight
    header = read_header(sorted(directory.glob("*.bil.hdr"))[0])
    bands = xr.open_zarr(rendered / "m.zarr")["band"].values
    return np.asarray(header.wavelengths)[bands], np.asarray(header.fwhm)[bands]


# --- the simulator and the sources -----------------------------------------------------------------

def test_simulated_headers_give_pika_l_widths(flight):
    from archive.simulator.sensor import band_fwhm

    directory, bare = flight
    for hdr in sorted(directory.glob("*.bil.hdr")):
        h = read_header(hdr)
        assert h.fwhm is not None and len(h.fwhm) == BANDS
        np.testing.assert_allclose(h.fwhm, band_fwhm(np.asarray(h.wavelengths)))
        assert 2.5 <= min(h.fwhm) < 2.6 and 2.9 < max(h.fwhm) <= 3.0  # Pika L: 2.5-3 nm
    assert read_header(sorted(bare.glob("*.bil.hdr"))[0]).fwhm is None
    # a binned (few-band) sensor: bands as wide as their spacing
    np.testing.assert_allclose(band_fwhm(np.linspace(400.0, 1000.0, 6)), 120.0)


def test_raw_and_memory_sources_carry_fwhm(flight):
    from archive.sources import MemoryFlightSource, RawFlightSource

    directory, bare = flight
    raw = RawFlightSource(directory, NavigationParams())
    assert raw.fwhm == read_header(sorted(directory.glob("*.bil.hdr"))[0]).fwhm
    assert RawFlightSource(bare, NavigationParams()).fwhm is None
    poses = [raw.poses(0)]
    data = [raw.read_bands(0, [0, 1, 2])]
    mem = MemoryFlightSource(data, poses, wavelengths=[400, 402, 404], fwhm=[2.5, 2.6, 2.7])
    assert mem.fwhm == (2.5, 2.6, 2.7) and mem.header(0).fwhm == (2.5, 2.6, 2.7)
    assert MemoryFlightSource(data, poses).fwhm is None
    with pytest.raises(FormatError, match=r"'fwhm' lists 2 values for 3 bands"):
        MemoryFlightSource(data, poses, fwhm=[2.5, 2.6])


def test_wrong_length_fwhm_is_a_format_error_naming_file_and_key(flight, tmp_path):
    directory, _ = flight
    broken = tmp_path / "broken"
    shutil.copytree(directory, broken)
    hdr = sorted(broken.glob("*.bil.hdr"))[1]
    text = re.sub(r"fwhm = \{[^}]*\}", "fwhm = {2.5, 2.6}", hdr.read_text())
    hdr.write_text(text)
    with pytest.raises(FormatError) as err:
        read_header(hdr)
    assert str(hdr) in str(err.value) and "'fwhm' lists 2 values for 301 bands" in str(err.value)
    from archive.sources import RawFlightSource

    with pytest.raises(FormatError, match=re.escape(hdr.name)):
        RawFlightSource(broken, NavigationParams())


def test_ingested_flight_keeps_its_fwhm(flight, scheduler, tmp_path):
    import zarr

    from archive.collection import read_info, read_poses
    from archive.ingest.command import ingest
    from archive.sources import RawFlightSource, open_source

    directory, bare = flight
    raw = RawFlightSource(directory, NavigationParams())
    archive_dir = tmp_path / "archive"
    (result,) = ingest([str(directory)], archive_dir, FOV, progress=False)
    col = open_source(result.cid, NavigationParams(), archive=archive_dir)
    assert col.fwhm == raw.fwhm and col.header(0).fwhm == raw.fwhm
    store = col.store
    np.testing.assert_array_equal(zarr.open_group(store, mode="r")["fwhm"][...], raw.fwhm)
    assert read_poses(store).fwhm == list(raw.fwhm)

    # and through a render from the collection
    _render(result.cid, tmp_path / "c.hdr", scheduler, "--archive", str(archive_dir))
    with_fwhm = read_header(tmp_path / "c.hdr")
    bands = [int(np.argmin(np.abs(np.asarray(raw.wavelengths) - float(w)))) for w in PICK.split(",")]
    np.testing.assert_allclose(with_fwhm.fwhm, np.asarray(raw.fwhm)[bands], atol=1e-4)

    # a store ingested before fwhm was recorded: the cubes' recorded headers, else None
    shutil.rmtree(store / "fwhm")
    assert read_info(store).fwhm == raw.fwhm and read_poses(store).fwhm is None
    group = zarr.open_group(store, mode="r+")
    attrs = dict(group.attrs)
    for cube in attrs["cubes"]:
        del cube["header"]["fwhm"]
    group.attrs.put(attrs)
    assert read_info(store).fwhm is None
    assert open_source(result.cid, NavigationParams(), archive=archive_dir).fwhm is None

    # a flight without fwhm: a NaN array, read back as None
    (bare_result,) = ingest([str(bare)], tmp_path / "archive2", FOV, progress=False)
    assert open_source(bare_result.cid, NavigationParams(), archive=tmp_path / "archive2").fwhm is None


# --- the outputs -----------------------------------------------------------------------------------

def test_cog_imagery_metadata(rendered, expected):
    wl, fwhm = expected
    with rasterio.open(rendered / "m.tif") as ds:
        assert ds.count == 3 and np.isfinite(ds.read(1)).mean() > 0.3
        for b in range(ds.count):
            imagery = ds.tags(b + 1, ns="IMAGERY")
            assert float(imagery["CENTRAL_WAVELENGTH_UM"]) == pytest.approx(wl[b] / 1000.0, abs=1e-9)
            assert float(imagery["FWHM_UM"]) == pytest.approx(fwhm[b] / 1000.0, abs=1e-9)
            tags = ds.tags(b + 1)  # the nm items and the description stay
            assert float(tags["wavelength"]) == pytest.approx(wl[b], abs=1e-4)
            assert float(tags["fwhm"]) == pytest.approx(fwhm[b], abs=1e-4)
            assert ds.descriptions[b].endswith(f"{wl[b]:.1f} nm")
        assert len(set(np.round(fwhm, 4))) == 3  # the check tells the bands apart


def test_gdalinfo_reports_cog_wavelengths(rendered, expected):
    gdalinfo = shutil.which("gdalinfo")
    if gdalinfo is None:
        pytest.skip("no gdalinfo binary")
    info = json.loads(subprocess.run([gdalinfo, "-json", str(rendered / "m.tif")], check=True,
                                     capture_output=True, text=True).stdout)
    wl, fwhm = expected
    for b, band in enumerate(info["bands"]):
        imagery = band["metadata"]["IMAGERY"]
        assert float(imagery["CENTRAL_WAVELENGTH_UM"]) == pytest.approx(wl[b] / 1000.0, abs=1e-9)
        assert float(imagery["FWHM_UM"]) == pytest.approx(fwhm[b] / 1000.0, abs=1e-9)


def test_envi_writes_fwhm_and_gdal_reads_it(rendered, expected):
    wl, fwhm = expected
    text = (rendered / "m.hdr").read_text()
    assert "fwhm = {" in text
    header = read_header(rendered / "m.hdr")
    np.testing.assert_allclose(header.fwhm, fwhm, atol=1e-4)
    np.testing.assert_allclose(header.wavelengths, wl, atol=1e-4)
    with rasterio.open(rendered / "m") as ds:
        assert ds.driver == "ENVI"
        envi = ds.tags(ns="ENVI")
        np.testing.assert_allclose([float(v) for v in envi["fwhm"].strip("{}").split(",")], fwhm, atol=1e-4)
        for b in range(ds.count):
            imagery = ds.tags(b + 1, ns="IMAGERY")
            assert float(imagery["CENTRAL_WAVELENGTH_UM"]) == pytest.approx(wl[b] / 1000.0, abs=WIDTH_TOL_UM)
            assert float(imagery["FWHM_UM"]) == pytest.approx(fwhm[b] / 1000.0, abs=WIDTH_TOL_UM)


def test_zarr_cf_and_geozarr_attributes(rendered, expected):
    wl, fwhm = expected
    ds = xr.open_zarr(rendered / "m.zarr", decode_coords="all")
    np.testing.assert_allclose(ds["fwhm"].values, fwhm)
    np.testing.assert_allclose(ds["wavelength"].values, wl)
    assert ds["fwhm"].dims == ("band",) and ds["fwhm"].attrs["units"] == "nm"
    assert "width" in ds["fwhm"].attrs["long_name"]
    assert ds["wavelength"].attrs == {"units": "nm", "long_name": "band centre wavelength",
                                      "standard_name": "radiation_wavelength"}
    for name, axis in (("x", "X"), ("y", "Y")):
        attrs = ds[name].attrs
        assert attrs["units"] == "m" and attrs["axis"] == axis
        assert attrs["standard_name"] == f"projection_{name}_coordinate" and attrs["long_name"]
    assert ds.attrs["Conventions"].startswith("CF-")
    for name in ("radiance", "saturated"):
        assert ds[name].encoding.get("grid_mapping", ds[name].attrs.get("grid_mapping")) == "spatial_ref"
        assert ds[name].attrs["long_name"]

    # GeoZarr proj: / spatial: on the root and on the data arrays, equal to the grid
    transform, crs = ds.rio.transform(), ds.rio.crs
    height, width = ds.sizes["y"], ds.sizes["x"]
    with rasterio.open(rendered / "m.tif") as cog:  # the same grid as the COG
        assert tuple(cog.transform)[:6] == tuple(transform)[:6] and cog.crs == crs
    bbox = [transform.c, transform.f + height * transform.e, transform.c + width * transform.a, transform.f]
    for attrs in (ds.attrs, ds["radiance"].attrs, ds["saturated"].attrs):
        assert {c["name"] for c in attrs["zarr_conventions"]} == {"proj:", "spatial:"}
        assert attrs["proj:code"] == f"EPSG:{crs.to_epsg()}"
        assert attrs["spatial:dimensions"] == ["y", "x"]
        assert attrs["spatial:transform"] == list(transform)[:6]
        assert attrs["spatial:shape"] == [height, width]
        np.testing.assert_allclose(attrs["spatial:bbox"], bbox)
        assert attrs["spatial:registration"] == "pixel"
    assert rasterio.crs.CRS.from_wkt(ds.attrs["proj:wkt2"]) == crs
    # the x/y pixel centres agree with the transform
    np.testing.assert_allclose(ds["x"].values[:2], [transform.c + 0.5 * transform.a, transform.c + 1.5 * transform.a])
    np.testing.assert_allclose(ds["y"].values[0], transform.f + 0.5 * transform.e)


def test_a_source_without_fwhm_writes_none(rendered):
    with rasterio.open(rendered / "n.tif") as ds:
        for b in range(ds.count):
            imagery = ds.tags(b + 1, ns="IMAGERY")
            assert "CENTRAL_WAVELENGTH_UM" in imagery and "FWHM_UM" not in imagery
            assert "fwhm" not in ds.tags(b + 1)
        assert "fwhm" not in ds.tags()
    text = (rendered / "n.hdr").read_text()
    assert "fwhm" not in text and "wavelength = {" in text
    assert read_header(rendered / "n.hdr").fwhm is None
    ds = xr.open_zarr(rendered / "n.zarr")
    assert "fwhm" not in ds.variables and "wavelength" in ds.coords


def test_envi_fwhm_follows_wavelength_units_and_length_is_checked(tmp_path):
    from archive.errors import InputError
    from archive.formats.envi import write_envi

    data = np.zeros((2, 3, 4), np.uint16)
    path = write_envi(tmp_path / "c.bil", data, {"wavelength units": "Micrometers", "wavelength": [0.5, 0.6],
                                                 "fwhm": [0.0025, 0.003]}, interleave="bil")
    header = read_header(path)
    assert header.wavelengths == pytest.approx((500.0, 600.0)) and header.fwhm == pytest.approx((2.5, 3.0))
    with pytest.raises(InputError, match="metadata 'fwhm' has 3 values for 2 bands"):
        write_envi(tmp_path / "d.bil", data, {"fwhm": [1.0, 2.0, 3.0]})
