"""A render plan as lazy dask arrays (builds graphs, never computes them).

:func:`mosaic_arrays` turns a :class:`~archive.graph.plan.RenderPlan` into two ``dask.array``
collections: the mosaicked values ``(band, y, x)`` float32, one block per output tile (the 1024 px
Zarr chunks of :mod:`archive.outputs`) and band group, and the saturation flags ``(y, x)`` uint8.
Their blocks are computed by the render graph's own task bodies (:mod:`archive.graph.tasks`):
one :func:`~archive.graph.tasks.lookup_task` per cube, one :func:`~archive.graph.tasks.render_task`
per cube and band group, one :func:`~archive.graph.tasks.assemble_task` (the overlap rules of
:mod:`archive.overlap`) per tile and band group. Computing some bands runs only their groups'
renders (and the lookups); tiles no cube touches are NaN without any render.

The sources, meshes, lookups, renders and rule keys are the nodes of :mod:`archive.graph.nodes`,
as in :func:`archive.graph.build.build_render_graph`: the same keys for the same request (when its
band groups share the lookups, as they do unless the lookups exceed its ``LOOKUP_BYTES``, and no
provenance layer is written). GL tasks (lookups and renders)
are annotated ``resources={"GPU": 1}`` like the render graph's, and never fused with other tasks
(``block_fusion``): they keep their keys and run as tasks of their own, in the worker thread that
owns the GL context. Dask's array optimizer drops layer annotations when it fuses (dask/dask#7036),
so on a distributed cluster they reach the scheduler only when computed with
``dask.config.set({"optimization.fuse.active": False})``.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from dask.task_spec import DataNode, Task, TaskRef

from archive.graph.nodes import GL_RESOURCES, Node, RenderNodes, task_arg
from archive.graph.plan import RenderPlan
from archive.graph.tasks import assemble_task
from archive.grid import boxes_intersect
from archive.overlap import OverlapRule
from archive.params import MeshSpec
from archive.outputs.base import CHUNK

__all__ = ["GLTask", "mosaic_arrays", "nan_tile", "tile_saturation", "tile_values", "zero_tile"]


# ---------------------------------------------------------------------------------------------
# Block bodies (plain functions of explicit inputs)
# ---------------------------------------------------------------------------------------------
def tile_values(assembled: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """The values (nbands, h, w) float32 of an :func:`~archive.graph.tasks.assemble_task` result."""
    return assembled[0]


def tile_saturation(height: int, width: int, *assembled: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """(height, width) uint8: 1 where some band group's assembled tile is flagged saturated."""
    mask = np.zeros((height, width), bool)
    for _, saturated in assembled:
        mask |= saturated
    return mask.astype(np.uint8)


def nan_tile(nbands: int, height: int, width: int) -> np.ndarray:
    """(nbands, height, width) float32 NaN: a tile no cube covers."""
    return np.full((nbands, height, width), np.nan, np.float32)


def zero_tile(height: int, width: int) -> np.ndarray:
    """(height, width) uint8 zeros: the saturation of a tile no cube covers."""
    return np.zeros((height, width), np.uint8)


# ---------------------------------------------------------------------------------------------
# Graph
# ---------------------------------------------------------------------------------------------
class GLTask(Task):
    """A task dask never fuses with its neighbours (as distributed's P2P barrier tasks do): a GL task
    keeps its key and its annotation, and runs as a task of its own."""

    __slots__ = ()

    @property
    def block_fusion(self) -> bool:
        return True


def _sizes(total: int, size: int) -> tuple[int, ...]:
    return tuple(min(size, total - start) for start in range(0, total, size))


def _task(node: Node) -> Task:
    """The task spec of ``node`` (a :class:`GLTask` for the GL nodes)."""
    kind = GLTask if node.gl else Task
    return kind(node.key, node.func, *map(task_arg, node.args), **node.kwargs)


def assemble_keyed(rule: OverlapRule, tile, nbands: int, boxes, *renders_and_keys):
    """:func:`~archive.graph.tasks.assemble_task` of a rule that compares a key
    (:attr:`~archive.overlap.OverlapRule.key`): the renders, then each render's key, all positional."""
    n = len(boxes)
    return assemble_task(rule, tile, nbands, boxes, *renders_and_keys[:n], keys=renders_and_keys[n:])


def mosaic_arrays(plan: RenderPlan, sources: Sequence, *, mode: str, overlap: OverlapRule,
                  mesh_spec: MeshSpec | None = None, layers=None):
    """(values, saturated) lazy ``dask.array`` collections of ``plan`` rendered from ``sources``.

    values: (nbands, grid height, grid width) float32, NaN where no line covers a pixel, chunked
    (one band group, CHUNK, CHUNK); saturated: (grid height, grid width) uint8, chunked (CHUNK,
    CHUNK). mesh_spec: the :class:`~archive.params.MeshSpec` of a plan that holds its meshes, only
    for keys (as in :func:`~archive.graph.build.build_render_graph`; default the plan's); layers: the
    :class:`~archive.geometry.provenance.ProvenanceSpec` of the layer the overlap rule compares (its only layer).
    """
    key_layer = overlap.key
    if key_layer is not None and layers is None:
        raise ValueError(f"the '{overlap.name}' rule needs a ProvenanceSpec of its {key_layer} layer")
    import dask.array as da
    from dask.base import tokenize
    from dask.highlevelgraph import HighLevelGraph, MaterializedLayer

    nodes = RenderNodes(plan, sources, mode=mode, mesh_spec=mesh_spec, layers=layers)
    source_nodes = {key: DataNode(key, value) for key, value in nodes.data().items()}
    meshes = {node.key: _task(node) for node in nodes.meshes()}   # built on the workers
    lookups: dict = {}
    zeniths: dict = {}
    zenith_key: dict[int, str] = {}
    renders: dict = {}
    render_key: dict[tuple[int, int], str] = {}
    for j in range(len(plan.jobs)):
        lookup = nodes.lookup(j)
        lookups[lookup.key] = _task(lookup)
        if key_layer is not None:   # the compared layer of the cube's pixels (CPU, from the lookup)
            stack = nodes.cube_layers(j, lookup.key)
            pick = nodes.layer_pick(stack.key, key_layer)
            zeniths[stack.key], zeniths[pick.key] = _task(stack), _task(pick)
            zenith_key[j] = pick.key
        for g in range(len(plan.groups)):
            render = nodes.render(j, g, lookup.key)
            renders[render.key] = _task(render)
            render_key[j, g] = render.key

    grid = plan.grid
    name = tokenize(grid, plan.groups, overlap, [render_key[k] for k in sorted(render_key)], mode)
    values_name, saturated_name = f"mosaic-{name}", f"saturated-{name}"
    assembles: dict = {}
    values: dict = {}
    saturated: dict = {}
    for row0, col0, tile_grid in grid.tiles(CHUNK):
        i, k = row0 // CHUNK, col0 // CHUNK
        tile = (row0, col0, tile_grid.height, tile_grid.width)
        touching = [j for j, job in enumerate(plan.jobs) if boxes_intersect(tile, job.box)]
        boxes = tuple(plan.jobs[j].box for j in touching)
        group_keys = []
        for g, (b0, b1) in enumerate(plan.groups):
            vkey = (values_name, g, i, k)
            if not touching:
                values[vkey] = Task(vkey, nan_tile, b1 - b0, tile[2], tile[3])
                continue
            parts = [render_key[j, g] for j in touching]
            if key_layer is not None:
                zkeys = [zenith_key[j] for j in touching]
                akey = f"assemble-{tokenize(overlap, tile, b1 - b0, boxes, parts, zkeys)}"
                assembles[akey] = Task(akey, assemble_keyed, overlap, tile, b1 - b0, boxes,
                                       *map(TaskRef, parts + zkeys))
            else:
                akey = f"assemble-{tokenize(overlap, tile, b1 - b0, boxes, parts)}"
                assembles[akey] = Task(akey, assemble_task, overlap, tile, b1 - b0, boxes, *map(TaskRef, parts))
            values[vkey] = Task(vkey, tile_values, TaskRef(akey))
            group_keys.append(akey)
        skey = (saturated_name, i, k)
        saturated[skey] = (Task(skey, tile_saturation, tile[2], tile[3], *map(TaskRef, group_keys)) if group_keys
                           else Task(skey, zero_tile, tile[2], tile[3]))

    names = {kind: f"{kind}-{name}" for kind in ("sources", "meshes", "lookups", "zeniths", "renders", "assembles")}
    graph_layers = {names["sources"]: MaterializedLayer(source_nodes),
                    names["meshes"]: MaterializedLayer(meshes),
                    names["lookups"]: MaterializedLayer(lookups, annotations={"resources": dict(GL_RESOURCES)}),
                    names["zeniths"]: MaterializedLayer(zeniths),
                    names["renders"]: MaterializedLayer(renders, annotations={"resources": dict(GL_RESOURCES)}),
                    names["assembles"]: MaterializedLayer(assembles)}
    deps = {names["sources"]: set(), names["meshes"]: {names["sources"]},
            names["lookups"]: {names["sources"], names["meshes"]},   # meshes: data nodes or tasks
            names["zeniths"]: {names["sources"], names["lookups"]},
            names["renders"]: {names["sources"], names["lookups"]},
            names["assembles"]: {names["renders"], names["zeniths"]}}

    def array(layer_name: str, tasks: dict, chunks: tuple, dtype, ndim: int):
        graph = HighLevelGraph({**graph_layers, layer_name: MaterializedLayer(tasks)},
                               {**deps, layer_name: {names["assembles"]}})
        return da.Array(graph, layer_name, chunks, dtype=dtype, meta=np.empty((0,) * ndim, dtype))

    rows, cols = _sizes(grid.height, CHUNK), _sizes(grid.width, CHUNK)
    band_chunks = tuple(b1 - b0 for b0, b1 in plan.groups)
    return (array(values_name, values, (band_chunks, rows, cols), np.float32, 3),
            array(saturated_name, saturated, (rows, cols), np.uint8, 2))
