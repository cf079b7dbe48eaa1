"""Batch jobs: one output per flight, each flight a job of its own (DESIGN 9).

``archive render --archive A --query-... --out DIR --format F`` (and
``archive.georectify(..., per_flight=True)``) renders every source into ``DIR/<name>.<F>``:

- **Isolation.** Each flight is opened, planned, rendered and published on its own: a flight that
  fails (a corrupt chunk, a DEM that does not cover it, a worker that dies on it) leaves nothing at
  its output path (its temporaries are removed), and the others go on. One line per flight
  (done / skipped / failed and its one-line reason); :func:`run_batch` reports how many failed
  (the command exits 1 if any did).
- **Report.** ``DIR/report.json`` = ``{"outputs": [{"id", "status", "path", "error", "seconds"}],
  "flights", "done", "skipped", "failed", "pending", "complete"}``, written atomically before the
  first flight starts and rewritten as each flight finishes: a killed job leaves an honest report
  (its unfinished flights ``pending``, ``complete`` false).
- **Resume.** With ``resume``, a flight whose output is complete (its STAC Item, written last,
  exists) and whose recipe equals this request is skipped: the same options and sources
  (``archive:recipe.request``) AND the same inputs (``archive:recipe.inputs``: each source's content
  version and navigation parameters, :func:`archive.run.pipeline.recipe_inputs`; a flight re-ingested with another sync
  offset, or calibrated, is not the same recipe: its output is rendered again). An output without
  its Item (killed while publishing; a replaced output loses its old Item before its new data lands)
  is rendered again, and temporaries of killed runs are removed. A complete output made with other
  options is an error before anything starts, unless ``overwrite``.
- **One batch per folder.** The batch holds ``DIR/.archive-batch.lock`` (:class:`archive.files.FileLock`:
  host, PID, start, a heartbeat lease) from its first check to its last report: a second batch into
  the same ``DIR`` stops at once with one line naming who holds it.
- **Full disk.** A report that cannot be written (disk full) costs a warning while flights go on,
  and is written again at the next rewrite; if the last one fails, one line says so (exit non-zero).
- **Waves.** At most :func:`archive.run.cluster.flight_slots` flights are in the scheduler at once (from
  the workers' render slots and memory, counted again as workers come and go): the next flight is
  submitted when one finishes, so the tasks the scheduler holds, the submission time and the
  client's memory do not grow with the batch.
- **Planning ahead.** Opening, planning and building a flight (metadata only, on the client) runs in
  one thread of its own while the wave renders, at most a wave of flights ahead of their place in
  the scheduler: a flight is ready to submit when a place frees up, and the workers do not wait for
  the client (what the scheduler holds is unchanged).
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from archive import storage
from archive.errors import ArchiveError, InputError
from archive.files import FileLock, path_exists, remove_path, test_hold, write_atomic
from archive.run.session import BatchSummary, Job, render_failure, render_summary

__all__ = ["LOCK", "REPORT", "BatchOutput", "recipe_request", "run_batch"]

#: The batch report's file name in the output directory.
REPORT = "report.json"
#: The lock file a batch holds in its output directory.
LOCK = ".archive-batch.lock"


def recipe_request(options) -> dict:
    """The JSON form of a request as an output's Item records it (``archive:recipe.request``)."""
    return json.loads(json.dumps(dataclasses.asdict(options), default=str))


@dataclass
class BatchOutput:
    """One output of a batch (a flight, or a tile of flights): its source (id or directory; a tile's
    ids joined by commas), output, request (its recipe), status ('pending', 'done', 'skipped',
    'failed'), one-line error, seconds and summary."""

    source: str
    name: str
    output: object
    recipe: object
    status: str = "pending"
    error: str | None = None
    seconds: float | None = None
    summary: dict | None = None
    job: object = None
    futures: list = field(default_factory=list)
    left: int = 0
    started: float = 0.0
    remote: object = None   #: its :class:`~archive.outputs.publish.RemoteOutput` when --out is an s3:// folder
    inputs: list | None = None   #: :func:`archive.run.pipeline.recipe_inputs` when the batch was decided (the Item records it)
    note: str | None = None   #: why a complete output of the same request is rendered again
    properties: dict | None = None   #: more properties of its Item (a tile's ``archive:tile``)

    def entry(self) -> dict:
        path = str(self.output.path) if self.remote is None else str(self.remote.url)
        return {"id": self.name, "status": self.status, "path": path, "error": self.error,
                "seconds": None if self.seconds is None else round(self.seconds, 3)}


def _directory(out) -> Path:
    from archive.outputs.registry import looks_like_output

    if storage.is_url(out):   # an s3:// folder: each output staged locally, uploaded once, its Item last
        directory = storage.location(out)
        if looks_like_output(directory):
            raise InputError(directory, "looks like one output, but a batch job writes one output per flight",
                             "give --out s3://BUCKET/FOLDER (outputs FOLDER/<id>.<format>), or add --mosaic")
        return directory
    directory = Path(out).absolute()
    if directory.exists() and not directory.is_dir():
        raise InputError(directory, "is a file, but a batch job writes one output per flight into a directory",
                         "give --out DIR, or --mosaic for one output")
    if looks_like_output(directory):
        raise InputError(directory, "looks like one output file, but a batch job writes one output per flight",
                         "give --out DIR (outputs DIR/<id>.<format>), or add --mosaic")
    return directory


def _with_defaults(stored, options):
    """A stored request with the fields it lacks (recorded before they existed: --bounds, --align,
    --like) at their defaults, so that an older output of the same request is the same recipe."""
    if not isinstance(stored, dict):
        return stored
    missing = {f.name: f.default for f in dataclasses.fields(options)
               if f.name not in stored and f.default is not dataclasses.MISSING}
    return {**json.loads(json.dumps(missing, default=str)), **stored}


def _differences(stored: dict, wanted: dict) -> str:
    keys = [k for k in wanted if stored.get(k) != wanted.get(k)] + [k for k in stored if k not in wanted]
    return ", ".join(f"{k} {stored.get(k)!r} there, {wanted.get(k)!r} now" for k in keys[:4])


def _input_changes(stored: list | None, wanted: list | None) -> str:
    """What differs between two ``archive:recipe.inputs`` (for the line that says a flight is stale)."""
    if not isinstance(stored, list):
        return "its Item does not record them"
    if len(stored) != len(wanted or []):
        return f"{len(stored)} inputs there, {len(wanted or [])} now"
    for old, new in zip(stored, wanted or [], strict=True):
        if old == new or not isinstance(old, dict):
            continue
        name = new.get("source") or new.get("option")
        keys = [k for k in new if k != "version" and old.get(k) != new.get(k)] or ["version"]
        short = (lambda v: v[:12] if isinstance(v, str) and len(v) == 64 else v)
        return f"{name}: " + ", ".join(f"{k} {short(old.get(k))!r} there, {short(new.get(k))!r} now" for k in keys[:3])
    return "unknown"


def _remove_leftovers(output) -> None:
    """Temporaries of killed runs beside ``output``'s files: Item partials (``<name>.<hex>.partial``)
    and the output's ``.<name>.partial-<pid>@<host>...`` made on this host by a process that is gone
    (its check removes those). The folder's lock is held: no other batch writes here."""
    for final in output.finals:
        for tmp in final.parent.glob(f"{final.name}.*.partial"):
            remove_path(tmp)
    keep, output.overwrite = output.overwrite, True   # check only for the leftovers it removes
    try:
        output.check()
    finally:
        output.overwrite = keep


def _decide(flight: BatchOutput, resume: bool, overwrite: bool) -> None:
    """Settle what to do with ``flight`` before anything starts: skip it (``status`` 'skipped'), or
    render it (its Output replaces what is there when it may). InputError when its output exists and
    may not be replaced, or (with ``resume``) was made with another recipe and ``overwrite`` is off."""
    output = flight.output
    remote = flight.remote   # an s3:// output: the bucket's objects decide, the local staging output is new
    if remote is None:
        item, finals = output.item_path, output.finals
    else:
        item, finals = remote.item_url, [*remote.data_urls(), remote.item_url]
    data = [p for p in finals if p not in (item, output.quicklook)]
    complete = path_exists(item) and all(path_exists(p) for p in data)
    present = [p for p in finals if path_exists(p)]
    if resume and remote is None:
        _remove_leftovers(output)
    if complete and resume:
        try:
            recipe = json.loads(item.read_text())["properties"]["archive:recipe"]
            stored, stored_inputs = recipe["request"], recipe.get("inputs")
        except (OSError, ValueError, KeyError, TypeError):
            stored = stored_inputs = None
        wanted = recipe_request(flight.recipe)
        stored = _with_defaults(stored, flight.recipe)
        if stored == wanted and stored_inputs == flight.inputs:
            flight.status = "skipped"
            return
        if stored == wanted:
            # same request, other inputs (re-ingested, calibrated; or an Item that does not record
            # them): the output is stale and rendered again; its old Item goes first (publish.Output)
            flight.note = f"its inputs changed since it was rendered ({_input_changes(stored_inputs, flight.inputs)})"
            (remote or output).overwrite = True
            (remote or output).check()
            return
        if not overwrite:
            what = "an unreadable recipe" if stored is None else f"another recipe ({_differences(stored, wanted)})"
            raise InputError(item, f"the output of {flight.name} is complete but was made with {what}",
                             "pass --overwrite to render it again with this request, or choose another --out")
    if present and not (resume or overwrite):
        raise InputError(present[0], "output exists already",
                         "pass --resume to skip complete outputs of the same request, or --overwrite to "
                         "replace them")
    if present:
        (remote or output).overwrite = True
        if not complete:
            remove_path(item)   # an Item without its data, or of an output about to be replaced
    (remote or output).check()


def _reason(exc: BaseException) -> str:
    """One line saying why a flight failed (:func:`archive.run.session.render_failure`)."""
    return " ".join(render_failure(exc).split())


class _Report:
    """``DIR/report.json``, rewritten atomically whenever a flight finishes. A rewrite that fails
    (disk full, quota) does not stop the batch: ``warn`` is told once, the report stays as last
    written, and the next rewrite tries again (:meth:`write` returns whether it was written)."""

    def __init__(self, directory: Path, flights: list[BatchOutput], warn: Callable[[str], None] | None = None):
        self.path, self.flights = directory / REPORT, flights
        self.warn, self.error = warn or (lambda line: None), None
        for tmp in ([] if storage.is_url(directory) else directory.glob(f"{REPORT}.*.partial")):   # a killed run's report being rewritten
            remove_path(tmp)

    def write(self, complete: bool = False) -> bool:
        counts = {s: sum(f.status == s for f in self.flights) for s in ("done", "skipped", "failed", "pending")}
        doc = {"outputs": [f.entry() for f in self.flights], "flights": len(self.flights), **counts,
               "complete": complete}
        try:
            if not storage.is_url(self.path):
                self.path.parent.mkdir(parents=True, exist_ok=True)
            write_atomic(self.path, json.dumps(doc, indent=1) + "\n")
        except OSError as exc:
            if self.error is None:
                self.warn(f"warning: cannot write {self.path} ({exc.strerror or exc}); the flights go on and "
                          "the report is written again as they finish")
            self.error = exc
            return False
        self.error = None
        return True


def run_batch(options, out, *, format: str = "zarr", overwrite: bool = False, resume: bool = False,
              scheduler: str | None = None, workers: int | None = None, threads: int | None = None,
              quiet: bool = True, tell: Callable[[str], None] | None = None, wave: int | None = None,
              units: Sequence[tuple[str, object, dict]] | None = None) -> BatchSummary:
    """Render every source of ``options`` into ``out/<name>.<format>``, each flight on its own (see
    the module's docstring). ``tell(line)`` gets one line per flight as it finishes; ``wave``: flights
    in the scheduler at once (default :func:`archive.run.cluster.flight_slots`). Returns ``{"outputs":
    [per flight: id, status, path, error, seconds and, when done, the output's summary], "done",
    "skipped", "failed", "seconds", "graph_seconds", "submit_seconds" (opening, planning, building
    and submitting the flights), "report", "wave", "peak_tasks" (futures held at once)}``. Raises an
    ArchiveError before anything is rendered for problems of the whole request (``out``, ``format``,
    outputs that may not be replaced). ``units``: instead of one output per source, one output per
    ``(name, request, Item properties)`` (a tile of :mod:`archive.run.tiling`: the mosaic of its sources)."""
    from archive.outputs.publish import Output
    from archive.outputs.registry import format_named
    from archive.run.options import check_gsd
    from archive.run.pipeline import recipe_inputs

    started = time.perf_counter()
    check_gsd(options.gsd)
    fmt = format_named(format)
    directory = _directory(out)
    if options.archive is not None and not storage.is_url(options.archive):   # recipes independent of the cwd
        options = dataclasses.replace(options, archive=os.fspath(Path(options.archive).absolute()))
    tell = tell or (lambda line: None)
    made = not storage.is_url(directory) and not directory.exists()
    lock = _lock_directory(directory)
    try:
        flights = []
        if units is None:
            units = [(Path(src).name if Path(src).is_dir() else str(src), options.with_sources([src]), None)
                     for src in dict.fromkeys(options.sources)]
        for name, recipe, properties in units:
            remote = None
            if storage.is_url(directory):
                from archive.outputs.publish import RemoteOutput

                remote = RemoteOutput(str(directory / f"{name}{fmt.suffix}"), overwrite=bool(overwrite),
                                      provenance=options.provenance, zarr_format=options.zarr_format,
                                      compression=options.compression)
                output = remote.local
            else:
                output = Output(directory / f"{name}{fmt.suffix}", overwrite=bool(overwrite),
                                provenance=options.provenance, zarr_format=options.zarr_format,
                                compression=options.compression)
            flights.append(BatchOutput(",".join(recipe.sources), name, output, recipe, inputs=recipe_inputs(recipe),
                                  properties=properties, remote=remote))
        for flight in flights:
            _decide(flight, resume, overwrite)
        report = _Report(directory, flights, warn=lambda line: print(f"archive render: {line}", file=sys.stderr))
        if not report.write() and not path_exists(report.path):
            raise InputError(report.path, f"cannot write the batch report ({report.error.strerror or report.error})",
                             "free some space or choose another --out")
        _test_hold(flights)
        for flight in flights:
            if flight.status == "skipped":
                tell(f"skipped {flight.name}: {flight.entry()['path']} is complete (same recipe)")
            elif flight.note:
                tell(f"stale {flight.name}: {flight.note}; rendering it again")
        todo = [f for f in flights if f.status == "pending"]
        state = {"graph_seconds": 0.0, "submit_seconds": 0.0, "wave": 0, "peak_tasks": 0}
        if todo:
            try:
                _render(todo, report, tell, state, scheduler=scheduler, workers=workers, threads=threads,
                        quiet=quiet, wave=wave)
            except ArchiveError as exc:   # the whole batch stopped (its cluster did not start...)
                for flight in todo:
                    if flight.status == "pending":
                        flight.status, flight.error = "failed", " ".join(str(exc).split())
                report.write(complete=True)
                raise
        if not report.write(complete=True):
            raise InputError(report.path, f"the batch finished ({_counts_text(flights)}) but its report could not "
                             f"be written ({report.error.strerror or report.error})",
                             "free some space, then run the same command with --resume to write it")
    except BaseException:
        lock.release()
        _remove_staging(flights)
        if made:
            try:
                directory.rmdir()   # a refused batch leaves no empty folder behind
            except OSError:
                pass
        raise
    lock.release()
    _remove_staging(flights)
    outputs = []
    for f in flights:
        outputs.append({**(f.summary or {}), **f.entry(), "out": f.entry()["path"]})
    counts = {s: sum(f.status == s for f in flights) for s in ("done", "skipped", "failed")}
    return {"outputs": outputs, **counts, "seconds": time.perf_counter() - started,
            "graph_seconds": state["graph_seconds"], "submit_seconds": state["submit_seconds"],
            "report": str(report.path), "wave": state["wave"],
            "peak_tasks": state["peak_tasks"], "renders": sum((f.summary or {}).get("renders", 0) for f in flights)}


#: Test-only: ``ARCHIVE_TEST_HOLD_AFTER=N`` makes a batch stop and wait (until it is killed; with
#: ``N:PATH``, while the file PATH exists) as soon as its report says N flights are done, so that a
#: test kills it, or one of its workers, at a moment it controls, however loaded the machine (never
#: set outside tests).
TEST_HOLD_AFTER = "ARCHIVE_TEST_HOLD_AFTER"


def _test_hold(flights: list[BatchOutput]) -> None:
    """The :data:`TEST_HOLD_AFTER` hook (:func:`archive.files.test_hold`), called right after each
    rewrite of the report."""
    test_hold(TEST_HOLD_AFTER, sum(f.status == "done" for f in flights))


def _remove_staging(flights: list[BatchOutput]) -> None:
    """Remove the local staging folders of a batch into an s3:// folder."""
    for flight in flights:
        if flight.remote is not None:
            flight.remote.cleanup()


def _counts_text(flights: list[BatchOutput]) -> str:
    return ", ".join(f"{sum(f.status == s for f in flights)} {s}" for s in ("done", "skipped", "failed"))


def _lock_directory(directory: Path) -> FileLock:
    """Take the output folder's lock (:data:`LOCK`), creating the folder;
    :class:`~archive.files.LockHeldError` naming the holder when another live batch has it."""
    from archive.outputs.publish import unwritable_output

    try:
        if not storage.is_url(directory):   # a lock object in a bucket needs no folder
            directory.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(directory, f"cannot create the output folder ({exc.strerror or exc})",
                         "choose an output folder you can write to") from None
    lock = FileLock(directory / LOCK, "a batch render", what=f"output folder {directory}",
                    fix="wait for that batch to finish, or choose another --out")
    try:
        lock.acquire()
    except OSError as exc:
        raise unwritable_output(directory, exc) from None
    return lock


def _render(todo: list[BatchOutput], report: _Report, tell, state: dict, *, scheduler, workers, threads, quiet,
            wave) -> None:
    """Plan, submit (in waves), follow and publish ``todo``'s flights on a cluster."""
    from archive.run.pipeline import progress_lines
    from archive.run.session import Session

    say = progress_lines(quiet)
    # stops the worker processes (cancels Slurm worker jobs) at the end, once the writers of failed
    # flights are done on a cluster that outlives us; a close that fails is a warning, never the
    # batch's error nor a reason to leave temporaries
    try:
        with Session(scheduler, workers, threads, say, what=str(report.path.parent)) as session:
            _follow(session, todo, report, tell, state, quiet=quiet, wave=wave)
    finally:
        for flight in todo:
            flight.output.cleanup()


def _follow(session, todo: list[BatchOutput], report: _Report, tell, state: dict, *, quiet, wave) -> None:
    """:func:`_render`'s loop on the session's cluster: plan ahead, submit in waves, publish each
    flight as its last task ends."""
    from collections import deque
    from concurrent.futures import ThreadPoolExecutor

    from tqdm import tqdm

    from archive.run.pipeline import progress_lines
    from archive.run.session import Waves

    say = progress_lines(quiet)
    client = session.client
    queue = deque(todo)
    prepared: deque = deque()   # (flight, its planning's concurrent future), in submission order
    planner = ThreadPoolExecutor(1, thread_name_prefix="archive-plan")
    t0 = time.perf_counter()
    bar = tqdm(total=len(todo), desc="flights", unit="flight", disable=quiet, file=sys.stderr)
    try:
        budget = session.budget
        waves = Waves(session, wave)
        state["wave"] = waves.slots

        def plan_ahead() -> None:
            """Keep up to a wave of flights planned (in the planner's thread) ahead of the scheduler."""
            while queue and len(prepared) < max(waves.slots, 1):
                flight = queue.popleft()
                prepared.append((flight, planner.submit(_timed_prepare, flight, budget, say)))

        def finish(flight: BatchOutput, status: str, error: str | None = None) -> None:
            flight.status, flight.error = status, error
            flight.seconds = time.perf_counter() - flight.started
            # a failed flight's unfinished tasks cancelled; their writers waited for at the end
            waves.leave(flight, give_up=status == "failed", wait=False)
            if status == "failed":
                flight.output.cleanup()
                tell(f"failed {flight.name}: {error}")
            else:
                s = flight.summary
                tell(f"done {flight.name}: {s['width']} x {s['height']} px, {s['bands']} bands -> "
                     f"{flight.entry()['path']} ({flight.seconds:.1f} s)")
            flight.futures, flight.job = [], None
            report.write()
            bar.update(1)
            _test_hold(report.flights)

        def submit(flight: BatchOutput, planning) -> None:
            try:
                flight.job, graph, seconds = planning.result()
                state["submit_seconds"] += seconds
                flight.started = time.perf_counter() - seconds   # its planning, not its wait for a place
                t = time.perf_counter()
                futures = waves.submit(flight, graph.writes if len(graph) else [])
                state["submit_seconds"] += time.perf_counter() - t
            except Exception as exc:  # noqa: BLE001 - the flight fails alone
                finish(flight, "failed", _reason(exc))
                return
            if not futures:
                publish_flight(flight)

        def publish_flight(flight: BatchOutput) -> None:
            try:
                _publish(flight, client)
            except Exception as exc:  # noqa: BLE001
                finish(flight, "failed", _reason(exc))
                return
            finish(flight, "done")

        while queue or prepared or waves.active:
            plan_ahead()
            while prepared and waves.has_room():
                submit(*prepared.popleft())
                plan_ahead()
            state["wave"] = waves.largest
            state["peak_tasks"] = waves.peak
            if not waves.active:
                continue
            flight, status, exc = waves.next_done()
            if flight is None or flight.status != "pending":
                continue
            if status == "error":
                finish(flight, "failed", _reason(exc))
                continue
            if status == "cancelled":
                finish(flight, "failed", "its tasks were cancelled (the scheduler lost them)")
                continue
            bar.set_postfix_str(f"tasks {waves.done}/{waves.submitted}", refresh=False)
            if flight.left == 0:
                publish_flight(flight)
        state["graph_seconds"] = time.perf_counter() - t0
    finally:
        bar.close()
        planner.shutdown(wait=True, cancel_futures=True)   # no temporaries made after the clean-up


def _publish(flight: BatchOutput, client) -> None:
    """:func:`archive.run.pipeline.publish` of a flight, whose Item's recipe also records the inputs it
    was rendered from (``archive:recipe.inputs``, what ``--resume`` compares besides the request):
    the data renamed into place (an old Item removed first), then the Item, last."""
    from archive.run.pipeline import publish, worker_renderers

    job = flight.job
    job.renderers = worker_renderers(client)   # [] when a worker cannot say: a record, never a failure
    try:
        publish(job, flight.inputs, flight.properties)
        if flight.remote is not None:   # an s3:// folder: uploaded once, its Item last
            flight.remote.upload()
    finally:
        job.output.cleanup()   # its turn to publish ends with the Item
        if flight.remote is not None:
            flight.remote.cleanup()


def _timed_prepare(flight: BatchOutput, budget: int, say) -> tuple[Job, object, float]:
    """:func:`_prepare` in the planner's thread; the flight's clock starts here. (job, graph, seconds)."""
    flight.started = time.perf_counter()
    job, graph = _prepare(flight, budget, say)
    return job, graph, time.perf_counter() - flight.started


def _prepare(flight: BatchOutput, budget: int, say) -> tuple[Job, object]:
    """Open, plan and build one flight (metadata only; its sink created under temporary names)."""
    from archive.run.pipeline import build_output, open_inputs, plan_output

    recipe = flight.recipe
    nav = recipe.check()
    if len(recipe.sources) > 1:   # a tile: the mosaic of its flights
        planned = plan_output(open_inputs(recipe, nav, say, mosaic=True), budget=budget)
    else:
        planned = plan_output(open_inputs(recipe, nav, say, mosaic=False), [0], budget=budget)
    sink, graph = build_output(planned, flight.output)
    flight.summary = render_summary(planned, flight.output, graph)
    return Job(flight.output, planned, sink, recipe), graph
