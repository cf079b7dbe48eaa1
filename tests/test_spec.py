"""Downwelling-irradiance readers: the real Resonon .dcp, .spec files, refusals by name, the
Fraunhofer wavelength check and the band resampling."""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np
import pytest

from archive.errors import FormatError, MissingInputError
from archive.formats.spec import (IrradianceCalibration, downwelling_name, read_dcp, read_spec, write_dcp,
                                  write_spec)
from archive.sources.irradiance import FRAUNHOFER_NM, SkyIrradiance, CubeIrradiance, band_weights, fraunhofer_shift, separable

SAMPLES = Path(__file__).resolve().parents[2] / "shared" / "samples" / "resonon"
DCP = SAMPLES / "john-waczak__RobotTeam.jl" / "FLMS152151_Sept2019.dcp"


@pytest.mark.skipif(not DCP.is_file(), reason="real samples absent")
def test_real_dcp_matches_an_independent_reading():
    cal = read_dcp(DCP)
    # independent: zipfile + numpy, the header's wavelength list split by hand
    with zipfile.ZipFile(DCP) as z:
        gain = np.frombuffer(z.read("gain.spec"), "<f8")
        offset = np.frombuffer(z.read("offset.spec"), "<f4")
        text = z.read("gain.spec.hdr").decode()
    assert "\r\n" in text and "byte order" not in text          # the quirks: CRLF, no byte order
    inner = text[text.index("wavelength = {") + 14: text.index("}")]
    wl = np.array([float(v) for v in inner.split(",")])
    assert cal.gain.shape == cal.offset.shape == cal.wavelengths.shape == (2048,)
    assert cal.gain.dtype == np.float64
    np.testing.assert_array_equal(cal.gain, gain)
    np.testing.assert_array_equal(cal.offset, offset.astype(np.float64))
    np.testing.assert_array_equal(cal.wavelengths, wl)
    assert cal.wavelengths[0] == 339.708 and cal.wavelengths[-1] == 1024.49
    for i in (0, 3, 1000, 2047):      # spot checks
        assert cal.gain[i] == gain[i] and cal.offset[i] == np.float64(offset[i])
    assert cal.offset[1000] == np.float32(425.28)
    assert cal.shutter_ms == 5.7


def _spec(tmp_path: Path, name="x_downwelling_1_pre.spec", n=64, shutter=8.0) -> tuple[Path, np.ndarray]:
    wl = np.linspace(400, 900, n)
    values = 1000 + 10 * np.arange(n, dtype=float)
    return write_spec(tmp_path / name, values, wl, shutter), wl


def test_spec_round_trip_and_conversion(tmp_path):
    path, wl = _spec(tmp_path)
    s = read_spec(path)
    assert s.values.shape == (64,) and s.shutter_ms == 8.0
    np.testing.assert_array_equal(s.wavelengths, wl)
    cal = IrradianceCalibration(None, np.full(64, 2.0), np.full(64, 100.0), wl, 4.0)
    np.testing.assert_allclose(cal.white_radiance(s), (s.values - 100.0) * 2.0 * 0.5)
    write_dcp(tmp_path / "k.dcp", cal)
    back = read_dcp(tmp_path / "k.dcp")
    np.testing.assert_array_equal(back.gain, cal.gain)
    assert back.shutter_ms == 4.0
    assert downwelling_name("Juvika_June2022_Pika_L_12") == "Juvika_June2022_downwelling_12_pre.spec"
    assert downwelling_name("cube7") is None


def test_garbled_and_missing_files_are_refused_by_name(tmp_path):
    path, _ = _spec(tmp_path)
    hdr = path.with_name(path.name + ".hdr")
    with open(path, "ab") as f:          # one value too many
        f.write(b"\0" * 8)
    with pytest.raises(FormatError, match=path.name):
        read_spec(path)
    path, _ = _spec(tmp_path, "y.spec")
    hdr = path.with_name(path.name + ".hdr")
    hdr.write_text(hdr.read_text().replace("shutter", "shuttr"))
    with pytest.raises(FormatError, match="shutter"):
        read_spec(path)
    hdr.write_bytes(b"\x00garbage{{{")
    with pytest.raises(FormatError, match="y.spec.hdr"):
        read_spec(path)
    with pytest.raises(MissingInputError, match="z.spec"):
        read_spec(tmp_path / "z.spec")
    (tmp_path / "bad.dcp").write_bytes(b"not a zip")
    with pytest.raises(FormatError, match="bad.dcp"):
        read_dcp(tmp_path / "bad.dcp")
    with zipfile.ZipFile(tmp_path / "half.dcp", "w") as z:
        z.writestr("gain.spec", b"")
    with pytest.raises(FormatError, match="gain.spec.hdr"):
        read_dcp(tmp_path / "half.dcp")


def test_fraunhofer_shift_is_found_and_absent_lines_leave_it():
    wl = np.linspace(340, 1024, 2048)
    smooth = 1000 * np.exp(-0.5 * ((wl - 550) / 300) ** 2)
    true_shift = 0.8                          # recorded wavelengths are 0.8 nm short
    dips = np.ones_like(wl)
    for line in FRAUNHOFER_NM:
        dips -= 0.3 * np.exp(-0.5 * ((wl + true_shift - line) / 0.6) ** 2)
    shift, found = fraunhofer_shift(wl, smooth * dips)
    assert found >= 5 and abs(shift - true_shift) < 0.1
    assert fraunhofer_shift(wl, smooth) == (None, 0)


def test_band_resampling_and_time_interpolation():
    wl = np.linspace(340, 1024, 2048)
    w = band_weights(wl, [500.0, 700.0], [10.0, 20.0])
    np.testing.assert_allclose(w.sum(axis=1), 1.0)
    np.testing.assert_allclose(w @ wl, [500.0, 700.0], atol=0.05)   # centred
    sky = SkyIrradiance((CubeIrradiance("a", 0.0, np.array([1.0, 2.0]), None, 0),
                         CubeIrradiance("b", 10.0, np.array([2.0, 2.0]), None, 0)), "k.dcp")
    np.testing.assert_allclose(sky.per_line([-1.0, 5.0, 20.0]), [[1, 2], [1.5, 2], [2, 2]])
    spectrum, factor, error = separable(np.outer([1.0, 0.7], [3.0, 5.0]))
    assert error < 1e-12 and np.allclose(np.outer(factor, spectrum), np.outer([1.0, 0.7], [3.0, 5.0]))
    # a spectral change of 4 % between the ends of a cube costs at most ~1 % in the separable form
    x = np.stack([np.array([1.0, 1.0]) * (1 - t) + np.array([1.0, 1.04]) * t for t in np.linspace(0, 1, 50)])
    assert separable(x)[2] < 0.011
