"""Zonal statistics of spectral indices over the archive's time stack: one row per zone x flight x index.

Every flight is the lazy time stack's slice (:func:`archive.run.stacks.stack`): rendered from its raw
lines onto the stack's ONE aligned grid, so two dates of a field are compared pixel for pixel. Only
what the table needs is computed, as one Dask graph over the stack's own tasks:

- **bands**: only those the indices read (the render options' ``wavelengths``, the camera bands the
  indices chose: :func:`archive.analysis.indices.bind_indices`);
- **windows**: the zones are grouped by the stack's 1024 px tile their window starts in; a group's
  window (the union of its zones' pixel boxes) is sliced from each flight's lazy slice, so dask
  culls every tile (and every cube's render) no zone touches; a zone off the grid costs nothing;
- **per flight**: one task per window and flight (:func:`window_stats`: the indices, then
  ``exactextract`` over the window's zones), flights submitted in waves of two, so that the
  workers hold the renders of at most two flights' windows at a time; the client gets the rows.

Pixels are weighted by the fraction of them inside the zone (``exactextract``'s exact coverage):
``count`` is the sum of those fractions over the pixels with a value (float), ``coverage`` the
fraction of the zone they make (``count`` x GSD² / the zone's area in the grid's CRS). A pixel
flagged saturated (the lazy stack's ``saturated``: the raw DN of some rendered band, i.e. of some
band the table's indices read, at or above the camera's ceiling) has no value: it is left out of
``count``, ``coverage`` and every statistic of every index, and ``saturated`` is the sum of the
fractions of the flagged pixels in the zone (its imaged fraction is (``count`` + ``saturated``) x
GSD² / area). ``mean``, ``std``
(population), ``min``, ``max`` and the weighted quantiles ``p10``, ``median``, ``p90``
(exactextract's: Hyndman-Fan type 7 generalised to weights). A zone no flight images is listed
with count 0 and NaN statistics. The ``bands`` column records which camera band each symbol took.

Memory: a window task holds the window's needed bands and one index array (float32); a zone larger
than :data:`MAX_GROUP_PIXELS` gets a window of its own, its whole box (its size is the bound).
"""

from __future__ import annotations

import dataclasses
import math
import sys
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from archive.analysis.indices import BoundIndex, IndexSpec, bind_indices, evaluate
from archive.analysis.zones import Zones
from archive.errors import ArchiveError, InputError, RenderError

if TYPE_CHECKING:
    import pandas as pd

    from archive.run.options import RenderOptions

__all__ = ["COLUMNS", "MAX_GROUP_PIXELS", "STATS", "Window", "check_options", "plan_windows", "window_stats",
           "zonal_table"]

#: The statistics columns, in order.
STATS = ("count", "coverage", "saturated", "mean", "std", "min", "p10", "median", "p90", "max")
#: The table's columns (``geometry`` added last when asked for).
COLUMNS = ("zone", "flight", "datetime", "index", *STATS, "bands")
#: exactextract's operation for each statistic it computes, and the name of its result.
_OPS = {"count": ("count", "count"), "mean": ("mean", "mean"), "std": ("stdev", "stdev"), "min": ("min", "min"),
        "p10": ("quantile(q=0.1)", "quantile_10"), "median": ("median", "median"),
        "p90": ("quantile(q=0.9)", "quantile_90"), "max": ("max", "max")}
#: Pixels of a group's window above which a zone gets a window of its own.
MAX_GROUP_PIXELS = 2048 * 2048
#: Flights whose window tasks are in the scheduler at once.
FLIGHTS_AHEAD = 2


# ---------------------------------------------------------------------------------------------
# The task body (a plain function of explicit inputs)
# ---------------------------------------------------------------------------------------------
def window_stats(values: np.ndarray, wavelengths: Sequence[float], bounds: Sequence[float],
                 zones: Sequence[bytes], areas: Sequence[float], indices: Sequence[BoundIndex],
                 saturated: np.ndarray | None = None) -> list[list]:
    """Statistics of ``indices`` over ``zones`` on one window.

    values: (band, y, x) float32, rows north to south, NaN where no line was seen; saturated: (y, x),
    not 0 where a pixel is flagged saturated (left out of every index; None: no pixel is); wavelengths: nm of
    each band of ``values``; bounds: the window's (west, south, east, north), metres of the zones'
    CRS (pixels square: (east - west) / x = the GSD); zones: WKB polygons in that CRS; areas: each
    zone's area, m². Returns one row per zone and index (zone order, then index order):
    [zone position, index position, *STATS], NaN statistics (count 0) where no pixel has a value.
    """
    import shapely
    from exactextract import exact_extract
    from exactextract.feature import JSONFeatureSource
    from exactextract.raster import NumPyRasterSource

    west, south, east, north = (float(b) for b in bounds)
    gsd = (east - west) / values.shape[2]
    by_nm = {float(nm): values[k] for k, nm in enumerate(wavelengths)}
    flagged = None if saturated is None else np.asarray(saturated) != 0
    rasters = [NumPyRasterSource(_unflagged(evaluate(ix, by_nm), flagged), west, south, east, north, name=f"i{j}")
               for j, ix in enumerate(indices)]
    features = [{"type": "Feature", "properties": {"z": k}, "geometry": shapely.from_wkb(w).__geo_interface__}
                for k, w in enumerate(zones)]
    found = exact_extract(rasters, JSONFeatureSource(features), [op for op, _ in _OPS.values()], include_cols=["z"])
    flags = {}   # zone -> the coverage-weighted count of its flagged pixels (a pass of its own: one op, one raster)
    if flagged is not None and flagged.any():
        for f in exact_extract(NumPyRasterSource(flagged.astype(np.float32), west, south, east, north, name="s"),
                               JSONFeatureSource(features), ["sum"], include_cols=["z"]):
            v = f["properties"].get("sum")
            flags[int(f["properties"]["z"])] = 0.0 if v is None or math.isnan(v) else float(v)
    rows = []
    for feature in sorted(found, key=lambda f: f["properties"]["z"]):
        props = feature["properties"]
        z = int(props["z"])
        for j in range(len(indices)):
            def get(field: str) -> float:   # one raster: exactextract names its results without a prefix
                v = props.get(f"i{j}_{field}" if len(indices) > 1 else field)
                return math.nan if v is None else float(v)

            stats = {name: get(field) for name, (_, field) in _OPS.items()}
            stats["count"] = 0.0 if math.isnan(stats["count"]) else stats["count"]
            if stats["count"] == 0:
                stats.update({k: math.nan for k in _OPS if k != "count"})
            stats["coverage"] = stats["count"] * gsd * gsd / float(areas[z])
            stats["saturated"] = flags.get(z, 0.0)
            rows.append([z, j, *(stats[s] for s in STATS)])
    return rows


def _unflagged(index: np.ndarray, flagged: np.ndarray | None) -> np.ndarray:
    """``index`` with NaN where ``flagged`` (saturated pixels have no value)."""
    if flagged is None or not flagged.any():
        return index
    return np.where(flagged, np.float32(np.nan), index).astype(np.float32, copy=False)


# ---------------------------------------------------------------------------------------------
# Windows
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Window:
    """A window of the stack's grid and the zones it serves: rows ``r0:r1``, columns ``c0:c1``
    (pixels of the grid, north row 0), ``zones`` (positions in the zone list)."""

    r0: int
    r1: int
    c0: int
    c1: int
    zones: tuple[int, ...]

    @property
    def pixels(self) -> int:
        return (self.r1 - self.r0) * (self.c1 - self.c0)


def plan_windows(boxes: np.ndarray, x0: float, y0: float, gsd: float, shape: tuple[int, int],
                 chunk: int = 1024) -> tuple[list[Window], list[int]]:
    """(windows, off): the windows of zones of bounding ``boxes`` (zones, 4: west, south, east,
    north, m) on a grid of top-left corner (``x0``, ``y0``) m, ``gsd`` m pixels and ``shape`` (height,
    width), tiles of ``chunk`` px; ``off``: the zones with no pixel on the grid. Each zone's box is
    its pixels touched (edges rounded outward), clipped to the grid; zones are grouped by the tile
    their box starts in, a group's window is the union of its boxes (a zone whose addition would
    pass :data:`MAX_GROUP_PIXELS` gets a window of its own)."""
    height, width = shape
    groups: dict[tuple[int, int], list[list]] = {}
    off = []
    for z, (w, s, e, n) in enumerate(np.asarray(boxes, float)):
        c0, c1 = math.floor((w - x0) / gsd), math.ceil((e - x0) / gsd)
        r0, r1 = math.floor((y0 - n) / gsd), math.ceil((y0 - s) / gsd)
        c0, c1, r0, r1 = max(c0, 0), min(c1, width), max(r0, 0), min(r1, height)
        if c1 <= c0 or r1 <= r0:
            off.append(z)
            continue
        key = (r0 // chunk, c0 // chunk)
        for g in groups.setdefault(key, []):
            u = [min(g[0], r0), max(g[1], r1), min(g[2], c0), max(g[3], c1)]
            if (u[1] - u[0]) * (u[3] - u[2]) <= MAX_GROUP_PIXELS:
                g[:4] = u
                g[4].append(z)
                break
        else:
            groups[key].append([r0, r1, c0, c1, [z]])
    windows = [Window(g[0], g[1], g[2], g[3], tuple(g[4])) for key in sorted(groups) for g in groups[key]]
    return windows, off


# ---------------------------------------------------------------------------------------------
# The table
# ---------------------------------------------------------------------------------------------
def _camera_wavelengths(options: RenderOptions, nav) -> tuple[tuple[float, ...] | None, str]:
    """The band centres (nm) of the first flight of ``options`` and its name (metadata only)."""
    from archive.sources import open_source

    first = options.sources[0]
    source = open_source(first, nav, calibration=options.calibration, archive=options.archive)
    return source.wavelengths, f"flight {first}"


def _grid_of(da) -> tuple[int, float, float, float]:
    """(EPSG, x0, y0, gsd) of a lazy stack: the top-left corner (m) and pixel size of its grid."""
    from pyproj import CRS

    x, y = da["x"].values, da["y"].values
    gsd = float(x[1] - x[0]) if x.size > 1 else float(y[0] - y[1]) if y.size > 1 else math.nan
    epsg = CRS.from_wkt(da["spatial_ref"].attrs["crs_wkt"]).to_epsg()
    return int(epsg), float(x[0] - gsd / 2), float(y[0] + gsd / 2), gsd


def _wait(futures: list, flight: str) -> list:
    """The results of a flight's window tasks; a task's failure as one ArchiveError naming the flight."""
    from distributed import KilledWorker, wait

    wait(futures)
    out = []
    for future in futures:
        if future.status == "error":
            exc = future.exception()
            if isinstance(exc, ArchiveError):
                raise exc
            if isinstance(exc, KilledWorker):
                raise RenderError(f"{flight}: a Dask worker died while computing its zones ({exc}); it may have run "
                                  "out of memory: try a larger --gsd or smaller zones")
            raise RenderError(f"{flight}: a zonal task failed: {type(exc).__name__}: {exc}")
        if future.status == "cancelled":
            raise RenderError(f"{flight}: its tasks were cancelled (the scheduler lost them)")
        out.append(future.result())
        future.release()
    return out


def zonal_table(options: RenderOptions, zones: Zones, specs: Sequence[IndexSpec], *, geometry: bool = False,
                scheduler: str | None = None, workers: int | None = None, threads: int | None = None,
                quiet: bool = True, say=None) -> pd.DataFrame:
    """The zone x flight x index table of ``zones`` over the time stack of ``options`` (a
    :class:`~archive.run.options.RenderOptions`; its band selection is replaced by the bands the
    indices ``specs`` need), computed on ``scheduler`` (an address) or a local cluster of
    ``workers`` x ``threads``. A ``pandas.DataFrame`` of :data:`COLUMNS` (zones in file order, then
    flights in time order, then indices as asked; ``datetime``: the flight's first line, UTC), a
    ``geopandas.GeoDataFrame`` with the zones' geometries (their own CRS) when ``geometry``."""
    import dask
    import pandas as pd

    import distributed  # noqa: F401  (its configuration's defaults loaded before one is set below)

    from archive.run.cluster import ClusterStart, close_client, closed_or_warned, start_cluster
    from archive.run.stacks import stack

    say = say or (lambda text: None)
    started = time.perf_counter()
    nav = options.check()
    wavelengths, camera = _camera_wavelengths(options, nav)
    bound = bind_indices(specs, wavelengths, camera)
    needed = tuple(sorted({nm for ix in bound for nm in ix.wavelengths}))
    options = dataclasses.replace(options, wavelengths=needed, bands="all")
    client = cluster = None
    preload = dask.config.get("distributed.worker.preload", None) or []
    preload = [preload] if isinstance(preload, str) else list(preload)
    try:
        # the workers start (a local cluster's first preloading archive.analysis.worker) while the
        # flights are planned: the stack's grid, each flight's plan (metadata only)
        with dask.config.set({"distributed.worker.preload": ["archive.analysis.worker", *preload]}):
            starting = ClusterStart(scheduler, workers, say, threads)
            try:
                da, flags = stack(options, quiet=quiet, saturated=True)
            finally:
                client, cluster = start_cluster(starting, workers, say, threads)   # waits for it
        stack_nm = [float(v) for v in da["wavelength"].values]
        epsg, x0, y0, gsd = _grid_of(da)
        if math.isnan(gsd):
            gsd = float(options.gsd)
        geoms = zones.in_crs(epsg)
        boxes = np.array([g.bounds for g in geoms])
        areas = [float(g.area) for g in geoms]
        wkb = [g.wkb for g in geoms]
        windows, off = plan_windows(boxes, x0, y0, gsd, (da.sizes["y"], da.sizes["x"]),
                                    chunk=int(da.data.chunksize[-1]))
        flights = [str(f) for f in da["flight"].values]
        times = pd.to_datetime(da["time"].values).tz_localize("UTC")
        call = dask.delayed(window_stats, pure=True)
        results: dict[int, list] = {}
        queue, inflight = deque(range(len(flights))), deque()
        say(f"archive stats: {len(zones)} zones ({len(off)} off the grid) in {len(windows)} windows x "
            f"{len(flights)} flights x {len(bound)} indices, planned in {time.perf_counter() - started:.1f} s")
        bar = None
        if not quiet:
            from tqdm import tqdm

            bar = tqdm(total=len(flights), desc="stats", unit="flight", file=sys.stderr)
        try:
            while queue or inflight:
                while queue and len(inflight) < FLIGHTS_AHEAD:
                    t = queue.popleft()
                    slice_t, flags_t = da.data[t], flags.data[t]
                    tasks = []
                    for w in windows:
                        west, north = x0 + w.c0 * gsd, y0 - w.r0 * gsd
                        bounds = (west, north - (w.r1 - w.r0) * gsd, west + (w.c1 - w.c0) * gsd, north)
                        tasks.append(call(slice_t[:, w.r0:w.r1, w.c0:w.c1], stack_nm, bounds,
                                          [wkb[z] for z in w.zones], [areas[z] for z in w.zones], bound,
                                          flags_t[w.r0:w.r1, w.c0:w.c1]))
                    with dask.config.set({"optimization.fuse.active": False}):   # keeps the GL tasks' GPU annotations
                        inflight.append((t, client.compute(tasks) if tasks else []))
                t, futures = inflight.popleft()
                results[t] = _wait(futures, flights[t])
                if bar is not None:
                    bar.update(1)
        finally:
            pending = [f for _, fs in inflight for f in fs if not f.done()]
            if pending:
                client.cancel(pending, force=True)
            if bar is not None:
                bar.close()
    finally:
        if client is not None:
            closed_or_warned(lambda: close_client(client, cluster), "archive stats", "zonal statistics")
    # rows: (zone, flight, index) -> stats
    table: dict[tuple[int, int, int], list] = {}
    for t, per_window in results.items():
        for w, rows in zip(windows, per_window):
            for zpos, j, *stats in rows:
                table[w.zones[zpos], t, j] = stats
    empty = [0.0, 0.0, 0.0, *([math.nan] * (len(STATS) - 3))]
    records = []
    for z, zid in enumerate(zones.ids):
        for t, flight in enumerate(flights):
            for j, ix in enumerate(bound):
                records.append([zid, flight, times[t], ix.name, *table.get((z, t, j), empty), ix.describe()])
    frame = pd.DataFrame.from_records(records, columns=list(COLUMNS))
    frame.attrs["seconds"] = time.perf_counter() - started
    frame.attrs["windows"] = len(windows)
    if geometry:
        import geopandas as gpd

        position = {zid: k for k, zid in enumerate(zones.ids)}
        geom = zones.frame.geometry.values.take([position[z] for z in frame["zone"]])
        frame = gpd.GeoDataFrame(frame, geometry=gpd.GeoSeries(geom, crs=zones.frame.crs).values, crs=zones.frame.crs)
    return frame


def check_options(options: RenderOptions) -> None:
    """InputError for render options a zonal table cannot take (provenance layers)."""
    if options.provenance:
        raise InputError("--provenance", "a zonal table holds no provenance layers", "leave it out")
