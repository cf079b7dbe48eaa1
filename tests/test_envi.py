"""ENVI headers and cubes: round trips, real Resonon/Spectronon headers, bad inputs."""

from __future__ import annotations

import pickle
import tracemalloc
import zipfile
from pathlib import Path

import numpy as np
import pytest

from archive.errors import FormatError, InputError, MissingInputError
from archive.formats.envi import (EnviCube, data_path_for, parse_header_text, read_header,
                                 write_envi)

AVSTJOHN = "avstjohn__hyperspectral_analysis/20160228_17h18m_pika_L_1.bil.hdr"
BURUNDUKE = "Burunduke__gaps_filler/manual_Pika_L_28.bil.hdr"
DCP = "john-waczak__RobotTeam.jl/FLMS152151_Sept2019.dcp"


def _spectronon(samples: Path) -> Path:
    return next((samples / "tnigon__hs_process").glob("*.bip.hdr"))


def _cube(dtype: str, shape=(3, 5, 7)) -> np.ndarray:
    rng = np.random.default_rng(1)
    if np.dtype(dtype).kind == "f":
        return rng.normal(100.0, 30.0, shape).astype(dtype)
    info = np.iinfo(dtype)
    return rng.integers(info.min, info.max, shape, endpoint=True).astype(dtype)


@pytest.mark.parametrize("interleave", ["bil", "bip", "bsq"])
@pytest.mark.parametrize("dtype", ["uint16", "int16", "float32", "uint8", "float64"])
@pytest.mark.parametrize("byte_order", [0, 1])
@pytest.mark.parametrize("offset", [0, 128])
def test_round_trip(tmp_path, interleave, dtype, byte_order, offset):
    data = _cube(dtype)
    path = write_envi(tmp_path / f"c.{interleave}", data, {"wavelength": [400.5, 500.0, 600.25]},
                      interleave=interleave, byte_order=byte_order, header_offset=offset)
    assert path == tmp_path / f"c.{interleave}"
    assert (tmp_path / f"c.{interleave}.hdr").is_file()
    assert path.stat().st_size == offset + data.nbytes
    assert sorted(p.name for p in tmp_path.iterdir()) == [f"c.{interleave}", f"c.{interleave}.hdr"]
    cube = EnviCube(path)
    h = cube.header
    assert (h.bands, h.lines, h.samples) == (3, 5, 7)
    assert (h.interleave, h.byte_order, h.header_offset) == (interleave, byte_order, offset)
    assert h.wavelengths == (400.5, 500.0, 600.25)
    full = cube.read()
    assert full.dtype == np.dtype(dtype) and full.dtype.isnative
    np.testing.assert_array_equal(full, data)
    for b in range(3):
        band = cube.band(b)
        assert band.shape == (5, 7) and band.dtype.isnative
        np.testing.assert_array_equal(band, full[b])
    np.testing.assert_array_equal(cube.bands([2, 0]), data[[2, 0]])
    # opening by the header path gives the same cube
    np.testing.assert_array_equal(EnviCube(h.path).band(1), data[1])


def test_byte_order_on_disk(tmp_path):
    data = np.array([[[1, 258]]], dtype=np.uint16)
    write_envi(tmp_path / "big.bsq", data, byte_order=1)
    write_envi(tmp_path / "little.bsq", data, byte_order=0)
    assert (tmp_path / "big.bsq").read_bytes() == b"\x00\x01\x01\x02"
    assert (tmp_path / "little.bsq").read_bytes() == b"\x01\x00\x02\x01"


@pytest.mark.parametrize("interleave", ["bsq", "bil"])
def test_band_does_not_read_the_whole_file(tmp_path, interleave):
    # 400 MB sparse data file: reading it whole would allocate 400 MB, one band is 4 MB
    hdr = _write_header(tmp_path / f"big.{interleave}.hdr", samples=2000, lines=1000, bands=100,
                        interleave=interleave)
    with open(tmp_path / f"big.{interleave}", "wb") as f:
        f.truncate(2000 * 1000 * 100 * 2)
    cube = EnviCube(hdr)
    tracemalloc.start()
    try:
        band = cube.band(57)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert band.shape == (1000, 2000) and not band.any()
    assert peak < 3 * band.nbytes


def test_other_data_names_use_envi_standard_header(tmp_path):
    data = _cube("uint16", (4, 6, 5))
    path = write_envi(tmp_path / "x.img", data, interleave="bsq")
    assert (tmp_path / "x.hdr").is_file()
    cube = EnviCube(path)
    assert data_path_for(cube.header) == path
    np.testing.assert_array_equal(cube.band(3), data[3])


def test_explicit_hdr_path_and_metadata_pass_through(tmp_path):
    meta = {"map info": ["UTM", 1.0, 1.0, 441342.687073, 4855944.81177, 0.04, 0.04, 15, "T",
                         "WGS-84", "units  meters", "rotation  0.000"],
            "description": "a, b {nested} c", "flip radiometric calibration": True,
            "spatial window": (500, 1400), "framerate": 120.004800192, "gain": 8,
            "label": "x.bil", "samples": 99}  # structural keys in metadata are ignored
    data_path = write_envi(tmp_path / "out.hdr", np.zeros((2, 3, 4), np.float32), meta,
                           interleave="bil")
    assert data_path == tmp_path / "out"
    h = read_header(tmp_path / "out.hdr")
    assert h.samples == 4
    assert h.metadata["map info"] == meta["map info"]
    assert h.metadata["description"] == "a, b {nested} c"
    assert h.metadata["spatial window"] == (500, 1400)
    assert h.flip_radiometric_calibration is True
    assert h.framerate == 120.004800192 and h.gain == 8.0
    assert h.metadata["label"] == "x.bil"
    assert data_path_for(h) == tmp_path / "out"


def test_avstjohn_2016_header(resonon_samples):
    h = read_header(resonon_samples / AVSTJOHN)
    assert (h.samples, h.lines, h.bands) == (900, 2114, 285)
    assert (h.interleave, h.data_type, h.byte_order, h.header_offset) == ("bil", 12, 0, 0)
    assert h.dtype == np.dtype("<u2")
    assert h.bit_depth == 12
    assert h.flip_radiometric_calibration is True
    assert h.framerate == pytest.approx(120.0048, abs=1e-4)
    assert h.shutter == 8.233 and h.gain == 8.0
    assert (h.sample_binning, h.spectral_binning) == (1, 2)
    assert len(h.wavelengths) == 285
    assert h.wavelengths[0] == 398.047 and h.wavelengths[-1] == 1001.263
    assert h.metadata["spatial window"] == (500, 1400)
    assert h.metadata["band window"] == (328, 898)
    assert h.metadata["timestamp"] == "02/28/2016-17h18m"
    assert h.metadata["direction"] == "logo left"
    assert h.metadata["reflectance scale factor"] == 4095


def test_burunduke_2023_header(resonon_samples):
    h = read_header(resonon_samples / BURUNDUKE)
    assert (h.samples, h.lines, h.bands) == (900, 2000, 200)
    assert h.framerate == 249.0 and isinstance(h.metadata["framerate"], int)
    assert h.flip_radiometric_calibration is False
    assert (h.sample_binning, h.spectral_binning) == (1, 3)
    assert h.shutter == 3.742 and h.gain == 16.0
    assert h.bit_depth == 12  # from ceiling = 4095
    assert h.metadata["imager serial number"] == "Pika L-536"
    assert h.metadata["timestamp"] == "06/26/2023-09h03m18s"
    assert len(h.wavelengths) == 200 and h.wavelengths[-1] == 1030.66
    assert np.all(np.diff(h.wavelengths) > 0)


def test_spectronon_header(resonon_samples):
    path = _spectronon(resonon_samples)
    h = read_header(path)
    assert (h.samples, h.lines, h.bands, h.interleave, h.data_type) == (1827, 617, 240, "bip", 4)
    assert len(h.wavelengths) == 240 and h.wavelengths[:2] == (394.6, 396.6528)
    mi = h.metadata["map info"]
    assert mi[0] == "UTM" and mi[3] == 441342.687073 and mi[5] == 0.04 and mi[7] == 15
    assert mi[-2:] == ["units  meters", "rotation  0.000"]
    history = h.metadata["history"]
    assert history.startswith("input cube -> Radiance Conversion<SpecGroup>[")
    assert history.endswith("value:1.0 (floats)>]")
    assert "J:\\\\\\\\Shared Work" in history  # doubled backslashes kept verbatim
    assert "'Sync Offset (s)' value:-0.05" in history
    assert h.metadata["label"] == "Wells_rep2-7_20180628_16h56m_pika_gige_7.bil"
    assert h.framerate is None and h.sample_binning == 1


def test_spectronon_metadata_round_trip(tmp_path, resonon_samples):
    h = read_header(_spectronon(resonon_samples))
    data = np.zeros((240, 2, 3), np.float32)
    write_envi(tmp_path / "r.bip", data, h.metadata, interleave="bip")
    h2 = read_header(tmp_path / "r.bip")
    assert (h2.samples, h2.lines, h2.bands) == (3, 2, 240)
    assert h2.wavelengths == h.wavelengths
    for key in ("history", "map info", "label", "reflectance scale factor"):
        assert h2.metadata[key] == h.metadata[key], key


def test_dcp_members_parse(resonon_samples):
    with zipfile.ZipFile(resonon_samples / DCP) as zf:
        raw = zf.read("gain.spec.hdr")
        assert b"\r\n" in raw
        meta = parse_header_text(raw.decode(), "gain.spec.hdr")
        assert meta["bands"] == 2048 and meta["data type"] == 5 and "byte order" not in meta
        assert meta["shutter"] == 5.7 and len(meta["wavelength"]) == 2048
        offset_meta = parse_header_text(zf.read("offset.spec.hdr").decode(), "offset.spec.hdr")
        assert offset_meta["data type"] == 4
        gain = np.frombuffer(zf.read("gain.spec"), dtype="<f8")
        assert gain.size == 2048 and np.isfinite(gain).all()


def test_crlf_bom_and_brace_forms(tmp_path):
    text = ("\ufeffENVI\r\nsamples = 2\r\nlines= 1\r\nbands =3\r\ndata type = 4\r\n"
            "interleave = BSQ\r\nwavelength= {\r\n 400,\r\n 500,\r\n 600}\r\n"
            "history = x -> y<a>[b, 'c': D:\\\\d]\r\nspatial window = (1, 2)\r\n"
            "description = {line one,\r\n line {two}}\r\n; comment\r\nsome stray line\r\n")
    hdr = tmp_path / "a.bsq.hdr"
    hdr.write_bytes(text.encode("utf-8"))
    (tmp_path / "a.bsq").write_bytes(np.arange(6, dtype="<f4").tobytes())
    cube = EnviCube(tmp_path / "a.bsq")
    h = cube.header
    assert h.interleave == "bsq" and h.byte_order == 0 and h.header_offset == 0
    assert h.wavelengths == (400.0, 500.0, 600.0)
    assert h.metadata["history"] == "x -> y<a>[b, 'c': D:\\\\d]"
    assert h.metadata["description"] == "line one,\n line {two}"
    np.testing.assert_array_equal(cube.band(2), [[4.0, 5.0]])


def _write_header(path: Path, **keys) -> Path:
    base = {"samples": 4, "lines": 3, "bands": 2, "data type": 12, "interleave": "bil",
            "byte order": 0}
    base.update(keys)
    text = "ENVI\n" + "".join(f"{k} = {v}\n" for k, v in base.items() if v is not None)
    path.write_text(text)
    return path


@pytest.mark.parametrize("key", ["samples", "lines", "bands", "data type", "interleave"])
def test_missing_required_key(tmp_path, key):
    hdr = _write_header(tmp_path / "m.bil.hdr", **{key: None})
    with pytest.raises(FormatError, match=rf"m\.bil\.hdr.*'{key}'"):
        read_header(hdr)


@pytest.mark.parametrize("keys, words", [({"data type": 7}, "data type"),
                                         ({"interleave": "bxl"}, "interleave"),
                                         ({"byte order": 2}, "byte order"),
                                         ({"samples": "many"}, "samples")])
def test_bad_values(tmp_path, keys, words):
    hdr = _write_header(tmp_path / "v.bil.hdr", **keys)
    with pytest.raises(FormatError, match=rf"v\.bil\.hdr.*{words}"):
        read_header(hdr)


def test_not_envi_and_unclosed_brace(tmp_path):
    bad = tmp_path / "n.hdr"
    bad.write_text("samples = 3\n")
    with pytest.raises(FormatError, match=r"n\.hdr.*ENVI"):
        read_header(bad)
    unclosed = tmp_path / "u.hdr"
    unclosed.write_text("ENVI\nsamples = 3\nwavelength = {1, 2,\n3\n")
    with pytest.raises(FormatError, match=r"u\.hdr.*wavelength.*never"):
        read_header(unclosed)


def test_missing_files(tmp_path):
    with pytest.raises(MissingInputError, match=r"nothing\.bil\.hdr"):
        read_header(tmp_path / "nothing.bil")
    _write_header(tmp_path / "h.bil.hdr")
    with pytest.raises(MissingInputError, match=r"h\.bil"):
        EnviCube(tmp_path / "h.bil.hdr")


@pytest.mark.parametrize("delta, word", [(-2, "truncated"), (+6, "larger than expected")])
def test_data_size_mismatch(tmp_path, delta, word):
    _write_header(tmp_path / "s.bil.hdr", **{"header offset": 16})
    expected = 16 + 4 * 3 * 2 * 2
    (tmp_path / "s.bil").write_bytes(b"\0" * (expected + delta))
    with pytest.raises(FormatError, match=rf"s\.bil: data file is {word}: {expected + delta} "
                                          rf"bytes.*needs {expected} bytes"):
        EnviCube(tmp_path / "s.bil")


def test_band_index_and_write_checks(tmp_path):
    path = write_envi(tmp_path / "w.bsq", np.zeros((2, 2, 2), np.uint16))
    with pytest.raises(InputError, match="band 2 out of range"):
        EnviCube(path).band(2)
    with pytest.raises(InputError, match="3-D"):
        write_envi(tmp_path / "x.bsq", np.zeros((2, 2), np.uint16))
    with pytest.raises(InputError, match="no ENVI data type"):
        write_envi(tmp_path / "x.bsq", np.zeros((1, 2, 2), np.int64))
    with pytest.raises(InputError, match="2 values for 1 bands"):
        write_envi(tmp_path / "x.bsq", np.zeros((1, 2, 2), np.uint16), {"wavelength": [1, 2]})
    assert not (tmp_path / "x.bsq").exists()


def test_cube_pickles_without_open_files(tmp_path):
    data = _cube("int16", (2, 3, 4))
    cube = EnviCube(write_envi(tmp_path / "p.bil", data, interleave="bil", byte_order=1))
    clone = pickle.loads(pickle.dumps(cube))
    np.testing.assert_array_equal(clone.band(1), data[1])
    assert clone.header.dtype == np.dtype(">i2") and clone.shape == (2, 3, 4)
