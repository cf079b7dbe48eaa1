"""``archive ingest`` and ``archive verify``.

Ingest checks every raw flight completely (headers, data sizes, times, navigation coverage,
calibration) before touching the archive, then writes each into ``<id>.zarr.partial`` with a Dask
graph of per-(cube, band) chunk tasks and per-file checksum tasks, records checksums and metadata,
writes the completion marker, renames the store to ``<id>.zarr`` and catalogs it. A rerun after a
kill resumes the partial store (chunks already written with the right values are kept); a rerun
after success is a no-op.

One ingest per collection id at a time, across processes and hosts: each flight is written holding
its collection's lock (:func:`archive.collection.store_lock`, ``<id>.zarr.lock``); a second ingest of
the same flight says once that it waits, then finds the flight ingested. A full disk is one line
(the partial store stays, and the rerun resumes it).
"""

from __future__ import annotations

import argparse
import errno
import math
import os
import re
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

import archive
from archive import storage
from archive.catalog.root import ArchiveRoot, check_collection_id, create_archive
from archive.errors import ArchiveError, InputError
from archive.collection import (FORMAT, FORMAT_VERSION, NAV_COLUMNS, StorePlan, chunk_tasks, finish_store,
                                frame_to_attrs, hash_file_task, is_complete, open_partial, publish, read_attrs,
                                sha256_file, store_lock, write_chunk)
from archive.formats.icp import response as exposure_response
from archive.formats.trajectory import parse_columns
from archive.formats.lcf import gps_seconds_to_datetime
from archive.ingest.previews import add_previews
from archive.params import NavigationParams
from archive.sources.ground import auto_ground_height, camera_altitudes, check_ground_height
from archive.sources.raw import RawFlightSource


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


def _dem_of(terrain: dict | None) -> tuple[str, str] | None:
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


def _jsonable(value):
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
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
        "data_file": f.data.name, "header": _jsonable(h.metadata)}
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


class _Progress:
    """A tqdm bar advanced by a Dask scheduler callback."""

    def __init__(self, total: int, desc: str, enabled: bool):
        from dask.callbacks import Callback
        from tqdm import tqdm

        bar = tqdm(total=total, desc=desc, unit="task", disable=not enabled, file=sys.stderr)

        class _Cb(Callback):
            def _posttask(self, key, result, dsk, state, worker_id):
                bar.update(1)

        self.bar = bar
        self.callback = _Cb()


def write_flight(plan: StorePlan, root: ArchiveRoot, workers: int | None = None, progress: bool = True) -> bool:
    """Write ``plan`` into ``root`` (partial store, Dask graph, checksums, marker, rename). Returns
    whether the store was resumed from an interrupted run."""
    import dask
    from dask.base import tokenize

    partial = root.partial(plan.cid)
    resumed = open_partial(partial, plan)
    tasks = chunk_tasks(plan.data_files, plan.cube_lines, plan.bands, plan.chunk_lines)
    token = tokenize(plan.token(), resumed)
    chunk_jobs = [dask.delayed(write_chunk, pure=True)(str(partial), t, plan.chunk_lines, resumed,
                                                         dask_key_name=f"dn-chunk-{t.band}-{t.chunk}-{token}")
                  for t in tasks]
    hash_jobs = [dask.delayed(hash_file_task, pure=True)(path, dask_key_name=f"sha256-{k}-{token}")
                 for k, (path, _) in enumerate(plan.sources)]
    bar = _Progress(len(chunk_jobs) + len(hash_jobs), f"ingest {plan.cid}", progress)
    try:
        with bar.callback:
            chunks, files = dask.compute(chunk_jobs, hash_jobs, scheduler="threads",
                                         num_workers=workers or os.cpu_count() or 1)
    finally:
        bar.bar.close()
    finish_store(partial, plan, {(b, k): d for b, k, d in chunks}, dict(files))
    publish(partial, root.store(plan.cid))
    return resumed


def _same_sources(attrs: dict, plan: StorePlan) -> bool:
    """Whether the store whose attributes are ``attrs`` was ingested from the same files as
    ``plan``: same names and sizes, and the same sha256 for the small files (headers, times,
    navigation, calibration); data files are not re-hashed, so that a repeated ingest stays a
    quick no-op."""
    recorded = attrs.get("sources", [])
    if [(s["name"], s["size"]) for s in recorded] != [(plan.attrs["source_names"][p], n) for p, n in plan.sources]:
        return False
    data = set(plan.data_files)
    return all(path in data or sha256_file(path) == rec["sha256"]
               for (path, _), rec in zip(plan.sources, recorded, strict=True))


def _cataloged(root: ArchiveRoot, cid: str) -> bool:
    from archive.catalog.index import ensure_index, search

    if root.is_url:   # the index is a local cache, rebuilt from the Items when stale
        return storage.exists(root.item_path(cid)) and storage.exists(root.catalog_path) \
            and bool(search(ensure_index(root), ids=[cid]))
    if not root.item_path(cid).exists() or not root.index_path.exists() or not root.catalog_path.exists():
        return False  # (an archive made before the root catalog.json existed gets one)
    return bool(search(root.index_path, ids=[cid]))


@dataclass(frozen=True)
class IngestResult:
    cid: str
    store: Path
    status: str  # 'ingested' | 'resumed' | 'already ingested'


def ingest(directories: list[str], archive_path: str | os.PathLike, fov_deg: float,
           calibration: str | os.PathLike | None = None, ground_height: float | None = None,
           overwrite: bool = False, workers: int | None = None, progress: bool = True,
           sync_offset: float = 0.0, boresight: tuple[float, float, float] = (0.0, 0.0, 0.0),
           lever_arm: tuple[float, float, float] = (0.0, 0.0, 0.0), dem: str | os.PathLike | None = None,
           dem_datum: str | None = None, irradiance_calibration: str | os.PathLike | None = None,
           navigation: str | os.PathLike | None = None, navigation_columns: dict | None = None) -> list[IngestResult]:
    """Ingest raw flight ``directories`` into the archive (created when absent). Every flight is
    checked before anything is written; see the module docstring. ``dem`` / ``dem_datum``: the
    catalog footprint follows that terrain (:func:`prepare_flight`). ``irradiance_calibration``: the
    downwelling spectrometer's ``.dcp`` when it is not in the flight directories (their spectra are
    kept in the collection, issue 34). ``navigation``: a post-processed trajectory stored with each flight
    as its default navigation source (:func:`prepare_flight`)."""
    plans = [prepare_flight(d, fov_deg, calibration, ground_height, sync_offset, boresight, lever_arm,
                            dem, dem_datum, irradiance_calibration, navigation, navigation_columns)
             for d in directories]
    pairs = _distinct_flights(list(directories), plans)
    root = _create_archive(archive_path)
    results = []
    for directory, plan in pairs:
        if not overwrite and _already_ingested(root, plan, directory):
            results.append(IngestResult(plan.cid, root.store(plan.cid), "already ingested"))
            continue
        # One writer per collection id, across processes and hosts (DESIGN 5): a second ingest of
        # the same flight waits here, then finds it ingested.
        lock = store_lock(root.store(plan.cid), f"ingest of {plan.cid}")
        try:
            try:
                with _disk_full_is_an_error(root, plan.cid):
                    lock.acquire(wait=math.inf, notify=lambda line: print(f"archive ingest: {line}", file=sys.stderr))
            except OSError as exc:
                raise InputError(root.collections, f"cannot write there ({exc.strerror or exc})",
                                 "ingest into an archive you can write to") from None
            try:
                results.append(_ingest_one(root, plan, directory, overwrite, workers, progress))
            finally:
                lock.release()
        except DiskFullError as exc:   # the flights of this command done before it are named too
            if not results:
                raise
            done = ", ".join(f"{r.cid} ({r.status})" for r in results)
            raise DiskFullError(exc.where, f"{exc.problem}; ingested before it: {done}", exc.fix) from None
    if not root.is_url:   # archive/previews.py reads local stores only: an archive in object storage has none yet
        add_previews(root, [r.cid for r in results])   # the viewer's overviews (issue 36); after every lock is released
    return results


def _distinct_flights(directories: list[str], plans: list[StorePlan]) -> list[tuple[str, StorePlan]]:
    """(directory, plan) per flight, a directory given twice taken once; two directories holding
    the same flight id (a copy of a flight) are refused before anything is written."""
    seen: dict[str, str] = {}
    pairs = []
    for directory, plan in zip(directories, plans):
        first = seen.get(plan.cid)
        if first is None:
            seen[plan.cid] = directory
            pairs.append((directory, plan))
        elif os.path.realpath(first) != os.path.realpath(directory):
            raise InputError(directory, f"is the same flight as {first} (both are {plan.cid})",
                             "ingest one of them; remove the copy from the command line")
    return pairs


def _create_archive(archive_path: str | os.PathLike) -> ArchiveRoot:
    """:func:`create_archive`, tolerating another process creating the same new archive right now
    (its folders exist for a moment before its ``archive.json``; in object storage the marker is a
    conditional PUT, so both succeed)."""
    if storage.is_url(archive_path):
        return create_archive(archive_path)
    deadline = time.monotonic() + 10.0
    while True:
        try:
            return create_archive(archive_path)
        except InputError:
            path = Path(archive_path)
            made = ("collections", "catalog", "archive.json")   # what create_archive makes, marker last
            being_made = path.is_dir() and all(p.name in made or p.name.endswith(".partial") for p in path.iterdir())
            if not being_made or time.monotonic() > deadline:
                raise
            time.sleep(0.05)


def _ingest_one(root: ArchiveRoot, plan: StorePlan, directory: str, overwrite: bool, workers: int | None,
                progress: bool) -> IngestResult:
    """Ingest one prepared flight (its collection's lock held)."""
    from archive.catalog.describe import catalog_collection

    final = root.store(plan.cid)
    # in object storage an incomplete store under the final prefix is a killed run's: resumed below
    if (is_complete(final) if root.is_url else final.exists()) and not overwrite:
        _check_ingested(root, plan, directory)
        if not _cataloged(root, plan.cid):
            with _disk_full_is_an_error(root, plan.cid):
                catalog_collection(root, plan.cid)  # an earlier run may have died before cataloging
        return IngestResult(plan.cid, final, "already ingested")
    with _disk_full_is_an_error(root, plan.cid):
        resumed = write_flight(plan, root, workers, progress)
        catalog_collection(root, plan.cid)
    return IngestResult(plan.cid, final, "resumed" if resumed else "ingested")


def _check_ingested(root: ArchiveRoot, plan: StorePlan, directory: str) -> None:
    """InputError unless the existing store of ``plan``'s id is complete and holds this flight, ingested
    with the same navigation parameters and DEM (then a rerun is a no-op)."""
    final = root.store(plan.cid)
    if not is_complete(final):
        raise InputError(final, "exists but has no completion marker", "pass --overwrite to re-ingest")
    attrs = read_attrs(final)
    recorded = attrs.get("navigation_params") or {}
    wanted = plan.attrs["navigation_params"]
    if any(recorded.get(k, 0.0 if k == "sync_offset" else [0.0] * 3) != v for k, v in wanted.items()):
        raise InputError(final, f"was ingested with other navigation parameters ({recorded or 'none'}, "
                         f"now {wanted})", "pass --overwrite to re-ingest with the new ones")
    tracks = (attrs.get("navigation_tracks") or {}).get("default"), \
        (plan.attrs.get("navigation_tracks") or {}).get("default")
    if tracks[0] != tracks[1]:
        raise InputError(final, f"was ingested with another navigation source ({tracks[0] or 'lcf'}, now "
                         f"{tracks[1] or 'lcf'})", "pass --overwrite to re-ingest it so")
    old_dem = _dem_of(attrs.get("terrain"))
    if old_dem != _dem_of(plan.attrs.get("terrain")):
        new_dem = _dem_of(plan.attrs.get("terrain"))
        raise InputError(final, f"was ingested with {'the DEM ' + old_dem[0] if old_dem else 'no DEM'}, "
                         f"now {'the DEM ' + new_dem[0] if new_dem else 'none'}",
                         "pass --overwrite to re-ingest (the catalog footprint follows the DEM)")
    if not _same_sources(attrs, plan):
        raise InputError(final, f"holds a different flight than {directory} under the "
                         f"same id {plan.cid} (same sensor, same start second)",
                         "pass --overwrite to replace it")


def _already_ingested(root: ArchiveRoot, plan: StorePlan, directory: str) -> bool:
    """Whether ``plan``'s flight is ingested and cataloged as asked (read only, without the lock: a
    rerun after success writes nothing, not even a lock file); False when in any doubt (the locked
    path then decides, and says why)."""
    try:
        if not (is_complete(root.store(plan.cid)) if root.is_url else root.store(plan.cid).exists()):
            return False
        _check_ingested(root, plan, directory)
        return _cataloged(root, plan.cid)
    except (ArchiveError, OSError, ValueError):
        return False


def _disk_full(exc: BaseException) -> BaseException | None:
    """The error in ``exc``'s chain (``exc`` or what it wraps) that says the disk or the quota is full, if any."""
    import sqlite3

    seen = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        if isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT):
            return exc
        if isinstance(exc, sqlite3.OperationalError) and "full" in str(exc).lower():
            return exc
        exc = exc.__cause__ or exc.__context__
    return None


@contextmanager
def _disk_full_is_an_error(root: ArchiveRoot, cid: str) -> Iterator[None]:
    """A full disk (or quota) while writing the store, its checksums or the catalog (SQLite) becomes
    one line naming the full file (else the full folder) and the archive; what was written stays as the partial
    store, which the rerun resumes."""
    try:
        yield
    except Exception as exc:
        full = _disk_full(exc)
        if full is None:
            raise
        where = getattr(full, "filename", None) or _full_folder(root) or root.path   # the full file, else folder
        raise DiskFullError(where, f"the disk is full while ingesting {cid} into {root.path} ({type(exc).__name__}: "
                            f"{' '.join(str(exc).split())})",
                            "free some space, then run the same ingest again: it resumes where it stopped") from None


def _full_folder(root: ArchiveRoot) -> Path | None:
    """The first of the archive's folders (collections, catalog, the archive) whose file system has no
    free block left (a local archive; None when none, or in object storage)."""
    if root.is_url:
        return None
    for folder in (root.collections, root.path / "catalog", root.path):
        try:
            if os.statvfs(folder).f_bavail == 0:
                return folder
        except OSError:
            continue
    return None


class DiskFullError(InputError):
    """An ingest stopped by a full disk or quota (its partial store stays, for the rerun to resume)."""


def run(args: argparse.Namespace) -> int:
    """CLI handler of ``archive ingest``."""
    results = ingest(args.directories, args.archive, args.fov, calibration=args.calibration,
                     ground_height=args.ground_height, overwrite=args.overwrite, workers=args.workers,
                     progress=not args.quiet, sync_offset=args.sync_offset,
                     boresight=args.boresight or (0.0, 0.0, 0.0), lever_arm=args.lever_arm or (0.0, 0.0, 0.0),
                     dem=getattr(args, "dem", None), dem_datum=getattr(args, "dem_datum", None),
                     irradiance_calibration=getattr(args, "irradiance_calibration", None),
                     navigation=getattr(args, "navigation", None),
                     navigation_columns=parse_columns(getattr(args, "navigation_columns", None)))
    for r in results:
        print(f"{r.cid}: {r.status} ({r.store})")
    return 0
