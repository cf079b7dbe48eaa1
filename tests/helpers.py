"""Constants and shapes the test files share (``from helpers import FOV``; pytest puts ``tests/`` on
``sys.path``). The fixtures that build on them are in ``conftest.py``."""

from __future__ import annotations

#: degrees: the camera field of view of every simulated flight (``simulate_flight``'s default
#: ``fov_deg``), given to ingest and render as ``--fov``.
FOV = 47.5

#: The small flight the concurrency, fault, batch and publication tests share (2 cubes on one pass,
#: 4 bands, 64 samples x 100 lines); ``small_flights`` gives it for seeds 0, 1, ...
SMALL_FLIGHT = dict(cubes=2, bands=4, samples=64, lines=100, cubes_per_pass=2)

#: A 4-cube flight in 2 strips (2 passes), 6 bands 400-1000 nm, 64 samples x 150 lines, seed 3: the
#: render, library API tests' flight (``strips_flight``).
STRIPS_FLIGHT = dict(cubes=4, bands=6, samples=64, lines=150, cubes_per_pass=2, seed=3)

#: The terrain flights (``hills``, ``ridge`` in conftest): two passes of two cubes each, ~40 m above
#: 12 m of relief: hills of -4 to +8 m, everything seen; a ridge with an 83-degree back that hides a strip.
HILLS = dict(terrain="hills", cubes=4, cubes_per_pass=2, bands=4, samples=128, lines=200, seed=21)
RIDGE = dict(terrain="ridge", cubes=4, cubes_per_pass=2, bands=3, samples=96, lines=150, seed=22)

#: The tiniest flight a batch or an S3 archive needs (2 cubes, 2 bands, 24 samples x 40 lines).
TINY_FLIGHT = dict(cubes=2, bands=2, samples=24, lines=40, cubes_per_pass=2)


def ingest_each(directories, archive, fov: float = FOV, **options) -> list[str]:
    """Ingest each raw flight directory on its own into ``archive`` (field of view ``fov`` degrees,
    ``ingest``'s other ``options``); the collection id of each, in order (one collection a flight)."""
    from archive.ingest.command import ingest

    ids = []
    for directory in directories:
        (result,) = ingest([str(directory)], archive, fov, progress=False, **options)
        ids.append(result.cid)
    return ids


def eroded_dilated(inside, grid, d_px: float = 1.5):
    """(eroded, dilated): boolean (height, width) masks on ``grid``'s pixel centres of where
    ``inside(xx, yy)`` (eastings, northings in the grid's CRS, m -> bool of their shape) holds at every
    / at any of the 9 points displaced by -d_px, 0, +d_px pixels in x and y."""
    import numpy as np

    x, y = grid.xy_centres()
    xx, yy = np.meshgrid(x, y)
    d = d_px * grid.gsd
    eroded = np.ones(grid.shape, bool)
    dilated = np.zeros(grid.shape, bool)
    for dx in (-d, 0.0, d):
        for dy in (-d, 0.0, d):
            held = inside(xx + dx, yy + dy)
            eroded &= held
            dilated |= held
    return eroded, dilated


def inside_geometry(geometry: dict, lon, lat):
    """Boolean mask, of ``lon``'s shape, of the points (``lon``, ``lat``: arrays of one shape,
    degrees) inside a GeoJSON Polygon or MultiPolygon ``geometry`` (the outer ring of each polygon)."""
    import numpy as np

    from archive.catalog.footprint import points_in_polygon

    lon, lat = np.asarray(lon), np.asarray(lat)
    polygons = [geometry["coordinates"]] if geometry["type"] == "Polygon" else geometry["coordinates"]
    pts = np.stack([lon.ravel(), lat.ravel()], axis=-1)
    inside = np.zeros(len(pts), bool)
    for poly in polygons:
        inside |= points_in_polygon(pts, np.asarray(poly[0]))
    return inside.reshape(lon.shape)
