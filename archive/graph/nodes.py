"""The nodes of a render and their keys, written once (builds graphs, never computes them).

Both graphs of the package build their sources, meshes, lookups, renders, per-cube provenance
layers and overlap-rule keys here: the write graph (:mod:`archive.graph.build`, one task dict)
and the lazy arrays (:mod:`archive.graph.lazy`, a ``HighLevelGraph`` of task specs). So the same
request gives the same lookup and render keys in both by construction.

A :class:`Node` is a key, a task body (:mod:`archive.graph.tasks`) and its arguments, where a
:class:`Ref` stands for another node's result; ``gl`` marks the nodes that draw (annotated
``resources={"GPU": 1}``, run on the worker's GL thread). Builders turn nodes into their
collection's tasks. Keys are ``<kind>-<dask.base.tokenize(inputs)>``: the same inputs give the same
keys, run after run.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

from dask.base import tokenize

from archive.graph.plan import RenderPlan, mesh_task
from archive.graph.tasks import layers_task, lookup_task, pick_task, render_task

__all__ = ["BANDS_PER_PASS", "GL_RESOURCES", "Node", "Ref", "RenderNodes", "task_arg"]

#: Bands per GL pass in render tasks (8 = the renderer's most per pass).
BANDS_PER_PASS = 8
#: Annotation of the GL nodes (lookups and renders).
GL_RESOURCES = {"GPU": 1}


@dataclass(frozen=True)
class Ref:
    """The result of the node ``key``, as an argument of another node."""

    key: str


def task_arg(arg):
    """``arg`` as a task-spec argument: a :class:`Ref` as a reference to its node's result, a list
    holding Refs as a list of task-spec arguments, anything else as it is."""
    from dask.task_spec import List, TaskRef

    if isinstance(arg, Ref):
        return TaskRef(arg.key)
    if isinstance(arg, list) and any(isinstance(a, Ref) for a in arg):
        return List(*map(task_arg, arg))
    return arg


@dataclass(frozen=True)
class Node:
    """One task: ``key``, its body ``func`` called with ``args`` (:class:`Ref` for other nodes'
    results) and ``kwargs``; ``gl``: it draws (GPU resource)."""

    key: str
    func: Callable
    args: tuple = ()
    kwargs: dict = field(default_factory=dict)
    gl: bool = False

    @property
    def refs(self) -> list[str]:
        """Keys of the nodes this one takes."""
        return [a.key for a in self.args if isinstance(a, Ref)]


class RenderNodes:
    """The nodes of rendering ``plan`` from ``sources``: what every graph builder asks for.

    mode: radiometric mode of the renders; mesh_spec: the :class:`~archive.params.MeshSpec` the
    meshes were built from (only for keys; default the plan's :attr:`~archive.graph.plan.RenderPlan.mesh_spec`,
    which a plan holding its meshes lacks); layers: the :class:`~archive.geometry.provenance.ProvenanceSpec`
    of the per-cube layers (provenance, or the layer the overlap rule compares), or None.
    """

    def __init__(self, plan: RenderPlan, sources: Sequence, *, mode: str, mesh_spec: object = None, layers=None):
        self.plan, self.sources, self.mode, self.layers = plan, list(sources), mode, layers
        self.mesh_spec = plan.mesh_spec if mesh_spec is None else mesh_spec
        # every source's __dask_tokenize__ says what its renders depend on (files or stored content,
        # parameters), never its pixels
        self.tokens = [tokenize(s) for s in self.sources]

    # ---- data: the sources (values put into the graph as they are) and the meshes ------------
    def source_key(self, i: int) -> str:
        return f"source-{self.tokens[i]}"

    def data(self) -> dict[str, object]:
        """key -> value of every source of the plan, and of every cube mesh when the plan holds them
        (no :attr:`~archive.graph.plan.RenderPlan.mesh_spec`; else :meth:`meshes` builds them)."""
        out: dict[str, object] = {self.source_key(i): s for i, s in enumerate(self.sources)}
        if self.plan.mesh_spec is None:
            out.update({self.mesh_key(j): job.mesh for j, job in enumerate(self.plan.jobs)})
        return out

    def mesh_key(self, j: int) -> str:
        job = self.plan.jobs[j]
        return f"mesh-{tokenize(self.tokens[job.source], job.cube, self.mesh_spec)}"

    def meshes(self) -> list[Node]:
        """One task per cube job building its mesh on a worker (:func:`~archive.graph.plan.mesh_task`,
        any thread: CPU only) from the source and the plan's small ``mesh_spec`` (a few hundred
        bytes in the graph instead of the mesh); none when the plan holds its meshes."""
        spec = self.plan.mesh_spec
        if spec is None:
            return []
        return [Node(self.mesh_key(j), mesh_task, (Ref(self.source_key(job.source)), job.cube, spec))
                for j, job in enumerate(self.plan.jobs)]

    # ---- tasks ---------------------------------------------------------------------------------
    def lookup(self, j: int, *, count: bool = False, group: int | None = None, after: str | None = None) -> Node:
        """GL pass 1 of cube job ``j``: which (line, sample) each pixel of its window sees (with
        ``count`` also how many mesh layers cover it). ``group``: a band group's own lookup (when the
        groups cannot share one); ``after``: the key of a task it waits for (not in its key)."""
        job = self.plan.jobs[j]
        samples = int(self.sources[job.source].cubes[job.cube].samples)
        key = f"lookup-{tokenize(self.mesh_key(j), job.window, samples, count, *([] if group is None else [group]))}"
        return Node(key, lookup_task, (Ref(self.mesh_key(j)), job.window, samples, *_after(after)),
                    {"count": count}, gl=True)

    def render(self, j: int, g: int, lookup: str, *, after: str | None = None) -> Node:
        """The bands of band group ``g`` of cube job ``j`` drawn through the lookup ``lookup``
        (``BANDS_PER_PASS`` bands per GL pass); ``after`` as for :meth:`lookup`."""
        job = self.plan.jobs[j]
        b0, b1 = self.plan.groups[g]
        bands = self.plan.bands[job.source][b0:b1]
        key = f"render-{tokenize(self.tokens[job.source], job.cube, bands, lookup, self.mode, BANDS_PER_PASS)}"
        return Node(key, render_task, (Ref(self.source_key(job.source)), job.cube, bands, Ref(lookup), self.mode,
                                       BANDS_PER_PASS, *_after(after)), gl=True)

    def cube_layers(self, j: int, lookup: str) -> Node:
        """The provenance layers ``layers.names`` of cube job ``j`` on its window (CPU, from its lookup)."""
        job = self.plan.jobs[j]
        ground = None if self.layers.dem is not None else self.layers.ground
        key = f"layers-{tokenize(self.tokens[job.source], job.cube, j, lookup, self.layers)}"
        return Node(key, layers_task, (Ref(self.source_key(job.source)), job.cube, j, Ref(lookup), self.layers,
                                       ground))

    def layer_pick(self, layers: str, name: str) -> Node:
        """Layer ``name`` of the cube layers ``layers``: what an overlap rule compares (its ``key``)."""
        return Node(f"key-{tokenize(layers)}", pick_task, (Ref(layers), self.layers.names.index(name)))


def _after(key: str | None) -> tuple:
    return () if key is None else (Ref(key),)
