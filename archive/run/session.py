"""The session of one run (:class:`Session`: the cluster's lifecycle), the job of one output
(:class:`Job`) and the typed summaries a run returns; see :mod:`archive.run.runner`."""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TypedDict

from archive.run import cluster as clusters
from archive.run.cluster import ClusterClose, closed_or_warned, flight_slots, start_cluster, task_budget, wait_for_writers

__all__ = ["IN_PROCESS", "BatchSummary", "Job", "RenderSummary", "Session", "StackSummary", "Waves", "in_process",
           "render_failure", "render_summary", "task_failure"]

#: The ``scheduler`` of a run in this process: one worker's threads, no worker process to spawn (a
#: small job: ``archive render`` picks it below :data:`archive.run.command.SMALL_JOB_BYTES` of DN).
IN_PROCESS = "in-process"


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
    ``threads`` threads); ``what``: what the run writes, for the warning of a close that fails;
    ``connect``: how to start or reach the cluster instead of
    :func:`archive.run.cluster.start_cluster` (an ingest's workers need no GPU)."""

    def __init__(self, scheduler, workers: int | None, threads: int | None, say: Callable[[str], None], *,
                 what: str, command: str = "archive render", connect: Callable | None = None):
        self._args = (scheduler, workers, say, threads)
        self._connect = connect   # (scheduler, workers, say, threads) -> (client, cluster): not a render's
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

        scheduler, _, _, threads = self._args
        if scheduler == IN_PROCESS:
            self.client, self.cluster = in_process(threads)
        else:
            self.client, self.cluster = (self._connect or start_cluster)(*self._args)
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


class Waves:
    """The outputs of a run in the scheduler at once, and their tasks' completions (one place for the
    batch's and the stack's waves).

    ``wave``: outputs at once (default :meth:`Session.slots`, counted again every 5 s: workers come
    and go). An owner (a batch's flight, a stack's time step) enters with :meth:`submit` (its
    ``futures`` and ``left`` set), :meth:`next_done` gives each of its finished futures in turn
    (released, and counted off its ``left`` when it finished well), :meth:`leave` takes it out.
    The completions are followed on the session's client's event loop: ``as_completed()`` alone
    follows the futures on the default client's loop, another Client of the process (a notebook's,
    the bench's), where they arrive late (measured: 20 flights in 21 s instead of 4.7 s)."""

    def __init__(self, session: Session, wave: int | None = None):
        from distributed import as_completed

        self.session, self._fixed = session, wave
        self.slots = wave or session.slots()
        self.largest = self.slots   # the largest wave of the run
        self._counted = time.monotonic()
        self._completed = as_completed(loop=session.client.loop)
        self._owners: dict[str, object] = {}
        self.active: list = []
        self.peak = 0   # futures in the scheduler at once, at most
        self.done = self.submitted = 0

    def has_room(self) -> bool:
        """Whether another output may enter now."""
        if self._fixed is None and time.monotonic() - self._counted > 5.0:
            self.slots, self._counted = self.session.slots(), time.monotonic()
            self.largest = max(self.largest, self.slots)
        return len(self.active) < self.slots

    def submit(self, owner, writes: Sequence) -> list:
        """Compute ``writes`` (a graph's write keys' objects) for ``owner``: its ``futures`` and
        ``left`` set, it is active. Returns the futures ([] for nothing to compute)."""
        futures = list(self.session.client.compute(list(writes))) if len(writes) else []
        owner.futures, owner.left = futures, len(futures)
        self.active.append(owner)
        self.submitted += len(futures)
        for future in futures:
            self._owners[future.key] = owner
            self._completed.add(future)
        self.peak = max(self.peak, sum(len(o.futures) for o in self.active))
        return futures

    def next_done(self) -> tuple[object, str, BaseException | None]:
        """Wait for a future: (its owner, or None when it left already; 'finished', 'error' or
        'cancelled'; the task's exception for 'error'). Released; a finished one counted off the
        owner's ``left``."""
        future = next(self._completed)
        owner = self._owners.pop(future.key, None)
        status = future.status
        if status not in ("error", "cancelled"):
            # it was yielded because it finished: "pending"/"lost" now only says that its worker left
            # since (a cancelled Slurm job), taking the task's small result with it; the write was done
            status = "finished"
        exc = future.exception() if status == "error" else None
        future.release()
        if owner is not None and status == "finished":
            owner.left -= 1
            self.done += 1
        return owner, status, exc

    def leave(self, owner, give_up: bool = False, wait: bool = True) -> None:
        """``owner`` is out of the scheduler; ``give_up``: its unfinished tasks cancelled
        (:meth:`Session.abandon`, ``wait`` as there)."""
        if give_up:
            self.session.abandon(owner.futures, wait=wait)
        for future in owner.futures:
            self._owners.pop(future.key, None)
        if owner in self.active:
            self.active.remove(owner)


def in_process(threads: int | None = None):
    """(client, cluster): a Dask cluster in this process, one worker of ``threads`` threads (default
    the cores, at least 2) holding the GPU resource as a local cluster's workers do; its GL context
    made ahead on a thread (:func:`archive.run.cluster.warm_up`). Starting it spawns no process
    (bench/bench_small.py measures the difference)."""
    import logging
    import os
    import threading

    from distributed import Client, LocalCluster

    from archive.run.cluster import GL_SLOTS, positive, warm_up

    threads = positive(threads, "--threads", "threads per worker") or max(2, os.cpu_count() or 1)
    cluster = LocalCluster(n_workers=1, threads_per_worker=threads, processes=False, resources={"GPU": GL_SLOTS},
                           dashboard_address=":0", silence_logs=logging.CRITICAL)
    client = Client(cluster)
    threading.Thread(target=warm_up, name="archive-warm-up", daemon=True).start()
    return client, cluster


def task_failure(exc: BaseException, doing: str, death_advice: str, prefix: str = "", known: tuple = ()) -> str:
    """Why a task of an output or flight failed, in the words that follow its name: an ArchiveError's
    (or a ``known`` type's) own text, a dead worker's likely causes (``doing``: "rendering"...;
    ``death_advice``: what to try), else ``prefix`` and the exception's type and text."""
    from distributed import KilledWorker

    from archive.errors import ArchiveError

    if isinstance(exc, (ArchiveError, *known)):
        return str(exc)
    if isinstance(exc, KilledWorker):
        return f"a Dask worker died while {doing} it ({exc}); {death_advice}"
    return f"{prefix}{type(exc).__name__}: {exc}"


def render_failure(exc: BaseException) -> str:
    """Why a render task of an output failed, in the words a batch's line and a stack's error give
    after the output's name (:func:`task_failure`)."""
    return task_failure(exc, "rendering", "it may have run out of memory or crashed in OpenGL: try a larger --gsd "
                        "or fewer --wavelengths", "a render task failed: ")
