"""Render planning from metadata only: cube meshes, strips, the output grid and each cube's window.

Reads navigation (poses) but no pixels. A cube's *window* is the part of the output grid under its
mesh's bounding box (``grid.crop(mesh bounds)``, whole pixels): its render task draws only there.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from archive.errors import InputError
from archive.grid import Grid
from archive.navigation import (DEFAULT_MAX_VIEW_ANGLE, frame_interval, joined, projected_epsg, to_lonlat,
                                utm_epsg_for)

__all__ = ["CubeJob", "RenderPlan", "band_groups", "cube_meshes", "job_epsg", "plan_render", "strip_links"]

#: Bands drawn per render task (one RGBA texel fetch).
GROUP = 4


@dataclass(frozen=True, eq=False)
class CubeJob:
    """One cube to render: ``source`` index, ``cube`` index, its mesh and window on the output grid.

    box: (row0, col0, height, width) of the window in output pixels.
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
    """

    grid: Grid
    jobs: tuple[CubeJob, ...]
    bands: tuple[tuple[int, ...], ...]
    groups: tuple[tuple[int, int], ...]

    @property
    def nbands(self) -> int:
        return len(self.bands[0])


def band_groups(nbands: int, size: int = GROUP) -> tuple[tuple[int, int], ...]:
    """(start, stop) of consecutive output-band groups of at most ``size`` bands."""
    return tuple((b, min(b + size, nbands)) for b in range(0, nbands, size))


def strip_links(source, poses: Sequence) -> list[bool]:
    """links[i]: cube i+1 continues cube i's strip (:func:`archive.navigation.joined`: it starts
    within MAX_JOIN_FRAMES frame intervals of cube i's last line)."""
    links = []
    for i in range(len(poses) - 1):
        gap = float(poses[i + 1].time[0]) - float(poses[i].time[-1])
        interval = frame_interval(source.cubes[i].framerate, poses[i].time)
        links.append(bool(joined(gap, interval)))
    return links


def cube_meshes(source, fov_deg: float, ground_height: float,
                max_view_angle: float | None = DEFAULT_MAX_VIEW_ANGLE, *, terrain=None,
                gsd: float | None = None) -> list:
    """Ground mesh of every cube of ``source``, joined to its strip neighbours (closing/opening
    rows, each at its own line's mid-exposure); lines beyond ``max_view_angle`` degrees off nadir
    or without navigation are left out (see :func:`archive.render.mesh.build_mesh`).

    terrain: an opened :class:`archive.dem.Dem` instead of the flat ``ground_height`` (then
    ``gsd``, the output pixel in metres, sets the across-track segmentation; one error names all the
    ground the DEM lacks under the flight)."""
    from archive.render.mesh import build_mesh

    poses = [source.poses(i) for i in range(len(source.cubes))]
    extra = {}
    if terrain is not None:
        terrain.check_flight(poses, fov_deg)
        ground_height = math.nan
        extra = {"terrain": terrain, "gsd": gsd}
    links = strip_links(source, poses)
    meshes = []
    for i, info in enumerate(source.cubes):
        closing = poses[i + 1] if i < len(links) and links[i] else None
        opening = poses[i - 1] if i > 0 and links[i - 1] else None
        meshes.append(build_mesh(
            poses[i], fov_deg, ground_height, info.shutter_ms or 0.0, info.framerate or 0.0,
            closing=closing, opening=opening,
            closing_shutter_ms=source.cubes[i + 1].shutter_ms or 0.0 if closing is not None else None,
            opening_shutter_ms=source.cubes[i - 1].shutter_ms or 0.0 if opening is not None else None,
            max_view_angle=max_view_angle, **extra))
    return meshes


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
                gsd: float, group: int = GROUP, crs: int | str | None = None) -> RenderPlan:
    """The output grid (union of the meshes' bounds, snapped outward to ``gsd``, in the CRS of
    :func:`job_epsg`) and the cube jobs; meshes of another CRS are transformed into it (vertices,
    not rasters).

    meshes[s][c]: mesh of cube c of source s; bands[s]: source band indices of the output bands.
    """
    epsg = job_epsg(meshes, crs)
    meshes = [[m if m.epsg == epsg else m.to_epsg(epsg) for m in ms] for ms in meshes]
    kept = [m for ms in meshes for m in ms if m.rows >= 2]
    if not kept:
        raise InputError(None, "no line of the flights can be rendered (every line lacks navigation or "
                         "looks too far off nadir)", "check the sync offset and --max-view-angle")
    bounds = np.array([m.bounds_utm() for m in kept])
    grid = Grid.from_bounds(epsg, bounds[:, 0].min(), bounds[:, 1].min(), bounds[:, 2].max(),
                            bounds[:, 3].max(), gsd)
    jobs = []
    for s, ms in enumerate(meshes):
        for c, mesh in enumerate(ms):
            crop = grid.crop(*mesh.bounds_utm()) if mesh.rows >= 2 else None
            if crop is None:
                continue
            row0, col0, window = crop
            jobs.append(CubeJob(s, c, mesh, (row0, col0, window.height, window.width), window))
    lengths = {len(b) for b in bands}
    if len(lengths) != 1 or 0 in lengths:
        raise InputError(None, f"the sources select different numbers of bands ({sorted(lengths)})",
                         "render sources with the same bands together")
    return RenderPlan(grid, tuple(jobs), tuple(tuple(int(i) for i in b) for b in bands),
                      band_groups(lengths.pop(), group))
