"""Radiometric calibration packs (.icp): round trip, dark selection, binning, flip, bad inputs."""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np
import pytest

from archive.errors import FormatError, MissingInputError
from archive.formats.envi import read_header, write_envi
from archive.formats.icp import Calibration, DarkFrame, read_icp, response, write_icp

BANDS, SAMPLES = 8, 12
WAVELENGTHS = tuple(400.0 + 10.0 * k for k in range(BANDS))


def _calibration(gain_shutters=((0.0, 5.0), (8.0, 20.0), (10.0, 8.2))) -> Calibration:
    rng = np.random.default_rng(7)
    gain = rng.uniform(0.01, 0.02, (BANDS, SAMPLES))
    darks = tuple(DarkFrame(g, s, rng.integers(50, 200, (BANDS, SAMPLES)).astype(np.float64))
                  for g, s in gain_shutters)
    return Calibration(None, gain, 3.0, 0.0, WAVELENGTHS, darks)


def _cube_header(tmp_path: Path, samples: int, bands: int, wavelengths, **meta):
    meta = {"gain": 8, "shutter": 8.2, **meta}
    if wavelengths is not None:
        meta["wavelength"] = list(wavelengths)
    path = write_envi(tmp_path / "cube.bil", np.zeros((bands, 2, samples), np.uint16), meta,
                      interleave="bil")
    return read_header(path)


def test_response():
    assert response(3.0, 0.0, 3.0, 0.0) == 1.0
    assert response(6.0, 20.0, 3.0, 0.0) == pytest.approx(20.0)
    assert response(1.5, -6.0, 3.0, 0.0) == pytest.approx(0.5 * 10 ** (-0.3))


def test_round_trip(tmp_path):
    cal = _calibration(((0.0, 5.0), (8.0, 1.23456789)))
    write_icp(tmp_path / "cal.icp", cal)
    with zipfile.ZipFile(tmp_path / "cal.icp") as zf:
        names = set(zf.namelist())
    assert {"gain.bip", "gain.bip.hdr",
            "offset_8bands_4095ceiling_0gain_12samples_5shutter.bip",
            "offset_8bands_4095ceiling_8gain_12samples_1.23457shutter.bip.hdr"} <= names
    back = read_icp(tmp_path / "cal.icp")
    assert back.path == tmp_path / "cal.icp"
    np.testing.assert_array_equal(back.gain, cal.gain)
    assert back.gain.dtype == np.float64 and back.gain.shape == (BANDS, SAMPLES)
    assert (back.shutter_cal, back.gain_cal, back.wavelengths) == (3.0, 0.0, WAVELENGTHS)
    assert len(back.darks) == 2
    by_gain = {d.gain_db: d for d in back.darks}
    assert by_gain[8.0].shutter_ms == 1.23456789  # exact value from the frame's own header
    for dark in cal.darks:
        np.testing.assert_array_equal(by_gain[dark.gain_db].data, dark.data)


def test_non_integer_darks_round_trip(tmp_path):
    cal = _calibration(((4.0, 2.0),))
    cal = Calibration(None, cal.gain, 2.5, 3.0, None, (DarkFrame(4.0, 2.0, cal.darks[0].data + 0.25),))
    write_icp(tmp_path / "f.icp", cal)
    back = read_icp(tmp_path / "f.icp")
    np.testing.assert_array_equal(back.darks[0].data, cal.darks[0].data)
    assert back.wavelengths is None and back.gain_cal == 3.0


def test_select_dark_prefers_gain_then_shutter():
    cal = _calibration(((0.0, 8.0), (8.0, 20.0), (10.0, 8.2), (8.0, 5.0)))
    # gain 8.5: gain 8 is closer than gain 10, although the gain-10 frame has the exact shutter
    chosen = cal.select_dark(8.5, 8.2)
    assert (chosen.gain_db, chosen.shutter_ms) == (8.0, 5.0)
    chosen = cal.select_dark(8.0, 15.0)
    assert (chosen.gain_db, chosen.shutter_ms) == (8.0, 20.0)
    assert cal.select_dark(-3.0, 20.0).gain_db == 0.0


def _zip_with(path: Path, tmp: Path, members: dict[str, tuple[np.ndarray, dict]]) -> Path:
    with zipfile.ZipFile(path, "w") as zf:
        for name, (data, meta) in members.items():
            file = write_envi(tmp / name, data, meta, interleave="bip")
            zf.write(file, name)
            zf.write(tmp / (name + ".hdr"), name + ".hdr")
    return path


def test_multi_line_dark_is_averaged_and_name_fallback(tmp_path):
    gain = np.full((BANDS, 1, SAMPLES), 0.5)
    lines = np.stack([np.full((BANDS, SAMPLES), v, np.uint16) for v in (10, 20, 33)], axis=1)
    icp = _zip_with(tmp_path / "m.icp", tmp_path, {
        "gain.bip": (gain, {"gain": 2, "shutter": 4.0}),
        "offset_8bands_4095ceiling_6gain_12samples_7.5shutter.bip": (lines, {}),
    })
    cal = read_icp(icp)
    dark = cal.darks[0]
    assert (dark.gain_db, dark.shutter_ms) == (6.0, 7.5)  # from the name: the header has none
    np.testing.assert_allclose(dark.data, 21.0)
    assert (cal.shutter_cal, cal.gain_cal) == (4.0, 2.0)


def test_for_cube_binning_and_flip(tmp_path):
    cal = _calibration()
    wl_binned = [0.5 * (WAVELENGTHS[2 * k] + WAVELENGTHS[2 * k + 1]) for k in range(4)]
    header = _cube_header(tmp_path, SAMPLES // 3, 4, wl_binned, **{
        "sample binning": 3, "spectral binning": 2, "flip radiometric calibration": True})
    dark, gain = cal.for_cube(header)
    assert dark.shape == gain.shape == (4, 4) and dark.dtype == gain.dtype == np.float32
    d = cal.select_dark(8.0, 8.2).data
    assert d is cal.darks[1].data
    exp_dark = d.reshape(4, 2, 4, 3).sum(axis=(1, 3))[:, ::-1]
    exp_gain = cal.gain.reshape(4, 2, 4, 3).mean(axis=(1, 3))[:, ::-1] / 6
    np.testing.assert_allclose(dark, exp_dark, rtol=1e-6)
    np.testing.assert_allclose(gain, exp_gain, rtol=1e-6)
    # unflipped, 2016 key names, no wavelengths: exact band count needed
    header = _cube_header(tmp_path, SAMPLES // 3, 4, None, **{"spatial bin": 3, "spectral bin": 2})
    dark2, gain2 = cal.for_cube(header)
    np.testing.assert_allclose(dark2, exp_dark[:, ::-1], rtol=1e-6)
    np.testing.assert_allclose(gain2, exp_gain[:, ::-1], rtol=1e-6)


def test_for_cube_selects_bands_by_wavelength(tmp_path):
    cal = _calibration()
    header = _cube_header(tmp_path, SAMPLES, 3, [420.5, 450.0, 471.0])
    dark, gain = cal.for_cube(header)
    np.testing.assert_allclose(gain, cal.gain[[2, 5, 7]], rtol=1e-6)
    np.testing.assert_array_equal(dark, cal.darks[1].data[[2, 5, 7]])
    far = _cube_header(tmp_path, SAMPLES, 2, [420.0, 455.0])
    with pytest.raises(FormatError, match=r"cube\.bil\.hdr: band 1 \(455.0 nm\).*2.0 nm"):
        cal.for_cube(far)


def test_for_cube_mismatches(tmp_path):
    cal = _calibration()
    with pytest.raises(FormatError, match=r"cube\.bil\.hdr: cube has 5 samples.*12 samples"):
        cal.for_cube(_cube_header(tmp_path, 5, 2, None))
    with pytest.raises(FormatError, match=r"3 bands at spectral binning 1.*8 bands"):
        cal.for_cube(_cube_header(tmp_path, SAMPLES, 3, None))
    path = write_envi(tmp_path / "nogain.bil", np.zeros((8, 1, SAMPLES), np.uint16))
    with pytest.raises(FormatError, match=r"nogain\.bil\.hdr: key 'gain' is missing"):
        cal.for_cube(read_header(path))


def test_bad_packs(tmp_path):
    with pytest.raises(MissingInputError, match=r"none\.icp"):
        read_icp(tmp_path / "none.icp")
    bad = tmp_path / "bad.icp"
    bad.write_bytes(b"not a zip at all")
    with pytest.raises(FormatError, match=r"bad\.icp: not a readable ZIP"):
        read_icp(bad)
    dark = np.zeros((BANDS, 1, SAMPLES), np.uint16)
    nogain = _zip_with(tmp_path / "nogain.icp", tmp_path, {
        "offset_8bands_4095ceiling_0gain_12samples_5shutter.bip": (dark, {})})
    with pytest.raises(FormatError, match=r"nogain\.icp: no gain\.bip"):
        read_icp(nogain)
    nodark = _zip_with(tmp_path / "nodark.icp", tmp_path, {
        "gain.bip": (np.ones((BANDS, 1, SAMPLES)), {"gain": 0, "shutter": 3.0})})
    with pytest.raises(FormatError, match=r"nodark\.icp: no dark frames"):
        read_icp(nodark)
    shape = _zip_with(tmp_path / "shape.icp", tmp_path, {
        "gain.bip": (np.ones((BANDS, 1, SAMPLES)), {"gain": 0, "shutter": 3.0}),
        "offset_x.bip": (np.zeros((BANDS, 1, 5), np.uint16), {"gain": 0, "shutter": 3.0})})
    with pytest.raises(FormatError, match=r"shape\.icp: dark frame offset_x\.bip"):
        read_icp(shape)


def test_the_same_calibration_gives_the_same_bytes(tmp_path):
    """A pack written twice is the same bytes: its members carry a fixed zip time stamp, not their
    files' (two flights of one seed simulated across a 2 s boundary differed in calibration.icp)."""
    cal = _calibration(((0.0, 5.0),))
    write_icp(tmp_path / "a.icp", cal)
    write_icp(tmp_path / "b.icp", cal)
    assert (tmp_path / "a.icp").read_bytes() == (tmp_path / "b.icp").read_bytes()
    with zipfile.ZipFile(tmp_path / "b.icp") as zf:
        assert {i.date_time for i in zf.infolist()} == {(1980, 1, 1, 0, 0, 0)}
