"""Digital elevation models: heights under a flight, in its frame, and first hits of rays on them.

A DEM is a GeoTIFF (any raster GDAL reads) in any CRS and resolution. Only the part under the rays
asked for is read (a window of band 1). Its heights end up as metres above the WGS-84 ellipsoid, the
``.lcf`` altitude datum (DESIGN 5, "Terrain"):

- a DEM whose CRS declares its heights is taken at its word: a compound CRS with a vertical part
  (e.g. EPSG:32616+5773, UTM + EGM96 height) or a 3-D CRS with an ellipsoidal height axis (e.g.
  EPSG:4979, or a projected 3-D CRS);
- otherwise ``datum`` (``--dem-datum``) is required: 'ellipsoid', 'egm96' (EPSG:5773) or
  'egm2008' (EPSG:3855). A declared datum that disagrees with ``datum`` is refused, never guessed.

Geoid heights are converted with PROJ and its grid (Debian's ``proj-data`` ships ``egm96_15.gtx``
in ``/usr/share/proj``, which is appended to pyproj's data path here; pyproj's wheel carries no
grids). A grid PROJ cannot find is an error naming it; PROJ's "ballpark" vertical transformation
(a silent 0) is never used.

Resampling (:meth:`Dem.surface`): the heights are sampled on a regular north-up grid of the flight's
UTM zone (``SURFACE_OVERSAMPLING`` nodes per DEM pixel side). Every node's DEM pixel position is
computed with PROJ (exactly on a coarse lattice, bilinear in between: the projection's curvature
over a few metres is far below a micrometre), then the DEM is interpolated bilinearly between pixel
centres (a pixel covers its area: nodes up to half a pixel beyond the outer centres take the edge
value). The geoid separation is added the same way (it varies over kilometres). The terrain is the
bilinear interpolant of those nodes: :class:`Surface`.

Ray hits: :mod:`archive.terrain.surface` (:meth:`Surface.intersect`).
"""

from __future__ import annotations

import dataclasses
import math
import os
import threading
import warnings
from dataclasses import dataclass, field
from functools import cached_property, lru_cache
from pathlib import Path

import numpy as np

from archive.errors import FormatError, InputError, MissingInputError
from archive.terrain.surface import HIT_TOLERANCE, Surface, bilinear, flat_points  # noqa: F401 (re-exported)

__all__ = ["DATUMS", "Dem", "DemSpec", "Surface", "open_dem"]

#: Vertical datums ``--dem-datum`` accepts.
DATUMS = ("ellipsoid", "egm96", "egm2008")
_GEOID_EPSG = {"egm96": 5773, "egm2008": 3855}
_GEOID_GRID = {"egm96": "egm96_15.gtx (us_nga_egm96_15.tif)", "egm2008": "us_nga_egm08_25.tif (egm08_25.gtx)"}
#: Where Debian's proj-data puts PROJ's grids (added to pyproj's data path when present).
SYSTEM_PROJ_DIRS = ("/usr/share/proj",)
#: Surface nodes per DEM pixel side (the terrain is bilinear between nodes: 2 keeps it close to
#: the DEM's own bilinear surface).
SURFACE_OVERSAMPLING = 2
#: Most nodes of one surface (float64: 128 MiB); coarser nodes beyond.
MAX_NODES = 1 << 24
_FIX_DATUM = "pass --dem-datum ellipsoid|egm96|egm2008 (what the DEM's heights are measured from)"
_FIX_COVER = "give a DEM covering the whole flight and its swath"


# ---------------------------------------------------------------------------------------------
# PROJ set-up and vertical datums
# ---------------------------------------------------------------------------------------------
@lru_cache(maxsize=1)
def _append_system_grids() -> tuple[str, ...]:
    import pyproj.datadir

    current = pyproj.datadir.get_data_dir().split(os.pathsep)
    for d in SYSTEM_PROJ_DIRS:
        if os.path.isdir(d) and d not in current:
            pyproj.datadir.append_data_dir(d)
    return tuple(pyproj.datadir.get_data_dir().split(os.pathsep))


_PROJ_THREAD = threading.local()


def use_system_grids() -> tuple[str, ...]:
    """Append Debian's PROJ data directory (proj-data's geoid grids) to pyproj's search path, once
    per process, and make sure the calling thread's PROJ context searches it: pyproj keeps one
    context per thread, and a context made before the append keeps the old path (a worker thread
    that transformed coordinates before opening a geoid DEM in a mesh task did not find the grid).
    Returns pyproj's data directories."""
    import pyproj.datadir

    dirs = _append_system_grids()
    if not getattr(_PROJ_THREAD, "ready", False):
        pyproj.datadir.set_data_dir(os.pathsep.join(dirs))   # the same path, applied to this thread's context
        _PROJ_THREAD.ready = True
    return dirs


def _declared(crs) -> tuple[object, str | None, object]:
    """(horizontal 2-D CRS, declared datum label or None, vertical CRS or None) of a pyproj CRS."""
    if crs.is_compound:
        horizontal, vertical = crs.sub_crs_list[0], crs.sub_crs_list[1]
        epsg = vertical.to_epsg()
        label = next((k for k, v in _GEOID_EPSG.items() if v == epsg), None) or vertical.name
        return horizontal, label, vertical
    axes = crs.axis_info
    if len(axes) == 3 and "ellipsoidal height" in axes[2].name.lower():
        return crs.to_2d(), "ellipsoid", None
    if len(axes) == 3:
        raise InputError(None, f"3-D CRS {crs.name!r} with a {axes[2].name!r} axis is not understood", _FIX_DATUM)
    return crs, None, None


def _separation(horizontal, datum: str, vertical, where: str):
    """A function (x, y) in ``horizontal`` -> metres to ADD to the DEM's heights for heights above the
    WGS-84 ellipsoid; InputError naming the geoid grid when PROJ cannot find it."""
    from pyproj import CRS
    from pyproj.crs import CompoundCRS
    from pyproj.transformer import TransformerGroup

    geodetic = horizontal.geodetic_crs
    if datum == "ellipsoid" and geodetic is not None and "World Geodetic System 1984" in geodetic.datum.name:
        return None  # heights already above the WGS-84 ellipsoid
    dirs = use_system_grids()
    if datum == "ellipsoid":
        source = horizontal.to_3d()
    else:
        vcrs = vertical if vertical is not None else CRS.from_epsg(_GEOID_EPSG[datum])
        source = CompoundCRS(f"{horizontal.name} + {vcrs.name}", [horizontal, vcrs])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        group = TransformerGroup(source, CRS.from_epsg(4979), always_xy=True)
    grid = _GEOID_GRID.get(datum, f"the grid of {datum}")
    if not group.best_available or not group.transformers:
        missing = sorted({g.short_name for op in group.unavailable_operations for g in op.grids if not g.available})
        names = ", ".join(missing) or grid
        raise InputError("--dem-datum", f"{where}: converting {datum} heights needs the PROJ grid {names}, "
                         f"which is not installed (searched {os.pathsep.join(dirs)})",
                         "install Debian's proj-data package (egm96_15.gtx) or put the grid into one of "
                         "those directories (projsync --file NAME)")
    transformer = group.transformers[0]
    if "ballpark" in transformer.description.lower():
        raise InputError("--dem-datum", f"{where}: PROJ has no grid to convert {datum} heights ({grid})",
                         "install Debian's proj-data package")

    def separation(x, y):
        x = np.asarray(x, float)
        y = np.asarray(y, float)
        _, _, h = transformer.transform(x, y, np.zeros_like(x))
        h = np.asarray(h, float)
        if not np.all(np.isfinite(h)):
            raise InputError("--dem-datum", f"{where}: PROJ could not convert {datum} heights here ({grid})",
                             "check the DEM's CRS and --dem-datum")
        return h

    return separation


# ---------------------------------------------------------------------------------------------
# The DEM
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class DemSpec:
    """What identifies a DEM for rendering: its absolute path, datum (as given or declared), file
    size and modification time (so that graph keys change when the file does). Picklable."""

    path: str
    datum: str | None = None
    size: int = 0
    mtime_ns: int = 0
    offset: float = 0.0   #: metres added to every height (the viewer's vertical offset of a DEM)

    @classmethod
    def create(cls, path, datum: str | None = None) -> DemSpec:
        p = Path(path).absolute()
        try:
            st = p.stat()
            size, mtime = int(st.st_size), int(st.st_mtime_ns)
        except OSError:
            size, mtime = 0, 0
        return cls(str(p), None if datum is None else str(datum), size, mtime)

    def open(self) -> Dem:
        dem = open_dem(self.path, self.datum)
        return dem if not self.offset else dataclasses.replace(dem, offset=float(self.offset))

    def __dask_tokenize__(self):
        return ("DemSpec", self.path, self.datum, self.size, self.mtime_ns, self.offset)


@dataclass(frozen=True, eq=False)
class Dem:
    """An opened DEM (metadata only; pixels are read by :meth:`surface`).

    path: the file; datum: 'ellipsoid' | 'egm96' | 'egm2008' | the name of another vertical CRS
    (as declared); declared: the DEM's CRS says it; crs: its horizontal pyproj CRS; transform:
    the rasterio Affine of pixel corners; width, height: pixels; nodata: band 1's nodata value;
    pixel_m: the pixel side in metres (the smaller one); spec: :class:`DemSpec`.
    """

    path: Path
    datum: str
    declared: bool
    crs: object
    transform: object
    width: int
    height: int
    nodata: float | None
    pixel_m: float
    spec: DemSpec
    crs_epsg: int | None = None
    unit: float = 1.0
    _separation: object = field(default=None, repr=False)
    offset: float = 0.0   #: metres added to every height read (a vertical offset of the whole DEM)

    # -- coordinates ---------------------------------------------------------------------------
    def _to_dem(self, epsg: int, e, n):
        e = np.asarray(e, float)
        n = np.asarray(n, float)
        if self.crs_epsg == int(epsg):
            return e, n
        x, y = _transformer(int(epsg), self.crs.to_wkt()).transform(e, n)
        return np.asarray(x, float), np.asarray(y, float)

    def lonlat_box(self, epsg: int, e, n) -> str:
        """'lon W to E, lat S to N' (degrees) of UTM points ``e, n`` of ``epsg``."""
        lon, lat = _transformer(int(epsg), "EPSG:4326").transform(np.ravel(e), np.ravel(n))
        return (f"lon {np.nanmin(lon):.5f} to {np.nanmax(lon):.5f}, "
                f"lat {np.nanmin(lat):.5f} to {np.nanmax(lat):.5f}")

    def extent_text(self) -> str:
        """The DEM's own lon/lat box, for messages."""
        from pyproj import CRS

        cols = np.array([0, self.width, self.width, 0, self.width / 2])
        rows = np.array([0, 0, self.height, self.height, self.height / 2])
        t = self.transform
        x, y = t.a * cols + t.b * rows + t.c, t.d * cols + t.e * rows + t.f
        lon, lat = _transformer(self.crs.to_wkt(), CRS.from_epsg(4326).to_wkt()).transform(x, y)
        return f"lon {np.min(lon):.5f} to {np.max(lon):.5f}, lat {np.min(lat):.5f} to {np.max(lat):.5f}"

    # -- sampling ------------------------------------------------------------------------------
    def _sample(self, epsg: int, e: np.ndarray, n: np.ndarray, lattice: int = 1
                ) -> tuple[np.ndarray, np.ndarray]:
        """Ellipsoidal heights (shape of e) at UTM points of ``epsg``, bilinear between DEM pixel
        centres, NaN where the DEM has no value; and an ``outside`` mask (points beyond the DEM).

        e, n: 2-D grids of points; the CRS transform and the geoid separation are computed exactly
        every ``lattice`` points in each direction and bilinearly in between."""
        if self.crs_epsg == int(epsg):
            x, y = e, n
        else:
            x, y = _lattice(lambda a, b: self._to_dem(epsg, a, b), e, n, lattice)
        inv = ~self.transform
        cx = inv.a * x + inv.b * y + inv.c - 0.5     # centre-index coordinates
        cy = inv.d * x + inv.e * y + inv.f - 0.5
        outside = ~((cx >= -0.5) & (cx <= self.width - 0.5) & (cy >= -0.5) & (cy <= self.height - 0.5))
        heights = np.full(e.shape, np.nan)
        inside = ~outside
        if not inside.any():
            return heights, outside
        cx = np.clip(cx, 0.0, self.width - 1.0)
        cy = np.clip(cy, 0.0, self.height - 1.0)
        c0 = int(np.floor(cx[inside].min()))
        c1 = min(int(np.floor(cx[inside].max())) + 2, self.width)
        r0 = int(np.floor(cy[inside].min()))
        r1 = min(int(np.floor(cy[inside].max())) + 2, self.height)
        block = self._read(r0, r1, c0, c1)
        heights[inside] = bilinear(block, cy[inside] - r0, cx[inside] - c0)
        if self._separation is not None:
            heights += _lattice(lambda a, b: (self._separation(*self._to_dem(epsg, a, b)), None), e, n, lattice,
                                single=True)
        return heights, outside

    def _read(self, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        """Rows r0:r1, columns c0:c1 of band 1 as float64, NaN where masked or nodata."""
        import rasterio
        from rasterio.windows import Window

        try:
            with rasterio.open(self.path) as ds:
                window = Window(c0, r0, c1 - c0, r1 - r0)
                block = ds.read(1, window=window, out_dtype="float64")
                mask = ds.read_masks(1, window=window)
        except Exception as exc:  # a damaged file found while reading
            raise FormatError(self.path, f"cannot read the DEM's heights ({_one_line(exc)})",
                              "check the file") from None
        block = np.where(mask == 0, np.nan, block)
        if self.nodata is not None and not math.isnan(self.nodata):
            block = np.where(block == self.nodata, np.nan, block)
        return block + self.offset if self.offset else block

    def _aligned(self, epsg: int) -> float | None:
        """The pixel side (m) when the DEM is a north-up grid of square metre pixels in the UTM
        zone ``epsg`` itself (then surfaces take its pixel centres as nodes: no resampling)."""
        t = self.transform
        if (self.crs_epsg == int(epsg) and t.b == 0 and t.d == 0 and t.a > 0 and t.e < 0
                and abs(t.a + t.e) <= 1e-9 * t.a and abs(self.unit - 1.0) < 1e-12):
            return float(t.a)
        return None

    def heights_at(self, epsg: int, e, n) -> np.ndarray:
        """Ellipsoidal heights (m) at UTM points ``e, n`` of ``epsg`` (any shape); NaN where the DEM
        has no value or does not reach."""
        e = np.asarray(e, float)
        flat_e, flat_n = e.reshape(-1), np.broadcast_to(np.asarray(n, float), e.shape).reshape(-1)
        out = np.empty(flat_e.size)
        for a in range(0, flat_e.size, 2000):    # a window per 2000 points: bounded reads along long flights
            sl = slice(a, a + 2000)
            out[sl] = self._sample(epsg, flat_e[sl].reshape(1, -1), flat_n[sl].reshape(1, -1))[0][0]
        return out.reshape(e.shape)

    def surface(self, epsg: int, bounds: tuple[float, float, float, float], res: float | None = None) -> Surface:
        """The terrain over ``bounds`` (west, south, east, north, UTM metres of ``epsg``): heights
        above the ellipsoid on north-up nodes every ``res`` metres (default the DEM pixel /
        SURFACE_OVERSAMPLING), NaN where the DEM has no value."""
        w, s, e, n = (float(v) for v in bounds)
        px = self._aligned(epsg)
        if px is not None and not res:
            return self._pixel_surface(epsg, w, s, e, n, px)
        res = float(res) if res else self.pixel_m / SURFACE_OVERSAMPLING
        cols = int(math.ceil((e - w) / res)) + 1
        rows = int(math.ceil((n - s) / res)) + 1
        if rows * cols > MAX_NODES:
            res *= math.sqrt(rows * cols / MAX_NODES)
            cols = int(math.ceil((e - w) / res)) + 1
            rows = int(math.ceil((n - s) / res)) + 1
        ee, nn = np.meshgrid(w + res * np.arange(cols), n - res * np.arange(rows))
        lattice = max(1, int(4.0 / res))            # exact CRS transform every ~4 m
        heights, outside = self._sample(epsg, ee, nn, lattice)
        return Surface(int(epsg), w, n, res, heights, outside, self)

    def _pixel_surface(self, epsg: int, w: float, s: float, e: float, n: float, px: float) -> Surface:
        """:meth:`surface` of a DEM in the zone itself: its pixel centres over the bounds are the nodes
        (its own bilinear surface); nodes beyond its extent are NaN and ``outside``."""
        t = self.transform
        c0 = int(math.floor((w - t.c) / px - 0.5))
        c1 = int(math.ceil((e - t.c) / px - 0.5)) + 1
        r0 = int(math.floor((t.f - n) / px - 0.5))
        r1 = int(math.ceil((t.f - s) / px - 0.5)) + 1
        heights = np.full((r1 - r0, c1 - c0), np.nan)
        outside = np.ones(heights.shape, bool)
        a0, a1 = max(r0, 0), min(r1, self.height)
        b0, b1 = max(c0, 0), min(c1, self.width)
        if a1 > a0 and b1 > b0:
            heights[a0 - r0:a1 - r0, b0 - c0:b1 - c0] = self._read(a0, a1, b0, b1)
            outside[a0 - r0:a1 - r0, b0 - c0:b1 - c0] = False
        west, north = t.c + (c0 + 0.5) * px, t.f - (r0 + 0.5) * px
        if self._separation is not None:
            ee, nn = np.meshgrid(west + px * np.arange(c1 - c0), north - px * np.arange(r1 - r0))
            heights += _lattice(lambda a, b: (self._separation(a, b), None), ee, nn, max(1, int(4.0 / px)),
                                single=True)
        return Surface(int(epsg), west, north, px, heights, outside, self)

    def surface_under(self, epsg: int, origin: np.ndarray, directions: list[np.ndarray]) -> Surface:
        """A :class:`Surface` holding every ray from ``origin`` (n, 3: E, N, alt) along each of
        ``directions`` ((n, 3): dE, dN, dUp) down to the terrain (and the camera positions): the
        rays are cut at the highest and lowest heights found under them, until both settle."""
        origin = np.asarray(origin, float)
        h0 = self.heights_at(epsg, origin[:, 0], origin[:, 1])
        if not np.isfinite(h0).any():
            self.raise_uncovered(epsg, origin[:, 0], origin[:, 1], "under the flight track")
        lo, hi = float(np.nanmin(h0)), float(np.nanmax(h0))
        for _ in range(8):
            pts = [origin[:, :2]]
            for d in directions:
                down = d[:, 2] < -1e-9
                for level in (lo, hi):
                    lam = np.where(down, (origin[:, 2] - level) / np.where(down, -d[:, 2], 1.0), 0.0)
                    lam = np.maximum(lam, 0.0)
                    pts.append(origin[down, :2] + lam[down, None] * d[down, :2])
            pts = np.concatenate(pts)
            margin = 2.0 * self.pixel_m
            box = (pts[:, 0].min() - margin, pts[:, 1].min() - margin, pts[:, 0].max() + margin,
                   pts[:, 1].max() + margin)
            surf = self.surface(epsg, box)
            if not np.isfinite(surf.heights).any():
                self.raise_uncovered(epsg, pts[:, 0], pts[:, 1], "under the flight")
            s_lo, s_hi = surf.hmin, surf.hmax
            if s_lo >= lo - 1e-6 and s_hi <= hi + 1e-6:
                return surf
            lo, hi = min(lo, s_lo), max(hi, s_hi)
        return surf

    def intersect(self, epsg: int, origin: np.ndarray, directions: list[np.ndarray], chunk: int = 2000
                  ) -> list[tuple[np.ndarray, np.ndarray]]:
        """First hits of the rays from ``origin`` (n, 3: E, N, alt, UTM of ``epsg``) along each of
        ``directions`` ((n, 3): dE, dN, dUp): one (lam (n,), under (n,)) per direction (see
        :meth:`Surface.intersect`), traced ``chunk`` origins at a time (one surface each: memory stays
        bounded along long flights)."""
        origin = np.asarray(origin, float)
        out = [(np.full(len(origin), np.nan), np.zeros(len(origin), bool)) for _ in directions]
        for a in range(0, len(origin), chunk):
            sl = slice(a, a + chunk)
            part = [np.asarray(d, float)[sl] for d in directions]
            surface = self.surface_under(epsg, origin[sl], part)
            for (lam, under), d in zip(out, part):
                lam[sl], under[sl] = surface.intersect(origin[sl], d)
        return out

    def check_covers(self, epsg: int, origin: np.ndarray, directions: list[np.ndarray], chunk: int = 2000) -> None:
        """InputError unless the DEM has heights wherever the rays from ``origin`` (n, 3: E, N, alt)
        along ``directions`` ((n, 3) each: dE, dN, dUp) meet the ground: the message names the DEM
        and the lon/lat box of ALL the ground it lacks (beyond its extent, else its holes)."""
        origin = np.asarray(origin, float)
        uncovered, holes, rays = [], [], 0
        level = None
        for a in range(0, len(origin), chunk):
            sl = slice(a, a + chunk)
            part = [np.asarray(d, float)[sl] for d in directions]
            h0 = self.heights_at(epsg, origin[sl, 0], origin[sl, 1])
            if not np.isfinite(h0).any():      # nothing under this part of the track
                level = self.typical_height() if level is None else level
                uncovered += [flat_points(origin[sl], d, level) for d in part]
                continue
            surface = self.surface_under(epsg, origin[sl], part)
            level = surface.hmin if level is None else level
            for d in part:
                lam, failed, at = surface.trace(origin[sl], d)
                if failed.any():
                    out, hole, n = surface.gaps(origin[sl][failed], d[failed], at)
                    uncovered.append(out)
                    holes.append(hole)
                    rays += n
        if uncovered or holes:
            self.raise_gaps(epsg, np.concatenate(uncovered) if uncovered else np.zeros((0, 2)),
                            np.concatenate(holes) if holes else np.zeros((0, 2)), rays)

    def check_flight(self, poses, fov_deg: float, rays: int = 9) -> None:
        """:meth:`check_covers` for the swath of every line of ``poses`` (a sequence of
        :class:`archive.geometry.navigation.Poses` of one frame; lines without navigation skipped): ``rays``
        rays across each line's field of view, edges included."""
        t = math.tan(math.radians(fov_deg) / 2)
        origins, dirs = [], [[] for _ in range(rays)]
        frame = None
        for p in poses:
            frame = p.frame
            keep = np.ones(len(p), bool) if p.valid is None else np.asarray(p.valid, bool)
            if not keep.any():
                continue
            pos = np.asarray(p.position, float)[keep]
            origins.append(np.stack([pos[:, 1] + frame.origin_e, pos[:, 0] + frame.origin_n,
                                     frame.origin_alt - pos[:, 2]], axis=1))
            m = p.attitude[keep].as_matrix() if keep.size > 1 else np.atleast_3d(p.attitude.as_matrix())
            m = m.reshape(-1, 3, 3)
            for k, u in enumerate(np.linspace(-t, t, rays)):
                d = m[:, :, 1] * u + m[:, :, 2]
                dirs[k].append(np.stack([d[:, 1], d[:, 0], -d[:, 2]], axis=1))
        if frame is None or not origins:
            return
        self.check_covers(frame.epsg, np.concatenate(origins), [np.concatenate(d) for d in dirs])

    def typical_height(self) -> float:
        """The median height of a decimated read of the whole DEM, m above the ellipsoid (for
        messages: where rays that find no height would roughly meet the ground)."""
        import rasterio

        with rasterio.open(self.path) as ds:
            shape = (min(64, ds.height), min(64, ds.width))
            block = ds.read(1, out_shape=shape, masked=True).astype(float).filled(np.nan)
        if self.nodata is not None and not math.isnan(self.nodata):
            block[block == self.nodata] = np.nan
        level = float(np.nanmedian(block)) if np.isfinite(block).any() else 0.0
        if self._separation is not None:
            t = self.transform
            level += float(self._separation(np.array([t.c + t.a * self.width / 2]),
                                            np.array([t.f + t.e * self.height / 2]))[0])
        return level

    def raise_gaps(self, epsg: int, uncovered: np.ndarray, holes: np.ndarray, rays: int):
        if len(uncovered):
            self.raise_uncovered(epsg, uncovered[:, 0], uncovered[:, 1])
        self.raise_holes(epsg, holes[:, 0], holes[:, 1], rays)

    def raise_uncovered(self, epsg: int, e, n, what: str = "under the flight"):
        raise InputError("--dem", f"{self.path} does not cover the flight: no heights {what} at "
                         f"{self.lonlat_box(epsg, e, n)} (the DEM spans {self.extent_text()})", _FIX_COVER)

    def raise_holes(self, epsg: int, e, n, count: int):
        raise InputError("--dem", f"{self.path} has no heights (nodata or NaN) under the flight at "
                         f"{self.lonlat_box(epsg, e, n)} ({count} ray{'s' if count != 1 else ''} cross the holes)",
                         "fill the holes (e.g. gdal_fillnodata.py) or give a DEM without gaps there")


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


@lru_cache(maxsize=32)
def _transformer(src, dst):
    from pyproj import CRS, Transformer

    return Transformer.from_crs(CRS.from_user_input(src), CRS.from_user_input(dst), always_xy=True)


def _lattice(func, e: np.ndarray, n: np.ndarray, step: int, single: bool = False):
    """``func(e, n)`` -> (x, y) evaluated exactly every ``step`` nodes of the 2-D grids e, n (and on
    the last row/column) and bilinearly in between. single: func returns (value, None): one array."""
    if step <= 1 or e.shape[0] < 3 or e.shape[1] < 3:
        out = func(e, n)
        return out[0] if single else out
    rows = np.unique(np.append(np.arange(0, e.shape[0], step), e.shape[0] - 1))
    cols = np.unique(np.append(np.arange(0, e.shape[1], step), e.shape[1] - 1))
    sub = func(e[np.ix_(rows, cols)], n[np.ix_(rows, cols)])
    ri = np.interp(np.arange(e.shape[0]), rows, np.arange(rows.size))
    ci = np.interp(np.arange(e.shape[1]), cols, np.arange(cols.size))
    rr, cc = np.meshgrid(ri, ci, indexing="ij")
    parts = [sub[0]] if single else list(sub)
    out = [bilinear(p, rr, cc) for p in parts]
    return out[0] if single else tuple(out)


def open_dem(path, datum: str | None = None) -> Dem:
    """Open a DEM (metadata only) and settle its vertical datum (module docstring).

    datum: None (the DEM must declare it), 'ellipsoid', 'egm96' or 'egm2008'. Raises
    MissingInputError, FormatError (not a raster, no CRS) or InputError (no datum, disagreeing
    datum, missing geoid grid) with one-line messages naming the file."""
    import rasterio
    from pyproj import CRS
    from pyproj.exceptions import CRSError

    p = Path(path).absolute()
    if datum is not None and datum not in DATUMS:
        raise InputError("--dem-datum", f"unknown vertical datum {datum!r}", f"use one of {', '.join(DATUMS)}")
    if not p.exists():
        raise MissingInputError(p, "DEM (--dem)")
    if not p.is_file():
        raise InputError("--dem", f"{p} is not a file", "give a GeoTIFF DEM")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with rasterio.open(p) as ds:
                if ds.count < 1:
                    raise FormatError(p, "the DEM has no band", "give a single-band height raster")
                wkt = ds.crs.to_wkt() if ds.crs is not None else None
                transform, width, height = ds.transform, ds.width, ds.height
                nodata = ds.nodatavals[0]
    except FormatError:
        raise
    except Exception as exc:
        raise FormatError(p, f"not a raster GDAL can read as a DEM ({_one_line(exc)})", "give a GeoTIFF DEM") from None
    if not wkt:
        raise FormatError(p, "the DEM has no coordinate reference system",
                          "assign one, e.g. gdal_edit.py -a_srs EPSG:32616 FILE")
    if transform.is_identity or width < 2 or height < 2:
        raise FormatError(p, "the DEM is not georeferenced or has fewer than 2 x 2 pixels",
                          "give a georeferenced GeoTIFF")
    try:
        horizontal, declared, vertical = _declared(CRS.from_wkt(wkt))
    except CRSError as exc:
        raise FormatError(p, f"unreadable CRS ({_one_line(exc)})") from None
    except InputError as exc:
        raise InputError("--dem", f"{p}: {exc.problem}", exc.fix) from None
    if declared is None and datum is None:
        raise InputError("--dem-datum", f"{p} does not declare the vertical datum of its heights "
                         "(ellipsoidal and geoid heights differ by tens of metres)", _FIX_DATUM)
    if declared is not None and datum is not None and declared != datum:
        raise InputError("--dem-datum", f"{p} declares {declared} heights but --dem-datum is {datum}",
                         "leave --dem-datum out, or fix the DEM's CRS")
    resolved = declared or datum
    separation = _separation(horizontal, resolved, vertical, str(p))
    # pixel side in metres
    a, b, d, e = transform.a, transform.b, transform.d, transform.e
    sx, sy = math.hypot(a, d), math.hypot(b, e)
    if horizontal.is_geographic:
        lat = transform.d * width / 2 + transform.e * height / 2 + transform.f   # GDAL keeps (lon, lat) order
        sx *= 111320.0 * math.cos(math.radians(max(-89.0, min(89.0, lat))))
        sy *= 110570.0
        unit = 1.0
    else:
        unit = horizontal.axis_info[0].unit_conversion_factor if horizontal.axis_info else 1.0
        sx *= unit
        sy *= unit
    pixel_m = float(min(sx, sy))
    if separation is not None:
        x = transform.a * width / 2 + transform.b * height / 2 + transform.c
        y = transform.d * width / 2 + transform.e * height / 2 + transform.f
        separation(np.array([x]), np.array([y]))  # a missing grid fails now, not mid-render
    return Dem(p, resolved, declared is not None, horizontal, transform, int(width), int(height),
               None if nodata is None else float(nodata), pixel_m, DemSpec.create(p, datum), horizontal.to_epsg(),
               float(unit), separation)
