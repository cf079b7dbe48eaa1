"""What the live page is told: the flights being recorded, their cubes as the viewer serves them, the
coverage of each pass and the ground left between passes; ``GET /api/live``.

While a flight records, each complete cube is served by the viewer as a raw flight of its own (its
staged folder, :mod:`archive.watch.stage`; the id ``<cube base>-<first .lcf time>`` as
:func:`archive.sources.raw.flight_id` makes it): a cube never changes once complete, so nothing the
viewer or the page caches about it goes stale, and a tile over it is imagery as soon as it is listed.
Once the flight is ingested and its collection is in the catalog, its cubes leave the list and the
collection shows instead.

``GET /api/live`` = ``{"flights": [{"id", "cubes", "lines", "complete", "updated", ...}]}``: ``id``
``<folder name>/<image set>``; ``cubes``, ``lines``: the complete cubes listed so far and their lines;
``complete``: the flight is ingested (``collection`` names it) and nothing of it is being written;
``updated``: when it last changed (Unix seconds); also ``status`` (recording, ingesting, ingested,
failed, gone), ``cube_ids`` (the viewer's ids of its listed cubes), ``skipped`` (cube names reported
incomplete), ``passes`` (a GeoJSON MultiPolygon per pass: its coverage) and ``gaps`` (GeoJSON
MultiPolygon, lon/lat degrees: ground between consecutive passes nobody imaged).
"""

from __future__ import annotations

import math
import threading
import time
from pathlib import Path

import numpy as np

from archive.params import NavigationParams
from archive.view.registry import FlightRegistry

__all__ = ["GAP_MIN_M2", "LiveRegistry", "LiveState", "cube_feature", "live_routes", "passes_and_gaps", "swath_polygon"]

#: m²: smaller pieces of ground between passes are not reported as gaps (slivers of the outlines).
GAP_MIN_M2 = 2.0


def cube_feature(directory: Path, fov: float, ground_height: float | None = None) -> dict:
    """The viewer's Feature of a staged cube (a raw flight of one cube): its footprint at
    ``ground_height`` (m; the watch's ``--ground-height``; None: the header's, as the catalog computes a
    collection's), its times and wavelengths. Raises the source's ArchiveError (naming the file) for a
    cube the raw reader refuses."""
    from archive.catalog.footprint import flight_footprint
    from archive.formats.lcf import gps_seconds_to_datetime
    from archive.sources import open_source
    from archive.sources.ground import auto_ground_height

    source = open_source(directory, NavigationParams())
    ground = auto_ground_height([source]) if ground_height is None else float(ground_height)
    pose = source.poses(0)
    fp = flight_footprint(pose.time, pose.position, pose.attitude, source.frame, fov, ground,
                          source.cubes[0].samples, where=str(directory))
    start, end = gps_seconds_to_datetime(float(pose.time[0])), gps_seconds_to_datetime(float(pose.time[-1]))
    wl = source.wavelengths
    iso = [t.isoformat().replace("+00:00", "Z") for t in (start, end)]
    props = {
        "id": source.id, "kind": "raw", "live": True, "start_datetime": iso[0], "end_datetime": iso[1],
        "start_time": start.timestamp(), "end_time": end.timestamp(), "bands": source.cubes[0].bands,
        "min_wavelength": None if wl is None else float(min(wl)),
        "max_wavelength": None if wl is None else float(max(wl)),
        "wavelength": None if wl is None else [float(w) for w in wl], "sensor": None, "gsd": round(fp.gsd, 4),
        "fov_deg": fov, "ground_height": ground, "cubes": 1, "lines": int(source.cubes[0].lines),
        "samples": source.cubes[0].samples,
    }
    props["coverage"] = swath_polygon(pose.position, pose.attitude, source.frame, fov, ground, str(directory))
    ring = props["coverage"]["coordinates"][0]   # left edge out, right edge back
    half = (len(ring) - 1) // 2
    props["ends"] = [[ring[0], ring[-2]], [ring[half - 1], ring[half]]]   # first and last line: (left, right) lon/lat
    return {"type": "Feature", "id": source.id, "geometry": fp.geometry(), "bbox": fp.bbox(), "properties": props}


def swath_polygon(position, attitude, frame, fov: float, ground: float, where: str = "") -> dict:
    """The ground a cube's lines see, exactly (the catalog's footprint is a hull grown by a margin, to
    contain it): its left swath edge from the first line to the last, then its right edge back, on flat
    ground at ``ground`` m; lines seen further off nadir than the renderer draws left out. ``position``
    (lines, 3) N, E, D m in ``frame``; ``attitude`` (lines,) camera -> NED. A GeoJSON Polygon, lon/lat."""
    from pyproj import Transformer

    from archive.catalog.footprint import swath_edges
    from archive.geometry.navigation import DEFAULT_MAX_VIEW_ANGLE, view_angles

    seen = view_angles(attitude, fov) <= DEFAULT_MAX_VIEW_ANGLE
    left, right = swath_edges(position[seen], attitude[seen], fov, frame.origin_alt - float(ground), where)
    ring = np.vstack([left, right[::-1], left[:1]])   # (N, E) m
    lon, lat = Transformer.from_crs(int(frame.epsg), 4326, always_xy=True).transform(ring[:, 1] + frame.origin_e,
                                                                                     ring[:, 0] + frame.origin_n)
    return {"type": "Polygon", "coordinates": [[[float(x), float(y)] for x, y in zip(lon, lat)]]}


class LiveRegistry(FlightRegistry):
    """The viewer's flights (the archive's catalog) plus the live cubes, added and removed while it
    serves (:meth:`add_cube`, :meth:`remove`; any thread: the dict of raw flights is replaced whole,
    never changed in place, so a request iterating it sees one version)."""

    def __init__(self, archive, fov: float, ground_height: float | None = None, **caches):
        super().__init__(archive, (), fov, **caches)
        self.ground_height = ground_height   # the live cubes' (None: each header's)
        self._live_lock = threading.Lock()

    def add_cube(self, directory: Path) -> dict:
        """Serve the staged cube ``directory``; its Feature (:func:`cube_feature`)."""
        feature = cube_feature(Path(directory).absolute(), float(self.fov), self.ground_height)
        with self._live_lock:
            self.raw = {**self.raw, feature["id"]: (Path(directory).absolute(), feature)}
        return feature

    def remove(self, ids) -> None:
        """Stop serving the live cubes ``ids``."""
        gone = set(ids)
        with self._live_lock:
            self.raw = {k: v for k, v in self.raw.items() if k not in gone}


def _local_metres(lon0: float, lat0: float):
    """lon/lat degrees -> local east/north metres about (lon0, lat0) and back, each on (n, 2) arrays
    (equirectangular: enough for areas of a field and for sliver filtering)."""
    scale, origin = np.array([111320.0 * math.cos(math.radians(lat0)), 110540.0]), np.array([lon0, lat0])
    return (lambda xy: (xy - origin) * scale), (lambda xy: xy / scale + origin)


def passes_and_gaps(features: list[dict]) -> tuple[list[dict], dict]:
    """(the coverage of each pass as GeoJSON MultiPolygons, the gaps between consecutive passes as one
    MultiPolygon), lon/lat degrees, of one flight's cube ``features`` in capture order (each cube's exact
    ``coverage``, :func:`swath_polygon`, else its footprint). Cubes whose
    lines follow within 3.5 frame intervals (a recorder's cube switch) are one pass; a gap is ground
    inside the hull of two consecutive passes, across track of both (not beyond either's ends: a pass being
    flown has no gap ahead of it yet), that no pass covers, pieces under GAP_MIN_M2 left out."""
    from shapely import transform
    from shapely.geometry import mapping, shape
    from shapely.ops import unary_union

    if not features:
        return [], {"type": "MultiPolygon", "coordinates": []}
    groups: list[list[dict]] = [[features[0]]]
    for f in features[1:]:
        last = groups[-1][-1]["properties"]
        p = f["properties"]
        interval = (last["end_time"] - last["start_time"]) / max(1, last["lines"] - 1)
        if 0 <= p["start_time"] - last["end_time"] <= 3.5 * interval:
            groups[-1].append(f)
        else:
            groups.append([f])
    b = features[0]["bbox"]
    to_m, to_deg = _local_metres((b[0] + b[2]) / 2, (b[1] + b[3]) / 2)
    covered = [unary_union([transform(shape(f["properties"].get("coverage") or f["geometry"]), to_m).buffer(0.05)
                            for f in g]) for g in groups]
    everything = unary_union(covered)
    bands = [_band(g, to_m) for g in groups]
    gaps = []
    for (a, c), (ba, bc) in zip(zip(covered, covered[1:]), zip(bands, bands[1:])):
        # across track of both: not the ground beyond either pass's ends (a pass still being flown)
        between = unary_union([a, c]).convex_hull.difference(everything)
        if ba is not None and bc is not None:
            between = between.intersection(ba).intersection(bc)
        parts = getattr(between, "geoms", [between])
        gaps += [g for g in parts if g.geom_type == "Polygon" and g.area >= GAP_MIN_M2]

    def multi(geom) -> dict:
        polys = [g for g in getattr(geom, "geoms", [geom]) if g.geom_type == "Polygon" and not g.is_empty]
        found = mapping(transform(unary_union(polys), to_deg)) if polys else {"type": "MultiPolygon", "coordinates": []}
        if found["type"] == "Polygon":
            found = {"type": "MultiPolygon", "coordinates": [found["coordinates"]]}
        return {"type": "MultiPolygon", "coordinates": [[[list(map(float, pt)) for pt in ring] for ring in poly]
                                                        for poly in found["coordinates"]]}
    return [multi(c) for c in covered], multi(unary_union(gaps) if gaps else _empty())


def _band(group: list[dict], to_m, reach: float = 2.0):
    """The ground a pass sweeps across track, out to ``reach`` swath widths beyond either swath edge:
    between its first line's swath (first cube) and its last line's (last cube), each line stretched
    along itself (metres; lines a few degrees apart, stretched further, would cross); None without
    ``ends`` properties."""
    from shapely.geometry import Polygon

    try:
        first, last = (to_m(np.array(e, float)) for e in (group[0]["properties"]["ends"][0],
                                                         group[-1]["properties"]["ends"][1]))
    except (KeyError, TypeError, IndexError, ValueError):
        return None

    def stretched(seg):
        u = (seg[1] - seg[0]) * reach
        return seg[0] - u, seg[1] + u
    (a, b), (c, d) = stretched(first), stretched(last)
    band = Polygon([a, b, d, c])
    return band if band.is_valid and band.area > 0 else band.buffer(0)


def _empty():
    from shapely.geometry import Polygon

    return Polygon()


class LiveState:
    """The flights as ``/api/live`` tells them (any thread)."""

    def __init__(self):
        self._lock = threading.Lock()
        self._flights: dict[str, dict] = {}
        self._features: dict[str, list[dict]] = {}

    def flight(self, name: str, **fields) -> None:
        """Create or update flight ``name`` with ``fields`` (the keys of the module docstring)."""
        with self._lock:
            found = self._flights.setdefault(name, {
                "id": name, "cubes": 0, "lines": 0, "complete": False, "updated": time.time(), "status": "recording",
                "cube_ids": [], "skipped": [], "collection": None, "passes": [],
                "gaps": {"type": "MultiPolygon", "coordinates": []}})
            found.update(fields)
            found["updated"] = time.time()

    def add_cube(self, name: str, feature: dict) -> None:
        """A complete cube of flight ``name`` is listed (its viewer Feature)."""
        with self._lock:
            features = [f for f in self._features.get(name, []) if f["id"] != feature["id"]] + [feature]
            features.sort(key=lambda f: f["properties"]["start_time"])
            self._features[name] = features
        passes, gaps = passes_and_gaps(features)
        self.flight(name, cubes=len(features), lines=int(sum(f["properties"]["lines"] for f in features)),
                    cube_ids=[f["id"] for f in features], passes=passes, gaps=gaps, complete=False)

    def drop_cubes(self, name: str, ids) -> None:
        """Cubes ``ids`` of flight ``name`` are no longer listed (written over, gone, or ingested)."""
        gone = set(ids)
        with self._lock:
            features = [f for f in self._features.get(name, []) if f["id"] not in gone]
            self._features[name] = features
        self.flight(name, cube_ids=[f["id"] for f in features])

    def skipped(self, name: str, cube: str) -> None:
        with self._lock:
            found = self._flights.get(name)
            listed = [] if found is None else found["skipped"]
        self.flight(name, skipped=sorted(set(listed) | {cube}))

    def as_json(self) -> dict:
        with self._lock:
            return {"flights": [dict(f) for f in self._flights.values()], "time": time.time()}


def live_routes(state: LiveState) -> list:
    """The Starlette routes of the live page's server side: ``GET /api/live``."""
    from starlette.responses import JSONResponse
    from starlette.routing import Route

    async def live(request):
        return JSONResponse(state.as_json(), headers={"Cache-Control": "no-store"})

    return [Route("/api/live", live)]
