"""Resonon downwelling-irradiance files: raw sky spectra (``.spec`` + ``.spec.hdr``) and the
spectrometer's calibration pack (``.dcp``).

Every Resonon airborne kit carries an irradiance spectrometer (Ocean Insight Flame, 2048 pixels, with
a cosine corrector looking up). Beside cube ``<ImageSetName>_Pika_L_<k>.bil`` the recorder writes
``<ImageSetName>_downwelling_<k>_pre.spec`` + ``.spec.hdr``: an ENVI file of one raw spectrum
(``bands`` = spectrometer pixels, 1 line, 1 sample; ``wavelength`` in nm; ``shutter`` in ms).

The ``.dcp`` pack is a ZIP of ``gain.spec`` (float64), ``offset.spec`` (float32) and their
``.spec.hdr`` (CRLF line endings, no ``byte order``, the spectrometer's wavelengths, the calibration
``shutter`` in ms). The real pack ``FLMS152151_Sept2019.dcp`` (tests/test_spec.py) is read as is.

Units (DESIGN 11, as massipipe reads Resonon's): ``X = (raw - offset) * gain * (shutter_cal /
shutter)`` is in uW/(pi cm2 um): the radiance of a white Lambertian panel in the camera's unit
(microflicks, 1e-5 W m-2 sr-1 nm-1). Reflectance = L / X; E (W m-2 nm-1) = pi * X * 1e-5.
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
from archive.formats.envi import EnviHeader, array_from_bytes, header_from_metadata, parse_header_text, write_envi

__all__ = ["IrradianceCalibration", "Spectrum", "downwelling_name", "read_dcp", "read_spec", "write_dcp",
           "write_spec", "MAX_SPEC_PIXELS"]

#: Spectrometer pixels accepted (bounded before a header is trusted: a Flame has 2048).
MAX_SPEC_PIXELS = 1 << 16
#: Largest header accepted, bytes (a real .dcp header is 18 KB).
_MAX_HEADER = 1 << 20
_CUBE_RE = re.compile(r"^(?P<set>.*)_pika_l_(?P<k>\d+)$", re.IGNORECASE)


@dataclass(frozen=True, eq=False)
class Spectrum:
    """One raw downwelling spectrum.

    path: the ``.spec`` file; values: (pixels,) float64 raw counts; wavelengths: (pixels,) nm;
    shutter_ms: the spectrometer's exposure (ms); header: every header key.
    """

    path: Path
    values: np.ndarray
    wavelengths: np.ndarray
    shutter_ms: float
    header: EnviHeader


@dataclass(frozen=True, eq=False)
class IrradianceCalibration:
    """A ``.dcp`` pack: gain and offset (pixels,) float64 (offset read as float32), the
    spectrometer's wavelengths (pixels,) nm and the calibration shutter (ms)."""

    path: Path | None
    gain: np.ndarray
    offset: np.ndarray
    wavelengths: np.ndarray
    shutter_ms: float

    def white_radiance(self, spectrum: Spectrum) -> np.ndarray:
        """(pixels,) float64 ``X = (raw - offset) * gain * (shutter_cal / shutter)``: the radiance of
        a white Lambertian panel under that sky, uW/(pi cm2 um) = microflicks. InputError naming the
        spectrum when its pixels or wavelengths differ from the pack's."""
        if spectrum.values.shape != self.gain.shape:
            raise InputError(spectrum.path, f"{spectrum.values.size} spectrometer pixels, calibration "
                             f"{self.path} has {self.gain.size}",
                             "use the .dcp of this spectrometer (--irradiance-calibration FILE.dcp)")
        if np.max(np.abs(spectrum.wavelengths - self.wavelengths)) > 0.5:
            raise InputError(spectrum.path, f"wavelengths differ from calibration {self.path}'s by up to "
                             f"{np.max(np.abs(spectrum.wavelengths - self.wavelengths)):.2f} nm",
                             "use the .dcp of this spectrometer (--irradiance-calibration FILE.dcp)")
        return (spectrum.values - self.offset) * self.gain * (self.shutter_ms / spectrum.shutter_ms)


def downwelling_name(cube_base: str) -> str | None:
    """``<ImageSetName>_downwelling_<k>_pre.spec`` for cube base ``<ImageSetName>_Pika_L_<k>``
    (case of 'Pika_L' ignored); None when the base does not follow Resonon's naming."""
    m = _CUBE_RE.match(cube_base)
    return None if m is None else f"{m.group('set')}_downwelling_{m.group('k')}_pre.spec"


def _header(raw: bytes, where: str) -> EnviHeader:
    if len(raw) > _MAX_HEADER:
        raise FormatError(where, f"header is {len(raw)} bytes, more than {_MAX_HEADER}", "is this a .spec.hdr?")
    text = raw.decode("utf-8-sig", errors="replace").replace("\r\n", "\n")
    try:
        header = header_from_metadata(parse_header_text(text, where), Path(where))
    except FormatError:
        raise
    except (ValueError, KeyError) as exc:
        raise FormatError(where, f"not a readable ENVI header ({exc})", "re-copy it from the recorder") from None
    n = header.samples * header.lines * header.bands
    if header.samples * header.lines != 1 and header.bands != 1:
        raise FormatError(where, f"holds {header.bands} bands x {header.lines} lines x {header.samples} samples, "
                          "expected one spectrum", "pass the spectrometer's .spec files")
    if not 1 < n <= MAX_SPEC_PIXELS:
        raise FormatError(where, f"spectrum of {n} pixels, expected 2..{MAX_SPEC_PIXELS}")
    return header


def _values(header: EnviHeader, raw: bytes, where: str) -> np.ndarray:
    data = array_from_bytes(header, raw, where)
    values = np.asarray(data, np.float64).ravel()
    if not np.all(np.isfinite(values)):
        raise FormatError(where, "spectrum holds NaN or infinite values", "re-copy it from the recorder")
    return values


def _wavelengths(header: EnviHeader, n: int, where: str) -> np.ndarray:
    wl = header.wavelengths
    if wl is None or len(wl) != n:
        raise FormatError(where, f"'wavelength' must list {n} values (one per spectrometer pixel)",
                          "re-copy the header from the recorder")
    wl = np.asarray(wl, np.float64)
    if not np.all(np.diff(wl) > 0):
        raise FormatError(where, "wavelengths are not increasing")
    return wl


def _shutter(header: EnviHeader, where: str) -> float:
    value = header.shutter
    if value is None or not np.isfinite(value) or value <= 0:
        raise FormatError(where, f"'shutter' = {value!r}, expected the exposure in ms (> 0)",
                          "re-copy the header from the recorder")
    return float(value)


def read_spec(path: str | os.PathLike) -> Spectrum:
    """A raw downwelling spectrum ``<name>.spec`` (its header ``<name>.spec.hdr``).

    MissingInputError when either file is missing, FormatError (naming the file and the fix) when the
    header is garbled, the data size disagrees with it, or ``wavelength`` / ``shutter`` are missing.
    """
    path = Path(path)
    if path.suffix.lower() == ".hdr":
        path = path.with_suffix("")
    hdr = path.with_name(path.name + ".hdr")
    for p, what in ((path, "downwelling spectrum (.spec)"), (hdr, "downwelling spectrum header (.spec.hdr)")):
        if not p.is_file():
            raise MissingInputError(p, what, "copy it from the recorder, or render with --white-reference FILE "
                                    "or --mode radiance")
    if hdr.stat().st_size > _MAX_HEADER:
        raise FormatError(hdr, f"header is larger than {_MAX_HEADER} bytes", "is this a .spec.hdr?")
    header = _header(hdr.read_bytes(), str(hdr))
    if path.stat().st_size != header.data_size:
        raise FormatError(path, f"is {path.stat().st_size} bytes, {hdr.name} expects {header.data_size}",
                          "re-copy the spectrum (file and header) from the recorder")
    values = _values(header, path.read_bytes(), str(path))
    return Spectrum(path, values, _wavelengths(header, values.size, str(hdr)), _shutter(header, str(hdr)), header)


def read_dcp(path: str | os.PathLike) -> IrradianceCalibration:
    """The spectrometer's calibration pack (see the module docstring). MissingInputError when absent,
    FormatError naming the pack and member when it is not a ZIP, lacks a member, or its members
    disagree (sizes, wavelengths)."""
    path = Path(path)
    if not path.is_file():
        raise MissingInputError(path, "downwelling calibration (.dcp)", "check --irradiance-calibration")
    try:
        zf = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError) as exc:
        raise FormatError(path, f"not a readable ZIP calibration pack ({exc})",
                          "pass the spectrometer's .dcp (a ZIP of gain.spec and offset.spec)") from None
    members = {}
    with zf:
        names = {PurePosixPath(n).name.lower(): n for n in zf.namelist() if not n.endswith("/")}
        for key in ("gain.spec", "offset.spec"):
            for name in (key, key + ".hdr"):
                if name not in names:
                    raise FormatError(path, f"no {name} in the calibration pack",
                                      "a .dcp holds gain.spec, offset.spec and their .spec.hdr")
                if zf.getinfo(names[name]).file_size > MAX_SPEC_PIXELS * 8 + _MAX_HEADER:
                    raise FormatError(path, f"member {name} is too large for a spectrometer calibration")
            where = f"{path}!{names[key]}"
            try:
                header = _header(zf.read(names[key + ".hdr"]), where + ".hdr")
                values = _values(header, zf.read(names[key]), where)
            except zipfile.BadZipFile as exc:
                raise FormatError(path, f"damaged ZIP member ({exc})", "re-copy the .dcp") from None
            members[key] = (header, values, _wavelengths(header, values.size, where + ".hdr"), where)
    (gh, gain, gwl, gwhere), (_, offset, owl, owhere) = members["gain.spec"], members["offset.spec"]
    if gain.shape != offset.shape or np.max(np.abs(gwl - owl)) > 1e-6:
        raise FormatError(path, f"gain.spec ({gain.size} pixels) and offset.spec ({offset.size}) do not match",
                          "re-copy the .dcp")
    return IrradianceCalibration(path, gain, offset, gwl, _shutter(gh, gwhere + ".hdr"))


def write_spec(path: str | os.PathLike, values: np.ndarray, wavelengths: np.ndarray, shutter_ms: float,
               dtype=np.float64) -> Path:
    """Write one spectrum (pixels,) as ``path`` (``.spec``) + ``.spec.hdr``, Resonon's layout
    (bip, 1 line, 1 sample, ``shutter`` ms); returns the ``.spec`` path."""
    values = np.asarray(values, dtype).reshape(-1, 1, 1)
    path = Path(path)
    write_envi(path.with_name(path.name + ".hdr"), values,
               {"wavelength": [float(w) for w in wavelengths], "shutter": float(shutter_ms)}, interleave="bip")
    return path


def write_dcp(path: str | os.PathLike, calibration: IrradianceCalibration) -> None:
    """Write ``calibration`` as a ``.dcp`` ZIP (stored): ``gain.spec`` float64, ``offset.spec``
    float32 and their headers, as the kit's packs are."""
    with atomic_path(Path(path)) as tmp, tempfile.TemporaryDirectory() as scratch, \
            zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_STORED) as zf:
        for name, values, dtype in (("gain.spec", calibration.gain, np.float64),
                                    ("offset.spec", calibration.offset, np.float32)):
            file = write_spec(Path(scratch) / name, values, calibration.wavelengths, calibration.shutter_ms, dtype)
            zf.write(file, name)
            zf.write(file.with_name(name + ".hdr"), name + ".hdr")
