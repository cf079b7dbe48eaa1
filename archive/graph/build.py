"""Build (never compute) the Dask graph of a render: render -> assemble and write.

Per cube, one lookup task (GL pass 1, annotated ``resources={"GPU": 1}``) records which (line,
sample) each pixel of the cube's window sees; per cube and band group, one render task (GPU too)
draws the group's bands through that lookup, 8 bands per GL pass. Per output tile (1024 x 1024, the
Zarr chunks) and band group, one writer task mosaics the renders that touch the tile in capture
order and writes the result into the tile's own chunks (chunk-aligned: no two tasks write into one
chunk), band by band through one reused chunk buffer. Each writer also ORs its saturation mask into
the previous group's (a chain per tile); one last task per tile writes it. Tiles no cube touches
get no task: their chunks read back as NaN.

Memory: priorities make one band group finish (render, then assemble and write) before the next
starts, so about one group's cube renders (cube window x group x float32 each) are held at a time.
:func:`with_task_groups` sizes the groups so that one render holds at most ``TASK_VALUES_BYTES``.

Keys are ``<kind>-<dask.base.tokenize(inputs)>``, so the same inputs give the same graph.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import dask
from dask.base import tokenize
from dask.delayed import Delayed, delayed

from archive.graph.plan import GROUP, RenderPlan, band_groups
from archive.graph.tasks import assemble_write_task, lookup_task, render_task, write_saturated_task
from archive.outputs import CHUNK, MosaicStore

__all__ = ["RenderGraph", "TASK_VALUES_BYTES", "build_render_graph", "task_group_size", "with_task_groups"]

#: Rendered values one render task may hold, bytes (window px x bands x 4 B): 32 bands of a 1.4 Mpx
#: cube window. Larger groups mean fewer GL set-ups and reads per band; smaller ones less memory.
TASK_VALUES_BYTES = 192 * 1024**2
#: Most bands per render task (and per assembly / writer task).
MAX_GROUP = 64
#: Bands per GL pass in render tasks (8 = the renderer's most per pass).
BANDS_PER_PASS = 8


def task_group_size(plan: RenderPlan, budget: int = TASK_VALUES_BYTES) -> int:
    """Bands per render task for ``plan``: as many whole 8-band GL passes as fit ``budget`` bytes of
    values for the largest cube window (at most MAX_GROUP), but never fewer than GROUP (4) bands."""
    biggest = max((job.window.width * job.window.height for job in plan.jobs), default=1)
    fit = budget // (4 * max(biggest, 1))
    return max(GROUP, min(MAX_GROUP, fit // BANDS_PER_PASS * BANDS_PER_PASS))


def with_task_groups(plan: RenderPlan, budget: int = TASK_VALUES_BYTES) -> RenderPlan:
    """``plan`` with its band groups resized by :func:`task_group_size` (the groups the graph uses)."""
    return dataclasses.replace(plan, groups=band_groups(plan.nbands, task_group_size(plan, budget)))


@dataclasses.dataclass(frozen=True)
class RenderGraph:
    """The built graph: ``writes`` are the final tasks (values writers, then saturation writers);
    ``assemblies`` counts the values writers (one per tile and band group, each assembling its tile)."""

    writes: tuple[Delayed, ...]
    renders: int
    assemblies: int

    def __len__(self) -> int:
        return len(self.writes)


def build_render_graph(plan: RenderPlan, sources: Sequence, store: MosaicStore, *, mode: str,
                       overlap: str, mesh_spec: object = None) -> RenderGraph:
    """Dask graph rendering ``plan`` from ``sources`` into the Zarr ``store``.

    mesh_spec: the parameters the meshes were built from (fov, ground height...), only for keys.
    """
    # every source's __dask_tokenize__ says what its renders depend on (files or stored content,
    # parameters), never its pixels
    tokens = [tokenize(s) for s in sources]
    source_nodes = [delayed(s, name=f"source-{t}", traverse=False) for s, t in zip(sources, tokens)]

    # Priorities (higher runs first) finish one band group before starting the next, and assemble
    # and write a tile as soon as its renders exist: only one group's renders are held at a time.
    ngroups = len(plan.groups)

    def priority(g: int, stage: int) -> int:
        return 2 * (ngroups - g) + stage

    # renders[(job index, group index)]; one lookup (GL pass 1) per cube, shared by its groups
    renders: dict[tuple[int, int], Delayed] = {}
    for j, job in enumerate(plan.jobs):
        mesh_key = f"mesh-{tokenize(tokens[job.source], job.cube, mesh_spec)}"
        mesh = delayed(job.mesh, name=mesh_key, traverse=False)
        samples = int(sources[job.source].cubes[job.cube].samples)
        lkey = f"lookup-{tokenize(mesh_key, job.window, samples)}"
        with dask.annotate(resources={"GPU": 1}, priority=priority(0, 0)):
            lookup = delayed(lookup_task, pure=True)(mesh, job.window, samples, dask_key_name=lkey)
        for g, (b0, b1) in enumerate(plan.groups):
            bands = plan.bands[job.source][b0:b1]
            key = f"render-{tokenize(tokens[job.source], job.cube, bands, lkey, mode, BANDS_PER_PASS)}"
            with dask.annotate(resources={"GPU": 1}, priority=priority(g, 0)):
                renders[j, g] = delayed(render_task, pure=True)(
                    source_nodes[job.source], job.cube, bands, lookup, mode, BANDS_PER_PASS,
                    dask_key_name=key
                )

    writes: list[Delayed] = []
    saturation: list[Delayed] = []
    assemblies = 0
    for row0, col0, tile_grid in plan.grid.tiles(CHUNK):
        tile = (row0, col0, tile_grid.height, tile_grid.width)
        touching = [j for j, job in enumerate(plan.jobs) if _intersects(tile, job.box)]
        if not touching:
            continue
        boxes = tuple(plan.jobs[j].box for j in touching)
        mask = None  # saturation so far: each group's writer ORs in its own (one small mask per tile)
        for g, (b0, b1) in enumerate(plan.groups):
            parts = [renders[j, g] for j in touching]
            akey = tokenize(overlap, tile, b1 - b0, boxes, [p.key for p in parts])
            wkey = f"write-{tokenize(store, b0, tile, akey, None if mask is None else mask.key)}"
            with dask.annotate(priority=priority(g, 1)):
                mask = delayed(assemble_write_task)(store, overlap, b0, tile, b1 - b0, boxes, mask, *parts,
                                                    dask_key_name=wkey)
            writes.append(mask)
            assemblies += 1
        skey = f"saturated-{tokenize(store, tile, mask.key)}"
        with dask.annotate(priority=priority(ngroups, 1)):
            saturation.append(delayed(write_saturated_task)(store, tile, mask, dask_key_name=skey))
    return RenderGraph(tuple(writes + saturation), len(renders), assemblies)


def _intersects(a: tuple[int, int, int, int], b: tuple[int, int, int, int]) -> bool:
    return a[0] < b[0] + b[2] and b[0] < a[0] + a[2] and a[1] < b[1] + b[3] and b[1] < a[1] + a[3]
