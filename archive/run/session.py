"""The session of one run (:class:`Session`: the cluster's lifecycle), the job of one output
(:class:`Job`) and the typed summaries a run returns; see :mod:`archive.run.runner`."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TypedDict

from archive.run import cluster as clusters
from archive.run.cluster import ClusterClose, closed_or_warned, flight_slots, start_cluster, task_budget, wait_for_writers

__all__ = ["BatchSummary", "Job", "RenderSummary", "Session", "StackSummary", "render_summary"]


@dataclass
class Job:
    """One output of a run: its :class:`archive.outputs.publish.Output`, plan
    (:class:`archive.run.pipeline.OutputPlan`), sink and graph (None once submitted), the options that
    render it alone again (its recipe), and the GL renderers the workers opened (for its Item)."""

    output: object
    planned: object
    sink: object
    options: object
    graph: object = None
    renderers: list | None = None


class RenderSummary(TypedDict):
    """One output's summary (:func:`archive.georectify`; each flight of a batch adds its entry's keys)."""

    out: str
    width: int
    height: int
    gsd: float
    epsg: int
    bands: int
    wavelengths: list | None
    mode: str
    cubes: int
    sources: int
    renders: int
    assemblies: int
    left_out: dict
    provenance: str | None
    seconds: float
    graph_seconds: float


class BatchSummary(TypedDict, total=False):
    """A batch's summary (per flight or per tile): ``outputs`` (per output: id, status, path, error,
    seconds and, when done, its :class:`RenderSummary` keys), counts, times, the report's path, the
    wave size and the most futures held at once (``tiles``: the tiles' count, tiled batches only)."""

    outputs: list[dict]
    done: int
    skipped: int
    failed: int
    seconds: float
    graph_seconds: float
    submit_seconds: float
    report: str
    wave: int
    peak_tasks: int
    renders: int
    tiles: int


class StackSummary(TypedDict):
    """A stack's summary: the flights it holds (time order), those added, skipped and left out, render
    tasks run, its grid and bands, and the wall time."""

    out: str
    flights: list[str]
    added: list[str]
    skipped: list[str]
    left_out: list[str]
    renders: int
    width: int
    height: int
    gsd: float
    epsg: int
    bands: int
    seconds: float


def render_summary(planned, output, graph, **times: float) -> dict:
    """The :class:`RenderSummary` keys of a planned and built output (``times``: seconds, graph_seconds
    when known)."""
    g, plan = planned.plan.grid, planned.plan
    return {"out": str(output.path), "width": g.width, "height": g.height, "gsd": g.gsd, "epsg": g.epsg,
            "bands": plan.nbands, "wavelengths": planned.wavelengths, "mode": planned.params.mode,
            "cubes": len(plan.jobs), "sources": len(planned.sources), "renders": graph.renders,
            "assemblies": graph.assemblies, **times, "left_out": dict(planned.left_out or {}),
            "provenance": None if not output.provenance else str(output.provenance_path or output.path)}


class Session:
    """The cluster of one run (see the module docstring); a context manager.

    ``scheduler``: an address, an :class:`archive.run.cluster.SlurmJobs`, a
    :class:`archive.run.cluster.ClusterStart` or None (a local cluster of ``workers`` processes of
    ``threads`` threads); ``what``: what the run writes, for the warning of a close that fails."""

    def __init__(self, scheduler, workers: int | None, threads: int | None, say: Callable[[str], None], *,
                 what: str, command: str = "archive render"):
        self._args = (scheduler, workers, say, threads)
        self.what, self.command = what, command
        self.client = self.cluster = None
        self._closing: ClusterClose | None = None
        self._budget: int | None = None
        self._abandoned = False
        self._outlives = False

    def __enter__(self) -> Session:
        return self.start()

    def start(self) -> Session:
        """Start (or take) the cluster; returns the session."""
        from distributed import LocalCluster

        self.client, self.cluster = start_cluster(*self._args)
        # a shared scheduler or Slurm jobs go on after the command: their tasks may still write
        self._outlives = not isinstance(self.cluster, LocalCluster)
        return self

    @property
    def shared(self) -> bool:
        """Whether the run's scheduler is someone else's (``--scheduler``): other clients' tasks too."""
        return self.cluster is None

    @property
    def budget(self) -> int:
        """The render task budget of the workers (:func:`archive.run.cluster.task_budget`), asked once."""
        if self._budget is None:
            self._budget = task_budget(self.client)
        return self._budget

    def slots(self) -> int:
        """Outputs in the scheduler at once (:func:`archive.run.cluster.flight_slots`), counted now:
        workers come and go."""
        return flight_slots(self.client, self.budget)

    def abandon(self, futures: Sequence, wait: bool = True) -> None:
        """Cancel the futures of an output given up; with ``wait``, on a cluster that outlives the
        command, return once no task of the client writes any more (so that the output's temporaries
        can be removed for good), else wait so when the session ends."""
        pending = [f for f in futures if not f.done()]
        if pending:
            self.client.cancel(pending, force=True)
        self._abandoned = True
        if wait and self._outlives and pending:
            wait_for_writers(self.client)

    def close_early(self) -> None:
        """Every task has ended: the workers stop in the background while the outputs are published."""
        self._closing = ClusterClose(self.client, self.cluster)
        self.client = self.cluster = None

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """End the session: on a cluster that outlives the command, wait for the writers of what was
        given up; close the client and the cluster (a failure is one warning line)."""
        client, cluster = self.client, self.cluster
        self.client = self.cluster = None
        if client is not None:
            if self._abandoned and self._outlives:
                wait_for_writers(client)
            closed_or_warned(lambda: clusters.close_client(client, cluster), self.command, self.what)
        if self._closing is not None:
            closed_or_warned(self._closing.join, self.command, self.what)
