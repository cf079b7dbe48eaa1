"""Render planning from metadata only: cube meshes, strips, the output grid and each cube's window.

Reads navigation (poses) but no pixels. A cube's *window* is the part of the output grid under its
mesh's bounding box (``grid.crop(mesh bounds)``, whole pixels): its render task draws only there.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from archive.errors import InputError, NoLineOnGrid
from archive.grid import Grid, GridRequest, aligned, boxes_intersect
from archive.geometry.navigation import (DEFAULT_MAX_VIEW_ANGLE, frame_interval, joined, projected_epsg, to_lonlat,
                                utm_epsg_for)
from archive.params import MeshSpec

__all__ = ["CubeJob", "RenderPlan", "band_groups", "cube_mesh", "cube_meshes", "job_epsg", "mesh_task",
           "plan_render", "spec_meshes", "strip_links"]

#: Bands drawn per render task (one RGBA texel fetch).
GROUP = 4


@dataclass(frozen=True, eq=False)
class CubeJob:
    """One cube to render: ``source`` index, ``cube`` index, its mesh and window on the output grid.

    box: (row0, col0, height, width) of the window in output pixels (on a grid asked for on the GSD
    lattice it may reach past the grid: see :func:`plan_render`). mesh: None in a plan whose
    meshes tasks build (:attr:`RenderPlan.mesh_spec`).
    """

    source: int
    cube: int
    mesh: object
    box: tuple[int, int, int, int]
    window: Grid


@dataclass(frozen=True, eq=False)
class RenderPlan:
    """Everything the graph needs, in capture order (source order, then cube order).

    grid: output grid. jobs: cubes touching it. bands: per source, the source band index of each
    output band (all the same length). groups: (start, stop) output band ranges, one task each.
    mesh_spec: the :class:`~archive.params.MeshSpec` tasks build the cube meshes from on the
    workers (:func:`mesh_task`; the jobs then hold no mesh: :meth:`without_meshes`), or None: the
    jobs' meshes go into the graph as values.
    """

    grid: Grid
    jobs: tuple[CubeJob, ...]
    bands: tuple[tuple[int, ...], ...]
    groups: tuple[tuple[int, int], ...]
    mesh_spec: MeshSpec | None = None

    def without_meshes(self, spec: MeshSpec) -> RenderPlan:
        """This plan with its meshes left to tasks built from ``spec`` (its ``epsg`` must be the
        grid's): the client keeps the windows, not the meshes."""
        if spec.epsg is None or int(spec.epsg) != self.grid.epsg:
            raise ValueError(f"meshes in EPSG:{spec.epsg} for a grid in EPSG:{self.grid.epsg}")
        jobs = tuple(dataclasses.replace(job, mesh=None) for job in self.jobs)
        return dataclasses.replace(self, jobs=jobs, mesh_spec=spec)

    @property
    def nbands(self) -> int:
        return len(self.bands[0])


def band_groups(nbands: int, size: int = GROUP) -> tuple[tuple[int, int], ...]:
    """(start, stop) of consecutive output-band groups of at most ``size`` bands."""
    return tuple((b, min(b + size, nbands)) for b in range(0, nbands, size))


def _continues(source, poses: Sequence, i: int) -> bool:
    """Cube i+1 continues cube i's strip (``poses[k]``: cube k's poses)."""
    gap = float(poses[i + 1].time[0]) - float(poses[i].time[-1])
    interval = frame_interval(source.cubes[i].framerate, poses[i].time)
    return bool(joined(gap, interval))


def strip_links(source, poses: Sequence) -> list[bool]:
    """links[i]: cube i+1 continues cube i's strip (:func:`archive.geometry.navigation.joined`: it starts
    within MAX_JOIN_FRAMES frame intervals of cube i's last line)."""
    return [_continues(source, poses, i) for i in range(len(poses) - 1)]


class _PosesOf:
    """``poses[k]``: cube k's poses of ``source``, read once (from ``known`` when given)."""

    def __init__(self, source, known: Sequence | None = None):
        self.source, self.known = source, {} if known is None else dict(enumerate(known))

    def __getitem__(self, k: int):
        if k not in self.known:
            self.known[k] = self.source.poses(k)
        return self.known[k]


def cube_mesh(source, cube: int, fov_deg: float, ground_height: float,
              max_view_angle: float | None = DEFAULT_MAX_VIEW_ANGLE, *, terrain=None, gsd: float | None = None,
              poses: Sequence | None = None):
    """Ground mesh of cube ``cube`` of ``source``, joined to its strip neighbours (closing/opening
    rows, each at its own line's mid-exposure: the neighbours' poses are read too); lines beyond
    ``max_view_angle`` degrees off nadir or without navigation are left out (see
    :func:`archive.render.mesh.build_mesh`). The mesh is in the source's local frame (its UTM zone).

    terrain: an opened :class:`archive.terrain.dem.Dem` instead of the flat ``ground_height`` (m; then
    ``gsd``, the output pixel in metres, sets the across-track segmentation); poses: every cube's
    poses, when the caller has them (:func:`cube_meshes`)."""
    from archive.render.mesh import build_mesh

    poses = _PosesOf(source, poses)
    n = len(source.cubes)
    extra = {} if terrain is None else {"terrain": terrain, "gsd": gsd}
    if terrain is not None:
        ground_height = math.nan
    closing = poses[cube + 1] if cube + 1 < n and _continues(source, poses, cube) else None
    opening = poses[cube - 1] if cube > 0 and _continues(source, poses, cube - 1) else None
    cubes = source.cubes
    return build_mesh(
        poses[cube], fov_deg, ground_height, cubes[cube].shutter_ms or 0.0, cubes[cube].framerate or 0.0,
        closing=closing, opening=opening,
        closing_shutter_ms=cubes[cube + 1].shutter_ms or 0.0 if closing is not None else None,
        opening_shutter_ms=cubes[cube - 1].shutter_ms or 0.0 if opening is not None else None,
        max_view_angle=max_view_angle, **extra)


def cube_meshes(source, fov_deg: float, ground_height: float,
                max_view_angle: float | None = DEFAULT_MAX_VIEW_ANGLE, *, terrain=None,
                gsd: float | None = None) -> list:
    """:func:`cube_mesh` of every cube of ``source`` (in cube order).

    terrain: an opened :class:`archive.terrain.dem.Dem` instead of the flat ``ground_height`` (then
    ``gsd``, the output pixel in metres, sets the across-track segmentation; one error names all the
    ground the DEM lacks under the flight)."""
    poses = [source.poses(i) for i in range(len(source.cubes))]
    if terrain is not None:
        terrain.check_flight(poses, fov_deg)
    return [cube_mesh(source, i, fov_deg, ground_height, max_view_angle, terrain=terrain, gsd=gsd, poses=poses)
            for i in range(len(source.cubes))]


@functools.lru_cache(maxsize=8)
def _opened_dem(spec):
    """A worker's opened DEM of ``spec`` (metadata only: heights are read per mesh), once per process."""
    return spec.open()


def spec_meshes(source, spec: MeshSpec, terrain=None) -> list:
    """:func:`cube_meshes` of every cube of ``source`` as ``spec`` says (field of view, flat ground or
    DEM, view-angle limit; in the source's local frame): ``terrain`` is ``spec.dem`` opened, when
    the caller has it (else it is opened here)."""
    if spec.dem is not None and terrain is None:
        terrain = _opened_dem(spec.dem)
    return cube_meshes(source, spec.fov_deg, spec.flat_ground, spec.max_view_angle, terrain=terrain,
                       gsd=spec.gsd if terrain is not None else None)


def mesh_task(source, cube: int, spec: MeshSpec):
    """Task body: the ground mesh of cube ``cube`` of ``source`` (:func:`cube_mesh`) as ``spec`` says,
    in the output grid's CRS ``spec.epsg``: the mesh :func:`plan_render` planned the cube's window with."""
    terrain = None if spec.dem is None else _opened_dem(spec.dem)
    mesh = cube_mesh(source, cube, spec.fov_deg, spec.flat_ground, spec.max_view_angle, terrain=terrain,
                     gsd=spec.gsd)
    return mesh if mesh.epsg == int(spec.epsg) else mesh.to_epsg(int(spec.epsg))


def job_epsg(meshes: Sequence[Sequence], crs: int | str | None = None) -> int:
    """EPSG code of a job's output grid: ``crs`` when given (any projected CRS in metres: an EPSG
    code, 'EPSG:XXXX' or a pyproj-readable string), else the UTM zone holding most of the meshes'
    rows (ties: the lowest code)."""
    if crs is not None:
        return projected_epsg(crs)
    counts: dict[int, int] = {}
    for ms in meshes:
        for m in ms:
            if m.rows == 0:
                continue
            e, n = m.ground_utm().reshape(-1, 2).mean(axis=0)
            lon, lat = to_lonlat(e, n, m.epsg)
            zone = utm_epsg_for(lon, lat)
            counts[zone] = counts.get(zone, 0) + m.rows
    if not counts:
        return min({m.epsg for ms in meshes for m in ms})
    return max(sorted(counts), key=lambda z: counts[z])


def plan_render(sources: Sequence, meshes: Sequence[Sequence], bands: Sequence[Sequence[int]],
                gsd: float, group: int = GROUP, crs: int | str | None = None,
                grid: GridRequest | None = None) -> RenderPlan:
    """The output grid (``grid``'s :meth:`~archive.grid.GridRequest.decide`; by default the union of
    the meshes' bounds, snapped outward to ``gsd``, in the CRS of :func:`job_epsg`) and the cube jobs
    (the cubes whose meshes touch it, each windowed to the grid); meshes of another CRS are
    transformed into it (vertices, not rasters). InputError when ``grid`` (--bounds, --like) holds
    no line of the flights.

    meshes[s][c]: mesh of cube c of source s; bands[s]: source band indices of the output bands.
    """
    request = GridRequest() if grid is None else grid
    epsg = job_epsg(meshes, request.like.epsg if request.like is not None else crs)
    meshes = [[m if m.epsg == epsg else m.to_epsg(epsg) for m in ms] for ms in meshes]
    kept = [m for ms in meshes for m in ms if m.rows >= 2]
    if not kept:
        raise InputError(None, "no line of the flights can be rendered (every line lacks navigation or "
                         "looks too far off nadir)", "check the sync offset and --max-view-angle")
    bounds = np.array([m.bounds_utm() for m in kept])
    footprint = (bounds[:, 0].min(), bounds[:, 1].min(), bounds[:, 2].max(), bounds[:, 3].max())
    grid = request.decide(epsg, footprint, gsd)
    # On a grid asked for (--bounds --align, --like, a tile, a stack) that lies on the GSD lattice, a
    # cube's window is its own box on that lattice, whatever the grid's extent (it may reach past
    # the grid: the writers keep what falls inside): a pixel is then drawn with the same GL set-up
    # in every such grid, so tiles stitched equal their union and a stack's slice its --like render,
    # bit for bit. Elsewhere (the footprint grid, which holds every window) the window is the crop.
    on_lattice = (request.bounds is not None or request.like is not None) and aligned(grid)
    jobs = []
    for s, ms in enumerate(meshes):
        for c, mesh in enumerate(ms):
            if mesh.rows < 2:
                continue
            if on_lattice:
                window = Grid.from_bounds(epsg, *mesh.bounds_utm(), grid.gsd)
                box = (round((grid.y0 - window.y0) / grid.gsd), round((window.x0 - grid.x0) / grid.gsd),
                       window.height, window.width)
                if not boxes_intersect(box, (0, 0, grid.height, grid.width)):
                    continue
                jobs.append(CubeJob(s, c, mesh, box, window))
                continue
            crop = grid.crop(*mesh.bounds_utm())
            if crop is None:
                continue
            row0, col0, window = crop
            jobs.append(CubeJob(s, c, mesh, (row0, col0, window.height, window.width), window))
    if not jobs:
        option = "--like" if request.like is not None else "--bounds"
        w, s_, e, n = grid.bounds
        fw, fs, fe, fn = footprint
        fix = f"give {option} over the flights, or other flights"
        if request.like is None and request.bounds is not None and _looks_like_degrees(request.bounds):
            fix = (f"these look like degrees: {option} takes metres in the output CRS (EPSG:{epsg}): "
                   f"{_in_metres(request.bounds, epsg)}")
        raise NoLineOnGrid(option, f"the grid W,S,E,N = {w:.0f},{s_:.0f},{e:.0f},{n:.0f} (EPSG:{epsg}) holds no line "
                         f"of the flights, which cover {fw:.0f},{fs:.0f},{fe:.0f},{fn:.0f}", fix)
    lengths = {len(b) for b in bands}
    if len(lengths) != 1 or 0 in lengths:
        raise InputError(None, f"the sources select different numbers of bands ({sorted(lengths)})",
                         "render sources with the same bands together")
    return RenderPlan(grid, tuple(jobs), tuple(tuple(int(i) for i in b) for b in bands),
                      band_groups(lengths.pop(), group))


def _looks_like_degrees(bounds: tuple[float, float, float, float]) -> bool:
    """Whether W,S,E,N read as longitudes and latitudes (|lon| <= 180, |lat| <= 90, a box under 1 degree
    wide): a user who gave ``--bounds`` in degrees instead of the output CRS's metres."""
    w, s, e, n = bounds
    return all(abs(v) <= 180 for v in (w, e)) and all(abs(v) <= 90 for v in (s, n)) and e - w < 1 and n - s < 1


def _in_metres(bounds: tuple[float, float, float, float], epsg: int) -> str:
    """The lon/lat box ``bounds`` (degrees, WGS 84) in EPSG ``epsg`` as the 'W,S,E,N' text --bounds takes."""
    from pyproj import Transformer

    to = Transformer.from_crs(4326, epsg, always_xy=True)
    w, s, e, n = to.transform_bounds(*bounds)
    return f"{w:.0f},{s:.0f},{e:.0f},{n:.0f}"
