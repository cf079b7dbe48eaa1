"""ENVI header parsing and cube access (Resonon and Spectronon flavours; pixels read with ``os.preadv``).

Headers are parsed robustly: values in braces may span many lines and contain commas, brackets,
quotes and backslashes (Spectronon's ``history``); a brace block ends at the last ``}`` of the line
where the brace depth returns to zero. Tuples in parentheses, Python booleans, CRLF line endings and
a UTF-8 BOM are accepted. Every key is kept (lower-cased, inner whitespace collapsed) in
:attr:`EnviHeader.metadata`.

Axis orders: a cube is ``(band, line, sample)``; a single band is ``(line, sample)``.
"""

from __future__ import annotations

import os
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from archive.errors import FormatError, InputError, MissingInputError
from archive.files import atomic_path
from archive.formats.pread import read_bands as read_raw_bands

__all__ = [
    "DTYPES",
    "EnviCube",
    "EnviHeader",
    "array_from_bytes",
    "data_path_for",
    "header_from_metadata",
    "header_path_for",
    "header_text",
    "parse_header_text",
    "read_header",
    "write_envi",
]

#: ENVI ``data type`` code -> numpy dtype (byte order applied separately).
DTYPES: dict[int, np.dtype] = {
    1: np.dtype(np.uint8),
    2: np.dtype(np.int16),
    3: np.dtype(np.int32),
    4: np.dtype(np.float32),
    5: np.dtype(np.float64),
    12: np.dtype(np.uint16),
    13: np.dtype(np.uint32),
}
_CODES: dict[np.dtype, int] = {v: k for k, v in DTYPES.items()}

INTERLEAVES = ("bil", "bip", "bsq")
DATA_SUFFIXES = (".bil", ".bip", ".bsq")
_REQUIRED = ("samples", "lines", "bands", "data type", "interleave")
# Keys written by write_envi itself; metadata entries with these names are ignored there.
_STRUCTURAL = {"samples", "lines", "bands", "data type", "interleave", "byte order",
               "header offset", "file type"}
# Brace values kept as one string: free text that may contain commas.
_TEXT_KEYS = {"description", "coordinate system string", "history"}
_INT_RE = re.compile(r"[+-]?\d+")
_FLOAT_RE = re.compile(r"[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?|[+-]?(nan|inf|infinity)", re.I)


@dataclass(frozen=True, eq=False)
class EnviHeader:
    """A parsed ENVI header.

    ``metadata`` holds every key of the file (lower-cased, values parsed to str, int, float, bool,
    list for ``{...}`` and tuple for ``(...)``), including the structural ones. ``wavelengths`` and
    ``fwhm`` are per band in nm (converted from ``wavelength units``, which ENVI applies to both).
    """

    path: Path
    samples: int
    lines: int
    bands: int
    interleave: str
    data_type: int
    byte_order: int
    header_offset: int
    wavelengths: tuple[float, ...] | None
    metadata: dict[str, object] = field(default_factory=dict)
    #: Full width at half maximum of each band's spectral response (``fwhm``), nm; None if absent.
    fwhm: tuple[float, ...] | None = None

    @property
    def dtype(self) -> np.dtype:
        """numpy dtype of the data file, with its byte order."""
        return DTYPES[self.data_type].newbyteorder(">" if self.byte_order else "<")

    @property
    def shape(self) -> tuple[int, int, int]:
        """``(bands, lines, samples)``."""
        return (self.bands, self.lines, self.samples)

    @property
    def data_size(self) -> int:
        """Expected data file size in bytes, header offset included."""
        return self.header_offset + self.samples * self.lines * self.bands * self.dtype.itemsize

    def _number(self, *keys: str) -> float | None:
        for key in keys:
            value = self.metadata.get(key)
            if value is None:
                continue
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise FormatError(self.path, f"key '{key}' = {value!r} is not a number")
            return float(value)
        return None

    @property
    def framerate(self) -> float | None:
        """Line rate in Hz (``framerate``)."""
        return self._number("framerate")

    @property
    def shutter(self) -> float | None:
        """Exposure time in ms (``shutter``)."""
        return self._number("shutter")

    @property
    def gain(self) -> float | None:
        """Sensor gain in dB (``gain``)."""
        return self._number("gain")

    @property
    def bit_depth(self) -> int | None:
        """``bit depth`` (2016 headers); derived from ``ceiling`` (2023 headers) if absent."""
        value = self._number("bit depth")
        if value is not None:
            return int(value)
        ceiling = self._number("ceiling")
        if ceiling is not None and ceiling > 0:
            return int(round(np.log2(ceiling + 1)))
        return None

    @property
    def flip_radiometric_calibration(self) -> bool | None:
        """``flip radiometric calibration``: the calibration's samples must be reversed."""
        value = self.metadata.get("flip radiometric calibration")
        if value is None:
            return None
        if isinstance(value, bool):
            return value
        if isinstance(value, int) and value in (0, 1):
            return bool(value)
        raise FormatError(self.path, f"'flip radiometric calibration' = {value!r} is not True/False")

    def _binning(self, *keys: str) -> int:
        value = self._number(*keys)
        if value is None:
            return 1
        if value != int(value) or value < 1:
            raise FormatError(self.path, f"'{keys[0]}' = {value!r} is not a positive integer")
        return int(value)

    @property
    def sample_binning(self) -> int:
        """Spatial binning factor (``sample binning``, 2016: ``spatial bin``); 1 when absent."""
        return self._binning("sample binning", "spatial bin", "spatial binning")

    @property
    def spectral_binning(self) -> int:
        """Spectral binning factor (``spectral binning``, 2016: ``spectral bin``); 1 when absent."""
        return self._binning("spectral binning", "spectral bin")


# ----------------------------------------------------------------------------------------------
# parsing


def _scalar(text: str) -> object:
    """Parse one value: bool, int, float or (stripped) str."""
    text = text.strip()
    if text in ("True", "true", "TRUE"):
        return True
    if text in ("False", "false", "FALSE"):
        return False
    if _INT_RE.fullmatch(text):
        return int(text)
    if _FLOAT_RE.fullmatch(text):
        return float(text)
    return text


def _split_list(inner: str) -> list[object]:
    inner = inner.strip()
    if not inner:
        return []
    return [_scalar(item) for item in inner.split(",")]


def _decode(raw: bytes) -> str:
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        text = raw.decode("latin-1")
    return text.replace("\r\n", "\n").replace("\r", "\n")


def parse_header_text(text: str, where: Path | str) -> dict[str, object]:
    """Parse the text of an ENVI header into ``{key: value}`` (keys lower-cased).

    ``where`` names the file in error messages. Raises :class:`FormatError` when the ``ENVI``
    magic line is missing or a brace block is never closed.
    """
    lines = text.lstrip("\ufeff").split("\n")
    start = 0
    while start < len(lines) and not lines[start].strip():
        start += 1
    if start == len(lines) or lines[start].strip() != "ENVI":
        raise FormatError(where, "not an ENVI header: the first line must be 'ENVI'")
    meta: dict[str, object] = {}
    i = start + 1
    while i < len(lines):
        line = lines[i]
        i += 1
        stripped = line.strip()
        if not stripped or stripped.startswith(";") or "=" not in stripped:
            continue
        key, value = stripped.split("=", 1)
        key = " ".join(key.split()).lower()
        value = value.strip()
        if value.startswith("{"):
            first = i
            block = value
            depth = value.count("{") - value.count("}")
            while depth > 0 and i < len(lines):
                block += "\n" + lines[i]
                depth += lines[i].count("{") - lines[i].count("}")
                i += 1
            if depth > 0:
                raise FormatError(where, f"brace opened for key '{key}' on line {first} is never "
                                  "closed with '}'")
            inner = block[1:block.rfind("}")]
            if key in _TEXT_KEYS:
                meta[key] = inner.strip()
            else:
                meta[key] = _split_list(inner.replace("\n", " "))
        elif value.startswith("(") and value.endswith(")"):
            meta[key] = tuple(_split_list(value[1:-1]))
        else:
            meta[key] = _scalar(value)
    return meta


def _require_int(meta: Mapping[str, object], key: str, where: Path, minimum: int = 0) -> int:
    if key not in meta:
        raise FormatError(where, f"required key '{key}' is missing",
                          "an ENVI header needs samples, lines, bands, data type and interleave")
    value = meta[key]
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise FormatError(where, f"key '{key}' = {value!r} is not an integer >= {minimum}")
    return value


def header_from_metadata(meta: dict[str, object], path: Path) -> EnviHeader:
    """Build an :class:`EnviHeader` from parsed metadata, checking the required keys."""
    for key in _REQUIRED:
        if key not in meta:
            raise FormatError(path, f"required key '{key}' is missing",
                              "an ENVI header needs samples, lines, bands, data type and interleave")
    samples = _require_int(meta, "samples", path, 1)
    lines = _require_int(meta, "lines", path, 1)
    bands = _require_int(meta, "bands", path, 1)
    data_type = _require_int(meta, "data type", path)
    if data_type not in DTYPES:
        raise FormatError(path, f"unsupported 'data type' = {data_type}",
                          f"supported ENVI codes: {sorted(DTYPES)}")
    interleave = str(meta["interleave"]).strip().lower()
    if interleave not in INTERLEAVES:
        raise FormatError(path, f"unknown 'interleave' = {meta['interleave']!r}",
                          "expected bil, bip or bsq")
    byte_order = _require_int(meta, "byte order", path) if "byte order" in meta else 0
    if byte_order not in (0, 1):
        raise FormatError(path, f"'byte order' = {byte_order} must be 0 (little) or 1 (big)")
    offset = _require_int(meta, "header offset", path) if "header offset" in meta else 0
    units = str(meta.get("wavelength units", "nanometers")).strip().lower()
    scale = 1000.0 if units in ("micrometers", "micrometer", "microns", "um", "µm") else 1.0
    return EnviHeader(path=path, samples=samples, lines=lines, bands=bands, interleave=interleave,
                      data_type=data_type, byte_order=byte_order, header_offset=offset,
                      wavelengths=_per_band(meta, "wavelength", bands, scale, path), metadata=meta,
                      fwhm=_per_band(meta, "fwhm", bands, scale, path))


def _per_band(meta: Mapping[str, object], key: str, bands: int, scale: float,
              path: Path) -> tuple[float, ...] | None:
    """The per-band list ``key`` (``wavelength``, ``fwhm``) times ``scale`` (to nm), None when absent;
    FormatError naming the file and key for non-numeric values or a length other than ``bands``."""
    if key not in meta:
        return None
    values = meta[key]
    values = values if isinstance(values, list | tuple) else [values]
    if not all(isinstance(v, int | float) and not isinstance(v, bool) for v in values):
        raise FormatError(path, f"'{key}' holds non-numeric values")
    if len(values) != bands:
        raise FormatError(path, f"'{key}' lists {len(values)} values for {bands} bands",
                          "give one value per band, or remove the key")
    return tuple(float(v) * scale for v in values)


def header_path_for(path: str | os.PathLike) -> Path:
    """The header of ``path``: itself if it ends with ``.hdr``, else ``<path>.hdr`` or
    ``<stem>.hdr`` (first that exists)."""
    path = Path(path)
    if path.suffix.lower() == ".hdr":
        return path
    candidates = [path.with_name(path.name + ".hdr"), path.with_suffix(".hdr")]
    for candidate in candidates:
        if candidate.is_file():
            return candidate
    raise MissingInputError(candidates[0], "ENVI header",
                            f"expected {candidates[0].name} or {candidates[1].name} next to the data")


def read_header(path: str | os.PathLike) -> EnviHeader:
    """Read an ENVI header, given the ``.hdr`` path or the data file path."""
    hdr = header_path_for(path)
    if not hdr.is_file():
        raise MissingInputError(hdr, "ENVI header")
    meta = parse_header_text(_decode(hdr.read_bytes()), hdr)
    return header_from_metadata(meta, hdr)


def data_path_for(header: EnviHeader) -> Path:
    """The data file belonging to ``header``: ``x.bil`` for ``x.bil.hdr``; for ``x.hdr`` the
    first existing of ``x``, ``x.<interleave>``, ``x.img``, ``x.dat``, ``x.raw``."""
    hdr = header.path
    stem = hdr.with_suffix("")
    if stem.suffix.lower() in DATA_SUFFIXES + (".img", ".dat", ".raw"):
        candidates = [stem]
    else:
        candidates = [stem] + [stem.with_name(stem.name + s)
                               for s in (f".{header.interleave}", ".img", ".dat", ".raw")]
    for candidate in candidates:
        if candidate.is_file():
            return candidate
    raise MissingInputError(candidates[0], f"data file of header {hdr.name}")


# ----------------------------------------------------------------------------------------------
# data access


def _file_shape(header: EnviHeader) -> tuple[int, int, int]:
    b, l, s = header.bands, header.lines, header.samples
    return {"bsq": (b, l, s), "bil": (l, b, s), "bip": (l, s, b)}[header.interleave]


def _to_cube_order(array: np.ndarray, interleave: str) -> np.ndarray:
    """File-order array -> (band, line, sample) view."""
    if interleave == "bil":
        return array.transpose(1, 0, 2)
    if interleave == "bip":
        return array.transpose(2, 0, 1)
    return array


def _native(array: np.ndarray) -> np.ndarray:
    """Copy into a C-contiguous, native-byte-order array."""
    return np.ascontiguousarray(array, dtype=array.dtype.newbyteorder("="))


def array_from_bytes(header: EnviHeader, raw: bytes, where: str | os.PathLike = "") -> np.ndarray:
    """Decode a whole data file held in memory into ``(bands, lines, samples)``, native order."""
    if len(raw) != header.data_size:
        raise FormatError(where or header.path,
                          f"data is {len(raw)} bytes, header {header.path.name} expects "
                          f"{header.data_size} bytes")
    flat = np.frombuffer(raw, dtype=header.dtype, offset=header.header_offset)
    return _native(_to_cube_order(flat.reshape(_file_shape(header)), header.interleave))


class EnviCube:
    """An ENVI cube on disk. Only the header is read at construction; pixel reads open the file,
    read the requested bands with ``os.preadv`` (:mod:`archive.formats.pread`: no memory map, so no
    file pages count in the process's RSS) and close it: the object holds no open file and pickles
    cheaply.
    """

    def __init__(self, path: str | os.PathLike):
        self.header: EnviHeader = read_header(path)
        p = Path(path)
        self.path: Path = p if p.suffix.lower() != ".hdr" and p.is_file() else data_path_for(self.header)
        size = self.path.stat().st_size
        if size != self.header.data_size:
            kind = "truncated" if size < self.header.data_size else "larger than expected"
            raise FormatError(
                self.path,
                f"data file is {kind}: {size} bytes, but {self.header.path.name} (header offset "
                f"{self.header.header_offset} + {self.header.lines} lines x {self.header.samples} "
                f"samples x {self.header.bands} bands x {self.header.dtype.itemsize} bytes) needs "
                f"{self.header.data_size} bytes",
                "re-copy the cube or fix the header")

    def __repr__(self) -> str:
        h = self.header
        return f"EnviCube({str(self.path)!r}, bands={h.bands}, lines={h.lines}, samples={h.samples})"

    @property
    def shape(self) -> tuple[int, int, int]:
        """``(bands, lines, samples)``."""
        return self.header.shape

    def _read(self, idx: Sequence[int]) -> np.ndarray:
        h = self.header
        return read_raw_bands(self.path, h.dtype, h.interleave, h.shape, h.header_offset, idx)

    def _check_band(self, b: int) -> int:
        if isinstance(b, bool) or not isinstance(b, int | np.integer):
            raise InputError(self.path, f"band index {b!r} is not an integer")
        if not 0 <= b < self.header.bands:
            raise InputError(self.path, f"band {b} out of range 0..{self.header.bands - 1}")
        return int(b)

    def band(self, b: int) -> np.ndarray:
        """Band ``b`` (0-based) as ``(lines, samples)``, native byte order; reads only that band."""
        return self._read([self._check_band(b)])[0]

    def bands(self, idx: Sequence[int]) -> np.ndarray:
        """Bands ``idx`` as ``(len(idx), lines, samples)``, native byte order; reads only those bands."""
        return self._read([self._check_band(b) for b in idx])

    def read(self) -> np.ndarray:
        """The whole cube as ``(bands, lines, samples)``, native byte order."""
        return self._read(range(self.header.bands))


# ----------------------------------------------------------------------------------------------
# writing


def _format_value(value: object) -> str:
    if isinstance(value, bool | np.bool_):
        return "True" if value else "False"
    if isinstance(value, np.floating):
        return str(value)
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, int | np.integer):
        return str(int(value))
    if isinstance(value, np.ndarray):
        return _format_value(value.tolist())
    if isinstance(value, tuple):
        return "(" + ", ".join(_format_value(v) for v in value) + ")"
    if isinstance(value, list):
        return "{" + ", ".join(_format_value(v) for v in value) + "}"
    return str(value)


def header_text(meta: Mapping[str, object]) -> str:
    """The text of an ENVI header holding ``meta`` in its order: the one ENVI header writer of the
    package (cubes written here, rendered ENVI outputs, the simulator's raw headers).

    Keys are lower-cased with inner whitespace collapsed; values: lists as ``{a, b}`` (their items
    formatted alike, strings as given), tuples as ``(a, b)``, Python floats with full precision
    (``repr``), booleans as ``True``/``False``; free-text keys (``description``, ``coordinate system
    string``, ``history``) and strings spanning lines in braces; ``map info`` given without braces
    gets them. Ends with a newline. InputError for a key that is empty or holds ``=``."""
    lines = ["ENVI"]
    for key, value in meta.items():
        key = " ".join(str(key).split()).lower()
        if not key or "=" in key:
            raise InputError(None, f"metadata key {key!r} cannot be written to an ENVI header")
        text = _format_value(value)
        if key in _TEXT_KEYS and isinstance(value, str) or (isinstance(value, str) and "\n" in text):
            text = "{" + text + "}"
        elif key == "map info" and isinstance(value, str) and not text.startswith("{"):
            text = "{" + text + "}"
        lines.append(f"{key} = {text}")
    return "\n".join(lines) + "\n"


def _paths_for_write(path: str | os.PathLike) -> tuple[Path, Path]:
    path = Path(path)
    if path.suffix.lower() == ".hdr":
        return path.with_suffix(""), path
    if path.suffix.lower() in DATA_SUFFIXES:
        return path, path.with_name(path.name + ".hdr")
    return path, path.with_suffix(".hdr")


def write_envi(path: str | os.PathLike, data: np.ndarray, metadata: Mapping[str, object] | None = None,
               interleave: str = "bsq", byte_order: int = 0, header_offset: int = 0) -> Path:
    """Write ``data`` ``(bands, lines, samples)`` as an ENVI cube and return the data file path.

    ``path`` is the data file (``x.bil`` -> header ``x.bil.hdr``; ``x.img`` -> ``x.hdr``) or an
    explicit ``.hdr`` path (the data file is then the path without ``.hdr``). ``metadata`` is
    written after the structural keys (samples, lines, bands, data type, interleave, byte order,
    header offset, which are taken from the arguments and ignored in ``metadata``): lists as
    ``{a, b}``, tuples as ``(a, b)``, floats with full precision, ``map info`` as given. A
    ``wavelength`` or ``fwhm`` list must have one value per band. Both files are written under temporary
    names and renamed at the end, the header last.
    """
    data = np.asarray(data)
    if data.ndim != 3:
        raise InputError(path, f"cube data must be 3-D (bands, lines, samples), got shape {data.shape}")
    if min(data.shape) < 1:
        raise InputError(path, f"cube data has an empty axis: shape {data.shape}")
    code = _CODES.get(data.dtype.newbyteorder("="))
    if code is None:
        raise InputError(path, f"dtype {data.dtype} has no ENVI data type",
                         "use uint8, int16, int32, uint16, uint32, float32 or float64")
    interleave = interleave.lower()
    if interleave not in INTERLEAVES:
        raise InputError(path, f"unknown interleave {interleave!r}", "use bil, bip or bsq")
    if byte_order not in (0, 1):
        raise InputError(path, f"byte order {byte_order!r} must be 0 (little) or 1 (big)")
    if header_offset < 0:
        raise InputError(path, f"header offset {header_offset} must be >= 0")
    bands, lines, samples = data.shape
    meta: dict[str, object] = {
        "samples": samples, "lines": lines, "bands": bands, "header offset": int(header_offset),
        "file type": "ENVI Standard", "data type": code, "interleave": interleave,
        "byte order": int(byte_order),
    }
    for key, value in (metadata or {}).items():
        key = " ".join(str(key).split()).lower()
        if key not in _STRUCTURAL:
            meta[key] = value
    for key in ("wavelength", "fwhm"):
        if key not in meta:
            continue
        wl = meta[key]
        wl = list(np.ravel(np.asarray(wl, dtype=float))) if not isinstance(wl, list) else wl
        if len(wl) != bands:
            raise InputError(path, f"metadata '{key}' has {len(wl)} values for {bands} bands")
        meta[key] = [float(v) for v in wl]
    data_path, hdr_path = _paths_for_write(path)
    file_order = {"bsq": (0, 1, 2), "bil": (1, 0, 2), "bip": (1, 2, 0)}[interleave]
    out = np.ascontiguousarray(data.transpose(file_order),
                               dtype=data.dtype.newbyteorder(">" if byte_order else "<"))
    # the data file is renamed into place first, the header (what readers open) last
    with atomic_path(hdr_path) as tmp_hdr:
        with atomic_path(data_path) as tmp_data, open(tmp_data, "wb") as f:
            if header_offset:
                f.write(b"\0" * header_offset)
            out.tofile(f)
        tmp_hdr.write_text(header_text(meta), encoding="utf-8")
    return data_path
