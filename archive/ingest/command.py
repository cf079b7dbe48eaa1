"""``archive ingest``: raw flights into Zarr collections, cataloged.

Ingest checks every raw flight completely (headers, data sizes, times, navigation coverage,
calibration: :mod:`archive.ingest.prepare`) before touching the archive, then writes each into
``<id>.zarr.partial`` with a Dask graph of dn chunk tasks (:func:`archive.collection.write_chunks`,
a run of bands of one line chunk each) and per-file checksum tasks, records checksums and metadata,
writes the completion marker, renames the store to ``<id>.zarr`` and catalogs it. A rerun after a
kill resumes the partial store (chunks already written with the right values are kept); a rerun
after success is a no-op.

Where it runs: in this process (threads: ``threads``, default every core; every flight checked before
anything is written, one bad flight refuses the command), or on the distributed engine
(``scheduler``: an address, or :class:`archive.run.cluster.SlurmJobs`; or a local cluster of
``workers`` >= 2 processes): each flight a unit of its own, failing alone (:mod:`archive.ingest.cluster`).

One ingest per collection id at a time, across processes and hosts: each flight is written holding
its collection's lock (:func:`archive.collection.store_lock`, ``<id>.zarr.lock``); a second ingest of
the same flight says once that it waits, then finds the flight ingested. A full disk is one line
(the partial store stays, and the rerun resumes it).
"""

from __future__ import annotations

import argparse
import math
import os
import sys

from archive.catalog.root import ArchiveRoot
from archive.collection import StorePlan, finish_store, open_partial, publish, store_lock
from archive.errors import InputError
from archive.ingest.checks import (DiskFullError, already_ingested, disk_full_is_an_error, distinct_flights,
                                   open_archive_root)
from archive.ingest.flight import (IngestResult, PrepareArguments, begin_flight, finish_flight, flight_tasks,
                                   split_results, store_choices)
from archive.ingest.previews import add_previews
from archive.ingest.prepare import collection_id, jsonable, prepare_flight, sensor_name

__all__ = ["DiskFullError", "IngestResult", "begin_flight", "collection_id", "finish_flight", "flight_tasks", "ingest",
           "prepare_flight", "run", "sensor_name", "write_flight"]

_jsonable = jsonable   # the name tests/test_collection.py imports


class _Progress:
    """A tqdm bar advanced by a Dask scheduler callback."""

    def __init__(self, total: int, desc: str, enabled: bool):
        from dask.callbacks import Callback
        from tqdm import tqdm

        bar = tqdm(total=total, desc=desc, unit="task", disable=not enabled, file=sys.stderr)

        class _Cb(Callback):
            def _posttask(self, key, result, dsk, state, worker_id):
                bar.update(1)

        self.bar = bar
        self.callback = _Cb()


def write_flight(plan: StorePlan, root: ArchiveRoot, workers: int | None = None, progress: bool = True,
                 prewritten: str | os.PathLike | None = None) -> bool:
    """Write ``plan`` into ``root`` in this process (partial store, Dask graph on ``workers`` threads,
    default every core; checksums, marker, rename). ``prewritten``: a folder of chunks written ahead
    (:mod:`archive.ingest.ahead`; those that are exactly this plan's are moved in, not written again).
    Returns whether the store was resumed from an interrupted run."""
    import dask

    from archive.ingest.ahead import adopt

    partial = root.partial(plan.cid)
    resumed = open_partial(partial, plan)
    known_chunks, known_files = ({}, {}) if prewritten is None or root.is_url else adopt(prewritten, plan, partial)
    tasks = flight_tasks(plan, partial, resumed, frozenset(k for _, k in known_chunks), frozenset(known_files))
    jobs = [dask.delayed(function, pure=True)(*args, dask_key_name=key) for key, function, args in tasks]
    bar = _Progress(len(jobs), f"ingest {plan.cid}", progress)
    try:
        with bar.callback:
            (results,) = dask.compute(jobs, scheduler="threads", num_workers=workers or os.cpu_count() or 1)
    finally:
        bar.bar.close()
    chunks, files = split_results(plan, results)
    finish_store(partial, plan, {**known_chunks, **chunks}, {**known_files, **files})
    publish(partial, root.store(plan.cid))
    return resumed


def ingest(directories: list[str], archive_path: str | os.PathLike, fov_deg: float,
           calibration: str | os.PathLike | None = None, ground_height: float | None = None,
           overwrite: bool = False, workers: int | None = None, progress: bool = True,
           sync_offset: float = 0.0, boresight: tuple[float, float, float] = (0.0, 0.0, 0.0),
           lever_arm: tuple[float, float, float] = (0.0, 0.0, 0.0), dem: str | os.PathLike | None = None,
           dem_datum: str | None = None, irradiance_calibration: str | os.PathLike | None = None,
           navigation: str | os.PathLike | None = None, navigation_columns: dict | None = None, *,
           scheduler=None, threads: int | None = None, compression: str | None = None,
           checksum: str | None = None, report: str | os.PathLike | None = None,
           tell=None, wave_tasks: int | None = None,
           prewritten: str | os.PathLike | None = None) -> list[IngestResult]:
    """Ingest raw flight ``directories`` into the archive (created when absent); see the module docstring.
    ``dem`` / ``dem_datum``: the catalog footprint follows that terrain (:func:`prepare_flight`).
    ``irradiance_calibration``: the downwelling spectrometer's ``.dcp`` when it is not in the flight
    directories (their spectra are kept in the collection, issue 34). ``navigation``: a post-processed
    trajectory stored with each flight as its default navigation source (:func:`prepare_flight`).

    Where: ``scheduler`` (a Dask scheduler's address, a :class:`archive.run.cluster.SlurmJobs`) or
    ``workers`` >= 2 (a local cluster of that many processes of ``threads`` threads): on the distributed
    engine, each flight failing alone (its result 'failed' with its one-line error; ``report``: a JSON
    report rewritten as each flight ends; ``tell(line)``: one line per flight as it ends; ``wave_tasks``:
    tasks kept in the scheduler at most, :func:`archive.ingest.cluster.ingest_on_cluster`); else in this
    process on ``threads`` threads (default every core; ``workers`` 1 or None), every flight checked before
    anything is written. ``compression``: the dn codec by name (:data:`archive.collection.layout.DN_COMPRESSIONS`,
    default 'fast'); ``checksum``: 'blake3' (default) or 'sha256' for the dn chunks and raw files.
    ``prewritten``: a folder of dn chunks written ahead by ``archive watch`` (:mod:`archive.ingest.ahead`;
    in this process only: refused with a cluster)."""
    from archive.ingest.cluster import ingest_on_cluster

    codec, checksum = store_choices(compression, checksum)
    arguments = PrepareArguments(fov_deg, calibration, ground_height, sync_offset, tuple(boresight), tuple(lever_arm),
                                 dem, dem_datum, irradiance_calibration, navigation, navigation_columns, codec, checksum)
    if workers is not None and (isinstance(workers, bool) or int(workers) < 1):
        raise InputError("--workers", f"expected a positive number of worker processes, got {workers!r}")
    if scheduler is not None or (workers or 1) > 1:
        if prewritten is not None:
            raise InputError("--prewritten", "chunks written ahead are moved in by an ingest in this process",
                             "leave out --scheduler/--workers, or --prewritten")
        return ingest_on_cluster(list(directories), archive_path, arguments, scheduler=scheduler, workers=workers,
                                 threads=threads, overwrite=overwrite, progress=progress, report=report, tell=tell,
                                 wave_tasks=wave_tasks)
    if report is not None:
        raise InputError("--report", "reports the flights of an ingest on a cluster",
                         "add --scheduler ADDRESS, --cluster slurm or --workers N (N >= 2), or leave --report out")
    plans = [arguments.prepare(d) for d in directories]
    pairs = distinct_flights(list(directories), plans)
    root = open_archive_root(archive_path)
    results = []
    for directory, plan in pairs:
        if not overwrite and already_ingested(root, plan, directory):
            results.append(IngestResult(plan.cid, root.store(plan.cid), "already ingested", directory))
            continue
        # One writer per collection id, across processes and hosts (DESIGN 5): a second ingest of
        # the same flight waits here, then finds it ingested.
        lock = store_lock(root.store(plan.cid), f"ingest of {plan.cid}")
        try:
            try:
                with disk_full_is_an_error(root, plan.cid):
                    lock.acquire(wait=math.inf, notify=lambda line: print(f"archive ingest: {line}", file=sys.stderr))
            except OSError as exc:
                raise InputError(root.collections, f"cannot write there ({exc.strerror or exc})",
                                 "ingest into an archive you can write to") from None
            try:
                began = begin_flight(root, plan, directory, overwrite)
                if isinstance(began, IngestResult):
                    results.append(began)
                    continue
                with disk_full_is_an_error(root, plan.cid):
                    resumed = write_flight(plan, root, threads, progress, prewritten)
                results.append(finish_flight(root, plan, directory, resumed))
            finally:
                lock.release()
        except DiskFullError as exc:   # the flights of this command done before it are named too
            if not results:
                raise
            done = ", ".join(f"{r.cid} ({r.status})" for r in results)
            raise DiskFullError(exc.where, f"{exc.problem}; ingested before it: {done}", exc.fix) from None
    if not root.is_url:   # archive/previews.py reads local stores only: an archive in object storage has none yet
        add_previews(root, [r.cid for r in results])   # the viewer's overviews (issue 36); after every lock is released
    return results


def run(args: argparse.Namespace) -> int:
    """CLI handler of ``archive ingest``: one line per flight (on a cluster, 'failed DIR: why' for a flight
    that failed alone; exit code 1 when one did)."""
    from archive.formats.trajectory import parse_columns
    from archive.ingest.arguments import where

    results = ingest(args.directories, args.archive, args.fov, calibration=args.calibration,
                     ground_height=args.ground_height, overwrite=args.overwrite, workers=args.workers,
                     progress=not args.quiet, sync_offset=args.sync_offset,
                     boresight=args.boresight or (0.0, 0.0, 0.0), lever_arm=args.lever_arm or (0.0, 0.0, 0.0),
                     dem=getattr(args, "dem", None), dem_datum=getattr(args, "dem_datum", None),
                     irradiance_calibration=getattr(args, "irradiance_calibration", None),
                     navigation=getattr(args, "navigation", None),
                     navigation_columns=parse_columns(getattr(args, "navigation_columns", None)),
                     scheduler=where(args), threads=args.threads, compression=args.compression,
                     checksum=args.checksum, report=args.report, tell=print,
                     prewritten=getattr(args, "prewritten", None))
    cluster = where(args) is not None or (args.workers or 1) > 1
    if not cluster:
        for r in results:
            print(f"{r.cid}: {r.status} ({r.store})")
        return 0
    failed = [r for r in results if r.status == "failed"]
    counts = {s: sum(r.status == s for r in results) for s in ("ingested", "resumed", "already ingested")}
    print(f"archive ingest: {len(results)} flights: " + ", ".join(f"{n} {s}" for s, n in counts.items())
          + f", {len(failed)} failed")
    return 1 if failed else 0
