"""The output grid: one small immutable value passed everywhere (CRS, affine, shape).

A :class:`Grid` is north-up and pixel-is-area: square pixels of ``gsd`` metres, the top-left
*corner* of pixel (row 0, col 0) at UTM ``(x0, y0)``. Rows grow southwards, columns eastwards;
rasters on a grid are ``(band, y, x)`` = ``(band, row, col)``. Every operation returns a new grid.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from archive.errors import InputError

# Bounds within this fraction of a pixel of a multiple of the GSD count as on it (float noise).
_SNAP_TOLERANCE = 1e-6


@dataclass(frozen=True)
class Grid:
    """North-up output grid.

    epsg: EPSG code of the (UTM) CRS.
    gsd: pixel size, metres.
    x0, y0: UTM easting / northing of the top-left corner of the top-left pixel, metres.
    width, height: number of columns / rows.
    """

    epsg: int
    gsd: float
    x0: float
    y0: float
    width: int
    height: int

    def __post_init__(self) -> None:
        if not (isinstance(self.gsd, (int, float)) and math.isfinite(self.gsd) and self.gsd > 0):
            raise InputError("grid", f"gsd must be a positive number of metres, got {self.gsd!r}")
        for name in ("width", "height"):
            value = getattr(self, name)
            if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value <= 0:
                raise InputError("grid", f"{name} must be a positive integer, got {value!r}")
            object.__setattr__(self, name, int(value))
        if not (math.isfinite(self.x0) and math.isfinite(self.y0)):
            raise InputError("grid", f"corner must be finite, got ({self.x0!r}, {self.y0!r})")
        object.__setattr__(self, "epsg", int(self.epsg))
        object.__setattr__(self, "gsd", float(self.gsd))
        object.__setattr__(self, "x0", float(self.x0))
        object.__setattr__(self, "y0", float(self.y0))

    # ---- construction -------------------------------------------------------------------
    @classmethod
    def from_bounds(
        cls, epsg: int, west: float, south: float, east: float, north: float, gsd: float
    ) -> Grid:
        """The smallest grid with corners on multiples of ``gsd`` that contains the bounds (metres)."""
        if not (isinstance(gsd, (int, float)) and math.isfinite(gsd) and gsd > 0):
            raise InputError("grid", f"gsd must be a positive number of metres, got {gsd!r}")
        if not all(math.isfinite(v) for v in (west, south, east, north)):
            raise InputError("grid", f"bounds must be finite, got {(west, south, east, north)}")
        if east < west or north < south:
            raise InputError(
                "grid", f"bounds (W, S, E, N) = {(west, south, east, north)} are inverted",
                "give west <= east and south <= north",
            )
        c0 = math.floor(west / gsd + _SNAP_TOLERANCE)
        c1 = math.ceil(east / gsd - _SNAP_TOLERANCE)
        r0 = math.ceil(north / gsd - _SNAP_TOLERANCE)
        r1 = math.floor(south / gsd + _SNAP_TOLERANCE)
        return cls(epsg, gsd, c0 * gsd, r0 * gsd, max(c1 - c0, 1), max(r0 - r1, 1))

    # ---- geo-referencing ---------------------------------------------------------------
    @property
    def transform(self):
        """GDAL/rasterio affine transform (pixel (col, row) -> UTM (x, y) of the pixel corner)."""
        from affine import Affine

        return Affine(self.gsd, 0.0, self.x0, 0.0, -self.gsd, self.y0)

    @property
    def crs(self):
        """rasterio CRS of the grid."""
        from rasterio.crs import CRS

        return CRS.from_epsg(self.epsg)

    @property
    def shape(self) -> tuple[int, int]:
        """(height, width) = (rows, cols)."""
        return (self.height, self.width)

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """(west, south, east, north), metres."""
        return (self.x0, self.y0 - self.height * self.gsd, self.x0 + self.width * self.gsd, self.y0)

    def xy_centres(self) -> tuple[np.ndarray, np.ndarray]:
        """UTM coordinates of the pixel centres: x (width,) eastings, y (height,) northings (north first)."""
        x = self.x0 + (np.arange(self.width) + 0.5) * self.gsd
        y = self.y0 - (np.arange(self.height) + 0.5) * self.gsd
        return x, y

    def rowcol(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """Fractional (row, col) of UTM points; pixel (r, c) spans [r, r+1) x [c, c+1), centre at +0.5."""
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        return (self.y0 - y) / self.gsd, (x - self.x0) / self.gsd

    # ---- sub-grids ----------------------------------------------------------------------
    def window(self, row0: int, col0: int, height: int, width: int) -> Grid:
        """The sub-grid of ``height`` x ``width`` pixels whose top-left pixel is (row0, col0) here."""
        if row0 < 0 or col0 < 0 or height <= 0 or width <= 0 or row0 + height > self.height or (
            col0 + width > self.width
        ):
            raise InputError(
                "grid",
                f"window rows {row0}..{row0 + height}, cols {col0}..{col0 + width} is not inside "
                f"the {self.height} x {self.width} grid",
            )
        return Grid(
            self.epsg, self.gsd, self.x0 + col0 * self.gsd, self.y0 - row0 * self.gsd, width, height
        )

    def tiles(self, size: int | tuple[int, int]) -> list[tuple[int, int, Grid]]:
        """Chunk-aligned tiling: ``(row0, col0, window)`` in row-major order, covering every pixel once.

        size: tile size in pixels, one int (square) or (height, width). Edge tiles are smaller.
        """
        th, tw = (size, size) if isinstance(size, (int, np.integer)) else size
        if th <= 0 or tw <= 0:
            raise InputError("grid", f"tile size must be positive, got {size!r}")
        out = []
        for r in range(0, self.height, th):
            for c in range(0, self.width, tw):
                h = min(th, self.height - r)
                w = min(tw, self.width - c)
                out.append((r, c, self.window(r, c, h, w)))
        return out

    def crop(
        self, west: float, south: float, east: float, north: float
    ) -> tuple[int, int, Grid] | None:
        """``(row0, col0, window)`` of the pixels of this grid that touch the bounds, None if none do."""
        c0 = max(math.floor((west - self.x0) / self.gsd), 0)
        c1 = min(math.ceil((east - self.x0) / self.gsd), self.width)
        r0 = max(math.floor((self.y0 - north) / self.gsd), 0)
        r1 = min(math.ceil((self.y0 - south) / self.gsd), self.height)
        if c1 <= c0 or r1 <= r0:
            return None
        return r0, c0, self.window(r0, c0, r1 - r0, c1 - c0)

    def intersect(self, other: Grid) -> tuple[int, int, Grid] | None:
        """The part of this grid inside ``other`` (same CRS and GSD, aligned pixels), as :meth:`crop`."""
        if other.epsg != self.epsg or not math.isclose(other.gsd, self.gsd, rel_tol=1e-9):
            raise InputError(
                "grid", f"cannot intersect grids of EPSG {self.epsg} / {self.gsd} m and "
                f"EPSG {other.epsg} / {other.gsd} m", "use one CRS and GSD",
            )
        off = np.array([(other.x0 - self.x0), (self.y0 - other.y0)]) / self.gsd
        if np.max(np.abs(off - np.round(off))) > 1e-6:
            raise InputError("grid", "cannot intersect grids whose pixels are not aligned")
        return self.crop(*other.bounds)

    def coarsened(self, factor: int, origin: tuple[float, float] = (0.0, 0.0)) -> Grid:
        """The grid of ``factor`` x larger pixels covering this one, its pixel edges on
        ``origin`` + multiples of the new pixel (x eastwards, y northwards; metres): the next level of
        a pyramid (Web-Mercator zooms: ``origin=(-HALF_WORLD, HALF_WORLD)``, ``factor=2``)."""
        if isinstance(factor, bool) or not isinstance(factor, int | np.integer) or factor < 1:
            raise InputError("grid", f"a grid is coarsened by a whole factor >= 1, got {factor!r}")
        gsd = self.gsd * int(factor)
        west, south, east, north = self.bounds
        c0 = math.floor((west - origin[0]) / gsd + _SNAP_TOLERANCE)
        c1 = math.ceil((east - origin[0]) / gsd - _SNAP_TOLERANCE)
        r0 = math.floor((origin[1] - north) / gsd + _SNAP_TOLERANCE)
        r1 = math.ceil((origin[1] - south) / gsd - _SNAP_TOLERANCE)
        return Grid(self.epsg, gsd, origin[0] + c0 * gsd, origin[1] - r0 * gsd, max(c1 - c0, 1), max(r1 - r0, 1))

    def __dask_tokenize__(self):
        return ("archive.grid.Grid", self.epsg, self.gsd, self.x0, self.y0, self.width, self.height)


def boxes_intersect(a: tuple[int, int, int, int], b: tuple[int, int, int, int]) -> bool:
    """Whether two pixel boxes ``(row0, col0, height, width)`` of one grid share a pixel."""
    return a[0] < b[0] + b[2] and b[0] < a[0] + a[2] and a[1] < b[1] + b[3] and b[1] < a[1] + a[3]


# ---------------------------------------------------------------------------------------------
# The grid a render asks for: --bounds, --align, --like
# ---------------------------------------------------------------------------------------------
def snapped(epsg: int, west: float, south: float, east: float, north: float, gsd: float) -> Grid:
    """The grid whose top-left corner is exactly (``west``, ``north``) and that covers the bounds
    (metres) with whole ``gsd`` pixels (the east and south edges rounded up to a whole pixel, within
    :data:`_SNAP_TOLERANCE` of one): ``gdalwarp -te W S E N -tr GSD GSD`` without ``-tap``."""
    if not all(math.isfinite(v) for v in (west, south, east, north)) or east <= west or north <= south:
        raise InputError("--bounds", f"W,S,E,N = {west:g},{south:g},{east:g},{north:g} is not a box",
                         "give west < east and south < north, metres in the output CRS")
    width = math.ceil((east - west) / gsd - _SNAP_TOLERANCE)
    height = math.ceil((north - south) / gsd - _SNAP_TOLERANCE)
    return Grid(epsg, gsd, west, north, max(width, 1), max(height, 1))


@dataclass(frozen=True)
class GridRequest:
    """What a render asks of its output grid, decided once into a :class:`Grid` by :meth:`decide`.

    like: a whole grid (``--like FILE``: CRS, GSD, corner and size of an existing output), used as
    is; bounds: (west, south, east, north) metres in the output CRS (``--bounds``); align: pixel
    edges on multiples of the GSD (``--align``, ``gdalwarp -tap``). Without ``like`` or ``bounds``
    the grid is the union of the flights' footprints, snapped outward to multiples of the GSD (so
    aligned already: ``align`` changes nothing there).
    """

    like: Grid | None = None
    bounds: tuple[float, float, float, float] | None = None
    align: bool = False

    @property
    def fixed(self) -> bool:
        """Whether the grid does not depend on the flights (``like``)."""
        return self.like is not None

    def decide(self, epsg: int, footprint: tuple[float, float, float, float], gsd: float) -> Grid:
        """The output grid in ``epsg`` at ``gsd`` m for flights whose meshes span ``footprint``
        (west, south, east, north; metres in ``epsg``). ``like`` wins whole (its CRS and GSD)."""
        if self.like is not None:
            return self.like
        if self.bounds is None:
            return Grid.from_bounds(epsg, *footprint, gsd)
        if self.align:
            return Grid.from_bounds(epsg, *self.bounds, gsd)
        return snapped(epsg, *self.bounds, gsd)

    def __dask_tokenize__(self):
        return ("archive.grid.GridRequest", self.like, self.bounds, self.align)


def aligned(grid: Grid) -> bool:
    """Whether the pixel edges of ``grid`` lie on multiples of its GSD (within float noise)."""
    off = np.array([grid.x0, grid.y0]) / grid.gsd
    return bool(np.max(np.abs(off - np.round(off))) <= 1e-6)


# ---------------------------------------------------------------------------------------------
# Web-Mercator (EPSG:3857) XYZ tiles as grids (the viewer's and the previews' tiles)
# ---------------------------------------------------------------------------------------------
#: Side of an XYZ tile, pixels.
TILE = 256
#: The sphere of Web Mercator, metres (mercantile's and PROJ's R).
EARTH_RADIUS = 6378137.0
#: Half the side of the Web-Mercator world square, metres (x and y run over +-HALF_WORLD).
HALF_WORLD = math.pi * EARTH_RADIUS
#: Deepest zoom served (2^30 tiles a side: 0.15 mm pixels at the equator).
MAX_ZOOM = 30
#: Largest side of a stats grid, pixels.
STATS_SIDE = 512
MERCATOR_EPSG = 3857
#: Latitudes are clipped to this (degrees) before projecting: the square's edge is ~85.0511.
MAX_LATITUDE = 85.06


def zoom_gsd(z: int) -> float:
    """Pixel size of zoom ``z`` tiles, metres of EPSG:3857."""
    return 2.0 * HALF_WORLD / TILE / 2.0**z


def tile_grid(z: int, x: int, y: int) -> Grid:
    """The EPSG:3857 grid of tile ``z/x/y`` (x eastwards, y southwards from the north-west corner of
    the world square, as Leaflet, OpenLayers and MapLibre number them; bounds from
    :func:`mercantile.xy_bounds`); InputError unless 0 <= z <= MAX_ZOOM and x, y are tiles of that zoom."""
    import mercantile

    for name, value in (("z", z), ("x", x), ("y", y)):
        if isinstance(value, bool) or not isinstance(value, int | np.integer):
            raise InputError(name, f"tile {name} must be an integer, got {value!r}")
    if not 0 <= z <= MAX_ZOOM:
        raise InputError("z", f"zoom {z} is out of range 0..{MAX_ZOOM}", "request a shallower tile")
    n = 1 << int(z)
    if not (0 <= x < n and 0 <= y < n):
        raise InputError("x/y", f"tile {x}/{y} does not exist at zoom {z} (0..{n - 1})")
    box = mercantile.xy_bounds(int(x), int(y), int(z))
    return Grid(MERCATOR_EPSG, zoom_gsd(z), box.left, box.top, TILE, TILE)


def lonlat_to_mercator(lon, lat) -> tuple[np.ndarray, np.ndarray]:
    """Longitude, latitude (degrees, arrays) -> EPSG:3857 x, y (m): :func:`mercantile.xy`'s spherical
    formulas on arrays, latitudes clipped to +-MAX_LATITUDE."""
    lon = np.asarray(lon, float)
    lat = np.clip(np.asarray(lat, float), -MAX_LATITUDE, MAX_LATITUDE)
    x = EARTH_RADIUS * np.radians(lon)
    y = EARTH_RADIUS * np.log(np.tan(np.pi / 4 + np.radians(lat) / 2))
    return x, y


def mercator_to_lonlat(x, y) -> tuple[np.ndarray, np.ndarray]:
    """EPSG:3857 x, y (m, arrays) -> longitude, latitude (degrees): :func:`mercantile.lnglat` on arrays."""
    x = np.asarray(x, float)
    y = np.asarray(y, float)
    return np.degrees(x / EARTH_RADIUS), np.degrees(2 * np.arctan(np.exp(y / EARTH_RADIUS)) - np.pi / 2)


def mercator_box(west: float, south: float, east: float, north: float) -> tuple[float, float, float, float]:
    """A W, S, E, N box in degrees as EPSG:3857 metres."""
    x, y = lonlat_to_mercator([west, east], [south, north])
    return (float(x[0]), float(y[0]), float(x[1]), float(y[1]))


def bbox_grid(west: float, south: float, east: float, north: float, side: int = STATS_SIDE) -> Grid:
    """An EPSG:3857 grid over the box (EPSG:3857 metres), its longer side ``side`` pixels."""
    width, height = max(east - west, 1e-6), max(north - south, 1e-6)
    gsd = max(width, height) / side
    return Grid(MERCATOR_EPSG, gsd, west, north, max(1, math.ceil(width / gsd - 1e-9)),
                max(1, math.ceil(height / gsd - 1e-9)))
