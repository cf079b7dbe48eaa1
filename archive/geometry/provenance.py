"""Provenance layers: for every output pixel, the raw pixel it took its value from and the geometry
it was seen under (``archive render --provenance``).

The layers, all float32 on the output grid (north row first), NaN where no line covers the pixel:

============== ========= ==============================================================================
name           units     meaning
============== ========= ==============================================================================
cube           1         index of the cube in the job's cube table (0-based; the output's
                         ``provenance_cubes`` attribute lists, per index, the source id — a
                         collection id identifies the flight in its archive —, the cube's file
                         base name and its index within the flight)
line           1         0-based line of that cube (its exposure is the pixel's value)
sample         1         0-based sample of that line
time           s         exposure-start time of the line, seconds since ``time_reference`` (an ISO
                         8601 UTC instant, the job's first line floored to the second; CF units
                         ``seconds since <time_reference>``). UTC, leap seconds removed.
view_zenith    degree    angle between the vertical and the ground-to-sensor direction, 0 = nadir
view_azimuth   degree    azimuth of the ground-to-sensor direction, clockwise from TRUE north, 0..360
path_length    m         distance from the ground point to the sensor (camera at mid-exposure)
sun_zenith     degree    solar zenith (topocentric, no refraction: NREL SPA via pvlib) at the line's
                         time and the camera's nadir position
sun_azimuth    degree    solar azimuth, clockwise from true north, 0..360
overlap_count  1         how many layers of the job's line meshes cover the pixel centre (passes; a
                         fold at a turn counts each layer), whatever rule picked the value
irradiance     1         the sky spectrometer's irradiance at the line (mean over bands) relative to the
                         median of the flight's spectra (issue 34): below 0.25 low; NaN without spectra
============== ========= ==============================================================================

cube, line and sample are integers stored exactly (float32 holds every integer below 2^24). The
ground point of a pixel is its centre at the ground height the meshes used (flat ground), or at the
DEM's height there (``--dem``). The geometry is the camera's at mid-exposure of the pixel's line, in
the flight's own UTM zone (whose metres are ground metres, whatever the output CRS; azimuths turned
to true north by that zone's grid convergence at the camera). Within one render the layers follow the mosaic rule: they describe exactly the written pixel.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta

import numpy as np

from archive.errors import InputError
from archive.params import MeshSpec

__all__ = ["LAYERS", "Layer", "ProvenanceSpec", "cube_layers", "layer_index", "provenance_spec",
           "sun_position"]


@dataclass(frozen=True)
class Layer:
    """One provenance layer: name, CF-style units and a one-line description."""

    name: str
    units: str
    description: str


LAYERS: tuple[Layer, ...] = (
    Layer("cube", "1", "index of the source cube in the provenance_cubes table (0-based)"),
    Layer("line", "1", "0-based line of the source cube"),
    Layer("sample", "1", "0-based sample of the source line"),
    Layer("time", "s", "exposure start of the source line, seconds since time_reference (UTC)"),
    Layer("view_zenith", "degree", "view zenith angle, ground to sensor"),
    Layer("view_azimuth", "degree", "view azimuth, ground to sensor, clockwise from true north"),
    Layer("path_length", "m", "distance from the ground point to the sensor"),
    Layer("sun_zenith", "degree", "solar zenith angle (topocentric, without refraction)"),
    Layer("sun_azimuth", "degree", "solar azimuth, clockwise from true north"),
    Layer("overlap_count", "1", "layers of the job's line meshes covering the pixel centre"),
    Layer("irradiance", "1", "downwelling irradiance of the source line (sky spectrometer, mean over the bands) "
          "relative to the median of the flight's spectra; below 0.25: low (dusk, heavy cloud); NaN: no spectra"),
)


def layer_index(name: str) -> int:
    """Position of layer ``name`` in :data:`LAYERS`."""
    for i, layer in enumerate(LAYERS):
        if layer.name == name:
            return i
    raise KeyError(name)


@dataclass(frozen=True)
class ProvenanceSpec:
    """What the per-cube layers of one output need besides the cube: the output CRS, the time
    reference (``reference_gps``: GPS seconds on the sources' .lcf scale of ``reference_utc``), the
    cube table (one dict per job, in job order), the ground (``ground``: the flat height, m, None
    with a DEM; or ``dem``, the :class:`archive.terrain.dem.DemSpec`: the render's
    :class:`~archive.params.MeshSpec`'s) and the layers to compute (all of :data:`LAYERS`, or only the
    nadir rule's key)."""

    epsg: int
    reference_gps: float
    reference_utc: str
    cubes: tuple = field(default=(), compare=False)
    ground: float | None = None
    dem: object = None
    names: tuple[str, ...] = tuple(layer.name for layer in LAYERS)

    @property
    def time_units(self) -> str:
        """CF units of the time layer."""
        return f"seconds since {self.reference_utc}"

    def __dask_tokenize__(self):
        return ("ProvenanceSpec", self.epsg, self.reference_gps, self.ground, self.dem, self.names)


def provenance_spec(plan, sources, mesh: MeshSpec, names: tuple[str, ...] | None = None) -> ProvenanceSpec:
    """The :class:`ProvenanceSpec` of a render plan (:class:`archive.graph.plan.RenderPlan`) whose
    meshes ``mesh`` says how they are built (its flat ground or DEM): time reference = the first line
    of the job, floored to the UTC second."""
    from archive.formats.lcf import gps_seconds_to_datetime

    first = min(float(sources[job.source].cubes[job.cube].first_time) for job in plan.jobs)
    utc = gps_seconds_to_datetime(first)
    fraction = utc.microsecond / 1e6
    utc = utc.replace(microsecond=0)
    cubes = tuple({"index": j, "source": str(sources[job.source].id), "cube": sources[job.source].cubes[job.cube].base,
                   "cube_index": int(job.cube)} for j, job in enumerate(plan.jobs))
    return ProvenanceSpec(int(plan.grid.epsg), first - fraction, utc.strftime("%Y-%m-%dT%H:%M:%SZ"), cubes,
                          None if mesh.ground_height is None else float(mesh.ground_height), mesh.dem,
                          tuple(layer.name for layer in LAYERS) if names is None else tuple(names))


def sun_position(unix_s: np.ndarray, lat_deg: np.ndarray, lon_deg: np.ndarray, height_m: np.ndarray,
                 delta_t: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(zenith, azimuth) of the sun in degrees, topocentric and without atmospheric refraction,
    azimuth clockwise from true north in 0..360, at UTC ``unix_s`` (seconds since 1970-01-01),
    WGS-84 latitude/longitude (degrees) and height (m), all broadcast to ``unix_s``'s shape (1-D).
    NREL's SPA (Reda & Andreas 2004, ±0.0003° over -2000..6000; pvlib's implementation); delta_t:
    TT - UT1 in seconds (default: pvlib's estimate for the month, within ~1 s of the observed one)."""
    from pvlib import spa

    unix_s = np.atleast_1d(np.asarray(unix_s, float))
    lat, lon, height = (np.broadcast_to(np.asarray(v, float), unix_s.shape) for v in (lat_deg, lon_deg, height_m))
    if unix_s.size == 0:
        return np.zeros(0), np.zeros(0)
    if delta_t is None:
        middle = datetime(1970, 1, 1) + timedelta(seconds=float(np.median(unix_s)))
        delta_t = float(spa.calculate_deltat(middle.year, middle.month))
    # pressure and temperature only enter the refraction term, which is not used here
    _, zenith, _, _, azimuth, _ = spa.solar_position_numpy(unix_s, lat, lon, height, 1013.25, 12.0, delta_t,
                                                           0.5667, 1)
    return np.asarray(zenith, float), np.asarray(azimuth, float) % 360.0


def _line_geometry(source, cube: int, spec: ProvenanceSpec):
    """Per line of ``cube``: time (s since the reference), camera (E, N, height) at mid-exposure in
    the flight's own UTM zone (its local frame's: conformal, scale within 0.04 %, so its metres are
    ground metres whatever the output CRS), that zone's EPSG, the grid bearing of true north there
    (rad) and the sun's (zenith, azimuth), degrees."""
    from archive.geometry.navigation import grid_convergence, to_lonlat

    info = source.cubes[cube]
    poses = source.poses(cube, delay=(info.shutter_ms or 0.0) / 2000.0)
    e, n, h = (np.asarray(v, float) for v in poses.frame.from_ned(poses.position))
    lon, lat = to_lonlat(e, n, poses.frame.epsg)
    start = np.asarray(source.line_times(cube), float)
    seconds = start - spec.reference_gps
    reference = datetime.strptime(spec.reference_utc, "%Y-%m-%dT%H:%M:%SZ").replace(tzinfo=UTC)
    unix = reference.timestamp() + seconds
    north = grid_convergence(lon, lat, poses.frame.epsg)
    sun_zenith, sun_azimuth = sun_position(unix, lat, lon, h)
    return seconds, np.stack([e, n, h], axis=-1), int(poses.frame.epsg), north, sun_zenith, sun_azimuth


def _relative_irradiance(source, cube: int) -> np.ndarray:
    """(lines,) float32 irradiance of the cube's lines relative to the median of the flight's spectra
    (per band, then the mean over bands), NaN when the source has no usable downwelling spectra."""
    from archive.errors import ArchiveError

    sky = getattr(source, "sky", None)
    lines = source.cubes[cube].lines
    try:
        found = sky() if sky is not None else None
    except ArchiveError:   # no spectra, or unusable ones: radiance renders do not need them
        found = None
    if found is None:
        return np.full(lines, np.nan, np.float32)
    reference = np.median(np.stack([c.x_bands for c in found.cubes]), axis=0)
    return np.mean(found.per_line(source.line_times(cube)) / reference, axis=1).astype(np.float32)


def cube_layers(source, cube: int, job: int, lookup, spec: ProvenanceSpec, ground: float | None = None
                ) -> np.ndarray:
    """The layers ``spec.names`` of one cube on its window (``lookup.grid``), (len(names), h, w)
    float32, NaN where the cube does not cover the pixel.

    lookup: the cube's :class:`archive.render.renderer.Lookup` (with ``count`` when 'overlap_count'
    is asked); job: the cube's index in the job (the 'cube' layer); ground: the flat ground height
    (m) the mesh used, ignored with ``spec.dem``.
    """
    grid = lookup.grid
    out = np.full((len(spec.names), grid.height, grid.width), np.nan, np.float32)
    covered = lookup.line >= 0
    if not covered.any():
        return out
    if "overlap_count" in spec.names and lookup.count is None:
        raise ValueError("the lookup has no count: rasterize it with count=True")
    # Dense over the window (no gather/scatter of the covered pixels), float32 in metres relative
    # to the window's north-west corner (float32 keeps 0.5 mm at 4 km).
    line = np.where(covered, lookup.line, 0)
    seconds, camera, frame_epsg, north, sun_zenith, sun_azimuth = _line_geometry(source, cube, spec)
    x = ((np.arange(grid.width) + 0.5) * grid.gsd).astype(np.float32)[None, :]
    y = (-(np.arange(grid.height) + 0.5) * grid.gsd).astype(np.float32)[:, None]
    rows = cols = None
    if spec.dem is not None or frame_epsg != spec.epsg:
        rows, cols = np.nonzero(covered)
    if spec.dem is not None:
        z = np.zeros(grid.shape, np.float32)
        z[rows, cols] = spec.dem.open().heights_at(spec.epsg, grid.x0 + x[0, cols].astype(float),
                                                   grid.y0 + y[rows, 0].astype(float))
    else:
        if ground is None or not math.isfinite(ground):
            raise InputError("ground height", "provenance layers need the ground height of a flat mesh")
        z = np.float32(ground)
    x0, y0 = grid.x0, grid.y0
    if frame_epsg != spec.epsg:
        # another output CRS (--crs, a flight of another zone): the pixel centres in the flight's
        # zone, whose metres are ground metres (an output CRS's may not be: Web Mercator's are 1.2
        # ground metres at 35 degrees)
        from archive.geometry.navigation import reproject

        e, n = reproject(grid.x0 + x[0, cols].astype(float), grid.y0 + y[rows, 0].astype(float),
                         spec.epsg, frame_epsg)
        x0, y0 = float(np.mean(e)), float(np.mean(n))
        x = np.zeros(grid.shape, np.float32)
        y = np.zeros(grid.shape, np.float32)
        x[rows, cols] = e - x0
        y[rows, cols] = n - y0
    dx = (camera[:, 0] - x0).astype(np.float32)[line] - x     # ground -> sensor, (E, N, up) m
    dy = (camera[:, 1] - y0).astype(np.float32)[line] - y
    dz = camera[:, 2].astype(np.float32)[line] - z
    horizontal = np.hypot(dx, dy)
    values = {
        "cube": lambda: np.float32(job),
        "line": lambda: lookup.line,
        "sample": lambda: lookup.sample,
        "time": lambda: seconds.astype(np.float32)[line],
        "view_zenith": lambda: np.degrees(np.arctan2(horizontal, dz)),
        "view_azimuth": lambda: np.degrees(np.arctan2(dx, dy) - north.astype(np.float32)[line]) % np.float32(360),
        "path_length": lambda: np.hypot(horizontal, dz),
        "sun_zenith": lambda: sun_zenith.astype(np.float32)[line],
        "sun_azimuth": lambda: sun_azimuth.astype(np.float32)[line],
        "overlap_count": lambda: lookup.count,
        "irradiance": lambda: _relative_irradiance(source, cube)[line],
    }
    for i, name in enumerate(spec.names):
        np.copyto(out[i], values[name](), where=covered, casting="unsafe")
    return out
