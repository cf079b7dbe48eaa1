"""``archive view``: a local web server (Starlette on uvicorn) for the archive's flights.

Endpoints (JSON unless said; errors are ``{"error": message}`` with a 4xx status and never a stack
trace):

- ``GET /`` the page (``static/index.html``); ``GET /static/...`` its assets (Leaflet vendored);
- ``GET /api/collections?bbox=W,S,E,N&datetime=A/B&wavelength=NM`` GeoJSON FeatureCollection of
  the footprints (id, time range, wavelength range, bands, nominal gsd, ``previews_zoom``: the finest
  zoom its ingest previews serve, None without them...), and ``damaged``: the
  flights the catalog cannot describe (``{id, reason, fix}``: an unreadable Item, a collection
  without an Item), each costing only itself; and ``overlaps``: the overlap rules the page offers
  (``{name, label, key, wins}``, the first the default; :data:`archive.drawing.query.OVERLAPS`);
- ``GET /api/collections/{id}`` what the page needs to build its controls (bands, modes, cubes,
  default ground height, lowest camera altitude, sync offset, ``navigation``: its navigation sources and
  the one drawn by default, ``boresight_deg`` as ingested);
- every request that draws (tiles, values, outline, point, stats) also takes ``navigation=lcf|NAME``
  (a navigation source the flight has) and ``boresight=ROLL,PITCH,YAW`` (degrees; default: as ingested);
- ``GET /api/collections/{id}/tiles/{z}/{x}/{y}.png?wavelengths=R,G,B|band=I&mode=&stretch=&cubes=A-B
  &ground_height=&sync_offset=`` a 256 x 256 EPSG:3857 tile drawn by the inverse renderer;
- ``GET /api/collections/{id}/values/{z}/{x}/{y}?bands=I,J,K&mode=&cubes=&ground_height=&sync_offset=
  &overlap=last|nadir&scale=1|2|4|8|16&window=0|1`` band values of a tile (float32 planes,
  little-endian; then the rule's key plane, named by ``X-Key``, for a rule that has one: the view
  zenith of ``nadir``), stretched and composed by the
  page; 204 where no line covers the tile; ``scale`` > 1: a coarse (side 256 / scale) preview;
  ``window=1``: only the rows and columns of the tile that hold a value (header ``X-Window: column,row,
  width,height``; a flight a few pixels wide at an overview zoom sends kilobytes, not 0.8 MB); the
  flight as ingested at a zoom at or above its ingest previews' finest (:mod:`archive.drawing.preview_layout`):
  from them, without the render thread, header ``X-Source: previews``;
- ``GET /api/values/batch?parts=ID/Z/X/Y/I,J,K;...&mode=&overlap=&window=1`` the band values of up to
  MAX_PARTS tiles of any flights in one response (one after the other; header ``X-Parts``: each
  part's status, bytes, side, window, key, error): what the page asks for flights drawn as ingested;
- ``GET /api/collections/{id}/outline?ground_height=&sync_offset=&cubes=`` GeoJSON MultiPolygon of
  the cubes' ground meshes (the footprint as drawn now);
- ``GET /api/collections/{id}/point?lon=&lat=&gsd=&mode=...`` the full spectrum of the output pixel
  at that point (the pixel of ``archive render --gsd GSD``'s grid), with cube, line, sample, time;
- ``GET /api/collections/{id}/stats?bbox=&wavelengths=&mode=&percentiles=2,98`` per band
  percentiles of the view;
- ``GET /api/status`` counters, cache sizes and the server's resident memory;
- ``GET /api/stacks`` the time stacks served (``--stack X.zarr``): name, time steps (flight,
  start), bands, grid, footprint; ``GET /api/stacks/{name}/tiles/{z}/{x}/{y}.png?time=T&bands=I,J,K``
  a tile of time step T (2-98 % stretch of that step), ``.../values/{z}/{x}/{y}?time=&bands=`` its
  float32 planes (each tile pixel the stack pixel under its centre: the Zarr's values),
  ``.../point?lon=&lat=&time=`` the spectrum of the stack pixel there (:mod:`archive.view.stacks`);
- ``GET /api/zones`` the zones of ``--zones`` (lon/lat GeoJSON), ``GET /api/zones/series?zone=ID``
  a zone's statistics per flight, by ``archive stats``' code (:mod:`archive.view.zones`);
- ``/stac/...`` the STAC API of the archive's catalog (:mod:`archive.catalog.api`).

All drawing runs on one render thread (:class:`~archive.view.worker.RenderThread`), the latest view
first: a request's ``X-Generation`` header (the page's clock at the view change, ms) orders the
queue, newest first (:func:`view_generation`); a request whose client has gone is cancelled before
it draws. Binding anything but a loopback address needs
``--allow-remote``; on loopback, requests must name a loopback Host (no DNS rebinding).
"""

from __future__ import annotations

import argparse
import ipaddress
import logging
import socket
import sys
import time
from importlib.resources import files
from pathlib import Path

from archive.catalog.api import stac_routes
from archive.catalog.root import ArchiveRoot
from archive.errors import ArchiveError, InputError, MissingInputError, RenderError
from archive.drawing.cache import ByteLRU
from archive.drawing.query import OVERLAPS, Stretch, overlap_choice, parse_bbox, parse_number, parse_query
from archive.grid import MAX_ZOOM, TILE, Grid, mercator_box, tile_grid
from archive.view.jobs import (describe_job, outline_job, point_job, settled, stats_job, tile_job, values_body,
                               values_job, values_window, view_generation)
from archive.view.registry import FlightRegistry
from archive.view.worker import Cancelled, RenderThread

__all__ = ["CACHE_SHARES", "OVERHEAD_MB", "cache_bytes", "check_host", "create_app", "is_loopback", "run", "serve", "view_generation"]

log = logging.getLogger("archive.view")

#: Default memory for the caches (tiles, band planes and previews, lookups, open flights), MiB.
DEFAULT_CACHE_MB = 512
#: How --cache-mb is shared: tiles (PNG and band values), band planes (and the ingest previews),
#: lookups (pass 1 of the renderer per cube and tile), open flights (sources, poses, meshes).
CACHE_SHARES = {"tiles": 0.25, "bands": 0.375, "lookups": 0.25, "flights": 0.125}
#: What the server needs beyond --cache-mb, MiB: Python and its libraries (~95 MB), the software
#: OpenGL renderer (~60 MB), the renderer's first use (~30 MB) and requests in flight (measured:
#: bench/RESULTS.md, "Viewer server memory").
OVERHEAD_MB = 250


def cache_bytes(cache_mb: int) -> dict[str, int]:
    """The byte limit of each of the viewer's caches (CACHE_SHARES of ``cache_mb`` MiB)."""
    return {name: int((int(cache_mb) << 20) * share) for name, share in CACHE_SHARES.items()}
LOOPBACK_NAMES = ("localhost", "127.0.0.1", "::1")
#: Tiles asked at most in one request of ``/api/values/batch`` (the page asks up to BATCH of state.js).
MAX_PARTS = 64


def is_loopback(host: str) -> bool:
    """Whether ``host`` (a name or address) is the loopback interface."""
    host = host.strip().strip("[]")
    if host.lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def check_host(host: str, allow_remote: bool) -> None:
    """InputError unless ``host`` is loopback or ``allow_remote`` is given."""
    if not is_loopback(host) and not allow_remote:
        raise InputError("--host", f"refusing to serve on {host!r}: not a loopback address, so anyone who can "
                         "reach this machine could read the archive",
                         "use --host 127.0.0.1 (the default), or add --allow-remote to serve the network on purpose")


class Viewer:
    """What the server holds: the flights, the render thread, the tile cache, counters."""

    def __init__(self, registry: FlightRegistry, tile_cache_bytes: int):
        self.registry = registry
        self.render = RenderThread()
        self.tiles = ByteLRU(tile_cache_bytes)
        self.started = time.time()
        self.cancelled = 0
        self.from_previews = 0   # band-value tiles answered from the ingest previews

    def status(self) -> dict:
        return {
            "uptime_s": round(time.time() - self.started, 3), "render": dict(self.render.counts),
            "queued": self.render.queued, "abandoned": self.cancelled, "from_previews": self.from_previews,
            "caches": {"tiles": self.tiles.stats().as_dict(), "bands": self.registry.bands_cache.stats().as_dict(),
                       "lookups": self.registry.lookup_cache.stats().as_dict(),
                       "flights": self.registry.flights_cache.stats().as_dict()},
            "rss_bytes": resident_bytes(),
        }


def resident_bytes() -> int | None:
    """This process's resident memory, bytes (Linux /proc), None elsewhere."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return None




# ---- the app ----------------------------------------------------------------------------------
def create_app(registry: FlightRegistry, *, tile_cache_bytes: int = int((DEFAULT_CACHE_MB << 20) * CACHE_SHARES["tiles"]),
               allowed_hosts: tuple[str, ...] | None = None, stacks: dict | None = None, extra_routes: tuple = ()):
    """The Starlette application serving ``registry``'s flights. allowed_hosts: Host header names
    accepted (None: any), e.g. the loopback names when bound to loopback; stacks: the time stacks
    served, by name (:func:`archive.view.stacks.open_stacks`); extra_routes: more Starlette routes
    (``archive watch``'s ``/api/live``: :func:`archive.watch.live.live_routes`)."""
    from contextlib import asynccontextmanager

    from starlette.applications import Starlette
    from starlette.concurrency import run_in_threadpool
    from starlette.exceptions import HTTPException
    from starlette.responses import HTMLResponse, JSONResponse, Response
    from starlette.routing import Mount, Route
    from starlette.staticfiles import StaticFiles

    from archive.view.residual import residual_routes

    viewer = Viewer(registry, tile_cache_bytes)
    static = files("archive.view") / "static"

    def error(status: int, message: str) -> JSONResponse:
        return JSONResponse({"error": message, "status": status}, status_code=status)

    async def on_archive_error(request, exc: ArchiveError):
        if isinstance(exc, MissingInputError):
            return error(404, str(exc))
        if isinstance(exc, RenderError):
            return error(500, f"rendering failed: {exc}")
        return error(400, str(exc))

    async def on_http_error(request, exc: HTTPException):
        message = exc.detail if exc.status_code != 404 else f"no such resource: {request.url.path}"
        return error(exc.status_code, str(message))

    async def on_cancelled(request, exc: Cancelled):
        viewer.cancelled += 1
        return Response(status_code=499)  # the client has gone; nobody reads this

    async def on_crash(request, exc: Exception):
        log.exception("archive view: %s %s failed", request.method, request.url.path)
        return error(500, f"internal error ({type(exc).__name__}); see the server's log")

    async def drawn(request, fn, *args):
        if await request.is_disconnected():
            raise Cancelled()
        return await viewer.render.run(settled, fn, *args, abandoned=request.is_disconnected,
                                       priority=view_generation(request.headers.get("x-generation")))

    def cid_of(request) -> str:
        return registry.check(request.path_params["cid"])

    async def index(request):
        return HTMLResponse((static / "index.html").read_text(encoding="utf-8"))

    def listed(bbox, when, wavelength) -> dict:
        """The matching flights' Features, each with ``previews_zoom``: the finest zoom its previews serve
        (None: drawn from the DN at every zoom)."""
        found = registry.features(bbox, when, wavelength)
        found["features"] = [{**f, "properties": {**f["properties"], "previews_zoom": registry.previews_zoom(f["id"])}}
                             for f in found["features"]]
        return found

    async def collections(request):
        p = request.query_params
        bbox = parse_bbox(p)
        wavelength = parse_number(p, "wavelength", 0.0, 1e5)
        when = p.get("datetime") or None
        if when is not None and len(when) > 100:
            raise InputError("datetime", f"value of {len(when)} characters is too long")
        found = await run_in_threadpool(listed, bbox, when, wavelength)
        found["overlaps"] = [choice.as_dict() for choice in OVERLAPS]
        return JSONResponse(found, media_type="application/geo+json")

    def tile_request(request):
        """(id, z, x, y, its EPSG:3857 grid, the parsed query) of a tile request."""
        z, x, y = (request.path_params[k] for k in ("z", "x", "y"))
        if z > MAX_ZOOM:
            raise InputError("z", f"zoom {z} is out of range 0..{MAX_ZOOM}", "request a shallower tile")
        return cid_of(request), z, x, y, tile_grid(z, x, y), parse_query(request.query_params)

    async def describe(request):
        return JSONResponse(await drawn(request, describe_job, registry, cid_of(request)))

    async def tile(request):
        cid, z, x, y, grid, query = tile_request(request)
        key = (cid, z, x, y, query)
        png = viewer.tiles.get(key)
        if png is None:
            png = await drawn(request, tile_job, registry, cid, grid, query)
            viewer.tiles.put(key, png, len(png))
        return Response(png, media_type="image/png", headers={"Cache-Control": "private, max-age=600"})

    def values_scale(params) -> int:
        scale = parse_number(params, "scale", 1, 16, 1)
        if scale not in (1, 2, 4, 8, 16):
            raise InputError("scale", f"expected 1, 2, 4, 8 or 16 (coarse previews), got {scale:g}")
        return int(scale)

    async def tile_values(request, cid, z, x, y, grid, query, scale: int, window: bool
                          ) -> tuple[dict, bytes | None]:
        """(headers, body) of the band values of one tile of one flight (float32 planes; see
        :func:`archive.drawing.png.encode_values`), cached per band; body None where no line covers
        the tile (204)."""
        import dataclasses

        import numpy as np

        if query.bands is None:
            raise InputError("bands", "give the 0-based band indices wanted, e.g. bands=3,5,7")
        common = dataclasses.replace(query, bands=None, stretch=Stretch())
        key_name = overlap_choice(query.overlap).key
        keyed = key_name is not None
        headers = {"Cache-Control": "private, max-age=600", "X-Bands": ",".join(map(str, query.bands)),
                   "X-Side": str(TILE // scale), "X-Key": key_name or ""}
        if (not keyed and query.cubes is None and query.ground_height is None and query.sync_offset is None
                and query.navigation is None and query.boresight is None):
            # the flight as ingested, zoomed out: its overview previews, without the DN (issue 36).
            # On the event loop: two stat() calls, then slices of arrays of a few KB (a level is read
            # once, ~1 ms); a thread hand-off per request cost more than that on loaded cores
            previews = registry.previews(cid)
            if previews is not None and previews.serves(query.bands, query.mode, z - scale.bit_length() + 1):
                coarse = Grid(grid.epsg, grid.gsd * scale, grid.x0, grid.y0, TILE // scale, TILE // scale)
                try:
                    planes = previews.values(coarse, query.bands)
                except (ArchiveError, OSError, ValueError) as exc:   # a damaged level: drawn from the DN
                    log.warning("archive view: %s: overview previews unreadable (%s); drawing from the DN", cid, exc)
                else:
                    headers["X-Source"] = "previews"
                    viewer.from_previews += 1
                    if planes is None:
                        return headers, None
                    return values_body(planes, None, headers, values_window(planes) if window else None)
        wanted = list(query.bands) + (["key"] if keyed else [])
        keys = {b: (cid, z, x, y, b, common, scale) for b in wanted}
        found = {b: viewer.tiles.get(k) for b, k in keys.items()}
        empty = viewer.tiles.get((cid, z, x, y, "empty", common, scale))
        missing = [b for b in query.bands if found[b] is None]
        if empty is None and (missing or (keyed and found["key"] is None)):
            asked = dataclasses.replace(query, bands=tuple(missing or query.bands[:1]))
            drawn_values = await drawn(request, values_job, registry, cid, grid, asked, scale)
            if drawn_values is None:
                empty = True
                viewer.tiles.put((cid, z, x, y, "empty", common, scale), True, 64)
            else:
                planes, key = drawn_values
                for b, plane in zip(asked.bands, planes, strict=True):
                    found[b] = plane
                    viewer.tiles.put(keys[b], plane, plane.nbytes)
                if keyed:
                    found["key"] = key
                    viewer.tiles.put(keys["key"], key, key.nbytes)
        if empty:
            return headers, None
        planes = np.stack([found[b] for b in query.bands])
        key = found["key"] if keyed else None
        place = None
        if window:
            # one window per tile and parameters, whichever bands ask: the page keeps the planes
            # of a tile together (a window differing from the one it has drops those, after an eviction)
            window_key = (cid, z, x, y, "window", common, scale)
            place = viewer.tiles.get(window_key)
            if place is None:
                place = values_window(planes)
                viewer.tiles.put(window_key, place, 64)
        return values_body(planes, key, headers, place)

    async def values(request):
        """Band values of a tile (:func:`tile_values`); 204 where no line covers the tile."""
        cid, z, x, y, grid, query = tile_request(request)
        headers, body = await tile_values(request, cid, z, x, y, grid, query, values_scale(request.query_params),
                                          request.query_params.get("window") == "1")
        if body is None:
            return Response(status_code=204, headers=headers)
        return Response(body, media_type="application/octet-stream", headers=headers)

    async def values_batch(request):
        """Band values of several tiles of several flights in one response (the page asks this for
        flights drawn as ingested: one request instead of one per flight and tile). ``parts=ID/Z/X/Y/
        I,J,K;...`` (at most MAX_PARTS), the other parameters shared (``mode``, ``overlap``,
        ``window``...); body: each part's planes one after the other; header ``X-Parts``: per part
        ``[status, bytes, side, window or null, key, error or null]`` (status 200, 204, or the 4xx an
        error of that part alone would have had)."""
        import json

        text = request.query_params.get("parts") or ""
        if len(text) > 200 * MAX_PARTS:
            raise InputError("parts", f"{len(text)} characters is too long")
        parts = [p for p in text.split(";") if p]
        if not 0 < len(parts) <= MAX_PARTS:
            raise InputError("parts", f"give 1 to {MAX_PARTS} parts ID/Z/X/Y/BANDS separated by ';', got {len(parts)}")
        shared = {k: v for k, v in request.query_params.items() if k not in ("parts", "bands")}
        scale = values_scale(shared)
        window = shared.get("window") == "1"
        index, bodies = [], []
        for part in parts:
            try:
                fields = part.split("/")
                if len(fields) != 5:
                    raise InputError("parts", f"expected ID/Z/X/Y/BANDS, got {part[:80]!r}")
                try:
                    z, x, y = (int(v) for v in fields[1:4])
                except ValueError:
                    raise InputError("parts", f"tile {'/'.join(fields[1:4])[:40]!r} is not Z/X/Y") from None
                cid = registry.check(fields[0])
                if z > MAX_ZOOM:
                    raise InputError("z", f"zoom {z} is out of range 0..{MAX_ZOOM}", "request a shallower tile")
                query = parse_query({**shared, "bands": fields[4]})
                headers, body = await tile_values(request, cid, z, x, y, tile_grid(z, x, y), query, scale, window)
            except ArchiveError as exc:
                status = 404 if isinstance(exc, MissingInputError) else 500 if isinstance(exc, RenderError) else 400
                index.append([status, 0, None, None, False, str(exc)])
                continue
            win = headers.get("X-Window")
            index.append([200 if body is not None else 204, len(body or b""), int(headers["X-Side"]),
                          [int(v) for v in win.split(",")] if win else None, bool(headers["X-Key"]), None])
            bodies.append(body or b"")
        return Response(b"".join(bodies), media_type="application/octet-stream",
                        headers={"Cache-Control": "no-store", "X-Parts": json.dumps(index, separators=(",", ":"))})

    async def outline(request):
        cid = cid_of(request)
        query = parse_query(request.query_params, channels=False)
        return JSONResponse(await drawn(request, outline_job, registry, cid, query))

    async def point(request):
        cid = cid_of(request)
        p = request.query_params
        lon = parse_number(p, "lon", -180.0, 180.0)
        lat = parse_number(p, "lat", -85.0, 85.0)
        if lon is None or lat is None:
            raise InputError("lon/lat", "both lon and lat (degrees) are required")
        gsd = parse_number(p, "gsd", 1e-3, 1e3)
        query = parse_query(p, channels=False)
        return JSONResponse(await drawn(request, point_job, registry, cid, lon, lat, gsd, query))

    async def stats(request):
        cid = cid_of(request)
        p = request.query_params
        bbox = parse_bbox(p)
        box = None if bbox is None else mercator_box(*bbox)
        query = parse_query(p)
        pct = p.get("percentiles") or "2,98"
        try:
            lo, hi = (float(v) for v in pct.split(","))
        except ValueError:
            raise InputError("percentiles", f"expected LOW,HIGH percentiles, got {pct[:40]!r}") from None
        if not 0 <= lo < hi <= 100:
            raise InputError("percentiles", f"expected 0 <= low < high <= 100, got {pct!r}")
        if box is None and query.bands is not None and query.cubes is None:
            # the whole flight's statistics of the previews' bands were computed at ingest
            previews = await run_in_threadpool(registry.previews, cid)
            found = None if previews is None else previews.flight_stats(query.bands, query.mode or previews.mode,
                                                                        (lo, hi))
            if found is not None:
                return JSONResponse(found)
        return JSONResponse(await drawn(request, stats_job, registry, cid, box, query, (lo, hi)))

    async def status(request):
        return JSONResponse(viewer.status())

    stacks = dict(stacks or {})

    def stack_of(request):
        name = request.path_params["name"]
        if name not in stacks:
            raise MissingInputError(name, "stack", "open one of /api/stacks")
        return stacks[name]

    async def stack_list(request):
        return JSONResponse({"stacks": [await run_in_threadpool(v.info) for v in stacks.values()]})

    def stack_tile_args(request):
        from archive.view.stacks import default_bands, parse_bands

        view = stack_of(request)
        z, x, y = (request.path_params[k] for k in ("z", "x", "y"))
        p = request.query_params
        return view, z, x, y, p.get("time", "0"), parse_bands(p.get("bands"), default_bands(view))

    async def stack_tile(request):
        view, *args = stack_tile_args(request)
        png = await run_in_threadpool(view.png, *args)
        return Response(status_code=204) if png is None else Response(png, media_type="image/png")

    async def stack_values(request):
        view, *args = stack_tile_args(request)
        planes = await run_in_threadpool(view.values, *args)
        if planes is None:
            return Response(status_code=204)
        return Response(planes.astype("<f4").tobytes(), media_type="application/octet-stream",
                        headers={"X-Bands": str(planes.shape[0])})

    async def stack_point(request):
        p = request.query_params
        lon, lat = parse_number(p, "lon", -180.0, 180.0), parse_number(p, "lat", -90.0, 90.0)
        if lon is None or lat is None:
            raise InputError("lon/lat", "a point needs lon and lat, degrees")
        found = await run_in_threadpool(stack_of(request).point, lon, lat, p.get("time", "0"))
        return JSONResponse(found if found is not None else {"error": "no stack pixel there", "status": 404},
                            status_code=200 if found is not None else 404)

    @asynccontextmanager
    async def lifespan(app):
        yield
        viewer.render.shutdown()
        registry.close()

    routes = [
        Route("/", index),
        Route("/api/status", status),
        Route("/api/collections", collections),
        Route("/api/collections/{cid}", describe),
        Route("/api/collections/{cid}/tiles/{z:int}/{x:int}/{y:int}.png", tile),
        Route("/api/collections/{cid}/values/{z:int}/{x:int}/{y:int}", values),
        Route("/api/values/batch", values_batch),
        Route("/api/collections/{cid}/outline", outline),
        Route("/api/collections/{cid}/point", point),
        Route("/api/collections/{cid}/stats", stats),
        Route("/api/stacks", stack_list),
        Route("/api/stacks/{name}/tiles/{z:int}/{x:int}/{y:int}.png", stack_tile),
        Route("/api/stacks/{name}/values/{z:int}/{x:int}/{y:int}", stack_values),
        Route("/api/stacks/{name}/point", stack_point),
        *residual_routes(stack_of),   # /api/stacks/{name}/residual (archive.view.residual, issue 33)
        *extra_routes,
        Mount("/static", StaticFiles(directory=str(static)), name="static"),
        *stac_routes(None if registry.archive is None else ArchiveRoot(registry.archive.path)),
    ]
    handlers = {ArchiveError: on_archive_error, HTTPException: on_http_error, Cancelled: on_cancelled,
                Exception: on_crash}
    app = Starlette(routes=routes, exception_handlers=handlers, lifespan=lifespan)
    app.state.viewer = viewer
    if allowed_hosts is None:
        return app
    return _HostCheck(app, allowed_hosts)


class _HostCheck:
    """ASGI middleware: HTTP requests whose Host header is not one of ``allowed`` get a 400 (a
    page of another site reaching the loopback server by DNS rebinding names its own host)."""

    def __init__(self, app, allowed):
        self.app = app
        self.allowed = {h.lower().strip("[]") for h in allowed}
        self.state = getattr(app, "state", None)

    async def __call__(self, scope, receive, send):
        if scope["type"] == "http":
            host = dict(scope.get("headers") or []).get(b"host", b"").decode("latin-1").lower()
            name = host.rsplit(":", 1)[0] if host.count(":") == 1 or host.startswith("[") else host
            if name.strip("[]") not in self.allowed:
                from starlette.responses import JSONResponse

                body = {"error": f"Host {host!r} is not served here; open the URL archive view printed", "status": 400}
                await JSONResponse(body, status_code=400)(scope, receive, send)
                return
        await self.app(scope, receive, send)


def _bind(host: str, port: int) -> socket.socket:
    family = socket.AF_INET6 if ":" in host.strip("[]") else socket.AF_INET
    # IPPROTO_TCP named explicitly: asyncio sets TCP_NODELAY only on sockets that say they are TCP
    # (with proto 0, Nagle's algorithm and the client's delayed ACK add 40 ms to each response).
    sock = socket.socket(family, socket.SOCK_STREAM, socket.IPPROTO_TCP)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((host.strip("[]"), port))
    except OSError as exc:
        sock.close()
        raise InputError("--port", f"cannot listen on {host}:{port}: {exc.strerror or exc}",
                         "choose another --port (0 picks a free one)") from None
    sock.listen(128)
    sock.set_inheritable(True)
    return sock


def url_of(sock: socket.socket) -> str:
    host, port = sock.getsockname()[:2]
    shown = f"[{host}]" if ":" in host else host
    return f"http://{shown}:{port}/"


def serve(registry: FlightRegistry, host: str = "127.0.0.1", port: int = 8000, *, allow_remote: bool = False,
          cache_mb: int = DEFAULT_CACHE_MB, announce=print, ready=None, stacks: dict | None = None,
          extra_routes: tuple = ()) -> None:
    """Serve ``registry`` until interrupted. ``announce(text)`` is told the URL once listening;
    ``ready(server)`` (optional) gets the uvicorn Server (tests stop it with ``should_exit``)."""
    import uvicorn

    check_host(host, allow_remote)
    sock = _bind(host, int(port))
    allowed = (*LOOPBACK_NAMES, host) if is_loopback(host) else None
    app = create_app(registry, tile_cache_bytes=cache_bytes(cache_mb)["tiles"], allowed_hosts=allowed, stacks=stacks,
                     extra_routes=tuple(extra_routes))
    config = uvicorn.Config(app, log_level="warning", access_log=False, lifespan="on",
                            timeout_graceful_shutdown=3)
    server = uvicorn.Server(config)
    if ready is not None:
        ready(server)
    announce(url_of(sock))
    try:
        server.run(sockets=[sock])
    finally:
        sock.close()


def run(args: argparse.Namespace) -> int:
    """The ``archive view`` command."""
    check_host(args.host, args.allow_remote)
    if not is_loopback(args.host):
        print(f"archive view: warning: serving on {args.host}, not loopback: anyone who can reach this machine "
              "can read the archive's flights", file=sys.stderr)
    if args.cache_mb <= 0:
        raise InputError("--cache-mb", f"must be a positive number of MiB, got {args.cache_mb}")
    limits = cache_bytes(args.cache_mb)
    registry = FlightRegistry(args.archive, args.directories, args.fov, bands_cache=ByteLRU(limits["bands"]),
                              lookup_cache=ByteLRU(limits["lookups"]), flights_cache=ByteLRU(limits["flights"]),
                              navigation=getattr(args, "navigation", None))
    count = len(registry.catalog_ids()) + len(registry.raw)
    from archive.view.stacks import open_stacks

    from archive.view.zones import open_zones, zone_routes

    stacks = open_stacks(getattr(args, "stack", None))
    zones = open_zones(getattr(args, "zones", None), getattr(args, "zone_id", None), registry, stacks)

    def announce(url: str) -> None:
        print(f"archive view: {count} flight{'s' if count != 1 else ''} at {url}  (Ctrl-C stops)", flush=True)

    try:
        serve(registry, args.host, args.port, allow_remote=args.allow_remote, cache_mb=args.cache_mb,
              announce=announce, stacks=stacks, extra_routes=zone_routes(zones))
    except KeyboardInterrupt:  # Ctrl-C is how a viewer is stopped: uvicorn has shut down cleanly
        pass
    finally:
        zones.close()
    print("archive view: stopped", flush=True)
    return 0
