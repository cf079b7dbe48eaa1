"""Which flights a viewer serves: the archive's catalog plus raw flight directories named on the
command line (ids checked before anything opens a store), as GeoJSON; opened flights kept."""

from __future__ import annotations

import dataclasses
import threading
import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from archive.errors import ArchiveError, InputError, MissingInputError
from archive.params import NavigationParams
from archive.drawing.cache import ByteLRU
from archive.drawing.flight import ViewedFlight

__all__ = ["BAND_WORKERS", "FLIGHTS_KEPT", "IDS_TTL_S", "FlightRegistry", "UnknownFlight"]

#: Flights kept open at most: more than an archive's screen of flights (20 at the zoom that fits them
#: all), or every change of that screen reopens some (~0.04 s each: source and meshes); fewer when
#: their arrays pass the flights cache's bytes (a flight's meshes are ~0.3 KB a line per ground
#: height kept).
FLIGHTS_KEPT = 32
#: Threads making band planes (:meth:`ViewedFlight.prepare`): the VM's cores.
BAND_WORKERS = 2
#: Seconds the list of catalog ids is trusted before the index is asked again.
IDS_TTL_S = 5.0


class UnknownFlight(MissingInputError):
    """An id that is neither in the archive's catalog nor one of the flights named (HTTP 404)."""

    def __init__(self, cid: str):
        shown = cid if len(cid) <= 80 else cid[:77] + "..."
        super().__init__(repr(shown), "collection", "GET /api/collections lists the ids this viewer serves")


class FlightRegistry:
    """The flights one viewer serves: the collections of ``archive`` (ids from its catalog index)
    and the raw flight ``directories`` (ids from their files; ``fov`` needed for those).

    ids are checked here (:meth:`check`) before anything opens a store: nothing else on disk is
    reachable. ``navigation``: the navigation source drawn when a request names none ('lcf' or a stored
    track's name, ``archive view --navigation``; a flight without it is drawn from its own default; None:
    every flight's default). :meth:`flight` opens flights lazily and keeps the last FLIGHTS_KEPT (call it from
    the render thread); its flights share ``workers``, BAND_WORKERS threads making band planes
    (:meth:`close` stops them).
    """

    def __init__(self, archive=None, directories: Sequence = (), fov: float | None = None,
                 bands_cache: ByteLRU | None = None, lookup_cache: ByteLRU | None = None,
                 flights_cache: ByteLRU | None = None, navigation: str | None = None):
        from archive.api import open_archive
        from archive.drawing.query import NAVIGATION_NAME

        self.archive = None if archive is None else open_archive(archive)
        self.fov = fov
        if navigation is not None and not NAVIGATION_NAME.fullmatch(str(navigation)):
            raise InputError("--navigation", f"{navigation!r} is not a navigation source's name",
                             "the viewer draws from what a collection stores: pass lcf or a stored track's name "
                             "(ingest a trajectory file with 'archive ingest --navigation FILE')")
        self.navigation = None if navigation is None else str(navigation)
        self.bands_cache = bands_cache if bands_cache is not None else ByteLRU(256 << 20)
        self.lookup_cache = lookup_cache if lookup_cache is not None else ByteLRU(64 << 20)
        #: the opened flights, each charged :meth:`ViewedFlight.nbytes` (:meth:`settle`)
        self.flights_cache = flights_cache if flights_cache is not None else ByteLRU(64 << 20)
        self._lock = threading.Lock()
        self._ids: tuple[float, frozenset] | None = None
        self._items: dict[str, tuple[int, dict]] = {}
        self._used: dict[str, ViewedFlight] = {}   # flights used since the last settle()
        self.workers = ThreadPoolExecutor(max_workers=BAND_WORKERS, thread_name_prefix="archive-view-bands")
        self.raw: dict[str, tuple[Path, dict]] = {}
        if directories and fov is None:
            raise InputError("--fov", "the field of view is required for raw flight directories",
                             "pass --fov DEG (47.5 for a Pika L and for 'archive simulate' flights)")
        for d in directories:
            path = Path(d).absolute()
            if not path.is_dir():
                raise MissingInputError(path, "flight directory")
            feature = _raw_feature(path, float(fov), taken=set(self.raw) | set(self.catalog_ids()))
            self.raw[feature["id"]] = (path, feature)
        if self.archive is None and not self.raw:
            raise InputError(None, "nothing to view", "give --archive ARCHIVE and/or raw flight directories")

    # ---- ids and the catalog -------------------------------------------------------------
    def catalog_ids(self) -> frozenset:
        if self.archive is None:
            return frozenset()
        with self._lock:
            now = time.monotonic()
            if self._ids is None or now - self._ids[0] > IDS_TTL_S:
                from archive.catalog.index import ensure_index, search

                self._ids = (now, frozenset(row.id for row in search(ensure_index(self.archive))))
            return self._ids[1]

    def check(self, cid: str) -> str:
        """``cid`` if this viewer serves it, else :class:`UnknownFlight`."""
        if cid in self.raw or cid in self.catalog_ids():
            return cid
        raise UnknownFlight(cid)

    def _item(self, cid: str) -> dict:
        path = self.archive.item_path(cid)
        try:
            stamp = path.stat().st_mtime_ns
        except OSError:
            raise UnknownFlight(cid) from None
        with self._lock:
            found = self._items.get(cid)
        if found is None or found[0] != stamp:
            from archive.catalog.index import read_item_file

            found = (stamp, _feature_of_item(read_item_file(path)))
            with self._lock:
                self._items[cid] = found
        return found[1]

    def feature(self, cid: str) -> dict:
        """The GeoJSON Feature of one served flight."""
        self.check(cid)
        if cid in self.raw:
            return self.raw[cid][1]
        return self._item(cid)

    def features(self, bbox=None, datetime: str | None = None, wavelength: float | None = None) -> dict:
        """GeoJSON FeatureCollection of the footprints matching every given filter (as ``archive
        catalog search``): bbox (W, S, E, N degrees), datetime 'A/B' (ISO 8601, '..' open),
        wavelength (nm, within the flight's bands). Catalog flights first (by start time), then
        raw flights."""
        features: list[dict] = []
        damaged: list[dict] = []
        if self.archive is not None:
            from archive.catalog.index import damaged_flights

            ids = self.archive.search(bbox=bbox, datetime=datetime, wavelength=wavelength)
            for cid in ids:
                try:
                    features.append(self._item(cid))
                except (ArchiveError, KeyError, TypeError, ValueError) as exc:  # costs only this flight
                    damaged.append({"id": cid, "reason": " ".join(str(exc).split())[:300],
                                    "fix": "run 'archive catalog rebuild'"})
            known = {d["id"] for d in damaged}
            damaged += [d.as_dict() for d in damaged_flights(self.archive) if d.id not in known]
            unusable = {d["id"] for d in damaged}  # e.g. an Item whose collection store is gone
            features = [f for f in features if f["id"] not in unusable]
        if self.raw:
            from archive.catalog.index import parse_datetime_range

            start, end = (None, None) if datetime is None else parse_datetime_range(datetime)
            for _, feature in self.raw.values():
                p = feature["properties"]
                fb = feature["bbox"]
                if bbox is not None and not (bbox[0] <= fb[2] and fb[0] <= bbox[2] and bbox[1] <= fb[3]
                                             and fb[1] <= bbox[3]):
                    continue
                if start is not None and p["end_time"] < start or end is not None and p["start_time"] > end:
                    continue
                if wavelength is not None and not (p["min_wavelength"] is not None
                                                   and p["min_wavelength"] <= wavelength <= p["max_wavelength"]):
                    continue
                features.append(feature)
        return {"type": "FeatureCollection", "features": features, "numberMatched": len(features),
                "damaged": damaged}

    # ---- overview previews (made at ingest) ----------------------------------------------
    def previews(self, cid: str):
        """The current :class:`~archive.drawing.preview_layout.Previews` of a checked catalog flight, None for a raw
        flight, a collection without current ones, or a viewer started with ``--navigation`` (the previews
        are drawn from the collection's default source; then tiles are drawn from the DN). Kept in the
        bands cache, charged their bytes, and read again when the collection or its previews change
        (their ``zarr.json``). Any thread (no OpenGL)."""
        if cid in self.raw or self.archive is None or getattr(self.archive, "is_url", False) or self.navigation:
            return None   # (previews are made and read for local archives only, so far)
        from archive.drawing.preview_layout import GROUP, read_previews

        store = self.archive.store(cid)
        stamp = []
        for meta in (store / "zarr.json", store / GROUP / "zarr.json"):
            try:
                stamp.append(meta.stat().st_mtime_ns)
            except OSError:
                stamp.append(None)
        if stamp[1] is None:
            return None
        key = (cid, "previews", *stamp)
        found = self.bands_cache.get_or_make(key, lambda: _sized(read_previews(store)))
        if found is None:
            return None

        def load(zoom: int):   # a level's values, kept in the bands cache too
            return self.bands_cache.get_or_make((*key, zoom), lambda: _sized_array(found.load(zoom)))
        return dataclasses.replace(found, load=load)

    def previews_zoom(self, cid: str) -> int | None:
        """The finest zoom the current previews of a checked flight serve (:meth:`previews`), None
        without them (the page opens at or above it: a first screen without the DN)."""
        found = self.previews(cid)
        return None if found is None else int(found.finest)

    # ---- opened flights ------------------------------------------------------------------
    def flight(self, cid: str) -> ViewedFlight:
        """The opened :class:`ViewedFlight` of a checked id (render thread only). Kept in the flights cache
        (at most FLIGHTS_KEPT, and their bytes within its limit); :meth:`settle` charges it what it
        holds after the job that used it."""
        self.check(cid)
        found = self._used.get(cid) or self.flights_cache.get(cid)
        if found is None:
            from archive.sources import open_source

            if cid in self.raw:
                directory = self.raw[cid][0]

                def opener(params, navigation):
                    return open_source(directory, params, navigation=navigation)
            else:
                archive = self.archive.path

                def opener(params, navigation):
                    return open_source(cid, params, archive=archive, navigation=navigation)
            found = ViewedFlight(cid, opener, self.fov, self.bands_cache, self.lookup_cache, self.workers,
                           navigation=self.navigation)
        self._used[cid] = found
        return found

    def settle(self) -> None:
        """Charge the flights used since the last call what they hold now (:meth:`ViewedFlight.nbytes`;
        the least recently used go beyond the cache's bytes or FLIGHTS_KEPT). The render thread
        calls it after each job."""
        used, self._used = self._used, {}
        for cid, flight in used.items():
            self.flights_cache.put(cid, flight, flight.nbytes())
        while len(self.flights_cache) > FLIGHTS_KEPT:
            self.flights_cache.pop_oldest()

    def close(self) -> None:
        """Stop the band workers (after what they are making)."""
        self.workers.shutdown(wait=True, cancel_futures=True)


def _sized(previews) -> tuple:
    """(previews, the bytes a cache charges them)."""
    return previews, 64 if previews is None else previews.nbytes


def _sized_array(values) -> tuple:
    return values, values.nbytes


def _feature_of_item(item: dict) -> dict:
    """A catalog Item as the viewer's GeoJSON Feature: geometry, bbox and the properties the
    page shows and filters by."""
    from archive.catalog.stac import item_summary

    s = item_summary(item)
    p = item.get("properties", {})
    props = {
        "id": s["id"], "kind": "collection", "start_datetime": s["start_iso"], "end_datetime": s["end_iso"],
        "start_time": s["start_time"], "end_time": s["end_time"], "bands": s["bands"],
        "min_wavelength": s["min_wavelength"], "max_wavelength": s["max_wavelength"],
        "wavelength": p.get("archive:wavelengths"), "sensor": s["sensor"], "gsd": s["gsd"],
        "fov_deg": p.get("archive:fov_deg"), "ground_height": p.get("archive:ground_height"),
        "cubes": p.get("archive:cubes"), "lines": p.get("archive:lines"), "samples": p.get("archive:samples"),
    }
    return {"type": "Feature", "id": s["id"], "geometry": item.get("geometry"), "bbox": s["bbox"],
            "properties": props}


def _raw_feature(directory: Path, fov: float, taken: set = frozenset()) -> dict:
    """The Feature of a raw flight directory: its footprint at the headers' ground height (as the
    catalog computes it for a collection), time range and wavelengths. Its id is the one ``archive
    ingest`` and ``archive info`` give it (``<sensor>_<UTC start>``), or, when that id is ``taken`` (the
    flight's own collection served beside it, another folder of the same flight), the raw source's
    (``<folder>-<first .lcf time>``)."""
    from scipy.spatial.transform import Rotation

    from archive.catalog.footprint import flight_footprint
    from archive.formats.lcf import gps_seconds_to_datetime
    from archive.sources import open_source
    from archive.sources.ground import auto_ground_height

    from archive.ingest.prepare import collection_id, sensor_name

    source = open_source(directory, NavigationParams())
    ground = auto_ground_height([source])
    fid = collection_id(sensor_name(source.header(0).metadata), gps_seconds_to_datetime(float(source.line_times(0)[0])))
    fid = source.id if fid in taken else fid
    poses = [source.poses(i) for i in range(len(source.cubes))]
    times = np.concatenate([p.time for p in poses])
    fp = flight_footprint(times, np.concatenate([p.position for p in poses]),
                          Rotation.concatenate([p.attitude for p in poses]), source.frame, fov, ground,
                          source.cubes[0].samples, where=str(directory))
    start, end = gps_seconds_to_datetime(float(times[0])), gps_seconds_to_datetime(float(times[-1]))
    wl = source.wavelengths
    iso = [t.isoformat().replace("+00:00", "Z") for t in (start, end)]
    props = {
        "id": fid, "kind": "raw", "start_datetime": iso[0], "end_datetime": iso[1],
        "start_time": start.timestamp(), "end_time": end.timestamp(), "bands": source.cubes[0].bands,
        "min_wavelength": None if wl is None else float(min(wl)),
        "max_wavelength": None if wl is None else float(max(wl)),
        "wavelength": None if wl is None else [float(w) for w in wl], "sensor": None, "gsd": round(fp.gsd, 4),
        "fov_deg": fov, "ground_height": ground, "cubes": len(source.cubes),
        "lines": int(sum(c.lines for c in source.cubes)), "samples": source.cubes[0].samples,
    }
    return {"type": "Feature", "id": fid, "geometry": fp.geometry(), "bbox": fp.bbox(), "properties": props}
