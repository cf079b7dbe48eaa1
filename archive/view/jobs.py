"""What the viewer's server asks of its render thread (:class:`~archive.view.worker.RenderThread`): one
job per request kind (a tile, band values, an outline, a point, statistics, a description), each
charged to the flights' cache afterwards; and the small helpers of the band-value answers."""

from __future__ import annotations

import math
import time

from archive.errors import InputError
from archive.view.registry import FlightRegistry
from archive.drawing.png import encode_values

__all__ = ["describe_job", "outline_job", "point_job", "registry_gsd", "settled", "stats_job", "tile_job",
           "values_body", "values_job", "values_window", "view_generation"]


def settled(fn, registry, *args, check):
    """``fn(registry, *args, check)``, then the flights it used charged what they hold now
    (:meth:`FlightRegistry.settle`): the open flights stay within their share of --cache-mb."""
    try:
        return fn(registry, *args, check)
    finally:
        registry.settle()


def tile_job(registry, cid, grid, query, check):
    return registry.flight(cid).tile(grid, query, check)


def values_job(registry, cid, grid, query, scale, check):
    flight = registry.flight(cid)
    gsd = registry.feature(cid)["properties"].get("gsd")
    return flight.band_values(grid, query, float(gsd) if gsd else None, scale, check)


def outline_job(registry, cid, query, check):
    return registry.flight(cid).outline(query)


def point_job(registry, cid, lon, lat, gsd, query, check):
    check()
    flight = registry.flight(cid)
    if gsd is None:
        gsd = registry_gsd(registry, cid)
    return flight.point(lon, lat, gsd, query)


def stats_job(registry, cid, box, query, percentiles, check):
    flight = registry.flight(cid)
    # the whole flight's statistics do not depend on where its pixels land: no meshes for them
    geometry = None if box is None else flight.view_geometry(query)
    return flight.stats(box, flight.bands(query), flight.mode(query), flight.cube_range(query.cubes), geometry,
                        percentiles)


def describe_job(registry, cid, check):
    return registry.flight(cid).describe()


def view_generation(header: str | None, now: float | None = None) -> float:
    """The render priority of a request: its ``X-Generation`` header (milliseconds since the epoch
    of the view change that asked for it, as the page sends), else (absent or not a number) the
    time it arrived, in the same unit. The render thread draws the highest first: the latest view
    before superseded ones still waiting."""
    if header is not None:
        try:
            value = float(header)
        except ValueError:
            value = math.nan
        if math.isfinite(value):
            return value
    return (time.time() if now is None else now) * 1000.0


def values_window(planes) -> tuple[int, int, int, int]:
    """(column, row, width, height) of the smallest window of (k, n, n) planes holding every finite
    value (at least one pixel)."""
    import numpy as np

    finite = np.isfinite(planes).any(axis=0)
    rows, cols = np.flatnonzero(finite.any(axis=1)), np.flatnonzero(finite.any(axis=0))
    if not rows.size:
        return 0, 0, 1, 1
    return int(cols[0]), int(rows[0]), int(cols[-1] - cols[0] + 1), int(rows[-1] - rows[0] + 1)


def values_body(planes, key, headers: dict, window: tuple[int, int, int, int] | None) -> tuple[dict, bytes]:
    """(headers, body) of a band-value tile: (k, n, n) ``planes`` and the (n, n) ``key`` (or None),
    only their ``window`` (column, row, width, height; None: the whole tile, no X-Window header)."""
    if window is not None:
        c0, r0, w, h = window
        planes = planes[:, r0:r0 + h, c0:c0 + w]
        key = None if key is None else key[r0:r0 + h, c0:c0 + w]
        headers = {**headers, "X-Window": ",".join(map(str, window))}
    return headers, encode_values(planes, key)


def registry_gsd(registry: FlightRegistry, cid: str) -> float:
    """The nominal pixel size of a flight (its catalog entry), m."""
    gsd = registry.feature(cid)["properties"].get("gsd")
    if gsd:
        return float(gsd)
    raise InputError("gsd", f"no nominal pixel size is known for {cid}", "pass gsd=M")
