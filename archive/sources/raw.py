"""A raw Resonon flight directory as a :class:`~archive.sources.base.FlightSource`."""

from __future__ import annotations

import dataclasses
import json
import os
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from archive.errors import InputError, MissingInputError
from archive.formats.envi import EnviCube, EnviHeader
from archive.formats.flight import CubeFiles, discover_flight
from archive.formats.icp import Calibration, read_icp
from archive.formats.lcf import read_lcf
from archive.formats.trajectory import on_gps_scale, read_trajectory
from archive.formats.times import read_times
from archive.sources.irradiance import SkyIrradiance
from archive.geometry.navigation import LocalFrame, local_frame_for
from archive.params import NavigationParams
from archive.sources.downwelling import DownwellingFiles
from archive.sources.base import CubeInfo, Radiometry, band_list, check_mode, radiometry_for
from archive.sources.navigation import CubeNavigation, FlightNavigation, NavigatedSource, trajectory_cube

__all__ = ["NAVIGATION_SIDECAR", "RawFlightSource", "flight_id", "read_navigation_sidecar"]

#: A raw flight directory's record of its navigation parameters (``archive calibrate --apply``):
#: JSON with 'sync_offset' (s), 'boresight_deg' (3), 'lever_arm_m' (3) and 'ground_height' (m or
#: null). Parameters not given by the caller default to it, as a collection's do to its ingest's.
NAVIGATION_SIDECAR = "navigation_params.json"


def read_navigation_sidecar(directory: str | os.PathLike) -> dict:
    """The sidecar of a raw flight directory ({} when there is none); InputError naming the file
    when it is not a JSON object."""
    path = Path(directory) / NAVIGATION_SIDECAR
    if not path.is_file():
        return {}
    try:
        record = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise InputError(path, f"cannot be read as JSON ({exc})", "fix or delete it") from None
    if not isinstance(record, dict):
        raise InputError(path, "is not a JSON object", "fix or delete it")
    return record


def flight_id(name: str, t0: float) -> str:
    """Id of a raw flight: its directory name made file-safe, and its first .lcf time (s)."""
    name = re.sub(r"[^A-Za-z0-9._-]+", "_", name).strip("._") or "flight"
    return f"{name}-{t0:.3f}"


@dataclass(frozen=True, eq=False)
class _RawCube:
    files: CubeFiles
    header: EnviHeader


class RawFlightSource(NavigatedSource):
    """A raw Resonon flight directory (``<base>.bil`` + ``.bil.hdr`` + ``.lcf`` + ``.bil.times``
    per cube, optional ``*.icp``).

    The constructor reads and checks the small files only: every header (and the data file size),
    every ``.times`` (count = lines), every ``.lcf``, and navigation coverage of every line
    (:class:`~archive.sources.navigation.FlightNavigation`). Pixels are read per call; the
    calibration is parsed on first use. ``white_reference``: (bands,) radiance of a white
    reference, for 'reflectance'.
    """

    fov_deg: float | None = None       # a raw flight does not record its field of view
    ground_height: float | None = None  # nor a ground height it was processed with

    def __init__(self, directory: str | os.PathLike, params: NavigationParams,
                 calibration: str | os.PathLike | None = None, white_reference: np.ndarray | None = None,
                 irradiance_calibration: str | os.PathLike | None = None,
                 navigation: str | os.PathLike | None = None, navigation_columns: dict | None = None):
        flight = discover_flight(directory)
        self.directory = Path(flight.directory)
        self.label = str(self.directory)
        recorded = read_navigation_sidecar(self.directory)   # archive calibrate --apply
        params = params.resolved(recorded)
        self.params = params
        if recorded.get("ground_height") is not None:
            self.ground_height = float(recorded["ground_height"])
        if calibration is not None:
            calibration = Path(calibration)
            if not calibration.is_file():
                raise MissingInputError(calibration, "calibration file", "check the --calibration path")
        self.calibration_path: Path | None = calibration if calibration is not None else flight.calibration
        self.has_calibration = self.calibration_path is not None
        self.white_reference = None if white_reference is None else np.asarray(white_reference, float)
        self._calibration: Calibration | None = None

        raw: list[_RawCube] = []
        nav: list[CubeNavigation] = []
        frame: LocalFrame | None = None
        for files in flight.cubes:
            header = EnviCube(files.data).header  # checks the data file size against the header
            times = read_times(files.times, expected_lines=header.lines)
            lcf = read_lcf(files.lcf)
            if frame is None:
                frame = local_frame_for(lcf)
            raw.append(_RawCube(files, header))
            nav.append(CubeNavigation(times, lcf, header.shutter, str(files.lcf)))
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
        self.fwhm: tuple[float, ...] | None = first.fwhm
        self.id: str = flight_id(self.directory.name, float(nav[0].lcf.time[0]))
        self.navigation_source = "lcf"
        self.recorded_navigation = tuple(nav)   #: the cubes' own .lcf (what an ingest stores as 'navigation')
        self.trajectory = None   #: the post-processed trajectory, its times on the .lcf scale (``.time``)
        if navigation is not None:   # a post-processed trajectory instead of the recorder's .lcf
            trajectory = read_trajectory(navigation, navigation_columns)
            gps = on_gps_scale(trajectory, nav[0].lcf.time[0])
            nav = [trajectory_cube(c, trajectory, gps, float(params.sync_offset or 0.0)) for c in nav]
            self.navigation_source = str(Path(navigation).absolute())
            self.trajectory = dataclasses.replace(trajectory, time=gps, week_seconds=False, utc=False)
        self.navigation = FlightNavigation(nav, frame, params)
        self.cubes: tuple[CubeInfo, ...] = tuple(
            CubeInfo(index=i, base=c.files.base, lines=c.header.lines, samples=c.header.samples,
                     bands=c.header.bands, wavelengths=c.header.wavelengths, shutter_ms=c.header.shutter,
                     gain_db=c.header.gain, framerate=c.header.framerate, bit_depth=c.header.bit_depth,
                     first_time=self.navigation.first_time(i))
            for i, c in enumerate(raw))
        self.downwelling = DownwellingFiles.find(self.directory, [c.files.base for c in raw], irradiance_calibration)
        self._sky: SkyIrradiance | None = None

    def __repr__(self) -> str:
        return f"RawFlightSource({str(self.directory)!r}, cubes={len(self.cubes)})"

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state["_calibration"] = None  # re-read on demand: keeps pickles small
        state["_sky"] = None
        return state

    def __dask_tokenize__(self):
        # The files (by name, size and modification time), the parameters, the calibration file
        # and the white reference: what renders depend on.
        files = tuple((str(c.files.data), c.files.data.stat().st_size, c.files.data.stat().st_mtime_ns)
                      for c in self._raw)
        white = None if self.white_reference is None else self.white_reference.tobytes()
        return ("RawFlightSource", str(self.directory), self.id, files, self.params,
                str(self.calibration_path), white, self.downwelling.token())

    # --- pixels and radiometry ----------------------------------------------------------------

    def header(self, cube: int) -> EnviHeader:
        return self._raw[self._check(cube)].header

    def files(self, cube: int) -> CubeFiles:
        return self._raw[self._check(cube)].files

    def read_bands(self, cube: int, bands: Sequence[int]) -> np.ndarray:
        """(len(bands), lines, samples) DN of ``cube``, native dtype (read with ``os.preadv``: no memory map)."""
        c = self._raw[self._check(cube)]
        return EnviCube(c.files.data).bands(band_list(bands, c.header.bands, str(c.files.data)))

    def calibration(self) -> Calibration | None:
        """The parsed calibration (``--calibration`` or the directory's ``*.icp``), or None."""
        if self._calibration is None and self.calibration_path is not None:
            self._calibration = read_icp(self.calibration_path)
        return self._calibration

    def radiometry(self, cube: int, bands: Sequence[int], mode: str,
                   white_reference: np.ndarray | None = None) -> Radiometry:
        """Radiometric terms of ``bands`` of ``cube`` in ``mode`` (see
        :func:`~archive.sources.base.radiometry_for`); reflectance divides by ``white_reference``
        (or the source's)."""
        check_mode(mode)
        c = self._raw[self._check(cube)]
        h = c.header
        idx = band_list(bands, h.bands, str(c.files.data))
        cal = self.calibration() if mode != "raw" else None

        def calibration():
            dark, gain = cal.for_cube(h)
            return np.asarray(dark)[idx], np.asarray(gain)[idx], cal.shutter_cal, cal.gain_cal

        white = white_reference if white_reference is not None else self.white_reference
        sky = None
        if mode == "reflectance" and white is None and self.downwelling.present:
            def sky():
                spectrum, factor, _ = self.sky().cube_terms(self.line_times(cube), idx, str(c.files.data))
                return spectrum, factor
        return radiometry_for(h, idx, mode, None if cal is None else calibration, white, self.label,
                              ("needs a radiometric calibration (*.icp) and there is none",
                               "pass --calibration FILE.icp, or use --mode raw"), sky=sky)

    def sky(self) -> SkyIrradiance:
        """The flight's downwelling irradiance (read on first use; InputError naming the missing or
        garbled file when it cannot be)."""
        if self._sky is None:
            if self.wavelengths is None:
                raise InputError(self._raw[0].header.path, "has no 'wavelength' key: the sky's spectra cannot be "
                                 "matched to the bands", "add it, or pass --white-reference FILE")
            self._sky = self.downwelling.read([self.navigation.first_time(i) for i in range(len(self.cubes))],
                                              self.wavelengths, self.fwhm)
        return self._sky
