"""Web-Mercator (EPSG:3857) XYZ tiles as output grids, and tile PNGs from rendered values.

Tile ``z/x/y`` (x eastwards, y southwards from the north-west corner of the world square, as
Leaflet, OpenLayers and MapLibre number them) is a 256 x 256 :class:`~archive.grid.Grid` in
EPSG:3857 whose pixel size is ``2 pi R / 256 / 2^z`` metres of the projection (R = 6378137 m);
the renderer samples its pixel centres like any other grid. No OpenGL here.
"""

from __future__ import annotations

import io
import math
from functools import lru_cache

import numpy as np

from archive.errors import InputError
from archive.grid import Grid

__all__ = ["HALF_WORLD", "MAX_ZOOM", "TILE", "bbox_grid", "encode_png", "encode_values", "lonlat_to_mercator", "mercator_box",
           "mercator_to_lonlat", "tile_grid", "transparent_png", "zoom_gsd"]

TILE = 256
EARTH_RADIUS = 6378137.0
#: Half the side of the Web-Mercator world square, metres (x and y run over +-HALF_WORLD).
HALF_WORLD = math.pi * EARTH_RADIUS
#: Deepest zoom served (2^30 tiles a side: 0.15 mm pixels at the equator).
MAX_ZOOM = 30
#: Largest side of a stats grid, pixels.
STATS_SIDE = 512
MERCATOR_EPSG = 3857


def zoom_gsd(z: int) -> float:
    """Pixel size of zoom ``z`` tiles, metres of EPSG:3857."""
    return 2.0 * HALF_WORLD / TILE / 2.0**z


def tile_grid(z: int, x: int, y: int) -> Grid:
    """The EPSG:3857 grid of tile ``z/x/y``; InputError unless 0 <= z <= MAX_ZOOM and x, y are
    tiles of that zoom."""
    for name, value in (("z", z), ("x", x), ("y", y)):
        if isinstance(value, bool) or not isinstance(value, int | np.integer):
            raise InputError(name, f"tile {name} must be an integer, got {value!r}")
    if not 0 <= z <= MAX_ZOOM:
        raise InputError("z", f"zoom {z} is out of range 0..{MAX_ZOOM}", "request a shallower tile")
    n = 1 << int(z)
    if not (0 <= x < n and 0 <= y < n):
        raise InputError("x/y", f"tile {x}/{y} does not exist at zoom {z} (0..{n - 1})")
    gsd = zoom_gsd(z)
    side = TILE * gsd
    return Grid(MERCATOR_EPSG, gsd, -HALF_WORLD + x * side, HALF_WORLD - y * side, TILE, TILE)


def lonlat_to_mercator(lon, lat) -> tuple[np.ndarray, np.ndarray]:
    """Longitude, latitude (degrees) -> EPSG:3857 x, y (m), spherical formulas (as PROJ's)."""
    lon = np.asarray(lon, float)
    lat = np.clip(np.asarray(lat, float), -85.06, 85.06)
    x = EARTH_RADIUS * np.radians(lon)
    y = EARTH_RADIUS * np.log(np.tan(np.pi / 4 + np.radians(lat) / 2))
    return x, y


def mercator_to_lonlat(x, y) -> tuple[np.ndarray, np.ndarray]:
    """EPSG:3857 x, y (m) -> longitude, latitude (degrees)."""
    x = np.asarray(x, float)
    y = np.asarray(y, float)
    return np.degrees(x / EARTH_RADIUS), np.degrees(2 * np.arctan(np.exp(y / EARTH_RADIUS)) - np.pi / 2)


def bbox_grid(west: float, south: float, east: float, north: float, side: int = STATS_SIDE) -> Grid:
    """An EPSG:3857 grid over the box (EPSG:3857 metres), its longer side ``side`` pixels."""
    width, height = max(east - west, 1e-6), max(north - south, 1e-6)
    gsd = max(width, height) / side
    return Grid(MERCATOR_EPSG, gsd, west, north, max(1, math.ceil(width / gsd - 1e-9)),
                max(1, math.ceil(height / gsd - 1e-9)))


def encode_png(values: np.ndarray, ranges, compress_level: int = 3) -> bytes:
    """A PNG of rendered values: (3, h, w) -> RGBA, (1, h, w) -> grey + alpha.

    ranges: per band (low, high), mapped linearly to 0..255 (clipped); alpha 255 where every band
    is finite, 0 (transparent) where any is NaN (no line covers the pixel).
    """
    from PIL import Image

    values = np.asarray(values, np.float32)
    if values.ndim != 3 or values.shape[0] not in (1, 3):
        raise ValueError(f"expected (1 or 3, h, w) values, got {values.shape}")
    k, h, w = values.shape
    finite = np.isfinite(values).all(axis=0)
    out = np.zeros((h, w, k + 1), np.uint8)
    for b in range(k):
        lo, hi = (float(v) for v in ranges[b])
        scale = 255.0 / (hi - lo) if hi > lo else 0.0
        with np.errstate(invalid="ignore"):
            channel = np.clip((values[b] - lo) * scale + 0.5, 0, 255)
        out[..., b] = np.where(finite, channel, 0).astype(np.uint8)
    out[..., k] = np.where(finite, 255, 0)
    buffer = io.BytesIO()
    Image.fromarray(out, "RGBA" if k == 3 else "LA").save(buffer, "PNG", compress_level=compress_level)
    return buffer.getvalue()


def encode_values(values: np.ndarray, key: np.ndarray | None = None) -> bytes:
    """A band-value tile as the browser reads it: the (k, n, n) float32 planes, then the (n, n)
    key plane if any, little-endian, row-major (north row first), NaN where no line covers."""
    planes = [np.asarray(values, "<f4")]
    if key is not None:
        planes.append(np.asarray(key, "<f4")[None])
    return b"".join(np.ascontiguousarray(p).tobytes() for p in planes)


@lru_cache(maxsize=1)
def transparent_png() -> bytes:
    """A fully transparent 256 x 256 PNG (tiles away from every line)."""
    return encode_png(np.full((1, TILE, TILE), np.nan, np.float32), [(0.0, 1.0)], 9)


def mercator_box(west: float, south: float, east: float, north: float) -> tuple[float, float, float, float]:
    """A W, S, E, N box in degrees as EPSG:3857 metres."""
    x, y = lonlat_to_mercator([west, east], [south, north])
    return (float(x[0]), float(y[0]), float(x[1]), float(y[1]))
