"""``archive ingest`` on the distributed engine: ``--scheduler ADDRESS``, ``--cluster slurm`` or a local
cluster of ``--workers N`` (N >= 2) processes. Each flight is a unit:

- **Checks** on a worker (:func:`prepare_task`: headers, sizes, times, navigation, calibration; the
  workers see the raw folders, calibration, DEM and trajectory files at the same paths as this command);
- **its store** laid out by this process (the partial store, under the collection's lock: one writer
  per id across processes and hosts), its **dn chunk tasks** (:func:`archive.collection.write_chunks`, a
  run of bands of one line chunk each) and raw-file checksum tasks run on the workers, writing straight
  into the partial store (a local archive on the shared file system, or s3://);
- **one publish step** here once all its tasks are done: checksums and metadata recorded, the marker
  written last, the store renamed into place and cataloged (the catalog's lock: one writer of the
  index at a time, whatever runs beside this command).

A flight that fails (its checks, a task, a worker dying on it again and again) costs only itself: one
line ``failed DIR: why``, its partial store kept for a rerun, the others go on, the command exits 1 at
the end. ``--report FILE``: JSON rewritten as each flight ends (``{"flights": [{"directory", "id",
"status", "error", "seconds"}], "total", counts, "pending", "complete"}``). A killed command or worker
resumes where it stopped: the rerun finds the partial stores and keeps their chunks that hold the
right values. **Waves**: at most ``wave_tasks`` tasks (default :func:`task_limit`) are in the scheduler
at once, and checks run at most a few flights ahead, so the scheduler's task count and this process's
memory do not grow with the number of flights.
"""

from __future__ import annotations

import json
import os
import sys
import time
from collections import deque
from dataclasses import dataclass, field

from archive import storage
from archive.collection import StorePlan, finish_store, open_partial, publish, store_lock
from archive.errors import ArchiveError, InputError
from archive.files import write_atomic
from archive.ingest.checks import already_ingested, disk_full_is_an_error, open_archive_root
from archive.ingest.flight import IngestResult, PrepareArguments, begin_flight, finish_flight, flight_tasks, split_results

__all__ = ["TaskFailed", "guarded", "ingest_on_cluster", "prepare_task", "task_limit"]


class TaskFailed(Exception):
    """A task's one-line error, as it travels back from a worker (archive's errors carry fields that
    do not survive pickling; this carries their text)."""


def guarded(function, *args):
    """Task body: ``function(*args)``, an :class:`~archive.errors.ArchiveError` raised as :class:`TaskFailed`
    with its one line (OSError and the like travel as they are: a full disk is still recognised)."""
    try:
        return function(*args)
    except ArchiveError as exc:
        raise TaskFailed(" ".join(str(exc).split())) from None


def prepare_task(arguments: PrepareArguments, directory: str) -> StorePlan:
    """Task body: the checked plan of one flight (:meth:`PrepareArguments.prepare`), run on a worker."""
    return guarded(arguments.prepare, directory)


def task_limit(client) -> int:
    """Tasks an ingest keeps in the scheduler at once: 8 per worker thread, at least 64 (a flight's
    tasks are submitted whole: a flight larger than this runs alone)."""
    workers = client.scheduler_info().get("workers", {}).values()
    threads = sum(int(w.get("nthreads") or 1) for w in workers) or 1
    return max(64, 8 * threads)


@dataclass(eq=False)
class _Flight:
    """One flight of a cluster ingest and where it stands."""

    directory: str
    status: str = "pending"    # pending | ingested | resumed | already ingested | failed
    cid: str | None = None
    error: str | None = None
    started: float = 0.0
    seconds: float | None = None
    plan: StorePlan | None = None
    lock: object = None
    resumed: bool = False
    futures: list = field(default_factory=list)
    results: list = field(default_factory=list)
    left: int = 0
    told: bool = False

    def entry(self) -> dict:
        return {"directory": self.directory, "id": self.cid, "status": self.status, "error": self.error,
                "seconds": None if self.seconds is None else round(self.seconds, 3)}


def _write_report(path, flights: list[_Flight], complete: bool) -> None:
    if path is None:
        return
    counts = {s: sum(f.status == s for f in flights) for s in ("ingested", "resumed", "already ingested", "failed",
                                                              "pending")}
    doc = {"flights": [f.entry() for f in flights], "total": len(flights), **counts, "complete": complete}
    try:
        write_atomic(path, (json.dumps(doc, indent=1) + "\n").encode())
    except OSError as exc:
        print(f"archive ingest: warning: cannot write the report {path} ({exc.strerror or exc})", file=sys.stderr)


def _reason(exc: BaseException) -> str:
    """One line saying why a flight failed (:func:`archive.run.session.task_failure`)."""
    from archive.run.session import task_failure

    return " ".join(task_failure(exc, "ingesting", "it may have run out of memory: give the workers more memory or "
                                 "fewer threads", known=(TaskFailed,)).split())


def _connect(scheduler, workers: int | None, say, threads: int | None):
    """(client, cluster or None): a scheduler's address (its workers need no GPU for ingest), Slurm worker
    jobs or a local cluster (:func:`archive.run.cluster.start_cluster`)."""
    from archive.run.cluster import SlurmJobs, start_cluster

    if isinstance(scheduler, str) and scheduler:
        from distributed import Client

        try:
            client = Client(scheduler, timeout="20s")
        except OSError as exc:
            raise InputError("--scheduler", f"cannot connect to {scheduler}: {exc}",
                             "start one with `dask scheduler` and workers with `dask worker ADDRESS` "
                             "(docs/deploy.md)") from None
        return client, None
    if isinstance(scheduler, SlurmJobs) or scheduler is None:
        return start_cluster(scheduler, workers, say, threads)
    raise InputError("--scheduler", f"expected a scheduler address or Slurm jobs, got {scheduler!r}")


def ingest_on_cluster(directories: list[str], archive_path, arguments: PrepareArguments, *, scheduler=None,
                      workers: int | None = None, threads: int | None = None, overwrite: bool = False,
                      progress: bool = True, report=None, tell=None, wave_tasks: int | None = None) -> list:
    """Ingest ``directories`` on the distributed engine, each flight a unit (the module docstring);
    returns one :class:`archive.ingest.command.IngestResult` per distinct directory, in order, failed
    flights included (status 'failed', their one-line error). ``tell(line)``: each flight's line as it ends."""
    from distributed import wait
    from tqdm import tqdm

    from archive.run.session import Session

    say = tell or (lambda line: None)
    seen: dict[str, _Flight] = {}
    for d in directories:   # a directory given twice is taken once; absolute: the workers run elsewhere
        seen.setdefault(os.path.realpath(d), _Flight(os.path.abspath(d)))
    flights = list(seen.values())
    arguments = arguments.absolute()
    root = open_archive_root(archive_path if storage.is_url(archive_path) else os.path.abspath(archive_path))
    _write_report(report, flights, False)
    # the cluster's lifecycle as a render's (start, tasks given up cancelled and, on a cluster that outlives
    # the command, their writers waited for at the end, a failing close one warning line)
    session = Session(scheduler, workers, threads, lambda line: print(line, file=sys.stderr), what=str(root.path),
                      command="archive ingest", connect=_connect).start()
    client = session.client
    bar = tqdm(total=len(flights), desc="flights", unit="flight", disable=not progress, file=sys.stderr)
    owners: dict[str, _Flight] = {}   # cid -> the flight of this command that holds it
    try:
        limit = wave_tasks or task_limit(client)
        threads_total = sum(int(w.get("nthreads") or 1) for w in client.scheduler_info()["workers"].values()) or 1
        queue = deque(flights)
        checking: dict = {}            # prepare future -> flight
        ready: deque[_Flight] = deque()   # checked, waiting for a place (or for the collection's lock)
        active: dict = {}              # task future -> (flight, index)
        running: list[_Flight] = []

        def finish(flight: _Flight, status: str, error: str | None = None) -> None:
            flight.status, flight.error = status, error
            flight.seconds = time.perf_counter() - flight.started
            for future in flight.futures:
                active.pop(future, None)
            if status == "failed":
                session.abandon(flight.futures, wait=False)
            flight.futures, flight.results, flight.plan = [], [], None
            if flight in running:
                running.remove(flight)
            if flight.lock is not None:
                flight.lock.release()
                flight.lock = None
            if owners.get(flight.cid) is flight and status == "failed":
                owners.pop(flight.cid, None)
            if status == "failed":
                say(f"archive ingest: failed {flight.directory}: {error}")
            else:
                say(f"archive ingest: {status} {flight.directory}: {flight.cid} ({flight.seconds:.1f} s)")
            _write_report(report, flights, False)
            bar.update(1)

        def check_more() -> None:
            while queue and len(checking) + len(ready) < max(2, threads_total):
                flight = queue.popleft()
                flight.started = time.perf_counter()
                future = client.submit(prepare_task, arguments, flight.directory, pure=False,
                                       key=f"ingest-check-{os.urandom(8).hex()}")
                checking[future] = flight

        def checked(flight: _Flight, plan: StorePlan) -> None:
            flight.cid = plan.cid
            other = owners.get(plan.cid)
            if other is not None:
                finish(flight, "failed", f"is the same flight as {other.directory} (both are {plan.cid}): ingest "
                       "one of them")
                return
            owners[plan.cid] = flight
            if not overwrite and already_ingested(root, plan, flight.directory):
                finish(flight, "already ingested")
                return
            flight.plan = plan
            ready.append(flight)

        def start(flight: _Flight) -> bool:
            """Take the flight's lock and submit its tasks; False when another process holds the lock."""
            plan = flight.plan
            lock = store_lock(root.store(plan.cid), f"ingest of {plan.cid}")
            with disk_full_is_an_error(root, plan.cid):
                owner = lock.try_acquire()
            if owner is not None:
                if not flight.told:
                    say(f"archive ingest: waiting: collection {plan.cid} is locked, {owner.describe()}")
                    flight.told = True
                return False
            flight.lock = lock
            began = begin_flight(root, plan, flight.directory, overwrite)
            if began is not None:
                finish(flight, began.status)
                return True
            partial = root.partial(plan.cid)
            with disk_full_is_an_error(root, plan.cid):
                flight.resumed = open_partial(partial, plan)
            tasks = flight_tasks(plan, partial, flight.resumed)
            flight.results = [None] * len(tasks)
            flight.futures = [client.submit(guarded, function, *args, key=key) for key, function, args in tasks]
            flight.left = len(tasks)
            for index, future in enumerate(flight.futures):
                active[future] = (flight, index)
            running.append(flight)
            return True

        def publish_flight(flight: _Flight) -> None:
            plan = flight.plan
            with disk_full_is_an_error(root, plan.cid):
                finish_store(root.partial(plan.cid), plan, *split_results(plan, flight.results))
                publish(root.partial(plan.cid), root.store(plan.cid))
            result = finish_flight(root, plan, flight.directory, flight.resumed)
            flight.futures = []
            finish(flight, result.status)

        def guard(flight: _Flight, step) -> None:
            try:
                step()
            except (ArchiveError, OSError, ValueError) as exc:   # this flight fails alone
                finish(flight, "failed", _reason(exc))

        while queue or checking or ready or running:
            check_more()
            waited = []
            while ready:
                flight = ready.popleft()
                tasks = sum(len(f.futures) for f in running)
                if running and tasks >= limit:
                    ready.appendleft(flight)
                    break
                started = []
                guard(flight, lambda flight=flight: started.append(start(flight)))
                if started == [False]:
                    waited.append(flight)
            ready.extend(waited)
            pending = list(checking) + list(active)
            if not pending:
                if ready:
                    time.sleep(0.2)   # every flight left waits for a lock another process holds
                continue
            try:
                done, _ = wait(pending, timeout=0.5 if waited else None, return_when="FIRST_COMPLETED")
            except TimeoutError:
                continue
            for future in done:
                if future in checking:
                    flight = checking.pop(future)
                    if future.status == "error":
                        finish(flight, "failed", _reason(future.exception()))
                    elif future.status == "cancelled":
                        finish(flight, "failed", "its checks were cancelled (the scheduler lost them)")
                    else:
                        guard(flight, lambda flight=flight, future=future: checked(flight, future.result()))
                    future.release()
                    continue
                owner = active.pop(future, None)
                if owner is None:
                    continue
                flight, index = owner
                if future.status in ("error", "cancelled"):   # "lost" (its worker left since): result() waits
                    why = _reason(future.exception()) if future.status == "error" else \
                        "its tasks were cancelled (the scheduler lost them)"
                    finish(flight, "failed", why)
                    continue
                flight.results[index] = future.result()
                flight.left -= 1
                if flight.left == 0:
                    guard(flight, lambda flight=flight: publish_flight(flight))
    finally:
        bar.close()
        for flight in flights:
            if flight.lock is not None:
                flight.lock.release()
        session.close()
    _write_report(report, flights, all(f.status != "pending" for f in flights))
    done_ids = [f.cid for f in flights if f.status in ("ingested", "resumed", "already ingested")]
    if not root.is_url and done_ids:   # the viewer's overviews, as a local ingest makes them
        from archive.ingest.previews import add_previews

        add_previews(root, done_ids)
    return [IngestResult(f.cid, None if f.cid is None else root.store(f.cid), f.status, f.directory, f.error,
                         f.seconds) for f in flights]
