"""Build (never compute) the Dask graph of a render: render -> assemble and write.

Per cube, one lookup task (GL pass 1, annotated ``resources={"GPU": 1}``) records which (line,
sample) each pixel of the cube's window sees; per cube and band group, one render task (GPU too)
draws the group's bands through that lookup, 8 bands per GL pass. Per output tile (1024 x 1024, the
Zarr chunks) and band group, one writer task (no resource: any thread of any worker) mosaics the
renders that touch the tile in capture order and writes the result through the output's *sink*
(:mod:`archive.outputs`; the graph reads only the capabilities of :class:`~archive.outputs.base.Sink`,
never which format it is): Zarr chunks, ENVI rows, or compressed COG tiles; no two tasks write the
same bytes. Zarr: each writer also ORs its saturation mask into the previous group's (a chain per
tile); one last task per tile writes it; tiles no cube touches get no task (their chunks read back
as NaN). ENVI and COG: tiles no cube touches get a task writing NaN. COG: each writer also spools
its tile's first overview level and returns that level's 2 x 2 average (its quarter of level 2);
per band group, overview tasks build each further level from the four quarters of the level below.

Memory: priorities make one band group finish (render, then assemble and write, then overviews)
before the next starts, and a render waits (through a small ``gate-`` task) until the writers
completed by the render RENDERS_AHEAD before it have run, so the renders held at a time are those
between a tile's first and last touching cube plus RENDERS_AHEAD, whatever the flight length and
however much faster renders are than writes. Within a group the cubes are rendered in
:func:`render_order` (swept along the passes when that holds fewer renders than capture order: a
tile is then complete once every pass crossing it has been drawn there, so the renders held do not
grow with the passes' length); writers still mosaic in capture order. :func:`with_task_groups`
sizes the groups so that one render holds at most ``TASK_VALUES_BYTES`` and all renders held at
once ``HELD_VALUES_BYTES``.

Keys are ``<kind>-<dask.base.tokenize(inputs)>``, so the same inputs give the same graph.
"""

from __future__ import annotations

import bisect
import dataclasses
from collections.abc import Sequence

import numpy as np
from dask.base import tokenize
from dask.delayed import Delayed
from dask.highlevelgraph import HighLevelGraph, MaterializedLayer
from dask.task_spec import DataNode, GraphNode, Task

from archive.grid import boxes_intersect
from archive.overlap import OverlapRule
from archive.params import MeshSpec
from archive.outputs.base import CHUNK
from archive.graph.nodes import BANDS_PER_PASS, GL_RESOURCES, Node, Ref, RenderNodes, task_arg
from archive.graph.plan import GROUP, RenderPlan, band_groups
from archive.graph.tasks import (VALUES_POOL, assemble_write_task, blank_write_task, gate_task, layout_task,
                                 overview_task, write_layers_task, write_saturated_task)

__all__ = ["HELD_VALUES_BYTES", "RenderGraph", "TASK_VALUES_BYTES", "build_render_graph", "live_renders", "render_order",
           "renders_held", "shared_lookup_bytes", "task_group_size", "with_task_groups"]

#: Directions (degrees apart) along which :func:`render_order` tries sweeping the cubes.
SWEEP_STEP = 15
#: Most (tile, cube) pairs :func:`live_renders` looks at (beyond: an absurd grid, every render held).
MAX_TILE_TOUCHES = 1 << 18
#: Rendered values one render task may hold, bytes (window px x bands x 4 B): 32 bands of a 1.4 Mpx
#: cube window. Larger groups mean fewer GL set-ups and reads per band; smaller ones less memory.
TASK_VALUES_BYTES = 192 * 1024**2
#: Most bands per render task (and per assembly / writer task).
MAX_GROUP = 64
#: Renders that may run ahead of the writers consuming earlier renders (in (group, capture)
#: order): bounds the renders held in memory whatever the flight length and GPU speed. 6, not 3:
#: the next band group's first renders then wait for the writers of the group's first strips only,
#: not for most of them, so renders and writes overlap (held-out flight to ENVI: writers alone in
#: 13-26 % of the task stream instead of 34-45 %; bench/RESULTS.md, issue 37). At most the plan's
#: cubes: one band group ahead.
RENDERS_AHEAD = 6
#: Lookups that band groups may share (held packed: 8 B per cube window pixel / LOOKUP_PACKING);
#: beyond, one per group and cube.
LOOKUP_BYTES = 256 * 1024**2
#: What packing (:class:`~archive.graph.tasks.PackedLookup`) at least gains on a lookup (measured:
#: ~20x on the paper flight's cube windows).
LOOKUP_PACKING = 8
#: Rendered values all renders of a band group held at once may take, bytes: the renders the
#: writers still wait for (:func:`live_renders`, which grows with the passes' length: a tile holds
#: the renders of every pass that crosses it) plus RENDERS_AHEAD, and the lookups the band groups
#: share (held all run: they grow with the cubes). Band groups shrink as passes get longer and
#: cubes more numerous, so that memory stays flat (issue 20).
HELD_VALUES_BYTES = 640 * 1024**2


def _touching(plan: RenderPlan, tile: tuple[int, int]) -> list[list[int]] | None:
    """For each output tile (``tile`` px) some cube touches, the jobs touching it (capture order),
    from each job's box (not from every tile of the grid); None past MAX_TILE_TOUCHES (an absurd
    grid, refused later by the size check)."""
    th, tw = tile
    tiles: dict[tuple[int, int], list[int]] = {}
    pairs = 0
    for j, job in enumerate(plan.jobs):
        row0, col0, height, width = job.box
        if height <= 0 or width <= 0:
            continue
        rows = range(row0 // th, (row0 + height - 1) // th + 1)
        cols = range(col0 // tw, (col0 + width - 1) // tw + 1)
        pairs += len(rows) * len(cols)
        if pairs > MAX_TILE_TOUCHES:
            return None
        for r in rows:
            for c in cols:
                tiles.setdefault((r, c), []).append(j)
    return list(tiles.values())


def live_renders(plan: RenderPlan, tile: tuple[int, int] = (CHUNK, CHUNK), order: Sequence[int] | None = None) -> int:
    """Most renders of one band group alive at once when the cubes are rendered in ``order`` (job
    indices; default :func:`render_order`): a render lives until the render of the last cube (in
    that order) touching any output tile (``tile`` px, height x width) it touches (that tile's
    writer needs them all). Every cube's, on a grid of more tiles than MAX_TILE_TOUCHES."""
    touching = _touching(plan, tile)
    if touching is None:
        return max(1, len(plan.jobs))
    if order is None:
        return _fewest(plan, touching)[1]
    return _live(touching, len(plan.jobs), order)


def _live(touching: list[list[int]], njobs: int, order: Sequence[int]) -> int:
    """:func:`live_renders` from the tiles' touching jobs (:func:`_touching`)."""
    position = {j: k for k, j in enumerate(order)}
    last = list(range(njobs))   # by position in the order
    for cubes in touching:
        at = [position[j] for j in cubes]
        end = max(at)
        for k in at:
            last[k] = max(last[k], end)
    ends = sorted(last)   # render k is alive from k to last[k]: started (0..k) minus ended before k
    return max([1] + [(k + 1) - bisect.bisect_left(ends, k) for k in range(njobs)])


def render_order(plan: RenderPlan, tile: tuple[int, int] = (CHUNK, CHUNK)) -> tuple[int, ...]:
    """The order in which the graph renders the cubes of a band group (job indices): the one that
    keeps the fewest renders alive (:func:`live_renders`) among capture order and the cubes sorted
    by their window's centre along directions every 15 degrees. A tile's writer needs every cube
    touching it, so in capture order the renders of a lawn mower's first pass wait for the passes
    that come back over their tiles (a whole pass: memory grows with the flight's length); swept
    along the passes, a tile is complete once the sweep has crossed it in every pass, whatever the
    length. The writers still mosaic in capture order: the order changes no value."""
    touching = _touching(plan, tile)
    if touching is None:
        return tuple(range(len(plan.jobs)))
    return _fewest(plan, touching)[0]


def _fewest(plan: RenderPlan, touching: list[list[int]]) -> tuple[tuple[int, ...], int]:
    """(order, renders alive) of :func:`render_order`, from the tiles' touching jobs (:func:`_touching`)."""
    capture = tuple(range(len(plan.jobs)))
    centres = np.array([(job.box[0] + job.box[2] / 2, job.box[1] + job.box[3] / 2) for job in plan.jobs])
    best, fewest = capture, _live(touching, len(capture), capture)
    for degrees in range(0, 180, SWEEP_STEP):
        angle = np.radians(degrees)
        along = centres @ np.array([np.cos(angle), np.sin(angle)]) if len(capture) else np.zeros(0)
        order = tuple(int(j) for j in np.argsort(along, kind="stable"))
        live = _live(touching, len(capture), order)
        if live < fewest:
            best, fewest = order, live
    return best, fewest


def renders_held(plan: RenderPlan) -> int:
    """Renders (each of one band group, its cube window's values) the graph holds at once for
    ``plan``, as :func:`task_group_size` counts them: :func:`live_renders` + RENDERS_AHEAD, but no
    more than the plan's cubes (a band group renders each cube once; measured on the 8-cube, 4-pass
    flight: 8.2 renders' bytes at most, against 10 counted without that bound), plus the free
    buffers of the values pool (:class:`~archive.graph.tasks.ValuesPool`). Without the bound short
    flights got smaller band groups than long ones and held less: memory grew with the flight
    (issue 20)."""
    return min(live_renders(plan) + RENDERS_AHEAD, len(plan.jobs)) + VALUES_POOL.keep


def shared_lookup_bytes(plan: RenderPlan) -> int:
    """Bytes the cubes' lookups take when the band groups share them (8 B per window pixel, packed
    LOOKUP_PACKING-fold: an upper bound), or 0 when they would exceed LOOKUP_BYTES (each group then
    makes its own, held like its renders). Shared lookups are held from the first group to the
    last: memory that grows with the number of cubes."""
    held = _lookup_bytes(plan)
    return held if held <= LOOKUP_BYTES else 0


def _lookup_bytes(plan: RenderPlan) -> int:
    """Bytes of all the plan's lookups, packed (an upper bound: 8 B per window pixel / LOOKUP_PACKING)."""
    return 8 * sum(job.window.width * job.window.height for job in plan.jobs) // LOOKUP_PACKING


def task_group_size(plan: RenderPlan, budget: int = TASK_VALUES_BYTES) -> int:
    """Bands per render task for ``plan``: as many as fit the bytes of values one render may hold
    for the largest cube window (whole 8-band GL passes from 16 bands on; at most MAX_GROUP, never
    fewer than GROUP = 4); a render may hold ``budget`` bytes, and all renders held at once
    (:func:`renders_held`) HELD_VALUES_BYTES less the shared lookups (:func:`shared_lookup_bytes`,
    held all run; at most half of it), scaled down with ``budget`` (small workers get a tenth of
    their memory as ``budget``, :func:`archive.run.cluster.task_budget`: the renders they hold at once
    shrink in proportion). Any size, not multiples of 4 only, so that the renders and lookups held
    stay near HELD_VALUES_BYTES (flat) whatever the flight's length."""
    biggest = max((job.window.width * job.window.height for job in plan.jobs), default=1)
    held = renders_held(plan)
    held_bytes = HELD_VALUES_BYTES * min(1.0, budget / TASK_VALUES_BYTES)
    held_bytes = max(held_bytes - shared_lookup_bytes(plan), held_bytes / 2)
    fit = int(min(budget, held_bytes // held)) // (4 * max(biggest, 1))
    if fit >= 2 * BANDS_PER_PASS:   # whole GL passes where that loses little
        fit = fit // BANDS_PER_PASS * BANDS_PER_PASS
    return min(MAX_GROUP, max(GROUP, fit))


def with_task_groups(plan: RenderPlan, budget: int = TASK_VALUES_BYTES) -> RenderPlan:
    """``plan`` with its band groups resized by :func:`task_group_size` (the groups the graph uses)."""
    return dataclasses.replace(plan, groups=band_groups(plan.nbands, task_group_size(plan, budget)))


@dataclasses.dataclass(frozen=True)
class RenderGraph:
    """The built graph: ``writes`` are the tasks the command waits for (values writers, blank-tile
    writers, overview tasks, saturation writers), all sharing one graph; ``assemblies`` counts the
    values writers (one per touched tile and band group, each assembling its tile)."""

    writes: tuple[Delayed, ...]
    renders: int
    assemblies: int

    def __len__(self) -> int:
        return len(self.writes)


class _TaskGraph:
    """The render graph as one low-level task dict, its tasks' priorities and its GL keys.

    One ``dask.delayed`` call per task would give every task its own HighLevelGraph naming all the
    layers below it: the command's memory would grow with the square of the tasks (measured: 398 MB
    at 2,241 tasks, 40 cubes of 32 bands; DESIGN.md section 8). Here the tasks go into one dict and
    the writes share one graph of one layer, annotated per key (priority; GPU resources of the GL
    tasks) as ``dask.annotate`` would."""

    def __init__(self) -> None:
        self.tasks: dict[str, GraphNode] = {}
        self.priority: dict[str, int] = {}
        self.resources: dict[str, dict] = {}   # the GL tasks' GL_RESOURCES

    def data(self, key: str, value: object) -> str:
        self.tasks[key] = DataNode(key, value)
        return key

    def add(self, key: str, func, *args, priority: int, gl: bool = False, **kwargs) -> str:
        """Task ``key`` calling ``func(*args, **kwargs)``, where a :class:`Ref` (also in a list) is
        another task's result; returns ``key``."""
        self.tasks[key] = Task(key, func, *map(task_arg, args), **{k: task_arg(v) for k, v in kwargs.items()})
        self.priority[key] = priority
        if gl:
            self.resources[key] = dict(GL_RESOURCES)
        return key

    def node(self, node: Node, priority: int) -> str:
        return self.add(node.key, node.func, *node.args, priority=priority, gl=node.gl, **node.kwargs)

    def delayed(self, keys: Sequence[str]) -> tuple[Delayed, ...]:
        """``keys`` as Delayed objects sharing this graph."""
        name = f"render-graph-{tokenize(sorted(self.tasks))}"
        layer = MaterializedLayer(self.tasks, annotations={"priority": self.priority.get,
                                                           "resources": self.resources.get})
        graph = HighLevelGraph({name: layer}, {name: set()})
        return tuple(Delayed(key, graph, layer=name) for key in keys)


def _ref(key: str | None) -> Ref | None:
    return None if key is None else Ref(key)


def build_render_graph(plan: RenderPlan, sources: Sequence, sink, *, mode: str,
                       overlap: OverlapRule, mesh_spec: MeshSpec | None = None, layers=None, layers_sink=None) -> RenderGraph:
    """Dask graph rendering ``plan`` from ``sources`` into ``sink`` (:class:`~archive.outputs.zarr.MosaicStore`,
    :class:`~archive.outputs.envi.EnviSink` or :class:`~archive.outputs.cog.CogSink`).

    mesh_spec: the :class:`~archive.params.MeshSpec` of a plan that holds its meshes (only for keys;
    default the plan's :attr:`~archive.graph.plan.RenderPlan.mesh_spec`).
    overlap: the rule mosaicking the cubes of a tile (:mod:`archive.overlap`).
    layers: a :class:`~archive.geometry.provenance.ProvenanceSpec` when per-cube provenance layers are needed:
    by a rule that compares one (its :attr:`~archive.overlap.OverlapRule.key`) and by ``layers_sink``, the sink the provenance layers
    are written into (one band per layer of ``layers.names``; ``None``: not written). Per cube, one
    layers task (CPU) computes them from the cube's lookup; per output tile one task assembles and
    writes them, in band group 0.
    """
    key_layer = overlap.key   # the layer the overlap rule compares, if any
    if (key_layer is not None or layers_sink is not None) and layers is None:
        raise ValueError(f"the '{overlap.name}' rule and provenance layers need a ProvenanceSpec")
    if key_layer is not None and key_layer not in layers.names:
        raise ValueError(f"the '{overlap.name}' rule needs the {key_layer} layer")
    nodes = RenderNodes(plan, sources, mode=mode, mesh_spec=mesh_spec, layers=layers)
    graph = _TaskGraph()
    for key, value in nodes.data().items():
        graph.data(key, value)

    # Priorities (higher runs first) finish one band group before starting the next, and write a
    # tile as soon as its renders exist, its overviews as soon as their tiles are written.
    ngroups, njobs = len(plan.groups), len(plan.jobs)

    def priority(g: int, stage: int, j: int = 0) -> int:
        """Group first, then stage (renders 0 < writers 1 < overviews 2), then render order."""
        return (3 * (ngroups - g) + stage) * (njobs + 1) + (njobs - j)

    # The order the cubes are rendered in (fewest renders held; the writers still mosaic in capture
    # order), the tiles to write, and for each render the tiles it completes (their last touching
    # cube in that order).
    tile_size = getattr(sink, "tile_size", (CHUNK, CHUNK))
    order = render_order(plan, tile_size)
    position = {j: s for s, j in enumerate(order)}
    for j, node in enumerate(nodes.meshes()):   # meshes built on the workers, ahead of their lookups
        graph.node(node, priority(0, 0, position[j]))
    tiles = []
    for row0, col0, tile_grid in plan.grid.tiles(tile_size):
        tile = (row0, col0, tile_grid.height, tile_grid.width)
        touching = [j for j, job in enumerate(plan.jobs) if boxes_intersect(tile, job.box)]
        if touching or sink.blank_tiles:
            tiles.append((tile, touching))
    completes: dict[int, list[int]] = {}  # position in the order -> tiles whose last touching render it is
    for t, (_, touching) in enumerate(tiles):
        if touching:
            completes.setdefault(max(position[j] for j in touching), []).append(t)

    # One lookup (GL pass 1) per cube, shared by its band groups while all of them fit
    # LOOKUP_BYTES (8 B per window pixel, packed); beyond that (long flights and several groups) each group
    # makes its own, so that held lookups do not grow with the flight either.
    shared = len(plan.groups) == 1 or _lookup_bytes(plan) <= LOOKUP_BYTES
    lookups: dict[tuple[int, int], str] = {}
    count = layers_sink is not None and "overlap_count" in layers.names

    def lookup(j: int, g: int, gate: str | None) -> str:
        if shared and (j, 0) in lookups:
            return lookups[j, 0]
        node = nodes.lookup(j, count=count and (shared or g == 0),   # layers come from group 0's lookups
                            group=None if shared else g, after=gate)
        lookups[j, 0 if shared else g] = graph.node(node, priority(g, 0, position[j]))
        return lookups[j, 0 if shared else g]

    # Provenance layers (and the overlap rule's key): per cube from group 0's lookup, on any thread.
    cube_layers: dict[int, str] = {}
    keys: dict[int, str] = {}
    layer_writers: dict[int, str] = {}   # tile number -> provenance writer

    def layers_of(j: int, lk: str) -> str:
        if j not in cube_layers:
            cube_layers[j] = graph.node(nodes.cube_layers(j, lk), priority(0, 0, position[j]))
            if key_layer is not None:
                keys[j] = graph.node(nodes.layer_pick(cube_layers[j], key_layer), priority(0, 0, position[j]))
        return cube_layers[j]

    # Renders in (group, render order) order. Backpressure: render number s (and its lookup) waits for
    # the writers that render s - RENDERS_AHEAD completed (a token of them), so renders never run
    # further ahead of the writers than that, however long the flight and however fast the GPU; and
    # never more than one band group ahead (a flight of fewer cubes than RENDERS_AHEAD: 6 renders of
    # a 2-cube flight were 3 band groups, and a 500 MB worker was restarted).
    ahead = max(1, min(RENDERS_AHEAD, len(order)))
    renders: dict[tuple[int, int], str] = {}
    writers: dict[tuple[int, int], str] = {}  # (tile number, group) -> values writer
    gates: list[str | None] = []
    masks: dict[int, str] = {}  # tile number -> saturation so far (Zarr: a chain per tile)
    assemblies = 0
    for g, (b0, b1) in enumerate(plan.groups):
        for s, j in enumerate(order):
            # the latest writers' token at or before s - ahead: each render waits at least
            # for what the render before it waited for
            gate = next((t for t in reversed(gates[:max(0, len(gates) - ahead + 1)]) if t is not None),
                        None)
            lk = lookup(j, g, gate)
            if layers is not None and g == 0:
                layers_of(j, lk)
            renders[j, g] = graph.node(nodes.render(j, g, lk, after=gate), priority(g, 0, s))
            done = []
            for t in completes.get(s, []):
                tile, touching = tiles[t]
                boxes = tuple(plan.jobs[i].box for i in touching)
                parts = [renders[i, g] for i in touching]
                mask = masks.get(t) if sink.saturation else None
                tile_keys = [keys[i] for i in touching] if key_layer is not None else None
                akey = tokenize(overlap, tile, b1 - b0, boxes, parts, tile_keys)
                wkey = f"write-{tokenize(sink, b0, tile, akey, mask)}"
                writers[t, g] = graph.add(wkey, assemble_write_task, sink, overlap, b0, tile, b1 - b0, boxes,
                                          _ref(mask), *map(Ref, parts), priority=priority(g, 1, s),
                                          keys=None if tile_keys is None else list(map(Ref, tile_keys)))
                assemblies += 1
                if layers_sink is not None and g == 0:
                    stacks = [cube_layers[i] for i in touching]
                    lwkey = f"write-layers-{tokenize(layers_sink, tile, overlap, boxes, stacks)}"
                    layer_writers[t] = graph.add(lwkey, write_layers_task, layers_sink, overlap, tile, layers.names,
                                                 boxes, *map(Ref, stacks), priority=priority(g, 1, s))
                    done.append(layer_writers[t])
                if sink.saturation:
                    masks[t] = writers[t, g]
                done.append(writers[t, g])
            gate = None
            if done:
                gate = graph.add(f"gate-{tokenize(done)}", gate_task, *map(Ref, done), priority=priority(g, 1, s))
            gates.append(gate)

    writes: list[str] = [writers[t, g] for t in range(len(tiles)) for g in range(len(plan.groups))
                         if (t, g) in writers]
    firsts: dict[tuple[int, int, int], str] = {}  # (tile row, tile col, group) -> writer (COG)
    for t, (tile, touching) in enumerate(tiles):
        for g, (b0, b1) in enumerate(plan.groups):
            if not touching:
                key = f"blank-{tokenize(sink, b0, b1, tile)}"
                writers[t, g] = graph.add(key, blank_write_task, sink, b0, tile, b1 - b0, priority=priority(g, 1))
                writes.append(writers[t, g])
            firsts[tile[0] // CHUNK, tile[1] // CHUNK, g] = writers[t, g]
    if layers_sink is not None:   # provenance: blank tiles, then overviews, as for the values
        layer_firsts: dict[tuple[int, int, int], str] = {}
        for t, (tile, touching) in enumerate(tiles):
            if not touching:
                key = f"blank-layers-{tokenize(layers_sink, tile)}"
                layer_writers[t] = graph.add(key, blank_write_task, layers_sink, 0, tile, len(layers.names),
                                             priority=priority(0, 1))
            layer_firsts[tile[0] // CHUNK, tile[1] // CHUNK, 0] = layer_writers[t]
        writes += layer_writers.values()
        writes += _overview_tasks(graph, layers_sink, [(0, len(layers.names))], layer_firsts, priority)
        writes += _layout_tasks(graph, layers_sink, [(0, len(layers.names))],
                                {(t, 0): w for t, w in layer_writers.items()}, priority)
    saturation: list[str] = []
    for t, mask in masks.items():
        tile = tiles[t][0]
        skey = f"saturated-{tokenize(sink, tile, mask)}"
        saturation.append(graph.add(skey, write_saturated_task, sink, tile, Ref(mask), priority=priority(ngroups, 1)))
    writes += _overview_tasks(graph, sink, plan.groups, firsts, priority)
    writes += _layout_tasks(graph, sink, plan.groups, writers, priority)
    return RenderGraph(graph.delayed(writes + saturation), len(renders), assemblies)


def _layout_tasks(graph: _TaskGraph, sink, groups, writers: dict, priority) -> list[str]:
    """For a sink that lays its output out as the render goes (COG: the full resolution in file
    order), one task per band group once the group's writers ran, each after the one before it."""
    if not hasattr(sink, "lay_out"):
        return []
    tasks: list[str] = []
    start: str | int = 0
    for g, (b0, b1) in enumerate(groups):
        written = [w for (t, wg), w in writers.items() if wg == g]
        key = f"layout-{tokenize(sink, b0, b1, start, written)}"
        start = graph.add(key, layout_task, sink, b0, b1 - b0, Ref(start) if isinstance(start, str) else start,
                          *map(Ref, written), priority=priority(g, 2))
        tasks.append(start)
    return tasks


def _overview_tasks(graph: _TaskGraph, sink, groups, firsts: dict, priority) -> list[str]:
    """Overview levels 2.. of a COG sink, per band group: tile (r, c) of level L from the tasks that
    returned tiles (2r.., 2c..) of level L - 1 (level 1: the writers, keyed by output tile)."""
    tasks: list[str] = []
    below = firsts
    for level in range(2, sink.overview_levels + 1):
        rows, cols = sink.tiles(level)
        current: dict[tuple[int, int, int], str] = {}
        for g, (b0, b1) in enumerate(groups):
            for r in range(rows):
                for c in range(cols):
                    kids = [None if k is None else below.get((*k, g)) for k in sink.children(level, r, c)]
                    key = f"overview-{tokenize(sink, level, r, c, b0, kids)}"
                    current[r, c, g] = graph.add(key, overview_task, sink, level, r, c, b0, b1 - b0,
                                                 *map(_ref, kids), priority=priority(g, 2))
        tasks += current.values()
        below = current
    return tasks
