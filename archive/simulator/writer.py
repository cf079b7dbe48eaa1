"""Files of a simulated cube in the Resonon airborne layout, written incrementally.

``<base>.bil`` (uint16, little endian, band-interleaved by line) grows block by block, so that a
cube never has to be held whole; ``<base>.bil.hdr`` mimics a 2023 Pika L header; ``<base>.lcf`` and
``<base>.bil.times`` use the writers of :mod:`archive.ingest`.
"""

from __future__ import annotations

import os
from datetime import timedelta
from pathlib import Path
from types import TracebackType

import numpy as np

from archive.formats.envi import header_text as envi_header_text
from archive.formats.lcf import GPS_EPOCH

__all__ = ["BilWriter", "header_text"]


def header_text(samples: int, lines: int, bands: int, wavelengths: np.ndarray, shutter_ms: float,
                gain_db: float, framerate: float, gps_time: float, label: str,
                ground_elevation: float | None = None, fwhm: np.ndarray | None = None) -> str:
    """Resonon-like raw header. ``timestamp`` is the GPS time of the first line, not UTC-corrected
    (as Resonon writes it). ``ground_elevation`` (m, same datum as the .lcf altitude), as the 2023
    acquisition software records it, lets ``--ground-height auto`` work. ``wavelengths`` and
    ``fwhm`` (bands,) nm; ``fwhm`` (spectral full width at half maximum) is left out when None.
    Written by the package's one ENVI header writer (:func:`archive.formats.envi.header_text`),
    numbers formatted as Resonon does."""
    stamp = (GPS_EPOCH + timedelta(seconds=float(gps_time))).strftime("%m/%d/%Y-%Hh%Mm%Ss")
    meta: dict[str, object] = {
        "data type": 12,
        "interleave": "bil",
        "lines": lines,
        "samples": samples,
        "bands": bands,
        "ceiling": 4095,
        "bit depth": 12,
        "sample binning": 1,
        "spectral binning": 1,
        "imager serial number": "Pika L-SIM",
        "shutter": f"{shutter_ms:g}",
        "shutter units": "milliseconds",
        "gain": f"{gain_db:g}",
        "framerate": f"{framerate:g}",
        "byte order": 0,
        "header offset": 0,
        "wavelength units": "nm",
        "wavelength": [f"{w:.3f}" for w in np.asarray(wavelengths, float)],
    }
    if fwhm is not None:
        meta["fwhm"] = [f"{w:.3f}" for w in np.asarray(fwhm, float)]
    meta.update({"direction": "logo right", "flip radiometric calibration": "False", "timestamp": stamp})
    if ground_elevation is not None:
        meta["ground elevation"] = f"{ground_elevation:.3f}"
    meta.update({"target": "simulate", "label": label})
    return envi_header_text(meta)


class BilWriter:
    """Append (bands, lines, samples) uint16 blocks to ``path`` in BIL order; on a clean exit check
    the line count and write the header (``path`` + ``.hdr``) last."""

    def __init__(self, path: Path, samples: int, lines: int, bands: int, header: str):
        self.path = Path(path)
        self.samples, self.lines, self.bands = samples, lines, bands
        self.header = header
        self.written = 0
        self._file = open(self.path, "wb")

    def write(self, block: np.ndarray) -> None:
        if block.shape[0] != self.bands or block.shape[2] != self.samples:
            raise ValueError(f"{self.path}: block shape {block.shape} does not match "
                             f"({self.bands}, *, {self.samples})")
        self._file.write(np.ascontiguousarray(block.transpose(1, 0, 2), dtype="<u2").tobytes())
        self.written += block.shape[1]

    def __enter__(self) -> BilWriter:
        return self

    def __exit__(self, kind: type | None, exc: BaseException | None, tb: TracebackType | None) -> None:
        self._file.close()
        if kind is None:
            if self.written != self.lines:
                raise ValueError(f"{self.path}: wrote {self.written} lines, expected {self.lines}")
            hdr = self.path.with_name(self.path.name + ".hdr")
            hdr.write_text(self.header, encoding="ascii")


def size_on_disk(directory: Path) -> int:
    """Total bytes of the files under ``directory``."""
    total = 0
    for root, _, files in os.walk(directory):
        total += sum(os.path.getsize(os.path.join(root, f)) for f in files)
    return total
