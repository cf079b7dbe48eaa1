"""Build (never compute) the Dask graph of a render: render -> assemble -> write.

Per cube and band group, one render task (annotated ``resources={"GPU": 1}``) draws the group's
bands on the cube's window. Per output tile (1024 x 1024, the Zarr chunks) and band group, one
assembly task mosaics the renders that touch the tile in capture order and one writer task writes
the result into the tile's own chunks (chunk-aligned: no two tasks write into one chunk). Each
writer also ORs its saturation mask into the previous group's (a chain per tile); one last task per
tile writes it. Tiles no cube touches get no task: their chunks read back as NaN.

Memory: priorities make one band group finish (render, assemble, write) before the next starts,
so at most one group's cube renders (cube window x 4 bands x float32 each) are held at a time.

Keys are ``<kind>-<dask.base.tokenize(inputs)>``, so the same inputs give the same graph.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import dask
from dask.base import tokenize
from dask.delayed import Delayed, delayed

from archive.graph.plan import RenderPlan
from archive.graph.tasks import assemble_task, render_task, write_saturated_task, write_values_task
from archive.outputs import CHUNK, MosaicStore

__all__ = ["RenderGraph", "build_render_graph", "source_token"]


def source_token(source) -> str:
    """Deterministic token of a flight source (what its renders depend on), without reading pixels."""
    if hasattr(source, "__dask_tokenize__"):
        return tokenize(source)
    directory = getattr(source, "directory", None)
    if directory is not None:  # a raw flight directory: its files, parameters and calibration
        return tokenize(type(source).__qualname__, str(directory), source.id, source.cubes,
                        getattr(source, "params", None), str(getattr(source, "calibration_path", None)),
                        getattr(source, "white_reference", None))
    return tokenize(source)


@dataclass(frozen=True)
class RenderGraph:
    """The built graph: ``writes`` are the final tasks (values writers, then saturation writers)."""

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
    tokens = [source_token(s) for s in sources]
    source_nodes = [delayed(s, name=f"source-{t}", traverse=False) for s, t in zip(sources, tokens)]

    # Priorities (higher runs first) finish one band group before starting the next, and assemble
    # and write a tile as soon as its renders exist: only one group's renders are held at a time.
    ngroups = len(plan.groups)

    def priority(g: int, stage: int) -> int:
        return 2 * (ngroups - g) + stage

    # renders[(job index, group index)]
    renders: dict[tuple[int, int], Delayed] = {}
    for j, job in enumerate(plan.jobs):
        mesh_key = f"mesh-{tokenize(tokens[job.source], job.cube, mesh_spec)}"
        mesh = delayed(job.mesh, name=mesh_key, traverse=False)
        for g, (b0, b1) in enumerate(plan.groups):
            bands = plan.bands[job.source][b0:b1]
            key = f"render-{tokenize(tokens[job.source], job.cube, bands, mesh_key, job.window, mode)}"
            with dask.annotate(resources={"GPU": 1}, priority=priority(g, 0)):
                renders[j, g] = delayed(render_task, pure=True)(
                    source_nodes[job.source], job.cube, bands, mesh, job.window, mode, dask_key_name=key
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
            akey = f"assemble-{tokenize(overlap, tile, b1 - b0, boxes, [p.key for p in parts])}"
            wkey = f"write-{tokenize(store, b0, tile, akey)}"
            with dask.annotate(priority=priority(g, 1)):
                assembled = delayed(assemble_task, pure=True)(overlap, tile, b1 - b0, boxes, *parts,
                                                              dask_key_name=akey)
                mask = delayed(write_values_task)(store, b0, tile, assembled, mask, dask_key_name=wkey)
            writes.append(mask)
            assemblies += 1
        skey = f"saturated-{tokenize(store, tile, mask.key)}"
        with dask.annotate(priority=priority(ngroups, 1)):
            saturation.append(delayed(write_saturated_task)(store, tile, mask, dask_key_name=skey))
    return RenderGraph(tuple(writes + saturation), len(renders), assemblies)


def _intersects(a: tuple[int, int, int, int], b: tuple[int, int, int, int]) -> bool:
    return a[0] < b[0] + b[2] and b[0] < a[0] + a[2] and a[1] < b[1] + b[3] and b[1] < a[1] + a[3]
