"""Reading and checking a raw flight for ingest (everything but the pixels): :func:`prepare_flight`
returns the :class:`~archive.collection.StorePlan` of its store, or raises one clear error naming the
cube or file. Writes nothing; runs in the command's process (a local ingest) or as a task on a Dask
worker (``archive ingest --scheduler``: the workers see the raw folders at the same paths)."""

from __future__ import annotations

import math
import os
import re
from pathlib import Path

import numpy as np

import archive
from archive.catalog.root import check_collection_id
from archive.collection import FORMAT, FORMAT_VERSION, NAV_COLUMNS, StorePlan, frame_to_attrs
from archive.errors import InputError
from archive.formats.icp import response as exposure_response
from archive.formats.lcf import gps_seconds_to_datetime
from archive.params import NavigationParams
from archive.sources.ground import auto_ground_height, camera_altitudes, check_ground_height
from archive.sources.raw import RawFlightSource

__all__ = ["collection_id", "dem_of", "jsonable", "prepare_flight", "sensor_name"]


def sensor_name(metadata: dict) -> str | None:
    """The sensor named by a header: imager serial number, else sensor type, else None."""
    for key in ("imager serial number", "sensor type", "sensor"):
        value = metadata.get(key)
        if value not in (None, ""):
            return str(value).strip()
    return None


def collection_id(sensor: str | None, start) -> str:
    """``<sensor>_<UTC start YYYYmmddTHHMMSS>``, sensor reduced to [A-Za-z0-9-] ('flight' if none)."""
    name = re.sub(r"[^A-Za-z0-9]+", "-", sensor or "").strip("-") or "flight"
    return check_collection_id(f"{name}_{start.strftime('%Y%m%dT%H%M%S')}")


def _ground_height(source: RawFlightSource, given: float | None) -> tuple[float, str]:
    """Ground height for the catalog footprint (m) and where it came from: ``given``, else the
    headers' ``ground elevation`` (as ``--ground-height auto``); checked for plausibility."""
    if given is not None:
        if not math.isfinite(given):
            raise InputError("--ground-height", f"must be a finite number of metres, got {given!r}")
        return check_ground_height(float(given), camera_altitudes(source), source.label, "--ground-height"), \
            "argument"
    return auto_ground_height([source]), "header 'ground elevation'"


def _terrain_record(src: RawFlightSource, fov_deg: float, dem_path, dem_datum: str | None,
                    ground_height: float | None, arrays: dict, samples: int, poses: list) -> tuple[float, str, dict]:
    """(ground height, its origin, the ``terrain`` attribute) of a flight ingested with a DEM: the
    footprint traced on the DEM (lon/lat rings, nominal GSD), the DEM's name and vertical datum."""
    from scipy.spatial.transform import Rotation

    from archive.catalog.footprint import flight_footprint
    from archive.terrain.dem import open_dem
    from archive.sources.ground import dem_record

    if ground_height is not None:
        raise InputError("--dem", f"--dem and --ground-height {ground_height:g} are exclusive: the DEM gives "
                         "the ground", "leave --ground-height out")
    dem = open_dem(dem_path, dem_datum)
    dem.check_flight(poses, float(fov_deg))   # names all the ground it lacks under the swath
    position = arrays["position"]
    frame = src.frame
    under = dem.heights_at(frame.epsg, position[:, 1] + frame.origin_e, position[:, 0] + frame.origin_n)
    if not np.isfinite(under).any():
        dem.raise_uncovered(frame.epsg, position[:, 1] + frame.origin_e, position[:, 0] + frame.origin_n,
                            "under the flight track")
    ground = check_ground_height(float(np.nanmedian(under)), camera_altitudes(src), src.label,
                                 f"the median height of the DEM {dem.path} under the track")
    fp = flight_footprint(arrays["time"], position, Rotation.from_quat(arrays["attitude"]), frame,
                          float(fov_deg), ground, samples, where=str(src.label), terrain=dem)
    rings = [[[round(float(x), 9), round(float(y), 9)] for x, y in ring] for ring in fp.lonlat()]
    record = {**dem_record(dem), "gsd": fp.gsd, "footprint_lonlat": rings}
    return ground, f"DEM {dem.path.name} (median under the track)", record


def dem_of(terrain: dict | None) -> tuple[str, str] | None:
    """(DEM path, datum) of a collection's ``terrain`` attribute, or None (ingested without a DEM)."""
    return None if not terrain else (str(terrain.get("dem_path")), str(terrain.get("datum")))


def _track(src: RawFlightSource, arrays: dict, dims: dict) -> str:
    """Add the source's trajectory, over the flight's lines and 2 s beyond, to ``arrays`` as ``track_<name>``
    ((epochs, 7) in the ``.lcf``'s columns and signs); returns the name (the file's stem, made safe)."""
    t = src.trajectory
    name = re.sub(r"[^A-Za-z0-9_-]", "_", Path(t.path).stem)[:64] or "track"
    name = "ppk" if name == "lcf" else name
    keep = (t.time >= arrays["time"][0] - 2.0) & (t.time <= arrays["time"][-1] + 2.0)
    arrays[f"track_{name}"] = np.stack([t.time, -t.roll, t.pitch, t.heading, t.lon, t.lat, t.height],
                                       axis=-1)[keep].astype(np.float64)
    dims[f"track_{name}"] = (f"{name}_epoch", "column")
    return name


def jsonable(value):
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [jsonable(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value


def prepare_flight(directory: str | os.PathLike, fov_deg: float, calibration: str | os.PathLike | None = None,
                   ground_height: float | None = None, sync_offset: float = 0.0,
                   boresight: tuple[float, float, float] = (0.0, 0.0, 0.0),
                   lever_arm: tuple[float, float, float] = (0.0, 0.0, 0.0),
                   dem: str | os.PathLike | None = None, dem_datum: str | None = None,
                   irradiance_calibration: str | os.PathLike | None = None,
                   navigation: str | os.PathLike | None = None, navigation_columns: dict | None = None) -> StorePlan:
    """Read and check a raw flight (everything but the pixels) and return what its store will hold.
    ``navigation``: a post-processed trajectory (SBET, CSV: :mod:`archive.formats.trajectory`) stored as
    the track named by its file's stem beside the ``.lcf`` (``track_<name>``, checksummed like every array)
    and made the collection's default navigation source (the stored poses follow it).
    ``sync_offset`` (s), ``boresight`` (roll, pitch, yaw degrees) and ``lever_arm`` (x, y, z metres,
    body frame) are recorded as the collection's navigation parameters (renders use them unless
    given others) and shape the stored poses and the catalog footprint.
    ``dem`` (with ``dem_datum`` when its CRS declares no vertical datum; exclusive with
    ``ground_height``): the catalog footprint follows the terrain (traced now, recorded as the
    ``terrain`` attribute with the DEM's name), and the recorded ground height is the DEM's median
    under the track (what flat renders of the collection use).
    Raises a clear ArchiveError naming the cube or file for a broken flight; writes nothing."""
    if not (np.isfinite(fov_deg) and 0 < fov_deg < 180):
        raise InputError("--fov", f"field of view {fov_deg} deg is not in (0, 180)", "47.5 for a Pika L")
    nav = NavigationParams(sync_offset=float(sync_offset),
                           boresight_deg=tuple(float(v) for v in boresight),
                           lever_arm_m=tuple(float(v) for v in lever_arm))
    src = RawFlightSource(directory, nav, calibration=calibration, irradiance_calibration=irradiance_calibration,
                          navigation=navigation, navigation_columns=navigation_columns)
    n = len(src.cubes)
    headers = [src.header(i) for i in range(n)]
    files = [src.files(i) for i in range(n)]
    first = headers[0]
    for h in headers[1:]:
        if h.samples != first.samples or h.dtype.newbyteorder("=") != first.dtype.newbyteorder("="):
            raise InputError(h.path, f"{h.samples} samples of {h.dtype}, but {first.path.name} has "
                             f"{first.samples} of {first.dtype}", "a flight's cubes must share samples and data type")
    times = [c.camera_time for c in src.navigation.cubes]  # as read and checked by the source
    lcfs = [c.lcf for c in src.recorded_navigation]   # the recorder's, whatever the poses follow
    poses = [src.poses(i) for i in range(n)]
    cal = src.calibration()
    darks, gains, gain_index = [], [], []
    resp = []
    for i, h in enumerate(headers):
        if cal is not None:
            dark, gain = cal.for_cube(h)  # FormatError naming the cube's header if they do not match
            darks.append(dark)
            for g, known in enumerate(gains):
                if known.shape == gain.shape and np.array_equal(known, gain):
                    gain_index.append(g)
                    break
            else:
                gain_index.append(len(gains))
                gains.append(gain)
        if cal is not None and h.shutter is not None and h.gain is not None:
            r = exposure_response(h.shutter, h.gain, cal.shutter_cal, cal.gain_cal)
        elif h.shutter is not None:
            r = exposure_response(h.shutter, h.gain or 0.0, 1.0, 0.0)
        else:
            r = 1.0
        resp.append(np.full(h.lines, r))

    line_offset = np.concatenate([[0], np.cumsum([h.lines for h in headers])]).astype(int)
    nav_offset = np.concatenate([[0], np.cumsum([len(lcf.time) for lcf in lcfs])]).astype(np.int64)
    arrays: dict[str, np.ndarray] = {
        "time": np.concatenate([src.line_times(i) for i in range(n)]),  # with the sync offset
        "camera_time": np.concatenate(times).astype(np.float64),
        "cube": np.concatenate([np.full(h.lines, i, np.uint16) for i, h in enumerate(headers)]),
        "position": np.concatenate([p.position for p in poses]),
        "attitude": np.concatenate([p.attitude.as_quat() for p in poses]),
        "response": np.concatenate(resp).astype(np.float64),
        "navigation": np.concatenate([np.stack([getattr(lcf, c) for c in NAV_COLUMNS], axis=-1) for lcf in lcfs]),
        "navigation_offset": nav_offset,
        "wavelength": np.asarray(first.wavelengths if first.wavelengths else [np.nan] * first.bands, np.float64),
        "fwhm": np.asarray(first.fwhm if first.fwhm else [np.nan] * first.bands, np.float64),
    }
    dims = {"time": ("line",), "camera_time": ("line",), "cube": ("line",), "position": ("line", "ned"),
            "attitude": ("line", "xyzw"), "response": ("line",), "navigation": ("nav_sample", "column"),
            "navigation_offset": ("cube_edge",), "wavelength": ("band",), "fwhm": ("band",)}
    if any(lcf.use is not None for lcf in lcfs):  # rows flagged 'do not use' (.lcf column 10 = 0)
        arrays["navigation_use"] = np.concatenate([np.ones(len(lcf.time), np.uint8) if lcf.use is None
                                                   else lcf.use.astype(np.uint8) for lcf in lcfs])
        dims["navigation_use"] = ("nav_sample",)
    track = _track(src, arrays, dims) if src.trajectory is not None else None
    downwelling = None
    if src.downwelling.present:   # the sky spectrometer's X per cube on the bands (issue 34)
        sky = src.sky()           # a missing or garbled .spec / .dcp is refused here, naming it
        arrays["downwelling"] = np.stack([c.x_bands for c in sky.cubes]).astype(np.float64)
        dims["downwelling"] = ("cube", "band")
        downwelling = {"calibration": Path(sky.calibration).name, "spectra": [Path(c.spec).name for c in sky.cubes],
                       "shift_nm": [c.shift_nm for c in sky.cubes]}
    if cal is not None:
        arrays["dark"] = np.stack(darks).astype(np.float32)
        arrays["gain"] = np.stack(gains).astype(np.float32)
        arrays["gain_index"] = np.asarray(gain_index, np.uint16)
        dims.update({"dark": ("cube", "band", "sample"), "gain": ("set", "band", "sample"), "gain_index": ("cube",)})

    sensor = sensor_name(first.metadata)
    start = gps_seconds_to_datetime(float(arrays["time"][0]))
    end = gps_seconds_to_datetime(float(arrays["time"][-1]))
    cid = collection_id(sensor, start)
    terrain = None
    if dem is not None:
        ground, ground_source, terrain = _terrain_record(src, fov_deg, dem, dem_datum, ground_height, arrays,
                                                         first.samples, poses)
    else:
        if dem_datum is not None:
            raise InputError("--dem-datum", "gives the vertical datum of a DEM, but no --dem was given",
                             "add --dem FILE, or leave --dem-datum out")
        ground, ground_source = _ground_height(src, ground_height)

    sources: list[tuple[str, int]] = []
    names: dict[str, str] = {}
    for f in files:
        for p in (f.data, f.header, f.times, f.lcf):
            sources.append((str(p), p.stat().st_size))
            names[str(p)] = p.name
    if src.calibration_path is not None:
        p = Path(src.calibration_path)
        sources.append((str(p), p.stat().st_size))
        names[str(p)] = p.name
    if track is not None:   # the trajectory file checksummed like the cubes' files
        p = Path(src.trajectory.path)
        sources.append((str(p), p.stat().st_size))
        names[str(p)] = p.name
    if downwelling is not None:   # checksummed like the cubes' files
        for p in [q for q, f in zip(src.downwelling.specs, src.downwelling.found, strict=True) if f]:
            for q in (p, p.with_name(p.name + ".hdr")):
                sources.append((str(q), q.stat().st_size))
                names[str(q)] = q.name
        p = src.downwelling.calibration
        sources.append((str(p), p.stat().st_size))
        names[str(p)] = p.name
    cubes = [{
        "index": i, "base": f.base, "lines": h.lines, "samples": h.samples, "bands": h.bands,
        "line_offset": int(line_offset[i]), "navigation_rows": int(nav_offset[i + 1] - nav_offset[i]),
        "data_file": f.data.name, "header": jsonable(h.metadata)}
        for i, (f, h) in enumerate(zip(files, headers, strict=True))]
    frame = src.frame
    attrs = {
        "archive:format": FORMAT,
        "archive:format_version": FORMAT_VERSION,
        "archive:id": cid,
        "archive:software": f"archive {archive.__version__}",
        "sensor": sensor,
        "start_datetime": start.isoformat(),
        "end_datetime": end.isoformat(),
        "fov_deg": float(fov_deg),
        "ground_height": ground,
        "ground_height_source": ground_source,
        "frame": frame_to_attrs(frame),
        "poses": "position/attitude at exposure start with navigation_params",
        "navigation_params": {"sync_offset": nav.sync_offset, "boresight_deg": list(nav.boresight_deg),
                              "lever_arm_m": list(nav.lever_arm_m)},
        "navigation_columns": list(NAV_COLUMNS),
        "response_reference": "calibration" if cal is not None else "1 ms at 0 dB",
        "calibration": None if cal is None else {
            "name": Path(src.calibration_path).name, "shutter_cal": float(cal.shutter_cal),
            "gain_cal": float(cal.gain_cal)},
        "dtype": first.dtype.newbyteorder("<").str,
        "cubes": cubes,
        "source_names": names,
    }
    if terrain is not None:
        attrs["terrain"] = terrain
    if downwelling is not None:
        attrs["downwelling"] = downwelling
    if track is not None:
        attrs["navigation_tracks"] = {"default": track, "tracks": {track: {
            "file": Path(src.trajectory.path).name, "columns": navigation_columns,
            "layout": "time (.lcf scale), roll (.lcf sign), pitch, yaw (true north; rad), lon, lat (deg), alt (m)"}}}
    return StorePlan(cid=cid, arrays=arrays, attrs=attrs, data_files=[str(f.data) for f in files],
                     cube_lines=[h.lines for h in headers], bands=first.bands, samples=first.samples,
                     dtype=first.dtype.newbyteorder("<"), sources=sources, dims=dims)


