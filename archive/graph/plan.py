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

__all__ = ["CubeJob", "RenderPlan", "band_groups", "cube_meshes", "plan_render", "strip_links"]

#: A cube joins the next one (same strip) when the next starts within this many frame intervals.
STRIP_GAP_FRAMES = 1.5
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


def _interval(source, cube: int, times: np.ndarray) -> float:
    rate = source.cubes[cube].framerate
    if rate:
        return 1.0 / float(rate)
    return float(np.median(np.diff(times))) if len(times) > 1 else math.inf


def strip_links(source, poses: Sequence) -> list[bool]:
    """links[i]: cube i+1 continues cube i's strip (it starts within 1.5 frame intervals of i's end)."""
    links = []
    for i in range(len(poses) - 1):
        gap = float(poses[i + 1].time[0]) - float(poses[i].time[-1])
        links.append(0.0 < gap <= STRIP_GAP_FRAMES * _interval(source, i, poses[i].time))
    return links


def cube_meshes(source, fov_deg: float, ground_height: float) -> list:
    """Ground mesh of every cube of ``source``, joined to its strip neighbours (closing/opening rows)."""
    from archive.render.mesh import build_mesh

    poses = [source.poses(i) for i in range(len(source.cubes))]
    links = strip_links(source, poses)
    meshes = []
    for i, info in enumerate(source.cubes):
        closing = poses[i + 1] if i < len(links) and links[i] else None
        opening = poses[i - 1] if i > 0 and links[i - 1] else None
        meshes.append(build_mesh(poses[i], fov_deg, ground_height, info.shutter_ms or 0.0,
                                 info.framerate or 0.0, closing=closing, opening=opening))
    return meshes


def plan_render(sources: Sequence, meshes: Sequence[Sequence], bands: Sequence[Sequence[int]],
                gsd: float, group: int = GROUP) -> RenderPlan:
    """The output grid (union of the meshes' bounds, snapped outward to ``gsd``) and the cube jobs.

    meshes[s][c]: mesh of cube c of source s; bands[s]: source band indices of the output bands.
    """
    epsg = {m.epsg for ms in meshes for m in ms}
    if len(epsg) != 1:
        raise InputError(None, f"the sources lie in several UTM zones (EPSG {sorted(epsg)})",
                         "render each zone separately")
    bounds = np.array([m.bounds_utm() for ms in meshes for m in ms])
    grid = Grid.from_bounds(epsg.pop(), bounds[:, 0].min(), bounds[:, 1].min(), bounds[:, 2].max(),
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
