"""Flight sources: the one I/O protocol the renderer and the pipeline read flights through.

A :class:`FlightSource` gives, per cube, camera poses (one per line, at exposure start), pixel reads
of chosen bands (band, line, sample) and the radiometric terms the shader applies::

    value = (DN - dark[band, sample]) * gain[band, sample] / response[line]

:class:`RawFlightSource` reads a raw Resonon flight directory (DESIGN 2); :class:`MemoryFlightSource`
holds arrays given directly (for tests). Both are picklable and cheap to send to Dask workers:
pixels are only read inside :meth:`read_bands`.
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np

from archive.errors import InputError, MissingInputError, NavigationError
from archive.ingest.envi import EnviCube, EnviHeader
from archive.ingest.flight import CubeFiles, discover_flight
from archive.ingest.icp import Calibration, read_icp, response
from archive.ingest.lcf import LcfData, read_lcf
from archive.ingest.navigation import (
    LocalFrame,
    Poses,
    Track,
    boresight_rotation,
    check_coverage,
    interpolate_poses,
    line_times,
    local_frame_for,
    track_from_lcf,
)
from archive.ingest.times import read_times
from archive.params import NavigationParams

__all__ = [
    "MODES", "NAV_TOLERANCE", "SYNC_TOLERANCE", "CubeInfo", "FlightSource", "MemoryFlightSource", "Radiometry",
    "RawFlightSource", "open_source",
]

MODES = ("raw", "relative", "radiance", "reflectance")

# Real .lcf files may stop up to ~15 ms before the last image line (see the samples README), and a
# sync offset moves lines past one end of their .lcf by design (the first line and the first .lcf
# row are simultaneous). Poses up to NAV_TOLERANCE + min(|sync offset|, SYNC_TOLERANCE) outside
# the .lcf are extrapolated from its first/last interval; anything further is a NavigationError.
NAV_TOLERANCE = 0.02  # s
SYNC_TOLERANCE = 0.1  # s

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
    """A flight the renderer can read: cubes in capture order sharing one local frame."""

    id: str
    frame: LocalFrame
    cubes: tuple[CubeInfo, ...]
    wavelengths: tuple[float, ...] | None

    def poses(self, cube: int, delay: float = 0.0) -> Poses:
        """Camera poses at exposure START of each line of ``cube`` (plus ``delay`` seconds, e.g.
        shutter/2 for mid-exposure poses)."""
        ...

    def read_bands(self, cube: int, bands: Sequence[int]) -> np.ndarray:
        """(len(bands), lines, samples) DN in the cube's native dtype."""
        ...

    def radiometry(self, cube: int, bands: Sequence[int], mode: str) -> Radiometry:
        """Radiometric terms for ``bands`` of ``cube`` in ``mode`` (one of MODES)."""
        ...


def _check_mode(mode: str) -> None:
    if mode not in MODES:
        raise InputError(None, f"unknown radiometric mode {mode!r}", f"use one of {', '.join(MODES)}")


def _check_cube(index: int, cubes: Sequence[CubeInfo], where: str) -> int:
    if isinstance(index, bool) or not isinstance(index, int | np.integer) or not 0 <= index < len(cubes):
        raise InputError(where, f"cube {index!r} out of range 0..{len(cubes) - 1}")
    return int(index)


def _band_list(bands: Sequence[int], nbands: int, where: str) -> list[int]:
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


def _white(white_reference, bands: list[int], nbands: int, where: str) -> np.ndarray:
    if white_reference is None:
        raise InputError(where, "mode 'reflectance' needs a white reference spectrum",
                         "pass --white-reference FILE, or use --mode radiance")
    white = np.asarray(white_reference, float).ravel()
    if white.size != nbands:
        raise InputError(where, f"white reference has {white.size} values for {nbands} bands",
                         "give one radiance per band, interpolated to the band wavelengths")
    sel = white[bands]
    if not np.all(np.isfinite(sel) & (sel > 0)):
        raise InputError(where, "white reference has zero, negative or NaN values in the selected bands")
    return sel


def radiometry_for(header: EnviHeader, bands: list[int], mode: str, calibration, white_reference,
                   where: str, no_calibration: tuple[str, str]) -> Radiometry:
    """Radiometric terms of ``bands`` (checked indices) of the cube described by ``header``.

    ``calibration`` is None (no calibration) or a callable returning (dark, gain, shutter_cal,
    gain_cal) for those bands: dark and gain (len(bands), samples) matched to the cube. Modes:

    - raw: dark 0, gain 1, response 1 (values are DN);
    - relative: dark from the calibration if there is one (else 0), gain 1, response = exposure
      against 1 ms at 0 dB (DN per ms at 0 dB);
    - radiance: dark and gain of the calibration, response = (shutter / shutter_cal) x
      10**((gain - gain_cal) / 20);
    - reflectance: radiance divided by ``white_reference`` (bands of the cube), per band.

    ``no_calibration`` is the (problem, fix) said when a mode needs a calibration and there is none.
    """
    h = header
    shape = (len(bands), h.samples)
    saturation = _saturation(h.bit_depth, h.dtype)
    if mode == "raw":
        return Radiometry(np.zeros(shape, np.float32), np.ones(shape, np.float32),
                          np.ones(h.lines, np.float32), saturation)
    if mode == "relative":
        dark = np.zeros(shape, np.float32) if calibration is None else np.asarray(calibration()[0], np.float32)
        exposure = _exposure(h.shutter, h.gain, RELATIVE_SHUTTER_MS, RELATIVE_GAIN_DB)
        return Radiometry(dark, np.ones(shape, np.float32), np.full(h.lines, exposure, np.float32), saturation)
    if calibration is None:
        raise InputError(where, f"mode '{mode}' {no_calibration[0]}", no_calibration[1])
    for key, value in (("shutter", h.shutter), ("gain", h.gain)):
        if value is None:
            raise InputError(h.path, f"no '{key}' key: cannot scale the calibration to this cube",
                             "add it to the header, or use --mode raw")
    dark, gain, shutter_cal, gain_cal = calibration()
    gain = np.asarray(gain, np.float64)
    if mode == "reflectance":
        gain = gain / _white(white_reference, bands, h.bands, where)[:, None]
    resp = response(h.shutter, h.gain, shutter_cal, gain_cal)
    return Radiometry(np.asarray(dark, np.float64).astype(np.float32), gain.astype(np.float32),
                      np.full(h.lines, resp, np.float32), saturation)


def _saturation(bit_depth: int | None, dtype: np.dtype) -> float | None:
    if bit_depth is None or dtype.kind not in "ui":
        return None
    return float(2 ** int(bit_depth) - 1)


@dataclass(frozen=True)
class _RawCube:
    files: CubeFiles
    header: EnviHeader
    times: np.ndarray   # (lines,) s, camera clock
    lcf: LcfData
    track: Track


def _safe_id(name: str, t0: float) -> str:
    name = re.sub(r"[^A-Za-z0-9._-]+", "_", name).strip("._") or "flight"
    return f"{name}-{t0:.3f}"


class RawFlightSource:
    """A raw Resonon flight directory (``<base>.bil`` + ``.bil.hdr`` + ``.lcf`` + ``.bil.times``
    per cube, optional ``*.icp``).

    The constructor reads and checks the small files only: every header (and the data file size),
    every ``.times`` (count = lines), every ``.lcf``, and that each cube's ``.lcf`` covers its line
    times up to mid-exposure of the last line. Pixels are read per call; the calibration is parsed
    on first use. ``white_reference``: (bands,) radiance of a white reference, for 'reflectance'.
    """

    def __init__(self, directory: str | os.PathLike, params: NavigationParams,
                 calibration: str | os.PathLike | None = None, white_reference: np.ndarray | None = None):
        flight = discover_flight(directory)
        self.directory = Path(flight.directory)
        self.params = params
        if calibration is not None:
            calibration = Path(calibration)
            if not calibration.is_file():
                raise MissingInputError(calibration, "calibration file", "check the --calibration path")
        self.calibration_path: Path | None = calibration if calibration is not None else flight.calibration
        self.white_reference = None if white_reference is None else np.asarray(white_reference, float)
        self._calibration: Calibration | None = None
        self._boresight = boresight_rotation(params.boresight_deg)

        raw: list[_RawCube] = []
        frame: LocalFrame | None = None
        for files in flight.cubes:
            header = EnviCube(files.data).header  # checks the data file size against the header
            times = read_times(files.times, expected_lines=header.lines)
            lcf = read_lcf(files.lcf)
            if frame is None:
                frame = local_frame_for(lcf)
            raw.append(_RawCube(files, header, times, lcf, track_from_lcf(lcf, frame)))
        if frame is None:
            raise InputError(self.directory, "no cubes found", "a flight directory holds <base>.bil cubes")
        self.frame: LocalFrame = frame
        self._raw: tuple[_RawCube, ...] = tuple(raw)

        first = raw[0].header
        for c in raw[1:]:
            if c.header.bands != first.bands:
                raise InputError(c.header.path, f"{c.header.bands} bands, but {first.path.name} has {first.bands}",
                                 "a flight's cubes must share their bands")
        self.wavelengths: tuple[float, ...] | None = first.wavelengths
        self.cubes: tuple[CubeInfo, ...] = tuple(
            CubeInfo(index=i, base=c.files.base, lines=c.header.lines, samples=c.header.samples,
                     bands=c.header.bands, wavelengths=c.header.wavelengths, shutter_ms=c.header.shutter,
                     gain_db=c.header.gain, framerate=c.header.framerate, bit_depth=c.header.bit_depth,
                     first_time=float(c.lcf.time[0]) + float(params.sync_offset))
            for i, c in enumerate(raw))
        self.id: str = _safe_id(self.directory.name, float(raw[0].lcf.time[0]))
        for i in range(len(raw)):
            self.check_navigation(i)

    def __repr__(self) -> str:
        return f"RawFlightSource({str(self.directory)!r}, cubes={len(self.cubes)})"

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state["_calibration"] = None  # re-read on demand: keeps pickles small
        return state

    # --- navigation ---------------------------------------------------------------------------

    def _tolerance(self) -> float:
        return NAV_TOLERANCE + min(abs(float(self.params.sync_offset)), SYNC_TOLERANCE)

    def line_times(self, cube: int) -> np.ndarray:
        """(lines,) exposure-start times of ``cube`` on the .lcf scale (sync offset included), s."""
        c = self._raw[_check_cube(cube, self.cubes, str(self.directory))]
        return line_times(c.times, c.lcf.time[0], self.params.sync_offset)

    def check_navigation(self, cube: int) -> None:
        """NavigationError naming the cube's .lcf unless it covers every line from exposure start
        of the first to mid-exposure of the last (within NAV_TOLERANCE)."""
        c = self._raw[cube]
        t = self.line_times(cube)
        half = 0.0 if c.header.shutter is None else c.header.shutter / 2000.0
        check_coverage(c.track.time, np.array([t[0], t[-1] + half]), str(c.files.lcf), self._tolerance())

    def track(self, cube: int) -> Track:
        """INS samples of ``cube``'s .lcf in the flight's frame."""
        return self._raw[_check_cube(cube, self.cubes, str(self.directory))].track

    def poses(self, cube: int, delay: float = 0.0) -> Poses:
        """Camera poses of every line of ``cube`` at exposure start + ``delay`` seconds:
        (lines, 3) NED positions, (lines,) camera -> NED attitudes."""
        cube = _check_cube(cube, self.cubes, str(self.directory))
        c = self._raw[cube]
        t = self.line_times(cube) + float(delay)
        return interpolate_poses(c.track, t, self.frame, boresight=self._boresight,
                                 lever_arm=self.params.lever_arm_m, where=str(c.files.lcf),
                                 tolerance=self._tolerance() + abs(float(delay)))

    # --- pixels and radiometry ----------------------------------------------------------------

    def header(self, cube: int) -> EnviHeader:
        return self._raw[_check_cube(cube, self.cubes, str(self.directory))].header

    def files(self, cube: int) -> CubeFiles:
        return self._raw[_check_cube(cube, self.cubes, str(self.directory))].files

    def read_bands(self, cube: int, bands: Sequence[int]) -> np.ndarray:
        """(len(bands), lines, samples) DN of ``cube``, native dtype (memory-mapped read)."""
        c = self._raw[_check_cube(cube, self.cubes, str(self.directory))]
        return EnviCube(c.files.data).bands(_band_list(bands, c.header.bands, str(c.files.data)))

    def calibration(self) -> Calibration | None:
        """The parsed calibration (``--calibration`` or the directory's ``*.icp``), or None."""
        if self._calibration is None and self.calibration_path is not None:
            self._calibration = read_icp(self.calibration_path)
        return self._calibration

    def radiometry(self, cube: int, bands: Sequence[int], mode: str,
                   white_reference: np.ndarray | None = None) -> Radiometry:
        """Radiometric terms of ``bands`` of ``cube`` in ``mode``:

        - raw: dark 0, gain 1, response 1 (values are DN);
        - relative: dark from the calibration if there is one (else 0), gain 1, response = exposure
          against 1 ms at 0 dB (DN per ms at 0 dB);
        - radiance: dark and gain of the calibration, response = (shutter / shutter_cal) x
          10**((gain - gain_cal) / 20);
        - reflectance: radiance divided by ``white_reference`` (or the source's), per band.
        """
        _check_mode(mode)
        cube = _check_cube(cube, self.cubes, str(self.directory))
        c = self._raw[cube]
        h = c.header
        idx = _band_list(bands, h.bands, str(c.files.data))
        cal = self.calibration() if mode != "raw" else None

        def calibration():
            dark, gain = cal.for_cube(h)
            return np.asarray(dark)[idx], np.asarray(gain)[idx], cal.shutter_cal, cal.gain_cal

        white = white_reference if white_reference is not None else self.white_reference
        return radiometry_for(h, idx, mode, None if cal is None else calibration, white, str(self.directory),
                              ("needs a radiometric calibration (*.icp) and there is none",
                               "pass --calibration FILE.icp, or use --mode raw"))


class MemoryFlightSource:
    """An in-memory flight for tests: cubes (bands, lines, samples) and their poses given directly.

    dark, gain: (bands, samples) calibration terms shared by all cubes (None: no calibration);
    responses: per cube (lines,) exposure factors (None: 1); white_reference: (bands,).
    'relative' uses dark (or 0), gain 1 and the responses.
    """

    def __init__(self, data: Sequence[np.ndarray], poses: Sequence[Poses], *, id: str = "memory",
                 wavelengths: Sequence[float] | None = None, dark: np.ndarray | None = None,
                 gain: np.ndarray | None = None, responses: Sequence[np.ndarray] | None = None,
                 bit_depth: int | None = None, white_reference: np.ndarray | None = None,
                 framerate: float | None = None, shutter_ms: float | None = None, gain_db: float | None = None):
        if len(data) == 0 or len(data) != len(poses):
            raise InputError(id, f"{len(data)} cubes for {len(poses)} pose sets", "give one Poses per cube")
        self.id = id
        self._data = [np.asarray(d) for d in data]
        self._poses = list(poses)
        self.frame = self._poses[0].frame
        nbands = self._data[0].shape[0]
        for i, (d, p) in enumerate(zip(self._data, self._poses, strict=True)):
            if d.ndim != 3 or d.shape[0] != nbands:
                raise InputError(id, f"cube {i} has shape {d.shape}, expected ({nbands}, lines, samples)")
            if len(p.time) != d.shape[1]:
                raise InputError(id, f"cube {i} has {d.shape[1]} lines but {len(p.time)} poses")
            if p.frame != self.frame:
                raise InputError(id, f"cube {i} poses are in another frame")
        self.wavelengths = None if wavelengths is None else tuple(float(w) for w in wavelengths)
        self._dark = None if dark is None else np.asarray(dark, np.float32)
        self._gain = None if gain is None else np.asarray(gain, np.float32)
        self._responses = None if responses is None else [np.asarray(r, np.float32) for r in responses]
        self.white_reference = white_reference
        self._bit_depth = bit_depth
        self.cubes = tuple(
            CubeInfo(index=i, base=f"{id}_{i}", lines=d.shape[1], samples=d.shape[2], bands=nbands,
                     wavelengths=self.wavelengths, shutter_ms=shutter_ms, gain_db=gain_db, framerate=framerate,
                     bit_depth=bit_depth, first_time=float(p.time[0]) if len(p.time) else math.nan)
            for i, (d, p) in enumerate(zip(self._data, self._poses, strict=True)))

    def poses(self, cube: int, delay: float = 0.0) -> Poses:
        """The given poses; with ``delay`` (s), interpolated between them (extrapolated past the last)."""
        p = self._poses[_check_cube(cube, self.cubes, self.id)]
        if delay == 0.0:
            return p
        if len(p.time) < 2:
            raise NavigationError(self.id, f"cube {cube}: cannot shift poses of a single line")
        track = Track(time=p.time, position=p.position, attitude=p.attitude)
        return interpolate_poses(track, p.time + delay, self.frame, where=self.id, tolerance=abs(delay))

    def read_bands(self, cube: int, bands: Sequence[int]) -> np.ndarray:
        d = self._data[_check_cube(cube, self.cubes, self.id)]
        return d[_band_list(bands, d.shape[0], self.id)].copy()

    def radiometry(self, cube: int, bands: Sequence[int], mode: str,
                   white_reference: np.ndarray | None = None) -> Radiometry:
        _check_mode(mode)
        cube = _check_cube(cube, self.cubes, self.id)
        info = self.cubes[cube]
        idx = _band_list(bands, info.bands, self.id)
        shape = (len(idx), info.samples)
        sat = _saturation(self._bit_depth, self._data[cube].dtype)
        ones = np.ones(info.lines, np.float32)
        resp = ones if self._responses is None else self._responses[cube]
        if mode == "raw":
            return Radiometry(np.zeros(shape, np.float32), np.ones(shape, np.float32), ones, sat)
        dark = np.zeros(shape, np.float32) if self._dark is None else self._dark[idx]
        if mode == "relative":
            return Radiometry(dark, np.ones(shape, np.float32), resp, sat)
        if self._gain is None:
            raise InputError(self.id, f"mode '{mode}' needs a radiometric calibration and there is none",
                             "pass --calibration FILE.icp, or use --mode raw")
        gain = self._gain[idx].astype(np.float64)
        if mode == "reflectance":
            white = white_reference if white_reference is not None else self.white_reference
            gain = gain / _white(white, idx, info.bands, self.id)[:, None]
        return Radiometry(dark, gain.astype(np.float32), resp, sat)


def open_source(path_or_id: str | os.PathLike, params: NavigationParams,
                calibration: str | os.PathLike | None = None,
                white_reference: np.ndarray | None = None,
                archive: str | os.PathLike | None = None) -> FlightSource:
    """A flight source: a raw flight directory, or a collection id in ``archive``.

    A directory wins over a collection of the same name. A collection carries its own calibration,
    so ``calibration`` must be None for one.
    """
    path = Path(path_or_id)
    if path.is_dir():
        return RawFlightSource(path, params, calibration=calibration, white_reference=white_reference)
    if archive is not None and not path.exists():
        if calibration is not None:
            raise InputError("--calibration", f"collection {path_or_id} carries the calibration it was "
                             "ingested with", "leave out --calibration, or re-ingest with another .icp")
        from archive.ingest.collection import CollectionSource

        return CollectionSource(archive, str(path_or_id), params, white_reference=white_reference)
    if path.exists():
        raise InputError(path, "is not a directory", "give a raw flight directory or a collection id with --archive")
    raise MissingInputError(path, "flight directory",
                            "give a raw flight directory, or a collection id together with --archive ARCHIVE")

