"""Time stacks: every flight of one place rendered from its raw lines onto one aligned grid (DESIGN 11).

``archive render --archive A --query-... --stack --out X.zarr`` (and :func:`run_stack`) writes one
Zarr store whose data variable (``radiance``, ``dn``... by mode) is ``(time, band, y, x)`` float32,
NaN where a flight has no line, with coordinates ``time`` (each flight's first line, UTC, CF-encoded
as microseconds since 1970-01-01) and ``flight`` (the collection id, along ``time``), ``saturated``
``(time, y, x)``, and the coordinates, CRS and grid of a mosaic output (:mod:`archive.outputs.zarr`),
so that ``--like X.zarr`` takes its grid.

- **Grid.** One aligned grid (pixel edges on multiples of the GSD): the union of the flights'
  footprints in the UTM zone holding most flights (``--crs`` forces one), or ``--bounds`` (snapped
  outward), or ``--like`` (taken whole). Each slice is its flight rendered alone onto that grid, by
  the same steps as ``archive render ID --like X.zarr`` (:func:`archive.run.pipeline.open_inputs`,
  ``plan_output``, ``build_output``): the same values, bit for bit.
- **Slice by slice.** Chunks are (1 flight, 1 band, 1024, 1024): a flight is rendered into a
  temporary single-flight store, its chunk files are moved into the stack at its time index, then
  the stack's metadata is rewritten with one more time step (the consolidated metadata last: a
  reader sees the stack before or after the slice, never half of it). A new stack is made under a
  temporary name and renamed into place with its first slice; ``--overwrite`` builds the new stack
  under a temporary name and replaces the old one when complete.
- **One writer.** A run holds the stack's lock (``.X.zarr.stack.lock`` beside it, :class:`~archive.files.FileLock`)
  from its first check to its Item: a second run of the same ``--out`` (another query, another host on a
  shared file system) is refused in one line naming the holder, before it reads or writes anything.
  Every time step records the digest of the recipe that wrote it (request and flight: ``recipe``);
  ``--resume`` refuses a stack holding a step of another recipe instead of keeping it.
- **Complete and resumable.** The stack's STAC Item ``X.zarr.json`` (datacube ``cube:dimensions``)
  is written last and says the stack is complete; ``--resume`` adds the flights of the request the
  stack lacks (after new ingests, or a killed run), at the end of ``time``, on the stack's own grid
  (a request with other options is refused unless ``--overwrite``). Flights that have no line on the
  grid are left out with a note.
- **Memory.** Flights enter the scheduler in waves, through the batches' own
  :class:`archive.run.session.Waves`: at most :func:`archive.run.cluster.flight_slots` flights at
  once (each rendering into its own temporary slice store; counted again as workers come and go),
  the next submitted when the earliest is committed; the client holds the plans of the wave only. Memory does not grow with the number of flights (bench/bench_stack.py).

:func:`stack` is the lazy form (``archive.stack``): the same values as an ``xarray.DataArray``
backed by dask, nothing rendered until computed.
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from archive import storage
from archive.errors import InputError, NoLineOnGrid
from archive.files import FileLock, host_name, path_exists, remove_path, replace_path
from archive.grid import Grid, GridRequest
from archive.outputs.stack import STACK_ATTR, StackFlight, StackLayout, add_slice, commit_stack, read_stack
from archive.run.session import StackSummary, render_failure

__all__ = ["STACK_ATTR", "StackFlight", "read_stack", "run_stack", "stack", "stack_grid", "survey"]


def _flight_name(source: str) -> str:
    return Path(source).name if Path(source).is_dir() else str(source)


def _alone(options, source: str):
    """The request of one flight of a stack: ``options`` for ``source`` alone, the grid left to the stack."""
    return dataclasses.replace(options.with_sources([source]), bounds=None, align=False, like=None)


def _time_span(planned) -> tuple[str, str]:
    """(first, last) line of a planned output, ISO 8601 UTC with microseconds."""
    from archive.formats.lcf import gps_seconds_to_datetime

    sources = planned.sources
    first = min(float(s.line_times(c)[0]) for s in sources for c in range(len(s.cubes)))
    last = max(float(s.line_times(c)[-1]) for s in sources for c in range(len(s.cubes)))
    iso = lambda t: gps_seconds_to_datetime(t).astimezone(UTC).isoformat(timespec="microseconds")  # noqa: E731
    return iso(first), iso(last)


@dataclass(frozen=True)
class _Surveyed:
    """A flight of a stack request as planning saw it: its source, name, first line (GPS s) and,
    when asked, its footprint grid's EPSG code and bounds (metres)."""

    source: str
    name: str
    first: float
    epsg: int | None = None
    bounds: tuple[float, float, float, float] | None = None


def survey(options, nav, sources: Sequence[str], say=None, footprints: bool = True,
           fov: float | None = None) -> list[_Surveyed]:
    """Open (and with ``footprints`` plan) each flight of ``sources`` alone, one at a time (metadata
    only: poses, no pixel), with the field of view ``fov`` (deg) decided for all of them; in time
    order (first line, then name)."""
    from archive.run.pipeline import open_inputs, plan_output

    say = say or (lambda text: None)
    out = []
    for src in sources:
        inputs = open_inputs(_alone(options, src), nav, say, mosaic=True, fov=fov)
        first = min(float(s.line_times(c)[0]) for s in inputs.sources for c in range(len(s.cubes)))
        epsg = bounds = None
        if footprints:
            grid = plan_output(inputs).plan.grid
            epsg, bounds = grid.epsg, grid.bounds
        out.append(_Surveyed(src, _flight_name(src), first, epsg, bounds))
        del inputs
    return sorted(out, key=lambda f: (f.first, f.name))


def stack_grid(options, nav, flights: Sequence[_Surveyed], say=None, fov: float | None = None) -> Grid:
    """The grid of a new stack of the surveyed ``flights`` (:func:`survey`): ``options.like``'s grid
    whole; else ``options.bounds`` or the union of the flights' footprints, pixel edges snapped
    outward to multiples of the GSD, in ``options.crs`` or the UTM zone most flights' grids are in
    (ties: the lowest EPSG code; a flight of another zone is planned again in it, with the field of
    view ``fov``, deg)."""
    from archive.run.pipeline import open_inputs, plan_output

    say = say or (lambda text: None)
    if options.like is not None:
        from archive.run.options import grid_request

        return grid_request(options).like
    epsgs = [f.epsg for f in flights]
    epsg = min(set(epsgs), key=lambda e: (-epsgs.count(e), e))
    boxes = []
    for f in flights:
        box = f.bounds
        if f.epsg != epsg:   # a flight of another zone: its footprint in the stack's CRS
            alone = dataclasses.replace(_alone(options, f.source), crs=f"EPSG:{epsg}")
            box = plan_output(open_inputs(alone, nav, say, mosaic=True, fov=fov)).plan.grid.bounds
        boxes.append(box)
    b = np.array(boxes)
    union = (float(b[:, 0].min()), float(b[:, 1].min()), float(b[:, 2].max()), float(b[:, 3].max()))
    return GridRequest(None, options.bounds, True).decide(epsg, union, float(options.gsd))


# ---------------------------------------------------------------------------------------------
# The store
# ---------------------------------------------------------------------------------------------
def _request_json(options) -> dict:
    """The stack's recipe: the request without its sources (a resume may add flights)."""
    from archive.run.batch import recipe_request

    return recipe_request(dataclasses.replace(options, sources=()))


def step_recipe(request: dict, source: str) -> str:
    """The digest (sha256 hex) of the recipe of one time step: the stack's ``request`` and the flight's
    ``source``; recorded with the step (``recipe``) so that a resume keeps only steps of its own recipe."""
    import hashlib

    text = json.dumps({"request": request, "source": str(source)}, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()


def _foreign_steps(flights: Sequence[StackFlight], request: dict) -> list[str]:
    """The ids of the steps of ``flights`` whose recorded recipe is not ``request``'s (steps of a stack
    written before recipes were recorded have none and are taken as the stack's request)."""
    return [f.id for f in flights if "recipe" in f.attrs and f.attrs["recipe"] != step_recipe(request, f.source)]


def stack_lock(out: Path) -> FileLock:
    """The lock a stack's writer holds (``.<name>.stack.lock`` beside the store), not yet taken."""
    return FileLock(out.with_name(f".{out.name}.stack.lock"), f"writing the stack {out.name}",
                    what=f"stack {out}", fix="wait for that run to finish, then --resume")



# ---------------------------------------------------------------------------------------------
# Writing a stack
# ---------------------------------------------------------------------------------------------
def _differences(stored: dict, wanted: dict) -> str:
    keys = [k for k in wanted if stored.get(k) != wanted.get(k)] + [k for k in stored if k not in wanted]
    return ", ".join(f"{k} {stored.get(k)!r} there, {wanted.get(k)!r} now" for k in keys[:4])


def run_stack(options, out, *, overwrite: bool = False, resume: bool = False, scheduler=None,
              workers: int | None = None, threads: int | None = None, quiet: bool = True,
              tell: Callable[[str], None] | None = None) -> StackSummary:
    """Write (or, with ``resume``, complete) the stack of ``options.sources`` at ``out`` (a .zarr);
    see the module docstring. ``tell(line)`` gets one line per flight (done / skipped / left out).
    Returns ``{"out", "flights" (ids in the stack, time order), "added", "skipped", "left_out",
    "renders" (render tasks run), "width", "height", "gsd", "epsg", "bands", "seconds"}``.
    ArchiveError before anything is written for problems of the whole request."""
    from archive.outputs.publish import Output
    from archive.run.pipeline import field_of_view, progress_lines

    started = time.perf_counter()
    tell = tell or (lambda line: None)
    say = progress_lines(quiet)
    nav = options.check()
    out = Path(out).absolute()
    if out.suffix.lower() != ".zarr":
        raise InputError(out, "a stack is one Zarr store (time, band, y, x)", "name --out X.zarr")
    if options.provenance:
        raise InputError("--provenance", "a stack holds no provenance layers",
                         "render the flight alone with --like X.zarr --provenance")
    if options.compression != "fast":   # its slices and store are made with the default codecs
        raise InputError("--compression", "a stack is written with the default compression (fast)",
                         "leave --compression out with --stack")
    if options.archive is not None and not storage.is_url(str(options.archive)):   # recipes independent of the cwd
        options = dataclasses.replace(options, archive=os.fspath(Path(options.archive).absolute()))
    fov = field_of_view(options)   # one field of view for all the flights
    Output(out, overwrite=True).check()   # a writable folder; temporaries of killed runs removed
    lock = stack_lock(out)
    try:
        lock.acquire()   # one writer at a time: a second is refused in one line naming the holder
    except OSError as exc:
        from archive.outputs.publish import unwritable_output

        raise unwritable_output(out.parent, exc) from None
    try:
        return _run_stack_locked(options, out, nav, fov, say, tell, started, overwrite=overwrite, resume=resume,
                                 scheduler=scheduler, workers=workers, threads=threads, quiet=quiet)
    finally:
        lock.release()


def _run_stack_locked(options, out: Path, nav, fov, say, tell, started: float, *, overwrite: bool, resume: bool,
                      scheduler, workers, threads, quiet: bool) -> dict:
    """:func:`run_stack` once the stack's lock is held."""
    from archive.run.session import Session, Waves
    from archive.outputs.publish import Output
    from archive.run.pipeline import build_output, open_inputs, plan_output

    for tmp in out.parent.glob(f"..{out.name}.slice-*.zarr.partial-*"):   # and their slice stores
        Output(tmp.parent / tmp.name[1:].split(".partial-")[0], overwrite=True).check()
    item_path = out.with_name(out.name + ".json")
    request = _request_json(options)
    existing = path_exists(out)
    if existing and not (resume or overwrite):
        raise InputError(out, "output exists already", "pass --resume to add the flights the stack lacks, or "
                         "--overwrite to make it again")
    layout: StackLayout | None = None
    flights: list[StackFlight] = []
    if existing and resume:
        try:
            layout, flights, stored = read_stack(out)
        except InputError:
            if not overwrite:
                raise
            layout, flights, stored = None, [], None
        if layout is not None and stored != request:
            if not overwrite:
                raise InputError(out, f"the stack was made with another request ({_differences(stored or {}, request)})",
                                 "pass the same options to --resume it, or --overwrite to make it again")
            layout, flights = None, []
        foreign = _foreign_steps(flights, request) if layout is not None else []
        if foreign:
            if not overwrite:
                raise InputError(out, f"time steps {', '.join(foreign[:3])} were written by another request",
                                 "pass --overwrite to make the stack again")
            layout, flights = None, []
    fresh = layout is None
    target = out if not fresh else out.with_name(f".{out.name}.partial-{os.getpid()}@{host_name()}")
    if fresh:
        remove_path(target)
    sources = list(dict.fromkeys(options.sources))
    have = {f.id for f in flights}
    todo = [s for s in sources if _flight_name(s) not in have]
    for s in sources:
        if _flight_name(s) in have:
            tell(f"skipped {_flight_name(s)}: in the stack already")
    # the flights to add, in time order (planned here one at a time, and again when rendered)
    surveyed = survey(options, nav, todo, say, footprints=layout is None and options.like is None, fov=fov)
    grid = layout.grid if layout is not None else stack_grid(options, nav, surveyed, say, fov)
    session = None
    added: list[str] = []
    left_out: list[str] = []
    renders = 0
    made_target = False
    try:
        if todo:
            session = Session(scheduler, workers, threads, say, what=f"stack {out}").start()
            budget, waves = session.budget, Waves(session)
            bar = None
            if not quiet:
                from tqdm import tqdm

                bar = tqdm(total=len(surveyed), desc="stack", unit="flight", file=sys.stderr)
            queue, inflight = deque(surveyed), deque()
            try:
                while queue or inflight:
                    # a wave: up to ``slots`` flights in the scheduler, each rendering into a slice store
                    # of its own; committed in time order as the earliest one completes
                    while queue and (waves.has_room() or not inflight):
                        one = queue.popleft()
                        t0 = time.perf_counter()
                        inputs = dataclasses.replace(open_inputs(_alone(options, one.source), nav, say, mosaic=True,
                                                                 fov=fov),
                                                     grid=GridRequest(grid))
                        try:
                            planned = plan_output(inputs, budget=budget)
                        except NoLineOnGrid:
                            left_out.append(one.name)
                            tell(f"left out {one.name}: no line of it on the stack's grid")
                            if bar is not None:
                                bar.update(1)
                            continue
                        if layout is None:
                            layout = _layout(grid, planned, options.zarr_format)
                        _check_like(layout, planned, one.name)
                        slice_out = Output(out.with_name(f".{out.name}.slice-{len(added) + len(inflight)}.zarr"),
                                           overwrite=True, zarr_format=layout.zarr_format)
                        record = _Slice(one, planned, slice_out, t0)
                        inflight.append(record)
                        record.sink, graph = build_output(planned, slice_out)
                        record.renders = graph.renders
                        waves.submit(record, graph.writes if len(graph) else [])
                    if not inflight:
                        continue
                    record = inflight[0]
                    while record.left:   # the earliest time step's tasks; the others' counted meanwhile
                        _check(*waves.next_done())
                    inflight.popleft()
                    waves.leave(record)
                    renders += record.renders
                    start, end = _time_span(record.planned)
                    flight = StackFlight(record.flight.name, record.flight.source, start, end,
                                         {**_flight_attrs(record.planned),
                                          "recipe": step_recipe(request, record.flight.source)})
                    if fresh and not made_target:
                        commit_stack(target, layout, [flight], request)   # the store, with its first time step
                        made_target = True
                    add_slice(Path(record.sink.path), target, layout, len(flights), layout.zarr_format)
                    flights.append(flight)
                    commit_stack(target, layout, flights, request)
                    record.output.cleanup()
                    if fresh and target != out and not overwrite:
                        replace_path(target, out)   # a new stack appears with its first slice: resumable
                        target = out
                        fresh = False
                    added.append(flight.id)
                    tell(f"done {flight.id}: time step {len(flights) - 1} "
                         f"({time.perf_counter() - record.started:.1f} s)")
                    if bar is not None:
                        bar.update(1)
                    _test_hold(len(added))
            finally:
                for record in inflight:   # given up: on a cluster that outlives us, no chunk lands after the clean-up
                    waves.leave(record, give_up=True)
                for record in inflight:
                    record.output.cleanup()
            if bar is not None:
                bar.close()
        if not flights:
            raise InputError("--stack", "no flight of the request has a line on the stack's grid",
                             "check --bounds / --like, or the query")
        remove_path(item_path)   # the stack changes: not complete until its new Item is written
        if target != out:
            replace_path(target, out)
            target = out
        _write_item(out, layout, flights, options)
    finally:
        if session is not None:   # a close that fails is one warning line, never the run's error
            session.close()
        if target != out:
            remove_path(target)
    g = layout.grid
    return {"out": str(out), "flights": [f.id for f in flights], "added": added,
            "skipped": [f.id for f in flights if f.id not in added], "left_out": left_out, "renders": renders,
            "width": g.width, "height": g.height, "gsd": g.gsd, "epsg": g.epsg, "bands": len(layout.bands),
            "seconds": time.perf_counter() - started}


def _test_hold(added: int) -> None:
    """Test-only: with ``ARCHIVE_TEST_HOLD_AFTER=N[:PATH]`` (:data:`archive.run.batch.TEST_HOLD_AFTER`,
    :func:`archive.files.test_hold`) a stack waits once N flights are committed (never set outside tests)."""
    from archive.run.batch import TEST_HOLD_AFTER
    from archive.files import test_hold

    test_hold(TEST_HOLD_AFTER, added)


@dataclass(eq=False)
class _Slice:
    """A flight of a wave: its survey, plan, slice output (a temporary single-flight store), sink,
    render count, futures and when its planning started."""

    flight: _Surveyed
    planned: object
    output: object
    started: float
    sink: object = None
    renders: int = 0
    futures: list = dataclasses.field(default_factory=list)
    left: int = 0   # its tasks not finished yet


def _check(record, status: str, exc: BaseException | None) -> None:
    """A finished task of a time step (:meth:`archive.run.session.Waves.next_done`): its error as an
    ArchiveError naming the flight (the stack stops)."""
    from archive.errors import ArchiveError, RenderError

    if record is None or status == "finished":
        return
    name = record.flight.name
    if status == "cancelled":
        raise RenderError(f"{name}: its tasks were cancelled (the scheduler lost them)")
    if isinstance(exc, ArchiveError):
        raise exc
    raise RenderError(f"{name}: {render_failure(exc)}")


#: Processing attributes that differ between the flights of a stack (kept per flight, not at the root).
_PER_FLIGHT = ("ground_height_m", "dem", "dem_datum", "sync_offset_s", "sources")


def _stack_attrs(attrs: dict) -> dict:
    return {k: v for k, v in attrs.items() if k not in _PER_FLIGHT}


def _flight_attrs(planned) -> dict:
    a = planned.attrs
    out = {k: a[k] for k in _PER_FLIGHT if k in a and k != "sources"}
    out["cubes"] = len(planned.plan.jobs)
    return json.loads(json.dumps(out, default=str))


def _layout(grid: Grid, planned, zarr_format: int) -> StackLayout:
    """The layout of a new stack whose first flight is ``planned``: its bands, or (an index output)
    one band per index, bands 0.., named by the indices (what each read: ``attrs["indices"]``)."""
    attrs = _stack_attrs(planned.attrs)
    if planned.indices:
        names = tuple(i.name for i in planned.indices)
        return StackLayout(grid, tuple(range(len(names))), None, None, planned.variable, attrs, zarr_format, names)
    return StackLayout(grid, tuple(planned.plan.bands[0]),
                       None if planned.wavelengths is None else tuple(planned.wavelengths),
                       None if planned.fwhm is None else tuple(planned.fwhm), planned.variable, attrs, zarr_format)


def _check_like(layout: StackLayout, planned, name: str) -> None:
    """InputError unless flight ``name`` gives the stack's bands and variable (an index stack: its
    indices, each from the same camera bands)."""
    if layout.names is not None or planned.indices:
        got = [i["describe"] for i in planned.attrs.get("indices", [])]
        want = [i.get("describe") for i in layout.attrs.get("indices", [])]
        if got != want:
            raise InputError(name, f"gives other index bands than the stack ({got} vs {want})",
                             "stack flights of one camera, with the stack's --index / --expression")
        return
    wl = None if planned.wavelengths is None else tuple(planned.wavelengths)
    if tuple(planned.plan.bands[0]) != layout.bands or wl != layout.wavelengths:
        raise InputError(name, f"selects other bands than the stack ({list(planned.plan.bands[0])} vs "
                         f"{list(layout.bands)})", "stack flights of one camera, or pass --wavelengths")
    if planned.variable != layout.variable:
        raise InputError(name, f"renders {planned.variable!r} but the stack holds {layout.variable!r}",
                         "pass --mode for every flight (a flight without calibration renders raw DN)")


def _write_item(out: Path, layout: StackLayout, flights: list[StackFlight], options) -> None:
    """The stack's STAC Item ``<out>.json`` (written last): a product Item of the grid and bands,
    the time span of its flights, and the datacube extension's ``cube:dimensions``/``cube:variables``."""
    from archive.catalog.product import render_command, stack_item
    from archive.catalog.stac import write_item
    from archive.outputs.zarr import FORMAT as ZARR

    command = render_command(options.with_sources([f.source for f in flights]), out) + " --stack"
    item = stack_item(out, fmt=ZARR, grid=layout.grid, band_indices=layout.bands, wavelengths=layout.wavelengths,
                      fwhm=layout.fwhm, variable=layout.variable, attrs=layout.attrs,
                      flights=[f.to_dict() for f in flights], command=command, request=options)
    if layout.names is not None:   # index bands: their names, and which camera band each symbol took
        indices = layout.attrs.get("indices", [])
        props = item["properties"]
        props["cube:dimensions"]["band"]["values"] = list(layout.names)
        props["archive:wavelengths"] = sorted({float(nm) for i in indices for nm in i["bands"].values()})
        props["archive:recipe"]["indices"] = indices
    write_item(out.with_name(out.name + ".json"), item)


def stack(options, *, band_group: int | None = None, quiet: bool = True, saturated: bool = False):
    """The stack of ``options`` as a lazy ``xarray.DataArray`` (time, band, y, x), nothing rendered
    until computed: each time step is :func:`archive.mosaic` of its flight alone on the stack's grid
    (:func:`stack_grid`), so its values are the Zarr stack's, bit for bit. Coordinates as the Zarr
    stack (``time`` as datetime64[ns] UTC, ``flight``, ``band``, ``wavelength``, x/y); the CRS set.
    A window (``.sel(x=..., y=...)``, ``.isel(time=...)``) renders only the flights and cubes under
    it (dask culls the other tiles' tasks; a tile no cube of a flight touches is NaN without GL).
    With ``saturated``: (values, flags), the flags the lazy (time, y, x) uint8 ``saturated`` of the
    Zarr stack (1 where the DN of some rendered band was saturated), sharing the values' tasks."""
    import xarray as xr

    from archive.run.pipeline import client_budget, field_of_view, plan as plan_of, planned_dataset, progress_lines

    nav = options.check()
    fov = field_of_view(options)   # one field of view for all the flights
    if options.provenance:
        raise InputError("provenance", "a stack holds no provenance layers")
    sources = list(dict.fromkeys(options.sources))
    surveyed = survey(options, nav, sources, progress_lines(quiet), footprints=options.like is None, fov=fov)
    grid = stack_grid(options, nav, surveyed, progress_lines(quiet), fov)
    budget = client_budget()
    steps = []
    for src in (f.source for f in surveyed):
        try:
            planned = plan_of(_alone(options, src), band_group=band_group, budget=budget, quiet=quiet,
                              grid=GridRequest(grid))
        except NoLineOnGrid:
            continue   # left out, as the Zarr stack leaves it out
        steps.append((_time_span(planned)[0], _flight_name(src), planned.variable, planned_dataset(planned)))
    if not steps:
        raise InputError("stack", "no flight of the request has a line on the stack's grid",
                         "check bounds / like, or the flights")
    steps.sort(key=lambda s: (s[0], s[1]))
    variable, first = steps[0][2], steps[0][3]
    for _, name, var, ds in steps:
        if var != variable or not np.array_equal(ds["band"].values, first["band"].values):
            raise InputError(name, "renders other bands or another variable than the stack's first flight",
                             "stack flights of one camera, or pass wavelengths and mode")
    times = [np.datetime64(datetime.fromisoformat(t).astimezone(UTC).replace(tzinfo=None), "ns") for t, *_ in steps]
    out = xr.concat([ds[variable] for *_, ds in steps], dim="time", coords="minimal", compat="override",
                    join="exact", combine_attrs="override")
    when = {"time": ("time", np.array(times)), "flight": ("time", [name for _, name, *_ in steps])}
    out = out.assign_coords(when)
    out["time"].attrs.update({"standard_name": "time", "long_name": "start of the flight (its first line), UTC"})
    if not saturated:
        return out
    flags = xr.concat([ds["saturated"] for *_, ds in steps], dim="time", coords="minimal", compat="override",
                      join="exact", combine_attrs="override").assign_coords(when)
    return out, flags
