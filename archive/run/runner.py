"""The one runner of every render: what kind of output a request makes, the job of one output, the
cluster's lifecycle, and the summaries a run returns.

Four kinds of output come out of one request (:class:`OutputKind`): one output at ``out``
(:func:`archive.run.pipeline.georectify`), one output per flight (:mod:`archive.run.batch`), one
output per tile of the output CRS (:mod:`archive.run.tiling`, tiles as the units of a batch) and a
time stack (:mod:`archive.run.stacks`). :func:`run` takes the kind as one value and hands the
request to its driver; each driver opens, plans and builds :class:`Job` s (an output with its plan,
sink and graph, and the options that render it alone again: :class:`archive.run.session.Job`), and
runs them inside a :class:`archive.run.session.Session`, which owns the cluster:

- started once per run (:func:`archive.run.cluster.start_cluster`: a local cluster, ``--scheduler``,
  Slurm jobs, or a start begun earlier by the command, :class:`archive.run.cluster.ClusterStart`);
- its task budget and wave size (:func:`archive.run.cluster.task_budget`, ``flight_slots``);
- tasks given up (a failed flight, a stack that stops) cancelled, and on a cluster that outlives the
  command (a shared scheduler, Slurm jobs) the writers waited for before temporaries are removed;
- closed when the run ends, in the background while the outputs are published when every task has
  ended (``Session.close_early``), and a close that fails is one warning line, never the run's
  error (:func:`archive.run.cluster.closed_or_warned`).

The summaries are typed (``RenderSummary``, ``BatchSummary``, ``StackSummary`` of :mod:`archive.run.session`):
dicts with the keys the CLI prints and the Python API returns.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

from archive.errors import InputError

__all__ = ["OutputKind", "run"]

Kind = Literal["single", "per_flight", "tiles", "stack"]


@dataclass(frozen=True)
class OutputKind:
    """What one request makes: ``single`` (one output at ``out``), ``per_flight`` (``out/<flight>.<format>``),
    ``tiles`` (``out/<EPSG>_<E0>_<N0>.<format>``, squares of ``tile_size`` metres) or ``stack`` (one
    Zarr store, time x band x y x x)."""

    name: Kind = "single"
    tile_size: float | None = None

    @classmethod
    def of(cls, *, per_flight: bool = False, stack: bool = False, tiles: float | None = None) -> OutputKind:
        """The kind the Python API's (and the CLI's) keywords ask for: ``stack`` first, then ``tiles``,
        then ``per_flight``, else one output."""
        if stack:
            return cls("stack")
        if tiles is not None:
            return cls("tiles", float(tiles))
        return cls("per_flight" if per_flight else "single")

    @property
    def many(self) -> bool:
        """Whether the request makes several outputs in a folder (a batch: per flight or per tile)."""
        return self.name in ("per_flight", "tiles")


def run(kind: OutputKind, request, out: str | os.PathLike, *, quicklook=None, format: str = "zarr",
        overwrite: bool = False, resume: bool = False, scheduler=None, workers: int | None = None,
        threads: int | None = None, quiet: bool = True, tell: Callable[[str], None] | None = None) -> dict:
    """Render ``request`` (:class:`archive.run.options.RenderOptions`) into ``out`` as ``kind`` says;
    returns the kind's summary. The checks that depend on the kind come first (a stack has no
    quicklook, only batches resume...)."""
    if kind.name == "stack":
        from archive.run.stacks import run_stack
        from archive.storage import is_url

        if quicklook:
            raise InputError("--quicklook", "a stack has no quicklook", "leave --quicklook out with --stack")
        if is_url(out):
            raise InputError(out, "a stack cannot be written into object storage yet",
                             "write it to a local or shared folder, then copy it")
        return run_stack(request, out, overwrite=overwrite, resume=resume, scheduler=scheduler, workers=workers,
                         threads=threads, quiet=quiet, tell=tell)
    if kind.many and quicklook:
        raise InputError("--quicklook", "only one quicklook per command",
                         "leave it out with --tiles" if kind.name == "tiles" else "add --mosaic, or leave it out")
    if kind.name == "tiles":
        from archive.run.tiling import run_tiles

        return run_tiles(request, out, kind.tile_size, format=format, overwrite=overwrite, resume=resume,
                         scheduler=scheduler, workers=workers, threads=threads, quiet=quiet, tell=tell)
    if kind.name == "per_flight":
        from archive.run.batch import run_batch

        return run_batch(request, out, format=format, overwrite=overwrite, resume=resume, scheduler=scheduler,
                         workers=workers, threads=threads, quiet=quiet, tell=tell)
    if resume:
        raise InputError("--resume", "resumes batch jobs (one output per flight)",
                         "leave it out: a single output is written whole or not at all")
    from archive.run.pipeline import georectify

    return georectify(request, out, quicklook=quicklook, overwrite=overwrite, scheduler=scheduler,
                      workers=workers, quiet=quiet, threads=threads)
