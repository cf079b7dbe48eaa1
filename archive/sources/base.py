"""The flight-source protocol and what every source shares: cube descriptions, radiometric terms,
argument checks and the one radiometry function.

A :class:`FlightSource` gives, per cube, camera poses (one per line, at exposure start), pixel reads
of chosen bands (band, line, sample) and the radiometric terms the shader applies::

    value = (DN - dark[band, sample]) * gain[band, sample] / response[line]

Implementations: :class:`archive.sources.raw.RawFlightSource` (a raw Resonon directory),
:class:`archive.sources.collection.CollectionSource` (an ingested Zarr collection),
:class:`archive.sources.memory.MemoryFlightSource` (arrays given directly, for tests). All are
picklable and cheap to send to Dask workers: pixels are only read inside ``read_bands``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from archive.errors import InputError
from archive.formats.envi import EnviHeader
from archive.formats.icp import response
from archive.geometry.navigation import LocalFrame, Poses, Track
from archive.params import NavigationParams

__all__ = ["MODES", "CubeInfo", "FlightSource", "Radiometry", "band_list", "check_cube", "check_mode",
           "radiometry_for", "saturation_for", "white_for"]

MODES = ("raw", "relative", "radiance", "reflectance")

# 'relative' mode: DN per ms of exposure at 0 dB, the same reference for every flight.
RELATIVE_SHUTTER_MS = 1.0
RELATIVE_GAIN_DB = 0.0


@dataclass(frozen=True)
class CubeInfo:
    """One cube of a flight.

    index: position in capture order (0-based); base: file base name (e.g. 'flight_Pika_L_3');
    lines, samples, bands: cube shape (band, line, sample); wavelengths: nm per band;
    shutter_ms: exposure (ms); gain_db: sensor gain (dB); framerate: line rate (Hz);
    bit_depth: sensor bits per DN; first_time: .lcf-scale time of line 0's exposure start (s),
    sync offset included.
    """

    index: int
    base: str
    lines: int
    samples: int
    bands: int
    wavelengths: tuple[float, ...] | None
    shutter_ms: float | None
    gain_db: float | None
    framerate: float | None
    bit_depth: int | None
    first_time: float


@dataclass(frozen=True, eq=False)
class Radiometry:
    """What the shader needs: ``value = (DN - dark) * gain / response``.

    dark: (nbands, samples) float32 DN; gain: (nbands, samples) float32 (output units per DN);
    response: (lines,) float32 exposure factor; saturation: DN at/above which a sample is saturated
    (2**bit_depth - 1), None if unknown.
    """

    dark: np.ndarray
    gain: np.ndarray
    response: np.ndarray
    saturation: float | None


@runtime_checkable
class FlightSource(Protocol):
    """A flight the renderer, the catalog and the graph read: cubes in capture order sharing one
    local frame. Every implementation passes the shared suite in ``tests/test_sources.py``.

    id: the flight's id (a collection id, or ``<directory name>-<first .lcf time>``);
    label: what messages name (the directory, the store path); frame: the local NED frame;
    cubes: per cube, shape and exposure; wavelengths: nm per band (None if the headers have none);
    fwhm: full width at half maximum of each band's spectral response, nm (the first cube's
    ``fwhm``; None if it has none);
    params: the navigation parameters poses are computed with; fov_deg: the field of view the source
    records (a collection's, as ingested), None if it records none; ground_height: the ground
    height (m, .lcf altitude datum) it records (a collection's, as ingested), None if none;
    has_calibration: whether radiance/reflectance are possible; white_reference: (bands,)
    radiance of a white reference for 'reflectance', or None.
    """

    id: str
    label: str
    frame: LocalFrame
    cubes: tuple[CubeInfo, ...]
    wavelengths: tuple[float, ...] | None
    fwhm: tuple[float, ...] | None
    params: NavigationParams
    fov_deg: float | None
    ground_height: float | None
    has_calibration: bool
    white_reference: np.ndarray | None

    def header(self, cube: int) -> EnviHeader:
        """The cube's ENVI header (all its keys in ``metadata``)."""
        ...

    def line_times(self, cube: int) -> np.ndarray:
        """(lines,) exposure-start times of ``cube`` on the .lcf scale, sync offset included, s."""
        ...

    def track(self, cube: int) -> Track:
        """The INS samples of ``cube``'s own navigation in the flight's frame."""
        ...

    def poses(self, cube: int, delay: float = 0.0) -> Poses:
        """Camera poses at exposure START of each line of ``cube`` (plus ``delay`` seconds, e.g.
        shutter/2 for mid-exposure poses)."""
        ...

    def read_bands(self, cube: int, bands: Sequence[int]) -> np.ndarray:
        """(len(bands), lines, samples) DN in the cube's native dtype."""
        ...

    def radiometry(self, cube: int, bands: Sequence[int], mode: str,
                   white_reference: np.ndarray | None = None) -> Radiometry:
        """Radiometric terms for ``bands`` of ``cube`` in ``mode`` (one of MODES)."""
        ...

    def __dask_tokenize__(self) -> object:
        """What renders of this source depend on (files or stored content, parameters), never
        the pixels: equal tokens mean equal renders."""
        ...


def check_mode(mode: str) -> None:
    if mode not in MODES:
        raise InputError(None, f"unknown radiometric mode {mode!r}", f"use one of {', '.join(MODES)}")


def check_cube(index: int, cubes: Sequence[CubeInfo], where: str) -> int:
    if isinstance(index, bool) or not isinstance(index, int | np.integer) or not 0 <= index < len(cubes):
        raise InputError(where, f"cube {index!r} out of range 0..{len(cubes) - 1}")
    return int(index)


def band_list(bands: Sequence[int], nbands: int, where: str) -> list[int]:
    out = []
    for b in bands:
        if isinstance(b, bool) or not isinstance(b, int | np.integer) or not 0 <= b < nbands:
            raise InputError(where, f"band {b!r} out of range 0..{nbands - 1}")
        out.append(int(b))
    return out


def _exposure(shutter_ms: float | None, gain_db: float | None, ref_shutter: float, ref_gain: float) -> float:
    """Exposure factor against a reference; a missing shutter or gain counts as the reference."""
    return response(ref_shutter if shutter_ms is None else shutter_ms, ref_gain if gain_db is None else gain_db,
                    ref_shutter, ref_gain)


def white_for(white_reference, bands: list[int], nbands: int, where: str) -> np.ndarray:
    if white_reference is None:
        raise InputError(where, "mode 'reflectance' needs a white reference spectrum or the flight's downwelling "
                         "spectra (<ImageSetName>_downwelling_<k>_pre.spec beside each cube and a *.dcp), "
                         "and it has neither", "pass --white-reference FILE, or use --mode radiance")
    white = np.asarray(white_reference, float).ravel()
    if white.size != nbands:
        raise InputError(where, f"white reference has {white.size} values for {nbands} bands",
                         "give one radiance per band, interpolated to the band wavelengths")
    sel = white[bands]
    if not np.all(np.isfinite(sel) & (sel > 0)):
        raise InputError(where, "white reference has zero, negative or NaN values in the selected bands")
    return sel


def radiometry_for(header: EnviHeader, bands: list[int], mode: str, calibration, white_reference,
                   where: str, no_calibration: tuple[str, str], responses: np.ndarray | None = None,
                   sky=None) -> Radiometry:
    """Radiometric terms of ``bands`` (checked indices) of the cube described by ``header``.

    ``calibration`` is None (no calibration) or a callable returning (dark, gain, shutter_cal,
    gain_cal) for those bands: dark and gain (len(bands), samples) matched to the cube. Modes:

    - raw: dark 0, gain 1, response 1 (values are DN);
    - relative: dark from the calibration if there is one (else 0), gain 1, response = exposure
      against 1 ms at 0 dB (DN per ms at 0 dB);
    - radiance: dark and gain of the calibration, response = (shutter / shutter_cal) x
      10**((gain - gain_cal) / 20);
    - reflectance: radiance divided by ``white_reference`` (bands of the cube), per band, when
      given; else by the sky's irradiance: ``sky`` a callable returning (spectrum (len(bands),),
      factor (lines,)), X(line, band) = factor[line] * spectrum[band] in the radiance's unit
      (:mod:`archive.sources.irradiance`): gain / spectrum per band, response x factor per line; neither:
      InputError naming what is missing.

    ``no_calibration`` is the (problem, fix) said when a mode needs a calibration and there is none.
    ``responses``: (lines,) exposure factors that replace the header's in 'relative', 'radiance' and
    'reflectance' (in-memory sources give them directly).
    """
    h = header
    shape = (len(bands), h.samples)
    saturation = saturation_for(h.bit_depth, h.dtype)
    if mode == "raw":
        return Radiometry(np.zeros(shape, np.float32), np.ones(shape, np.float32),
                          np.ones(h.lines, np.float32), saturation)
    if mode == "relative":
        dark = np.zeros(shape, np.float32) if calibration is None else np.asarray(calibration()[0], np.float32)
        exposure = _exposure(h.shutter, h.gain, RELATIVE_SHUTTER_MS, RELATIVE_GAIN_DB)
        resp = np.full(h.lines, exposure, np.float32) if responses is None else np.asarray(responses, np.float32)
        return Radiometry(dark, np.ones(shape, np.float32), resp, saturation)
    if calibration is None:
        raise InputError(where, f"mode '{mode}' {no_calibration[0]}", no_calibration[1])
    for key, value in (("shutter", h.shutter), ("gain", h.gain)):
        if value is None and responses is None:
            raise InputError(h.path, f"no '{key}' key: cannot scale the calibration to this cube",
                             "add it to the header, or use --mode raw")
    dark, gain, shutter_cal, gain_cal = calibration()
    gain = np.asarray(gain, np.float64)
    factor = None
    if mode == "reflectance" and (white_reference is not None or sky is None):
        gain = gain / white_for(white_reference, bands, h.bands, where)[:, None]
    elif mode == "reflectance":
        spectrum, factor = sky()
        gain = gain / np.asarray(spectrum, np.float64)[:, None]
    if responses is None:
        resp = np.full(h.lines, response(h.shutter, h.gain, shutter_cal, gain_cal), np.float32)
    else:
        resp = np.asarray(responses, np.float32)
    if factor is not None:
        resp = (resp.astype(np.float64) * np.asarray(factor, np.float64)).astype(np.float32)
    return Radiometry(np.asarray(dark, np.float64).astype(np.float32), gain.astype(np.float32), resp, saturation)


def saturation_for(bit_depth: int | None, dtype: np.dtype) -> float | None:
    if bit_depth is None or dtype.kind not in "ui":
        return None
    return float(2 ** int(bit_depth) - 1)


