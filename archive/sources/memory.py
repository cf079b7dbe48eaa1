"""An in-memory flight (arrays and poses given directly) as a :class:`~archive.sources.base.FlightSource`:
the fake the tests use beside the raw and collection sources."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from archive.errors import InputError, NavigationError
from archive.formats.envi import EnviHeader, header_from_metadata
from archive.geometry.navigation import Poses, Track, interpolate_poses
from archive.params import NavigationParams
from archive.sources.base import CubeInfo, Radiometry, band_list, check_cube, check_mode, radiometry_for

__all__ = ["MemoryFlightSource"]

_ENVI_TYPES = {np.dtype(np.uint8): 1, np.dtype(np.int16): 2, np.dtype(np.int32): 3, np.dtype(np.float32): 4,
               np.dtype(np.float64): 5, np.dtype(np.uint16): 12, np.dtype(np.uint32): 13}


class MemoryFlightSource:
    """An in-memory flight: cubes (bands, lines, samples) and their poses given directly.

    dark, gain: (bands, samples) calibration terms shared by all cubes (no ``gain``: no
    calibration; no ``dark``: 0); responses: per cube (lines,) exposure factors (None: 1);
    white_reference: (bands,). 'relative' uses dark (or 0), gain 1 and the responses.
    wavelengths, fwhm: (bands,) band centres and spectral widths (full width at half maximum), nm.
    fov_deg, ground_height: what the source records (None: nothing).
    """

    def __init__(self, data: Sequence[np.ndarray], poses: Sequence[Poses], *, id: str = "memory",
                 wavelengths: Sequence[float] | None = None, fwhm: Sequence[float] | None = None,
                 dark: np.ndarray | None = None,
                 gain: np.ndarray | None = None, responses: Sequence[np.ndarray] | None = None,
                 bit_depth: int | None = None, white_reference: np.ndarray | None = None,
                 framerate: float | None = None, shutter_ms: float | None = None, gain_db: float | None = None,
                 params: NavigationParams | None = None, fov_deg: float | None = None,
                 ground_height: float | None = None):
        if len(data) == 0 or len(data) != len(poses):
            raise InputError(id, f"{len(data)} cubes for {len(poses)} pose sets", "give one Poses per cube")
        self.id = id
        self.label = id
        self.params = (params if params is not None else NavigationParams()).resolved()
        self.fov_deg = fov_deg
        self.ground_height = ground_height
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
        self.fwhm = None if fwhm is None else tuple(float(w) for w in fwhm)
        self._dark = None if dark is None else np.asarray(dark, np.float32)
        self._gain = None if gain is None else np.asarray(gain, np.float32)
        self.has_calibration = self._gain is not None
        self._responses = None if responses is None else [np.asarray(r, np.float32) for r in responses]
        self.white_reference = None if white_reference is None else np.asarray(white_reference, float)
        self._headers = []
        for i, d in enumerate(self._data):
            meta: dict[str, object] = {"samples": d.shape[2], "lines": d.shape[1], "bands": nbands,
                                       "data type": _ENVI_TYPES.get(d.dtype.newbyteorder("="), 4),
                                       "interleave": "bsq", "byte order": 0}
            for key, value in (("wavelength", None if wavelengths is None else list(self.wavelengths)),
                               ("fwhm", None if fwhm is None else list(self.fwhm)),
                               ("bit depth", bit_depth), ("framerate", framerate), ("shutter", shutter_ms),
                               ("gain", gain_db)):
                if value is not None:
                    meta[key] = value
            self._headers.append(header_from_metadata(meta, f"{id} cube {i}"))
        self.cubes = tuple(
            CubeInfo(index=i, base=f"{id}_{i}", lines=d.shape[1], samples=d.shape[2], bands=nbands,
                     wavelengths=self.wavelengths, shutter_ms=shutter_ms, gain_db=gain_db, framerate=framerate,
                     bit_depth=bit_depth, first_time=float(p.time[0]) if len(p.time) else math.nan)
            for i, (d, p) in enumerate(zip(self._data, self._poses, strict=True)))

    def __dask_tokenize__(self):
        # In-memory arrays: hash their bytes (test-sized flights).
        from dask.base import tokenize

        return ("MemoryFlightSource", self.id, tokenize(self._data), tokenize([(p.time, p.position, p.attitude.as_quat())
                                                                             for p in self._poses]),
                None if self._dark is None else self._dark.tobytes(),
                None if self._gain is None else self._gain.tobytes(),
                None if self._responses is None else tokenize(self._responses),
                None if self.white_reference is None else self.white_reference.tobytes(), self.cubes)

    def header(self, cube: int) -> EnviHeader:
        """A header built from the arrays (samples, lines, bands, data type, exposure keys)."""
        return self._headers[check_cube(cube, self.cubes, self.id)]

    def line_times(self, cube: int) -> np.ndarray:
        return np.asarray(self._poses[check_cube(cube, self.cubes, self.id)].time, float)

    def track(self, cube: int) -> Track:
        p = self._poses[check_cube(cube, self.cubes, self.id)]
        return Track(time=p.time, position=p.position, attitude=p.attitude)

    def poses(self, cube: int, delay: float = 0.0) -> Poses:
        """The given poses; with ``delay`` (s), interpolated between them (extrapolated past the last)."""
        p = self._poses[check_cube(cube, self.cubes, self.id)]
        if delay == 0.0:
            return p
        if len(p.time) < 2:
            raise NavigationError(self.id, f"cube {cube}: cannot shift poses of a single line")
        track = Track(time=p.time, position=p.position, attitude=p.attitude)
        return interpolate_poses(track, p.time + delay, self.frame, where=self.id, tolerance=abs(delay))

    def read_bands(self, cube: int, bands: Sequence[int]) -> np.ndarray:
        d = self._data[check_cube(cube, self.cubes, self.id)]
        return d[band_list(bands, d.shape[0], self.id)].copy()

    def radiometry(self, cube: int, bands: Sequence[int], mode: str,
                   white_reference: np.ndarray | None = None) -> Radiometry:
        check_mode(mode)
        cube = check_cube(cube, self.cubes, self.id)
        info = self.cubes[cube]
        idx = band_list(bands, info.bands, self.id)
        resp = np.ones(info.lines, np.float32) if self._responses is None else self._responses[cube]

        def calibration():
            dark = np.zeros((len(idx), info.samples), np.float32) if self._dark is None else self._dark[idx]
            gain = np.ones((len(idx), info.samples), np.float32) if self._gain is None else self._gain[idx]
            return dark, gain, 1.0, 0.0

        calibrated = self._gain is not None or (mode == "relative" and self._dark is not None)
        white = white_reference if white_reference is not None else self.white_reference
        return radiometry_for(self._headers[cube], idx, mode, calibration if calibrated else None, white, self.id,
                              ("needs a radiometric calibration and there is none",
                               "pass --calibration FILE.icp, or use --mode raw"),
                              responses=None if mode == "raw" else resp)
