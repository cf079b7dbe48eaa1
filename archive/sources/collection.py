"""An ingested collection (a Zarr store of an archive) as a :class:`~archive.sources.base.FlightSource`."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from archive.collection import CheckedDn, StoredCalibration, read_downwelling, read_info, read_track
from archive.errors import InputError
from archive.formats.envi import EnviHeader
from archive.params import NavigationParams, recorded_navigation
from archive.sources.base import CubeInfo, Radiometry, band_list, check_mode, radiometry_for
from archive.sources.irradiance import CubeIrradiance, SkyIrradiance
from archive.sources.navigation import CubeNavigation, FlightNavigation, NavigatedSource

__all__ = ["CollectionSource"]


class CollectionSource(NavigatedSource):
    """A collection store (``<archive>/collections/<id>.zarr``) read as a flight.

    Poses are recomputed from the stored raw navigation with ``params`` (sync offset, boresight,
    lever arm) by the same :class:`~archive.sources.navigation.FlightNavigation` as the raw
    source, so both give identical poses, DN and radiometry. ``read_bands`` reads only the chunks
    of the cube's lines. ``fov_deg`` and ``ground_height`` are the ones ingested; navigation
    parameters left None (sync offset, boresight, lever arm) take the values
    given at ingest (attribute ``navigation_params``), else 0. Picklable. Use :func:`archive.sources.open_source` to open one by id.
    """

    def __init__(self, store: str | os.PathLike, id: str, params: NavigationParams,
                 white_reference: np.ndarray | None = None, navigation: str | None = None):
        info = read_info(store)
        self.store = info.store   # a Path, or a UPath for a collection in object storage
        self.label = str(self.store)
        self.id = id
        params = params.resolved(recorded_navigation(info.attrs))  # the mounting given at ingest / calibrate
        self.params = params
        self.white_reference = None if white_reference is None else np.asarray(white_reference, float)
        self.info = info
        self.fov_deg: float | None = info.fov_deg
        self.ground_height: float | None = info.ground_height
        self.frame = info.frame
        self._headers = [c.header for c in info.cubes]
        self._line_offset = [c.line_offset for c in info.cubes]
        cubes = [CubeNavigation(c.camera_time, c.lcf, c.header.shutter, self._where(c.index, c.base))
                 for c in info.cubes]
        tracks = info.attrs.get("navigation_tracks") or {}
        # the navigation source: None, the collection's default (a stored trajectory, else the .lcf); 'lcf'; a track
        self.navigation_source = (tracks.get("default") or "lcf") if navigation is None else str(navigation)
        if self.navigation_source != "lcf":
            cubes = self._on_track(cubes, self.navigation_source, float(params.sync_offset or 0.0))
        self.navigation = FlightNavigation(cubes, self.frame, params)
        self.wavelengths = self._headers[0].wavelengths
        self.fwhm = info.fwhm
        self.cubes = tuple(
            CubeInfo(index=i, base=c.base, lines=h.lines, samples=h.samples, bands=h.bands,
                     wavelengths=h.wavelengths, shutter_ms=h.shutter, gain_db=h.gain, framerate=h.framerate,
                     bit_depth=h.bit_depth, first_time=self.navigation.first_time(i))
            for i, (c, h) in enumerate(zip(info.cubes, self._headers, strict=True)))
        self._calibration = info.calibration
        self.has_calibration = self._calibration is not None
        self._dn = None
        self._stored_calibration = None   # opened on first use, per process (not pickled)

    def _on_track(self, cubes: list[CubeNavigation], name: str, sync: float) -> list[CubeNavigation]:
        """``cubes`` navigated by the stored trajectory ``name`` (:func:`archive.collection.read_track`)."""
        from archive.formats.trajectory import Trajectory
        from archive.sources.navigation import trajectory_cube

        a = read_track(self.store, name)
        track = Trajectory(Path(f"{self.store}#{name}"), a[:, 0], a[:, 5], a[:, 4], a[:, 6], -a[:, 1], a[:, 2],
                           a[:, 3], week_seconds=False)
        return [trajectory_cube(c, track, track.time, sync) for c in cubes]

    def __repr__(self) -> str:
        return f"CollectionSource({str(self.store)!r}, cubes={len(self.cubes)})"

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state["_dn"] = None
        state["_stored_calibration"] = None
        return state

    def __dask_tokenize__(self):
        # What renders depend on: the stored content (its plan token covers sources and layout),
        # the navigation parameters and the white reference; never the pixels.
        white = None if self.white_reference is None else self.white_reference.tobytes()
        return ("CollectionSource", str(self.store), self.id, self.info.plan, self.params, white)

    def _where(self, cube: int, base: str | None = None) -> str:
        return f"{self.store} cube {cube} ({base if base is not None else self.cubes[cube].base})"

    def header(self, cube: int) -> EnviHeader:
        """The cube's ENVI header as ingested (its path names the store, not a file)."""
        return self._headers[self._check(cube)]

    def read_bands(self, cube: int, bands: Sequence[int]) -> np.ndarray:
        """(len(bands), lines, samples) DN of ``cube`` in the stored (native) dtype; reads only the
        chunks holding those bands and the cube's lines, each checked against its recorded sha256
        (:class:`archive.collection.CheckedDn`: a corrupt chunk is a CorruptChunkError naming it)."""
        cube = self._check(cube)
        idx = band_list(bands, self.cubes[cube].bands, self._where(cube))
        if self._dn is None:
            self._dn = CheckedDn(self.store)
        l0 = self._line_offset[cube]
        return self._dn.read_bands(idx, l0, l0 + self.cubes[cube].lines)   # object storage: chunks fetched at once

    def radiometry(self, cube: int, bands: Sequence[int], mode: str,
                   white_reference: np.ndarray | None = None) -> Radiometry:
        """Radiometric terms of ``bands`` of ``cube`` in ``mode``, as the raw source's, from the
        calibration stored at ingest."""
        check_mode(mode)
        cube = self._check(cube)
        h = self._headers[cube]
        idx = band_list(bands, h.bands, self._where(cube))
        cal = self._calibration

        def calibration():
            if self._stored_calibration is None:
                self._stored_calibration = StoredCalibration(self.store)
            dark, gain = self._stored_calibration.read(cube, idx)
            return dark, gain, float(cal["shutter_cal"]), float(cal["gain_cal"])

        white = white_reference if white_reference is not None else self.white_reference
        sky = None
        if mode == "reflectance" and white is None and self.info.attrs.get("downwelling"):
            def sky():
                spectrum, factor, _ = self.sky().cube_terms(self.line_times(cube), idx, self._where(cube))
                return spectrum, factor
        return radiometry_for(h, idx, mode, None if cal is None else calibration, white, self.label,
                              ("needs a radiometric calibration and none was ingested",
                               "re-ingest with --calibration FILE.icp, or use --mode raw"), sky=sky)

    def sky(self) -> SkyIrradiance:
        """The downwelling irradiance stored at ingest, stamped at each cube's first line with this
        source's navigation parameters (InputError when the collection has none)."""
        record = self.info.attrs.get("downwelling")
        x = read_downwelling(self.store) if record else None
        if x is None:
            raise InputError(self.label, "was ingested without downwelling spectra",
                             "pass --white-reference FILE, or re-ingest the flight with its .spec files and .dcp")
        return SkyIrradiance(tuple(CubeIrradiance(name, float(self.navigation.first_time(i)), x[i], shift, 0)
                                   for i, (name, shift) in enumerate(zip(record["spectra"], record["shift_nm"],
                                                                         strict=True))),
                             record["calibration"])
