"""Resonon ``.icp`` imager radiometric calibration packs.

An ``.icp`` is a ZIP holding ``gain.bip`` + ``gain.bip.hdr`` (float64, one line of ``samples`` x
``bands``, radiance per DN at binning 1, its header's ``shutter`` (ms) and ``gain`` (dB) being the
reference exposure) and dark frames ``offset_<B>bands_4095ceiling_<G>gain_<S>samples_<SH>shutter.bip``
(+ ``.hdr``; uint16, one or more lines that are averaged). A dark frame's own header gives its exact
gain and shutter; the name only rounds them. All calibration arrays here are ``(band, sample)``.
"""

from __future__ import annotations

import os
import re
import tempfile
import zipfile
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

import numpy as np

from archive.errors import FormatError, InputError, MissingInputError
from archive.files import atomic_path
from archive.formats.envi import (EnviHeader, array_from_bytes, header_from_metadata,
                                 parse_header_text, write_envi)

__all__ = ["Calibration", "DarkFrame", "read_icp", "response", "write_icp"]

_DARK_NAME = re.compile(r"offset_(?P<bands>\d+)bands_(?P<ceiling>\d+)ceiling_(?P<gain>[-\d.]+)gain_"
                        r"(?P<samples>\d+)samples_(?P<shutter>[\d.]+)shutter\.bip$", re.I)
MAX_WAVELENGTH_ERROR_NM = 2.0


def response(shutter_ms: float, gain_db: float, shutter_cal: float, gain_cal: float) -> float:
    """Sensor response relative to the calibration exposure (dimensionless):
    ``(shutter / shutter_cal) * 10 ** ((gain - gain_cal) / 20)``; shutters in ms, gains in dB."""
    return (shutter_ms / shutter_cal) * 10.0 ** ((gain_db - gain_cal) / 20.0)


@dataclass(frozen=True, eq=False)
class DarkFrame:
    """A dark (offset) frame: ``data`` ``(bands, samples)`` float64 DN at binning 1, taken at
    ``gain_db`` (dB) and ``shutter_ms`` (ms)."""

    gain_db: float
    shutter_ms: float
    data: np.ndarray


@dataclass(frozen=True, eq=False)
class Calibration:
    """A radiometric calibration at binning 1.

    ``gain`` ``(bands, samples)`` float64: radiance per DN at the reference exposure
    ``shutter_cal`` (ms) / ``gain_cal`` (dB); ``wavelengths`` (nm) per band; ``darks`` the dark
    frames, each ``(bands, samples)`` like ``gain``.
    """

    path: Path | None
    gain: np.ndarray
    shutter_cal: float
    gain_cal: float
    wavelengths: tuple[float, ...] | None
    darks: tuple[DarkFrame, ...]

    def _where(self) -> str:
        return str(self.path) if self.path is not None else "calibration"

    def select_dark(self, gain_db: float, shutter_ms: float) -> DarkFrame:
        """The dark frame with the closest gain; among equally close gains, the closest shutter."""
        if not self.darks:
            raise InputError(self._where(), "calibration has no dark frames")
        return min(self.darks, key=lambda d: (abs(d.gain_db - gain_db),
                                              abs(d.shutter_ms - shutter_ms)))

    def for_cube(self, header: EnviHeader) -> tuple[np.ndarray, np.ndarray]:
        """``(dark, gain)``, each ``(bands, samples)`` float32, matched to the cube of ``header``.

        Radiance of the cube is then ``(DN - dark) * gain / response`` (DESIGN section 4).

        Binning: the camera SUMS the ``n = sample_binning x spectral_binning`` pixels of a bin, so
        the binned dark is the SUM of the pixel darks and the binned gain is the MEAN pixel gain
        divided by ``n`` (the binned radiance is the mean radiance of the pixels).
        Bands: spectral bins are windows of ``spectral_binning`` consecutive calibration bands;
        when wavelengths are known on both sides each cube band takes the window whose mean
        wavelength is nearest (error beyond 2 nm), otherwise the calibration must have exactly
        ``bands x spectral_binning`` bands. Samples: the calibration must have exactly
        ``samples x sample_binning`` samples. ``flip radiometric calibration = True`` reverses
        the samples. The dark frame is chosen by :meth:`select_dark` with the header's gain and
        shutter.
        """
        where = header.path
        sb, kb = header.sample_binning, header.spectral_binning
        if header.gain is None or header.shutter is None:
            missing = "gain" if header.gain is None else "shutter"
            raise FormatError(where, f"key '{missing}' is missing: needed to choose the dark frame")
        dark = self.select_dark(header.gain, header.shutter).data
        bands_cal, samples_cal = self.gain.shape
        if samples_cal != header.samples * sb:
            raise FormatError(where, f"cube has {header.samples} samples at sample binning {sb}, "
                              f"calibration {self._where()} has {samples_cal} samples "
                              f"(expected {header.samples * sb})", "use the imager's own .icp")
        gain_s = self.gain.reshape(bands_cal, header.samples, sb).mean(axis=2)
        dark_s = dark.reshape(bands_cal, header.samples, sb).sum(axis=2)
        if bands_cal < kb:
            raise FormatError(where, f"calibration {self._where()} has {bands_cal} bands, fewer "
                              f"than spectral binning {kb}")
        windows = np.lib.stride_tricks.sliding_window_view(np.arange(bands_cal), kb)
        if self.wavelengths is not None and header.wavelengths is not None:
            centres = np.asarray(self.wavelengths)[windows].mean(axis=1)
            wanted = np.asarray(header.wavelengths)
            pick = np.abs(centres[None, :] - wanted[:, None]).argmin(axis=1)
            error = np.abs(centres[pick] - wanted)
            if error.max() > MAX_WAVELENGTH_ERROR_NM:
                b = int(error.argmax())
                raise FormatError(where, f"band {b} ({wanted[b]} nm) has no calibration band "
                                  f"within {MAX_WAVELENGTH_ERROR_NM} nm in {self._where()} "
                                  f"(nearest {centres[pick[b]]:.3f} nm)", "use the imager's own .icp")
        elif bands_cal == header.bands * kb:
            pick = np.arange(header.bands) * kb
        else:
            raise FormatError(where, f"cube has {header.bands} bands at spectral binning {kb}, "
                              f"calibration {self._where()} has {bands_cal} bands and wavelengths "
                              "are missing to match them")
        rows = windows[pick]                                     # (bands, kb)
        gain_b = gain_s[rows].mean(axis=1) / (sb * kb)
        dark_b = dark_s[rows].sum(axis=1)
        if header.flip_radiometric_calibration:
            gain_b, dark_b = gain_b[:, ::-1], dark_b[:, ::-1]
        return (np.ascontiguousarray(dark_b, dtype=np.float32),
                np.ascontiguousarray(gain_b, dtype=np.float32))


def _member_header(zf: zipfile.ZipFile, icp: Path, name: str) -> EnviHeader:
    hdr_name = name + ".hdr"
    where = f"{icp}!{hdr_name}"
    try:
        raw = zf.read(hdr_name)
    except KeyError:
        raise FormatError(icp, f"member {name} has no header {hdr_name}") from None
    text = raw.decode("utf-8-sig", errors="replace").replace("\r\n", "\n")
    return header_from_metadata(parse_header_text(text, where), Path(where))


def _member_array(zf: zipfile.ZipFile, icp: Path, name: str) -> tuple[EnviHeader, np.ndarray]:
    """A member cube as ``(header, (bands, samples) float64)``, lines averaged."""
    header = _member_header(zf, icp, name)
    cube = array_from_bytes(header, zf.read(name), f"{icp}!{name}")
    return header, cube.astype(np.float64).mean(axis=1)


def _exposure(header: EnviHeader, match: re.Match | None, key: str, icp: Path, name: str) -> float:
    value = getattr(header, key)
    if value is None and match is not None:
        value = float(match.group(key))
    if value is None:
        raise FormatError(icp, f"member {name}: '{key}' missing from its header and name")
    return float(value)


def read_icp(path: str | os.PathLike) -> Calibration:
    """Read an ``.icp`` calibration pack (see the module docstring for the layout)."""
    path = Path(path)
    if not path.is_file():
        raise MissingInputError(path, "radiometric calibration (.icp)")
    try:
        zf = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError) as exc:
        raise FormatError(path, f"not a readable ZIP calibration pack ({exc})") from None
    with zf:
        names = {PurePosixPath(n).name: n for n in zf.namelist() if not n.endswith("/")}
        if "gain.bip" not in names:
            raise FormatError(path, "no gain.bip in the calibration pack",
                              "an .icp holds gain.bip, gain.bip.hdr and offset_*.bip dark frames")
        try:
            gain_header, gain = _member_array(zf, path, names["gain.bip"])
            shutter_cal = _exposure(gain_header, None, "shutter", path, "gain.bip")
            gain_cal = _exposure(gain_header, None, "gain", path, "gain.bip")
            darks = []
            for base in sorted(n for n in names if n.lower().startswith("offset")
                               and n.lower().endswith(".bip")):
                header, data = _member_array(zf, path, names[base])
                if data.shape != gain.shape:
                    raise FormatError(path, f"dark frame {base} is {data.shape} (bands, samples), "
                                      f"gain.bip is {gain.shape}")
                match = _DARK_NAME.search(base)
                darks.append(DarkFrame(_exposure(header, match, "gain", path, base),
                                       _exposure(header, match, "shutter", path, base), data))
        except zipfile.BadZipFile as exc:
            raise FormatError(path, f"damaged ZIP member ({exc})") from None
    if not darks:
        raise FormatError(path, "no dark frames (offset_*.bip) in the calibration pack")
    if shutter_cal <= 0:
        raise FormatError(path, f"gain.bip.hdr 'shutter' = {shutter_cal} must be > 0 ms")
    return Calibration(path, gain, shutter_cal, gain_cal, gain_header.wavelengths, tuple(darks))


def _dark_name(bands: int, samples: int, dark: DarkFrame) -> str:
    return (f"offset_{bands}bands_4095ceiling_{dark.gain_db:g}gain_{samples}samples_"
            f"{dark.shutter_ms:g}shutter.bip")


def write_icp(path: str | os.PathLike, calibration: Calibration) -> None:
    """Write ``calibration`` as an ``.icp`` ZIP (stored, no compression): ``gain.bip`` (float64)
    and one ``offset_*.bip`` per dark frame, each with its ``.hdr`` giving ``gain`` and ``shutter``.
    Dark frames are written as uint16 when their values are integers in 0..65535 (as Resonon
    does), else as float64 so that they round-trip exactly."""
    path = Path(path)
    gain = np.asarray(calibration.gain, dtype=np.float64)
    if gain.ndim != 2:
        raise InputError(path, f"calibration gain must be (bands, samples), got shape {gain.shape}")
    bands, samples = gain.shape
    if not calibration.darks:
        raise InputError(path, "calibration has no dark frames to write")
    base_meta: dict[str, object] = {"wavelength units": "nanometers"}
    if calibration.wavelengths is not None:
        base_meta["wavelength"] = [float(w) for w in calibration.wavelengths]
    members: list[tuple[str, np.ndarray, dict[str, object]]] = [
        ("gain.bip", gain, {"shutter": float(calibration.shutter_cal), "shutter units": "milliseconds",
                            "gain": float(calibration.gain_cal)})]
    for dark in calibration.darks:
        data = np.asarray(dark.data, dtype=np.float64)
        if data.shape != gain.shape:
            raise InputError(path, f"dark frame {data.shape} does not match gain {gain.shape}")
        exact = np.all(data == np.round(data)) and data.min() >= 0 and data.max() <= 65535
        name = _dark_name(bands, samples, dark)
        if any(name == m[0] for m in members):
            raise InputError(path, f"two dark frames share gain {dark.gain_db} dB and shutter "
                             f"{dark.shutter_ms} ms")
        members.append((name, data.astype(np.uint16) if exact else data,
                        {"shutter": float(dark.shutter_ms), "shutter units": "milliseconds",
                         "gain": float(dark.gain_db), "ceiling": 4095}))
    with atomic_path(path) as tmp, tempfile.TemporaryDirectory() as scratch, \
            zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_STORED) as zf:
        for name, data, meta in members:
            file = Path(scratch) / name
            write_envi(file, data[:, None, :], {**base_meta, **meta}, interleave="bip")
            for member, source in ((name, file), (name + ".hdr", file.with_name(name + ".hdr"))):
                # a fixed time stamp: the same calibration gives the same bytes (reproducible flights)
                info = zipfile.ZipInfo(member, date_time=(1980, 1, 1, 0, 0, 0))
                info.external_attr = 0o644 << 16
                zf.writestr(info, source.read_bytes(), compress_type=zipfile.ZIP_STORED)
