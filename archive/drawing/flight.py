"""The flights a viewer serves, and what it draws of them: tiles, point spectra, view statistics.

Which ids exist is :class:`archive.view.registry.FlightRegistry`'s (the archive's catalog, plus raw
flight directories named on the command line). :class:`ViewedFlight` holds one flight's caches and does its drawing with the inverse renderer:

- geometry per (ground height, sync offset, navigation source, boresight): the opened source, its cube meshes (the same
  :func:`~archive.graph.plan.cube_meshes` as ``archive render``) transformed to EPSG:3857 for tiles
  and to the UTM zone of ``archive render`` (:func:`~archive.graph.plan.job_epsg`) for points. A
  collection ingested with a DEM is drawn on its terrain (the meshes of ``archive render --dem``:
  at the flight's nominal GSD for tiles, at the point's GSD for spectra); its "ground height" is
  then a vertical offset of the DEM (m, 0 = the DEM as it is);
- lookups (pass 1 of the renderer: which line and sample each tile pixel sees) per cube and tile
  grid, shared by every band choice;
- band planes (:class:`archive.drawing.planes.BandPlanes`, ``ViewedFlight.planes``): a band of a cube in a
  mode, calibrated once for every (line, sample) as ``archive render`` does and kept, with its
  box-filtered levels for overview zooms (each value the mean of the 2^k x 2^k block of lines x
  samples around it), made on worker threads; a tile is then a gather through its lookup (no GL
  band pass per tile), the planes of the cubes around it made meanwhile;
- whole-flight 2/98 % statistics per (band, mode, cubes) from every 4th line and sample of those
  planes: computed once, whatever the ground height or sync offset.

Every method of :class:`ViewedFlight` may use OpenGL: call them from the viewer's one render thread
(:class:`archive.view.worker.RenderThread`), never from the event loop.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Callable, Sequence
from concurrent.futures import Executor
import dataclasses
from pathlib import Path

import numpy as np

from archive.errors import InputError
from archive.grid import Grid
from archive.overlap import LAST, OverlapRule, overlap_rule
from archive.params import NavigationParams
from archive.drawing.cache import ByteLRU
from archive.drawing.placement import Geometry, PosesKept, bounds_intersect, plane_index
from archive.drawing.planes import BandPlanes
from archive.drawing.query import ViewQuery
from archive.grid import MERCATOR_EPSG, bbox_grid
from archive.drawing.png import encode_png, transparent_png

__all__ = ["DEFAULT_RGB_NM", "ViewedFlight", "navigation_sources", "overview_level"]

#: Wavelengths of the default (true colour) channels, nm.
DEFAULT_RGB_NM = (640.0, 550.0, 460.0)
#: Geometries (ground height x sync offset) kept per flight.
GEOMETRIES_KEPT = 6
#: Whole-flight statistics sample every STATS_STEP-th line and sample of each cube.
STATS_STEP = 4
#: Widest block averaged for an overview pixel (2^k x 2^k lines x samples).
MAX_MIP = 8
#: Overview planes are made ahead for the cubes within this many tile widths of a requested tile.
AHEAD_TILES = 2
#: Rows of a cube's mesh kept in its outline (footprint drawn by the page).
OUTLINE_ROWS = 64


def overview_level(gsd: float, flight_gsd: float | None) -> int:
    """The block side (1, 2, 4 .. MAX_MIP flight pixels, lines x samples) averaged for an output pixel
    of ``gsd`` (m of EPSG:3857) over a flight of nominal pixel ``flight_gsd`` (m; None: unknown, 1):
    the power of two nearest their ratio (:meth:`ViewedFlight.band_values`, the ingest previews)."""
    if not flight_gsd:
        return 1
    return int(min(MAX_MIP, 2 ** max(0, round(math.log2(gsd / flight_gsd)))))


class ViewedFlight:
    """One flight of the viewer: its caches and drawing (see the module docstring).

    cid: the id it is served under; opener(params) -> a flight source with these navigation
    parameters; fov: field of view (deg) for the meshes, None: the one the source records;
    bands_cache / lookup_cache: shared byte-bounded caches of cube bands and lookups; workers:
    threads that make several band planes at once (:meth:`BandPlanes.prepare`; None: one after
    the other); navigation: the navigation source drawn when a query names none (``archive view
    --navigation``: 'lcf' or a stored track's name) where the flight has it, else the flight's own
    default (a collection's default track, else its ``.lcf``).

    ``opener(params, navigation)`` is given the navigation source too ('lcf', a track's name, or None:
    the source's default).
    """

    def __init__(self, cid: str, opener: Callable, fov: float | None, bands_cache: ByteLRU,
                 lookup_cache: ByteLRU, workers: Executor | None = None, navigation: str | None = None):
        self.id = cid
        self.opener = opener
        self.bands_cache = bands_cache
        self.lookup_cache = lookup_cache
        self._sources: OrderedDict = OrderedDict()
        self._geometries: OrderedDict = OrderedDict()
        self._ranges: OrderedDict = OrderedDict()
        self._posed: OrderedDict = OrderedDict()
        self._level = 1   # the overview level of the latest tile drawn
        probe = self.opener(NavigationParams(sync_offset=None, boresight_deg=None, lever_arm_m=None), None)
        own = getattr(probe, "navigation_source", None) or "lcf"   # the source's default
        #: the navigation sources this flight can be drawn from ('lcf' first, then stored tracks)
        self.navigation_sources = navigation_sources(probe)
        #: the one drawn when a query names none
        self.navigation = navigation if navigation in self.navigation_sources else own
        if self.navigation == own:
            self._sources[(None, own, None)] = probe
        first = self.source(None)
        self.fov = float(fov if fov is not None else (first.fov_deg or math.nan))
        if not (0 < self.fov < 180):
            raise InputError(first.label, "the field of view is unknown", "pass --fov DEG to 'archive view'")
        self.cubes = first.cubes
        self.wavelengths = first.wavelengths
        self.has_calibration = first.has_calibration
        self.planes = BandPlanes(cid, lambda: self.source(None), self.cubes, bands_cache, workers)

    def nbytes(self) -> int:
        """The bytes of the arrays this flight holds besides the shared caches: its opened sources,
        poses, meshes, radiometric terms and statistics (:func:`~archive.drawing.cache.held_bytes`),
        plus 64 KiB for its Python objects. What the viewer charges an open flight."""
        from archive.drawing.cache import held_bytes

        return held_bytes(self._sources, self._geometries, self._posed, self._ranges,
                          self.planes.radiometry_kept) + (64 << 10)

    # ---- sources and geometry ------------------------------------------------------------
    @staticmethod
    def _keep(cache: OrderedDict, key, value, limit: int):
        cache[key] = value
        cache.move_to_end(key)
        while len(cache) > limit:
            cache.popitem(last=False)
        return value

    def pose_key(self, sync_offset: float | None, navigation: str | None = None,
                 boresight: tuple[float, float, float] | None = None) -> tuple:
        """(sync offset, navigation source, boresight) as the caches key them: the navigation resolved
        (None: :attr:`navigation`), InputError naming ``navigation`` for a source the flight lacks."""
        if navigation is None:
            navigation = self.navigation
        elif navigation not in self.navigation_sources:
            raise InputError("navigation", f"flight {self.id} has no navigation source {navigation!r} (it has: "
                             f"{', '.join(self.navigation_sources)})", "pick one of those")
        return (sync_offset, navigation, None if boresight is None else tuple(float(v) for v in boresight))

    def source(self, sync_offset: float | None, navigation: str | None = None,
               boresight: tuple[float, float, float] | None = None):
        """The source with this sync offset (s; None: as ingested, else 0), navigation source
        ('lcf', a stored track's name; None: :attr:`navigation`) and boresight ((roll, pitch, yaw)
        degrees; None: as ingested)."""
        key = self.pose_key(sync_offset, navigation, boresight)
        found = self._sources.get(key)
        if found is not None:
            self._sources.move_to_end(key)
            return found
        # no field of view: sources do not use one (meshes take self.fov); the lever arm: as ingested
        params = NavigationParams(sync_offset=sync_offset, boresight_deg=key[2], lever_arm_m=None)
        return self._keep(self._sources, key, self.opener(params, key[1]), GEOMETRIES_KEPT)

    def terrain(self):
        """(the :class:`~archive.terrain.dem.DemSpec` of the DEM the collection was ingested with, its nominal
        GSD m) or None for a flight drawn on flat ground (raw flights, collections ingested flat)."""
        from archive.sources.ground import recorded_dem

        source = self.source(None)
        record = getattr(getattr(source, "info", None), "attrs", {}).get("terrain")
        spec = recorded_dem(record, self.id)
        return None if spec is None else (spec, float(record.get("gsd") or 0.05))

    def view_geometry(self, query: ViewQuery, gsd: float | None = None) -> Geometry:
        """:meth:`geometry` at the query's ground height, sync offset, navigation source and boresight."""
        return self.geometry(query.ground_height, query.sync_offset, gsd, query.navigation, query.boresight)

    def geometry(self, ground_height: float | None, sync_offset: float | None,
                 gsd: float | None = None, navigation: str | None = None,
                 boresight: tuple[float, float, float] | None = None) -> Geometry:
        """Meshes at this ground height (None: auto), sync offset (None: as ingested), navigation
        source and boresight (:meth:`source`). Over a DEM, ``ground_height`` is the DEM's vertical
        offset (m, None: 0) and ``gsd`` the output pixel the terrain meshes are built for (None: the
        flight's nominal GSD)."""
        terrain = self.terrain()
        if terrain is not None:
            gsd = float(gsd if gsd is not None else terrain[1])
        pose = self.pose_key(sync_offset, navigation, boresight)
        key = (ground_height, pose, gsd if terrain is not None else None)
        found = self._geometries.get(key)
        if found is not None:
            self._geometries.move_to_end(key)
            return found
        from archive.graph.plan import job_epsg, spec_meshes
        from archive.params import MeshSpec
        from archive.sources.select import resolve_ground_height

        source = self.source(*pose)
        posed = self._posed.get(pose)
        if posed is None or posed.source is not source:
            posed = self._keep(self._posed, pose, PosesKept(source), GEOMETRIES_KEPT)
        if terrain is not None:   # the meshes as 'archive render --dem' builds them (DEM moved by the offset)
            ground = 0.0 if ground_height is None else float(ground_height)
            spec = MeshSpec(self.fov, dem=dataclasses.replace(terrain[0], offset=ground), gsd=gsd)
            meshes = spec_meshes(posed, spec, spec.dem.open())
        else:
            ground = resolve_ground_height("auto" if ground_height is None else ground_height, [source])
            meshes = spec_meshes(posed, MeshSpec(self.fov, float(ground)))
        epsg = job_epsg([meshes])
        utm = tuple(m if m.epsg == epsg else m.to_epsg(epsg) for m in meshes)
        mercator = tuple(m.to_epsg(MERCATOR_EPSG) for m in meshes)
        bounds = np.array([m.bounds_utm() if m.rows >= 2 else (np.nan,) * 4 for m in mercator], float)
        return self._keep(self._geometries, key,
                          Geometry(source, float(ground), int(epsg), utm, mercator, bounds,
                                   gsd if terrain is not None else None, pose), GEOMETRIES_KEPT)

    def cube_range(self, cubes: tuple[int, int] | None) -> range:
        n = len(self.cubes)
        if cubes is None:
            return range(n)
        if cubes[1] >= n:
            raise InputError("cubes", f"cube {cubes[1] + 1} out of range: the flight has cubes 1..{n} (numbered "
                             f"as its files, {self.cubes[0].base}..{self.cubes[-1].base})")
        return range(cubes[0], cubes[1] + 1)

    def bands(self, query: ViewQuery) -> list[int]:
        """Source band indices of the channels of ``query`` (default: true colour)."""
        from archive.sources.select import select_bands

        nbands = self.cubes[0].bands
        if query.band is not None:
            if query.band >= nbands:
                raise InputError("band", f"band {query.band} out of range: the flight has bands 0..{nbands - 1}")
            return [query.band]
        if query.bands is not None:
            bad = [b for b in query.bands if b >= nbands]
            if bad:
                raise InputError("bands", f"band {bad[0]} out of range: the flight has bands 0..{nbands - 1}")
            return list(query.bands)
        source = self.source(None)
        if query.wavelengths is not None:
            return [select_bands(source, [w])[0] for w in query.wavelengths]
        return self.default_bands()

    def default_bands(self) -> list[int]:
        """True colour (the bands nearest 640, 550, 460 nm) when the flight spans it, else three
        bands at 3/4, 1/2 and 1/4 of its range."""
        from archive.sources.select import select_bands

        try:
            return [select_bands(self.source(None), [w])[0] for w in DEFAULT_RGB_NM]
        except InputError:
            n = self.cubes[0].bands
            return [min(n - 1, (3 * n) // 4), n // 2, n // 4]

    def mode(self, query: ViewQuery) -> str:
        mode = query.mode or ("radiance" if self.has_calibration else "raw")
        self.planes.radiometry(0, (0,), mode)  # InputError now when the mode is impossible
        return mode

    # ---- pixels ------------------------------------------------------------------------
    def lookup(self, geometry: Geometry, cube: int, grid: Grid):
        """Pass 1 of the renderer for ``cube`` on ``grid`` (cached); None when nothing is covered."""
        from archive.render.renderer import rasterize_lookup

        mesh = geometry.mercator[cube] if grid.epsg == MERCATOR_EPSG else geometry.utm[cube]

        def make():
            found = rasterize_lookup(mesh, grid, self.cubes[cube].samples)
            if found.box() is None:
                return None, 64
            return found, found.line.nbytes + found.sample.nbytes
        key = (self.id, geometry.ground_height, geometry.pose, geometry.gsd, cube, grid)
        return self.lookup_cache.get_or_make(key, make)

    def view_zenith(self, geometry: Geometry, cube: int, lookup) -> np.ndarray:
        """(height, width) float32 view zenith (deg) of the line each pixel of ``lookup.grid`` shows
        (NaN where not covered): the key of the 'nadir' rule, computed as ``archive render
        --provenance`` does (:func:`archive.geometry.provenance.cube_layers`)."""
        from archive.geometry.provenance import ProvenanceSpec, cube_layers

        key = (self.id, "view_zenith", geometry.ground_height, geometry.pose, geometry.gsd, cube, lookup.grid)
        found = self.lookup_cache.get(key)
        if found is not None:
            return found
        terrain = self.terrain() if geometry.gsd is not None else None
        dem = None if terrain is None else dataclasses.replace(terrain[0], offset=geometry.ground_height)
        # the time reference only shifts the sun layers, which are not asked for
        spec = ProvenanceSpec(lookup.grid.epsg, 0.0, "1980-01-06T00:00:00Z", (), geometry.ground_height, dem,
                              ("view_zenith",))
        zenith = cube_layers(geometry.source, cube, 0, lookup, spec, geometry.ground_height)[0]
        self.lookup_cache.put(key, zenith, zenith.nbytes)
        return zenith

    def rule_key_plane(self, geometry: Geometry, cube: int, lookup, layer: str) -> np.ndarray:
        """(height, width) float32 of the layer ``layer`` an overlap rule compares
        (:attr:`~archive.overlap.OverlapRule.key`) for the line each pixel of ``lookup.grid`` shows:
        the viewer computes the view zenith (:meth:`view_zenith`); ValueError for another layer."""
        if layer != "view_zenith":
            raise ValueError(f"the viewer computes no {layer} layer for an overlap rule (only view_zenith)")
        return self.view_zenith(geometry, cube, lookup)

    def render(self, grid: Grid, bands: Sequence[int], mode: str, cubes: range, geometry: Geometry,
               check: Callable[[], None] = lambda: None, overlap: OverlapRule = LAST) -> np.ndarray:
        """(len(bands), height, width) float32 of the cubes on ``grid`` (EPSG:3857, or the flight's
        UTM zone), NaN where no line covers, cubes combined by the rule ``overlap`` (:mod:`archive.overlap`,
        as ``archive render --overlap``).
        ``check()`` runs before each cube (raises to stop: an abandoned request)."""
        return self.render_keyed(grid, bands, mode, cubes, geometry, check, overlap)[0]

    def render_keyed(self, grid: Grid, bands: Sequence[int], mode: str, cubes: range, geometry: Geometry,
                     check: Callable[[], None] = lambda: None, overlap: OverlapRule = LAST, level: int = 1
                     ) -> tuple[np.ndarray, np.ndarray | None]:
        """:meth:`render` and, for a rule that compares a key (the 'nadir' rule: the view zenith, deg),
        the key of each pixel's winner ((height, width) float32, NaN where none; None for a rule
        without one, 'last'): what the browser compares
        between flights. Each pixel shows the value of the (line, sample) its lookup sees, from the
        band's plane (:meth:`BandPlanes.plane`; ``level`` > 1: the mean of the level x level block of
        the flight's pixels centred there, :meth:`BandPlanes.filtered`)."""
        mosaic = overlap.mosaic(len(bands), grid.height, grid.width)
        whole = (slice(0, grid.height), slice(0, grid.width))
        box = grid.bounds
        unflagged = np.zeros(grid.shape, bool)   # saturation does not change which value shows
        seen = []   # (cube, lookup): pass 1 first (GL, this thread), then the planes they need at once
        for c in cubes:
            if grid.epsg == MERCATOR_EPSG and not (np.isfinite(geometry.bounds[c]).all()
                                                    and bounds_intersect(geometry.bounds[c], box)):
                continue
            check()
            lookup = self.lookup(geometry, c, grid)
            if lookup is not None:
                seen.append((c, lookup))
        near = ()
        if level > 1 and grid.epsg == MERCATOR_EPSG:
            # the tiles around this one need the same level of their cubes: made meanwhile
            pad = AHEAD_TILES * grid.width * grid.gsd
            around = (box[0] - pad, box[1] - pad, box[2] + pad, box[3] + pad)
            near = [c for c in cubes if np.isfinite(geometry.bounds[c]).all()
                    and bounds_intersect(geometry.bounds[c], around)]
        self.planes.prepare([c for c, _ in seen], bands, mode, level, ahead=near)
        for c, lookup in seen:
            check()
            values = np.empty((len(bands), grid.height, grid.width), np.float32)
            index = plane_index(lookup)
            for i, b in enumerate(bands):
                np.take(self.planes.filtered(c, b, mode, level), index, out=values[i].reshape(-1), mode="clip")
            key = None if overlap.key is None else self.rule_key_plane(geometry, c, lookup, overlap.key)
            mosaic.feed(values, unflagged, *whole, key=key)
        values = mosaic.result()[0]
        return values, mosaic.winning_key()

    def band_values(self, grid: Grid, query: ViewQuery, flight_gsd: float | None, scale: int = 1,
                    check: Callable[[], None] = lambda: None) -> tuple[np.ndarray, np.ndarray | None] | None:
        """Band values of an EPSG:3857 tile grid for the browser to stretch and compose:
        ((len(bands), n, n) float32, the nadir key (n, n) or None), n = grid side / ``scale`` (a
        coarse preview), None when no line covers the tile.

        Where a tile pixel spans several of the flight's pixels (``flight_gsd`` m, overview zooms),
        its value is the mean over the block of 2^k x 2^k of the flight's pixels (lines x samples)
        centred on the one it sees, 2^k (up to MAX_MIP) the power of two nearest the ratio of the
        pixel sizes: anti-aliased as by a mipmapped texture (the band box-filtered once per cube,
        band and level, :meth:`BandPlanes.filtered`), at the cost of a full-resolution tile."""
        geometry, cubes, bands, mode, drawn = self._drawing(grid, query)
        if not drawn:
            return None
        side = grid.width // scale
        gsd = grid.gsd * scale
        level = overview_level(gsd, flight_gsd)
        self._level = level
        coarse = Grid(grid.epsg, gsd, grid.x0, grid.y0, side, side)
        values, key = self.render_keyed(coarse, bands, mode, cubes, geometry, check, overlap_rule(query.overlap, "overlap"),
                                        level)
        if not np.isfinite(values).any():
            return None
        return values, key

    def _drawing(self, grid: Grid, query: ViewQuery):
        """(geometry, cube range, bands, mode, whether the cubes' meshes reach ``grid``) of a query."""
        geometry = self.view_geometry(query)
        cubes = self.cube_range(query.cubes)
        union = geometry.union(cubes)
        drawn = union is not None and bounds_intersect(union, grid.bounds)
        return geometry, cubes, self.bands(query), self.mode(query), drawn

    # ---- what the API answers ----------------------------------------------------------
    def tile(self, grid: Grid, query: ViewQuery, check: Callable[[], None] = lambda: None) -> bytes:
        """PNG of one EPSG:3857 tile grid (transparent where no line covers)."""
        geometry, cubes, bands, mode, drawn = self._drawing(grid, query)
        if not drawn:
            return transparent_png()
        ranges = query.stretch.ranges
        if ranges is None:
            ranges = self.flight_ranges(bands, mode, cubes, geometry, query.stretch.percentiles)
        values = self.render(grid, bands, mode, cubes, geometry, check, overlap_rule(query.overlap, "overlap"))
        if not np.isfinite(values).any():
            return transparent_png()
        return encode_png(values, ranges)

    def flight_ranges(self, bands, mode, cubes, geometry, percentiles) -> tuple:
        """Per band (low, high) percentiles over the whole flight (:meth:`flight_percentiles`)."""
        pairs = []
        for lo, hi in zip(*self.flight_percentiles(bands, mode, cubes, percentiles)[:2], strict=True):
            lo = 0.0 if lo is None else lo
            hi = lo + 1.0 if hi is None or hi <= lo else hi
            pairs.append((lo, hi))
        return tuple(pairs)

    def flight_percentiles(self, bands, mode: str, cubes: range, percentiles) -> tuple[list, list, int]:
        """(low per band, high per band, values per band) of the whole flight's ``cubes``: the
        ``percentiles`` of every STATS_STEP-th line and sample of each cube's band plane (finite
        values; None where there is none). Per band, cached: a band, mode or cube-range change
        computes only what is new, and ground height and sync offset (where the pixels land, not
        their values) never do."""
        lows, highs, count = [], [], 0
        new = [int(b) for b in bands if (int(b), mode, cubes.start, cubes.stop, tuple(percentiles)) not in self._ranges]
        self.planes.prepare(cubes, new, mode)
        if new and self._level > 1:   # the tiles that follow (a band or mode change) need these: started now
            self.planes.prepare((), new, mode, self._level, ahead=cubes)
        for b in bands:
            key = (int(b), mode, cubes.start, cubes.stop, tuple(percentiles))
            found = self._ranges.get(key)
            if found is None:
                parts = []
                for c in cubes:
                    info = self.cubes[c]
                    plane = self.planes.plane(c, int(b), mode)[:-1].reshape(info.lines, info.samples)
                    part = plane[::STATS_STEP, ::STATS_STEP].reshape(-1)
                    parts.append(part[np.isfinite(part)])
                v = np.concatenate(parts) if parts else np.empty(0, np.float32)
                lo = hi = None
                if v.size:
                    lo, hi = (float(x) for x in np.percentile(v, percentiles))
                found = self._keep(self._ranges, key, (lo, hi, int(v.size)), 4096)
            else:
                self._ranges.move_to_end(key)
            lows.append(found[0])
            highs.append(found[1])
            count = max(count, found[2])
        return lows, highs, count

    def stats(self, bbox, bands: Sequence[int], mode: str, cubes: range, geometry: Geometry | None,
              percentiles=(2.0, 98.0)) -> dict:
        """Per band percentiles of the values inside ``bbox`` (W, S, E, N EPSG:3857 m), drawn on a
        grid of at most 512 px a side over the covered part; ``bbox`` None: of the whole flight
        (:meth:`flight_percentiles`: a sample of every cube's pixels, ``gsd`` None, ``sample``
        the step in lines and samples)."""
        out = {"band": [int(b) for b in bands], "mode": mode, "percentiles": list(percentiles),
               "wavelength": self.wavelengths_of(bands), "low": [None] * len(bands), "high": [None] * len(bands),
               "count": 0, "gsd": None}
        if bbox is None:
            out["low"], out["high"], out["count"] = self.flight_percentiles(bands, mode, cubes, percentiles)
            out["sample"] = STATS_STEP
            return out
        union = geometry.union(cubes)
        box = None
        if union is not None:
            box = (max(union[0], bbox[0]), max(union[1], bbox[1]), min(union[2], bbox[2]), min(union[3], bbox[3]))
            if box[0] >= box[2] or box[1] >= box[3]:
                box = None
        if box is None:
            return out
        grid = bbox_grid(*box)
        values = self.render(grid, bands, mode, cubes, geometry)
        out["gsd"] = grid.gsd
        for i, v in enumerate(values):
            v = v[np.isfinite(v)]
            out["count"] = max(out["count"], int(v.size))
            if v.size:
                lo, hi = np.percentile(v, percentiles)
                out["low"][i], out["high"][i] = float(lo), float(hi)
        return out

    def wavelengths_of(self, bands) -> list | None:
        return None if self.wavelengths is None else [float(self.wavelengths[b]) for b in bands]

    def point(self, lon: float, lat: float, gsd: float, query: ViewQuery) -> dict:
        """The full spectrum of the output pixel at (lon, lat) (:func:`archive.drawing.point.point_spectrum`)."""
        from archive.drawing.point import point_spectrum

        return point_spectrum(self, lon, lat, gsd, query)

    def outline(self, query: ViewQuery) -> dict:
        """GeoJSON MultiPolygon (lon, lat) of the cubes' ground meshes at the query's ground height,
        sync offset and cube range: one ring per cube, its left edge forwards and right edge back
        (at most OUTLINE_ROWS rows each)."""
        from archive.grid import mercator_to_lonlat

        geometry = self.view_geometry(query)
        polygons = []
        for c in self.cube_range(query.cubes):
            mesh = geometry.mercator[c]
            if mesh.rows < 2:
                continue
            g = mesh.ground_utm()
            step = max(1, mesh.rows // OUTLINE_ROWS)
            rows = np.unique(np.r_[np.arange(0, mesh.rows, step), mesh.rows - 1])
            ring = np.concatenate([g[rows, 0], g[rows[::-1], -1], g[rows[:1], 0]])
            lon, lat = mercator_to_lonlat(ring[:, 0], ring[:, 1])
            polygons.append([[[round(float(x), 8), round(float(y), 8)] for x, y in zip(lon, lat, strict=True)]])
        return {"type": "MultiPolygon", "coordinates": polygons}

    def describe(self) -> dict:
        """What the page needs to build its controls: cubes, bands, modes, default ground height
        and the camera's lowest altitude (the ground-height slider's range), the sync offset, the
        navigation sources (the one drawn by default) and the boresight (roll, pitch, yaw deg) as ingested."""
        from archive.sources.ground import camera_altitudes

        geometry = self.geometry(None, None)
        source = geometry.source
        modes = ["raw", "relative"] + (["radiance"] if self.has_calibration else [])
        return {
            "id": self.id, "fov_deg": self.fov, "bands": self.cubes[0].bands,
            "wavelength": self.wavelengths_of(range(self.cubes[0].bands)),
            "default_bands": self.default_bands(), "modes": modes,
            "default_mode": "radiance" if self.has_calibration else "raw",
            "units": {"raw": "DN", "relative": "DN per ms of exposure (0 dB)",
                      "radiance": "calibration radiance units (µflicks for Resonon)"},
            "ground_height": geometry.ground_height,
            "lowest_camera": float(np.min(camera_altitudes(source))),
            "terrain": (None if geometry.gsd is None else
                        {"dem": Path(self.terrain()[0].path).name, "offset": geometry.ground_height}),
            "sync_offset": float(source.params.sync_offset),
            "navigation": {"sources": list(self.navigation_sources), "default": self.navigation},
            "boresight_deg": [float(v) for v in source.params.boresight_deg],
            "cubes": [{"index": c.index, "base": c.base, "lines": c.lines, "samples": c.samples}
                      for c in self.cubes],
            "bounds_3857": geometry.union(range(len(self.cubes))),
        }


def navigation_sources(source) -> tuple[str, ...]:
    """The navigation sources a flight source can be drawn from: 'lcf' (the recorder's real-time
    solution), then the post-processed trajectories a collection stores (attribute
    ``navigation_tracks``, :func:`archive.collection.read.read_track`); a raw flight: 'lcf' only."""
    attrs = getattr(getattr(source, "info", None), "attrs", None) or {}
    tracks = (attrs.get("navigation_tracks") or {}).get("tracks") or {}
    return ("lcf", *sorted(str(name) for name in tracks if str(name) != "lcf"))
