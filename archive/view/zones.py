"""Zones in the viewer (``archive view --zones FIELDS.geojson|.gpkg|.shp [--zone-id PROP]``, issue 48
item 4): the fields drawn as outlines on the map, and a click on one plots its time series, one point
per flight, of the index the display shows.

- ``GET /api/zones``: the zones as a lon/lat GeoJSON FeatureCollection (each Feature's ``id`` the
  zone's id as ``archive stats`` names it), ``path`` and ``zone_id``; no Feature without ``--zones``;
  ``POST /api/zones?name=F.geojson`` (body: a GeoJSON file the page loaded) replaces them, read and
  refused as ``--zones`` reads a file;
- ``GET /api/zones/series?zone=ID&index=NDVI|a=NM&b=NM&mode=&gsd=&stack=NAME``: that zone's
  statistics for every served flight whose footprint meets the zone (``stack``: the flights of that
  served stack, on its grid), of NDVI (default) or of (a - b) / (a + b), the index display's two bands
  (``R<nm>`` band math, nearest bands), in ``mode`` (default ``reflectance``, as ``archive stats``),
  on the time stack's grid at ``gsd`` (default: the coarsest nominal GSD of those flights). Rows in
  time order: flight, datetime (UTC), count, coverage, saturated, mean, std, p10, median, p90 (a flight that
  does not image the zone: count 0, the statistics null).

The statistics are those of ``archive stats``: :func:`archive.analysis.zonal.zonal_table` called on
the one zone (its Zones restricted to it), nothing recomputed here. They run on a thread of this
module (one table at a time; the event loop and the render thread stay free) on a local Dask cluster
(one spawned worker of 2 threads with the 'GPU' resource, as ``archive stats`` starts for itself)
started at the first request and kept until the server stops (:meth:`ZoneServer.close`); answers are
kept per zone and parameters (:data:`KEEP` of them).
"""

from __future__ import annotations

import asyncio
import json
import math
import threading
import time
from collections import OrderedDict
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from archive.errors import InputError, MissingInputError

__all__ = ["KEEP", "MAX_UPLOAD", "ROW_FIELDS", "ZoneServer", "open_zones", "zone_routes"]

#: Answers kept (zone x parameters), the oldest dropped first.
KEEP = 64
#: Bytes of GeoJSON the page may send (a file loaded in the page: POST /api/zones).
MAX_UPLOAD = 16 << 20
#: The fields of each row of a series, in order.
ROW_FIELDS = ("flight", "datetime", "count", "coverage", "saturated", "mean", "std", "p10", "median", "p90")


def _number(value: float):
    value = float(value)
    return value if math.isfinite(value) else None


class ZoneServer:
    """The zones served (None: ``--zones`` not given) and what their series need: the flights of
    ``registry``, the ``stacks`` served."""

    def __init__(self, zones, registry, stacks: dict | None = None, zone_id: str | None = None):
        self.zones, self.registry, self.stacks, self.zone_id = zones, registry, dict(stacks or {}), zone_id
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="archive-view-zones")
        self._lock = threading.Lock()
        self._answers: OrderedDict = OrderedDict()
        self._cluster = None
        self.computed = 0   # tables computed (answers not from the cache)

    # ---- the zones ---------------------------------------------------------------------------
    def collection(self) -> dict:
        """The zones in lon/lat (GeoJSON), each Feature's ``id`` its zone id."""
        if self.zones is None:
            return {"type": "FeatureCollection", "features": [], "path": None, "zone_id": None}
        found = json.loads(self.zones.frame.to_crs(4326).to_json(drop_id=True))
        for feature, zid in zip(found["features"], self.zones.ids):
            feature["id"] = zid
        return {**found, "path": self.zones.path, "zone_id": self.zone_id}

    def one(self, zid: str):
        """The Zones of the zone ``zid`` alone (MissingInputError for an id the file has not)."""
        from archive.analysis.zones import Zones

        if self.zones is None or zid not in self.zones.ids:
            raise MissingInputError(zid, "zone", "click a zone of /api/zones")
        k = self.zones.ids.index(zid)
        return Zones(self.zones.path, self.zones.frame.iloc[[k]].reset_index(drop=True), (zid,))

    def load(self, body: bytes, name: str) -> dict:
        """Replace the zones by those of an uploaded GeoJSON file ``name`` (the page's file input or
        drop), read and refused as ``--zones`` reads a file; the new :meth:`collection`."""
        import tempfile

        from archive.analysis.zones import read_zones

        if len(body) > MAX_UPLOAD:
            raise InputError(name, f"{len(body) >> 20} MB of zones is more than the page may send ({MAX_UPLOAD >> 20} MB)",
                             "serve the file with archive view --zones FILE")
        with tempfile.TemporaryDirectory(prefix="archive-view-zones-") as folder:
            path = Path(folder) / "zones.geojson"
            path.write_bytes(body)
            try:
                zones = read_zones(path)
            except InputError as exc:
                raise InputError(name, str(exc.problem).replace(str(path), name), exc.fix) from None
        from archive.analysis.zones import Zones

        with self._lock:
            self.zones, self.zone_id = Zones(name, zones.frame, zones.ids), None
            self._answers.clear()
        return self.collection()

    # ---- the series --------------------------------------------------------------------------
    def request(self, params) -> dict:
        """The parsed parameters of a series request (InputError, naming the parameter, for a bad one)."""
        from archive.drawing.query import parse_number

        zid = params.get("zone")
        if not zid:
            raise InputError("zone", "give the zone's id: zone=ID (the ids of /api/zones)")
        a, b = parse_number(params, "a", 1.0, 1e5), parse_number(params, "b", 1.0, 1e5)
        if (a is None) != (b is None):
            raise InputError("a/b", "the index display's (a - b) / (a + b) needs both bands, a=NM&b=NM")
        name = params.get("index") or "NDVI"
        if a is not None:
            a, b = round(a), round(b)
            name = f"ND{a}_{b}"
            expression = f"{name}=(R{a}-R{b})/(R{a}+R{b})"
        elif name != "NDVI":
            raise InputError("index", f"{name[:40]!r}: the viewer plots NDVI or the index display's a, b",
                             "give index=NDVI, or a=NM&b=NM")
        else:
            expression = None
        mode = params.get("mode") or "reflectance"
        if mode not in ("raw", "relative", "radiance", "reflectance"):
            raise InputError("mode", f"{mode[:40]!r} is not raw, relative, radiance or reflectance")
        stack = params.get("stack") or None
        if stack is not None and stack not in self.stacks:
            raise MissingInputError(stack, "stack", "give one of /api/stacks")
        return {"zone": zid, "index": name, "expression": expression, "mode": mode, "stack": stack,
                "gsd": parse_number(params, "gsd", 1e-3, 1e3)}

    def _flights(self, zones, stack: str | None) -> tuple[list[str], dict[str, str], float | None]:
        """(sources, {table flight name: viewer id}, nominal GSD): the flights whose footprint meets the
        zone's box (the stack's flights with ``stack``)."""
        if stack is not None:
            ids = [f.id for f in self.stacks[stack].flights]
            return ids, {i: i for i in ids}, None
        box = tuple(float(v) for v in zones.frame.to_crs(4326).total_bounds)
        features = self.registry.features(bbox=box)["features"]
        sources, names, gsds = [], {}, []
        for f in features:
            if f["id"] in self.registry.raw:
                path = self.registry.raw[f["id"]][0]
                sources.append(str(path))
                names[path.name] = f["id"]
            else:
                sources.append(f["id"])
                names[f["id"]] = f["id"]
            if f["properties"].get("gsd"):
                gsds.append(float(f["properties"]["gsd"]))
        return sources, names, max(gsds) if gsds else None

    def scheduler(self) -> str:
        """The address of this server's local Dask cluster, started at the first call."""
        if self._cluster is None:
            import logging

            import dask
            from distributed import LocalCluster

            from archive.errors import RenderError

            # archive stats' own clusters preload archive.analysis.worker (see there)
            try:
                with dask.config.set({"distributed.worker.preload": ["archive.analysis.worker"]}):
                    self._cluster = LocalCluster(n_workers=1, threads_per_worker=2, processes=True,
                                                 resources={"GPU": 2}, dashboard_address=":0",
                                                 silence_logs=logging.CRITICAL)
            except (RuntimeError, OSError, TimeoutError) as exc:
                raise RenderError(f"the zones' local Dask cluster did not start ({type(exc).__name__}: {exc})") from None
        return self._cluster.scheduler_address

    def series(self, asked: dict) -> dict:
        """The series of :meth:`request`'s ``asked`` (blocking: run it on :meth:`run`'s thread)."""
        from archive.analysis.indices import parse_indices
        from archive.analysis.zonal import check_options, zonal_table
        from archive.run.options import RenderOptions

        started = time.perf_counter()
        zones = self.one(asked["zone"])
        sources, names, nominal = self._flights(zones, asked["stack"])
        answer = {"zone": asked["zone"], "index": asked["index"], "mode": asked["mode"], "stack": asked["stack"],
                  "flights": [names.get(Path(s).name, s) for s in sources], "rows": [], "bands": None}
        if not sources:
            answer.update(gsd=asked["gsd"], seconds=round(time.perf_counter() - started, 3),
                          message=f"no flight images zone {asked['zone']}")
            return answer
        gsd = asked["gsd"] or (None if asked["stack"] else nominal)
        if gsd is None and asked["stack"] is None:
            raise InputError("gsd", "the flights record no nominal GSD", "give gsd=M")
        key = (asked["zone"], tuple(sources), asked["index"], asked["mode"], gsd, asked["stack"])
        with self._lock:
            if key in self._answers:
                self._answers.move_to_end(key)
                return self._answers[key]
        archive = self.registry.archive
        options = RenderOptions.create(sources, gsd=gsd, mode=asked["mode"], fov=self.registry.fov,
                                       archive=None if archive is None else str(archive.path),
                                       like=None if asked["stack"] is None else self.stacks[asked["stack"]].path)
        check_options(options)
        specs = parse_indices([] if asked["expression"] else [asked["index"]],
                              [asked["expression"]] if asked["expression"] else [])
        table = zonal_table(options, zones, specs, scheduler=self.scheduler())
        rows = []
        for record in table.sort_values("datetime", kind="stable").itertuples(index=False):
            rows.append({"flight": names.get(record.flight, record.flight),
                         "datetime": record.datetime.strftime("%Y-%m-%dT%H:%M:%S.%fZ"),
                         **{k: _number(getattr(record, k)) for k in ROW_FIELDS[2:]}})
        self.computed += 1
        answer.update(gsd=float(options.gsd), rows=rows, bands=str(table["bands"].iloc[0]) if len(table) else None,
                      seconds=round(time.perf_counter() - started, 3))
        if not any(r["count"] for r in rows):
            answer["message"] = f"no flight images zone {asked['zone']}"
        with self._lock:
            self._answers[key] = answer
            while len(self._answers) > KEEP:
                self._answers.popitem(last=False)
        return answer

    async def run(self, asked: dict) -> dict:
        """:meth:`series` on this module's thread, awaited (the event loop goes on meanwhile)."""
        return await asyncio.wrap_future(self._pool.submit(self.series, asked))

    def close(self) -> None:
        """Stop the thread and the cluster (the server has stopped)."""
        self._pool.shutdown(wait=True, cancel_futures=True)
        if self._cluster is not None:
            cluster, self._cluster = self._cluster, None
            cluster.close()


def open_zones(path, zone_id: str | None, registry, stacks: dict | None = None) -> ZoneServer:
    """The :class:`ZoneServer` of ``archive view --zones PATH --zone-id PROP`` (path None: no zones),
    the zones read and checked as ``archive stats`` reads them (one-line InputError)."""
    if path is None:
        if zone_id is not None:
            raise InputError("--zone-id", "names the property of the zones of --zones", "give --zones FILE too")
        return ZoneServer(None, registry, stacks)
    from archive.analysis.zones import read_zones

    return ZoneServer(read_zones(path, zone_id), registry, stacks, zone_id)


def zone_routes(zones: ZoneServer) -> list:
    """The Starlette routes of ``zones`` (for :func:`archive.view.server.create_app`'s extra_routes)."""
    from starlette.concurrency import run_in_threadpool
    from starlette.responses import JSONResponse
    from starlette.routing import Route

    async def listed(request):
        if request.method == "POST":   # a GeoJSON file loaded in the page
            body = await request.body()
            name = (request.query_params.get("name") or "zones.geojson")[:200]
            return JSONResponse(await run_in_threadpool(zones.load, body, name), media_type="application/geo+json")
        return JSONResponse(await run_in_threadpool(zones.collection), media_type="application/geo+json")

    async def series(request):
        return JSONResponse(await zones.run(zones.request(request.query_params)))

    return [Route("/api/zones", listed, methods=["GET", "POST"]), Route("/api/zones/series", series)]
