"""``archive render``: georectify flights into one mosaic (Zarr, COG or ENVI) on a Dask cluster.

Steps: check every input early (clear one-line errors); open the sources; build the cube meshes and
the output grid (metadata only); build the Dask graph (:mod:`archive.graph`); run it on a local
cluster (one worker process, two threads, GL tasks one at a time: GL contexts are per thread) or on ``--scheduler``; then
convert the Zarr the workers wrote into the requested format and move it into place. Nothing is
left at ``--out`` when anything fails.

Batch jobs: ``--archive A --query-bbox/--query-datetime/--query-wavelength`` adds every matching
collection of A's catalog to the sources; without ``--mosaic`` each flight gets its own output
``--out DIR/<id>.<format>``, with ``--mosaic`` all go into one. Either way one graph runs them all
(one progress bar). Band groups are sized from the workers' memory limits (:func:`_task_budget`).
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from archive.errors import ArchiveError, InputError, MissingInputError, RenderError
from archive.outputs import Output, variable_for_mode
from archive.params import NavigationParams, RenderParams

__all__ = ["run", "render", "select_bands", "resolve_ground_height", "check_size",
           "TASK_BUDGET_BYTES", "OUTPUT_BUDGET"]

#: Largest render task: cube window x 4 bands x float32 (plus its flags), bytes.
TASK_BUDGET_BYTES = 2 * 1024**3
#: Largest output, in pixels x bands.
OUTPUT_BUDGET = 4e10
#: A requested wavelength must lie within this many band widths of a band.
WAVELENGTH_TOLERANCE = 1.5
GROUND_KEY = "ground elevation"


# ---------------------------------------------------------------------------------------------
# Input checks
# ---------------------------------------------------------------------------------------------
def _parse_floats(text: str, option: str) -> list[float]:
    try:
        values = [float(v) for v in text.replace(" ", "").split(",") if v]
    except ValueError:
        raise InputError(option, f"expected comma-separated numbers, got {text!r}", f"e.g. {option} 550,650") from None
    if not values or not all(math.isfinite(v) for v in values):
        raise InputError(option, f"expected comma-separated numbers, got {text!r}", f"e.g. {option} 550,650")
    return values


def select_bands(source, wavelengths: Sequence[float] | None = None, bands: str | None = "all") -> list[int]:
    """Source band indices to render: nearest bands to ``wavelengths`` (nm), else ``bands``.

    bands: 'all' or comma-separated 0-based indices. A wavelength farther than 1.5 band widths
    from every band is an InputError naming the source's range.
    """
    nbands = source.cubes[0].bands
    where = getattr(source, "directory", source.id)
    if wavelengths is not None:
        wl = None if source.wavelengths is None else np.asarray(source.wavelengths, float)
        if wl is None or len(wl) == 0:
            raise InputError(where, "the cubes have no 'wavelength' list", "use --bands all")
        spacing = np.abs(np.gradient(wl)) if len(wl) > 1 else np.array([10.0])
        out: list[int] = []
        for w in wavelengths:
            i = int(np.argmin(np.abs(wl - w)))
            if abs(wl[i] - w) > WAVELENGTH_TOLERANCE * spacing[i]:
                raise InputError(
                    "--wavelengths", f"no band near {w:g} nm in {where} (bands span "
                    f"{wl.min():.1f}-{wl.max():.1f} nm, nearest {wl[i]:.1f} nm)",
                    "choose wavelengths inside the cubes' range",
                )
            if i not in out:
                out.append(i)
        return out
    if bands is None or str(bands).strip().lower() == "all":
        return list(range(nbands))
    try:
        out = [int(b) for b in str(bands).split(",") if b.strip()]
    except ValueError:
        raise InputError("--bands", f"expected 'all' or 0-based band indices, got {bands!r}") from None
    bad = [b for b in out if not 0 <= b < nbands]
    if bad or not out:
        raise InputError("--bands", f"band {bad[0] if bad else bands} out of range 0..{nbands - 1}")
    return list(dict.fromkeys(out))


def resolve_ground_height(value: str | float | None, sources: Sequence) -> float:
    """A number (metres above the ellipsoid), or 'auto': every cube header's 'ground elevation'."""
    if value is not None and str(value).strip().lower() != "auto":
        try:
            h = float(value)
        except ValueError:
            raise InputError("--ground-height", f"expected metres or 'auto', got {value!r}") from None
        if not math.isfinite(h):
            raise InputError("--ground-height", f"expected a finite height, got {value!r}")
        return h
    found: dict[float, str] = {}
    for source in sources:
        header = getattr(source, "header", None)
        for i, info in enumerate(source.cubes):
            meta = header(i).metadata if header is not None else {}
            # a collection keeps the ground height it was ingested with
            raw = meta.get(GROUND_KEY, getattr(source, "ground_height", None))
            try:
                h = float(raw)  # type: ignore[arg-type]
            except (TypeError, ValueError):
                raise InputError(
                    getattr(source, "directory", source.id),
                    f"cube {info.base} has no usable '{GROUND_KEY}' header key for --ground-height auto",
                    "pass --ground-height M (metres above the ellipsoid, the .lcf altitude datum)",
                ) from None
            found.setdefault(h, info.base)
    if len(found) > 1:
        listing = ", ".join(f"{h:g} m ({base})" for h, base in found.items())
        raise InputError("--ground-height", f"the cubes disagree on '{GROUND_KEY}': {listing}",
                         "pass --ground-height M")
    return next(iter(found))


def _nice(x: float) -> float:
    """Round up to 1, 2 or 5 x 10^k."""
    k = 10 ** math.floor(math.log10(x))
    return next(m * k for m in (1, 2, 5, 10) if m * k >= x)


def check_size(plan, gsd: float) -> None:
    """InputError when the output or a render task would be absurdly large for this GSD."""
    grid = plan.grid
    total = grid.width * grid.height * plan.nbands
    group = max(b1 - b0 for b0, b1 in plan.groups)
    biggest = max((job.window.width * job.window.height for job in plan.jobs), default=0)
    task = biggest * (group * 4 + 2)
    if total > OUTPUT_BUDGET:
        suggest = _nice(gsd * math.sqrt(total / OUTPUT_BUDGET))
        raise InputError(
            "--gsd", f"{gsd:g} m gives a {grid.width} x {grid.height} px x {plan.nbands}-band output "
            f"({total:.3g} pixel-bands, {total * 4 / 1024**4:.1f} TiB), over the {OUTPUT_BUDGET:.0e} limit",
            f"use --gsd {suggest:g} or larger, or fewer --wavelengths",
        )
    if task > TASK_BUDGET_BYTES:
        suggest = _nice(gsd * math.sqrt(task / TASK_BUDGET_BYTES))
        raise InputError(
            "--gsd", f"{gsd:g} m makes one cube cover {biggest:.3g} px ({task / 1024**3:.1f} GiB per "
            f"{group}-band render task, limit {TASK_BUDGET_BYTES / 1024**3:.0f} GiB)",
            f"use --gsd {suggest:g} or larger",
        )


def _read_white_reference(path: str, wavelengths) -> np.ndarray:
    """(bands,) white radiance from a two-column text file (nm, radiance), interpolated to the bands."""
    p = Path(path)
    if not p.is_file():
        raise MissingInputError(p, "white reference spectrum", "check --white-reference")
    try:
        table = np.loadtxt(p, delimiter=None if "," not in p.read_text()[:200] else ",", ndmin=2)
    except ValueError as exc:
        raise InputError(p, f"cannot read a (wavelength nm, radiance) table: {exc}") from None
    if table.shape[1] < 2 or table.shape[0] < 2:
        raise InputError(p, "expected two columns (wavelength nm, radiance) and at least two rows")
    if wavelengths is None:
        raise InputError(p, "the cubes have no wavelengths to interpolate the white reference to")
    order = np.argsort(table[:, 0])
    return np.interp(np.asarray(wavelengths, float), table[order, 0], table[order, 1])


@dataclass
class _Inputs:
    sources: list
    bands: list[list[int]]
    params: RenderParams
    grounds: list[float]   # ground height (m) per source


def _check_args(args: argparse.Namespace) -> tuple[Output | None, NavigationParams]:
    """Checks that need no file reading (fast, before anything starts); the one Output (None in
    per-flight batch mode)."""
    gsd = args.gsd
    if not (isinstance(gsd, (int, float)) and math.isfinite(gsd) and gsd > 0):
        raise InputError("--gsd", f"must be a positive number of metres, got {gsd!r}", "e.g. --gsd 0.25")
    output = None
    if not getattr(args, "per_flight", False):
        output = Output(Path(args.out).absolute(), overwrite=bool(args.overwrite),
                        quicklook=None if not args.quicklook else Path(args.quicklook).absolute())
        output.check()
    if not args.sources:
        raise InputError("SOURCE", "nothing to render",
                         "give flight directories or collection ids, or --archive A with --query-bbox/"
                         "--query-datetime/--query-wavelength")
    archive = getattr(args, "archive", None)
    collections = [src for src in args.sources if not Path(src).is_dir()]
    for src in collections:
        if archive is None:
            raise MissingInputError(src, "flight directory",
                                    "give a raw flight directory, or a collection id together with --archive ARCHIVE")
    if args.fov is None and len(collections) < len(args.sources):
        raise InputError("--fov", "the field of view is required for raw flight directories",
                         "pass --fov DEG (47.5 for a Pika L and for 'archive simulate' flights)")
    if args.fov is None:
        args.fov = _collection_fov(archive, collections)
    if not (0 < args.fov < 180):
        raise InputError("--fov", f"must be between 0 and 180 degrees, got {args.fov:g}")
    if not math.isfinite(args.sync_offset):
        raise InputError("--sync-offset", f"must be a finite number of seconds, got {args.sync_offset!r}")
    if args.mode == "reflectance" and not getattr(args, "white_reference", None):
        raise InputError("--mode", "reflectance needs a white reference spectrum", "pass --white-reference FILE")
    return output, NavigationParams(fov_deg=float(args.fov), sync_offset=float(args.sync_offset))


def _collection_fov(archive, ids: Sequence[str]) -> float:
    """The field of view the collections were ingested with (they must agree); reads attributes only."""
    import zarr

    from archive.catalog.root import open_archive

    root = open_archive(archive)
    fovs = {float(zarr.open_group(root.require_collection(i), mode="r").attrs["fov_deg"]) for i in ids}
    if len(fovs) != 1:
        raise InputError("--fov", f"the collections were ingested with different fields of view {sorted(fovs)}",
                         "pass --fov DEG")
    return fovs.pop()


def _check_same_bands(sources: Sequence, bands: Sequence[Sequence[int]]) -> None:
    """InputError unless every source renders as many bands, at the same wavelengths (to 1/2 band)."""
    first = sources[0]
    for s, b in zip(sources[1:], bands[1:]):
        where = getattr(s, "directory", s.id)
        if len(b) != len(bands[0]):
            raise InputError(where, f"{len(b)} bands selected, but {len(bands[0])} in the first source",
                             "render sources with the same bands together, or pick --wavelengths")
        if first.wavelengths is None or s.wavelengths is None:
            continue
        w0 = np.asarray(first.wavelengths, float)
        tol = 0.5 * float(np.min(np.abs(np.diff(w0)))) if len(w0) > 1 else 1.0
        wa = w0[list(bands[0])]
        wb = np.asarray(s.wavelengths, float)[list(b)]
        worst = int(np.argmax(np.abs(wa - wb)))
        if abs(wa[worst] - wb[worst]) > tol:
            raise InputError(where, f"band at {wb[worst]:.1f} nm does not match {wa[worst]:.1f} nm of the "
                             "first source", "render sensors with different bands separately")


def _open_inputs(args: argparse.Namespace, nav: NavigationParams, say, mosaic: bool = True) -> _Inputs:
    from archive.sources import open_source

    # absolute paths: workers (maybe on another machine sharing the file system) open them again
    archive = getattr(args, "archive", None)
    sources = [open_source(Path(src).absolute() if Path(src).is_dir() else src, nav,
                           calibration=args.calibration, archive=archive) for src in args.sources]
    wavelengths = _parse_floats(args.wavelengths, "--wavelengths") if args.wavelengths else None
    bands = [select_bands(s, wavelengths, getattr(args, "bands", "all")) for s in sources]
    if mosaic:
        _check_same_bands(sources, bands)
    if getattr(args, "white_reference", None):
        for s in sources:
            s.white_reference = _read_white_reference(args.white_reference, s.wavelengths)
    mode = args.mode or "radiance"
    uncalibrated = [s for s in sources if getattr(s, "calibration_path", True) is None]
    if mode == "radiance" and uncalibrated and not args.calibration:
        where = getattr(uncalibrated[0], "directory", uncalibrated[0].id)
        say(f"archive render: {where} has no radiometric calibration (*.icp): rendering raw DN")
        mode = "raw"
    for s, b in zip(sources, bands):
        s.radiometry(0, b[:1], mode)  # mode problems (calibration, white reference) surface now
    if mosaic:
        grounds = [resolve_ground_height(args.ground_height, sources)] * len(sources)
    else:
        grounds = [resolve_ground_height(args.ground_height, [s]) for s in sources]
    params = RenderParams(gsd=float(args.gsd), ground_height=grounds[0], mode=mode,
                          bands=tuple(bands[0]), overlap=args.overlap, navigation=nav)
    return _Inputs(sources, bands, params, grounds)


# ---------------------------------------------------------------------------------------------
# Running the graph
# ---------------------------------------------------------------------------------------------
def _cluster(args: argparse.Namespace, say):
    """(client, cluster or None): ``--scheduler`` or a local cluster of GPU-resourced workers."""
    import logging

    from distributed import Client, LocalCluster

    if args.scheduler:
        try:
            client = Client(args.scheduler, timeout="20s")
        except OSError as exc:
            raise InputError("--scheduler", f"cannot connect to {args.scheduler}: {exc}",
                             "start one with `dask scheduler` and workers with `--resources GPU=1`") from None
        say(f"archive render: Dask dashboard at {client.dashboard_link}")
        workers = client.scheduler_info().get("workers", {})
        if not any((w.get("resources") or {}).get("GPU", 0) >= 1 for w in workers.values()):
            client.close()
            raise InputError(
                "--scheduler", f"no worker of {args.scheduler} offers the 'GPU' resource the render tasks need",
                f"start workers with `dask worker {args.scheduler} --nthreads 1 --resources GPU=1`",
            )
        return client, None
    workers = int(getattr(args, "workers", None) or 1)
    cores = max(1, (os.cpu_count() or 1) // workers)
    # Spawned worker processes (never forked after GL). Two threads each: the GPU=1 resource keeps
    # GL tasks one at a time per worker (each thread has its own context) while the other thread
    # assembles and compresses the previous band group.
    cluster = LocalCluster(n_workers=workers, threads_per_worker=2, processes=True,
                           resources={"GPU": 1}, env={"LP_NUM_THREADS": str(cores)},
                           dashboard_address=":0", silence_logs=logging.CRITICAL)  # errors come back here
    return Client(cluster), cluster


def _wait_for_writers(client, timeout: float = 60.0) -> None:
    """Wait until no worker is still running one of our writer tasks (best effort)."""
    deadline = time.monotonic() + timeout
    try:
        while time.monotonic() < deadline:
            running = [k for stack in client.call_stack().values() for k in stack]
            if not any(str(k).startswith(("write-", "saturated-")) for k in running):
                return
            time.sleep(0.2)
    except Exception:  # the scheduler may be gone already
        pass


def _execute(client, graph, quiet: bool, shared: bool) -> None:
    """Compute the writer tasks with a progress bar; re-raise the first task error as an ArchiveError.

    shared: the cluster outlives this command (``--scheduler``): on failure, cancel our tasks and
    wait for running writers, so that no chunk lands in the store after it is deleted.
    """
    from distributed import KilledWorker, as_completed
    from tqdm import tqdm

    futures = client.compute(list(graph.writes))
    done = as_completed(futures)
    del futures  # only as_completed holds them: results are released as soon as they are counted
    try:
        with tqdm(total=len(graph), desc="render", unit="task", disable=quiet, file=sys.stderr) as bar:
            for future in done:
                if future.status == "error":
                    future.result()  # raises the task's exception here
                future.release()
                bar.update(1)
    except BaseException as exc:
        if shared:
            client.cancel(list(done.futures), force=True)
            _wait_for_writers(client)
        if isinstance(exc, (ArchiveError, KeyboardInterrupt)) or not isinstance(exc, Exception):
            raise
        if isinstance(exc, KilledWorker):
            raise RenderError(f"a Dask worker died while rendering ({exc}); it may have run out of memory "
                              "or crashed in OpenGL: try a larger --gsd or fewer --wavelengths") from exc
        raise RenderError(f"a render task failed: {type(exc).__name__}: {exc}") from exc


# ---------------------------------------------------------------------------------------------
# The command
# ---------------------------------------------------------------------------------------------
def _resolve_query(args: argparse.Namespace) -> list[str] | None:
    """Collection ids of --archive matching the --query-* filters, appended to ``args.sources``
    (None, and nothing changed, when no filter is given). Sets ``args.per_flight``."""
    bbox, when = getattr(args, "query_bbox", None), getattr(args, "query_datetime", None)
    wavelength = getattr(args, "query_wavelength", None)
    args.per_flight = False
    if bbox is None and when is None and wavelength is None:
        return None
    if not getattr(args, "archive", None):
        raise InputError("--query-*", "a catalog query needs the archive to search", "pass --archive ARCHIVE")
    from archive.catalog.index import ensure_index, parse_bbox, parse_datetime_range, search
    from archive.catalog.root import open_archive

    box = parse_bbox(bbox) if bbox is not None else None
    start, end = parse_datetime_range(when) if when is not None else (None, None)
    if wavelength is not None and not (math.isfinite(wavelength) and wavelength > 0):
        raise InputError("--query-wavelength", f"{wavelength} is not a positive wavelength in nm")
    rows = search(ensure_index(open_archive(args.archive)), bbox=box, start=start, end=end,
                  wavelength=wavelength)
    if not rows:
        asked = ", ".join(f"{k} {v}" for k, v in (("--query-bbox", bbox), ("--query-datetime", when),
                                                   ("--query-wavelength", wavelength)) if v is not None)
        raise InputError(args.archive, f"no flight in the catalog matches {asked}",
                         "check the filters with 'archive catalog search'")
    ids = [r.id for r in rows]
    args.sources = list(args.sources or []) + [i for i in ids if i not in (args.sources or [])]
    args.per_flight = not getattr(args, "mosaic", False)
    return ids


def _flight_outputs(args: argparse.Namespace) -> list[Output]:
    """Per-flight batch mode: ``--out DIR/<name>.<format>`` for each source (checked now)."""
    directory = Path(args.out).absolute()
    if directory.exists() and not directory.is_dir():
        raise InputError(directory, "is a file, but a batch job writes one output per flight into a directory",
                         "give --out DIR, or --mosaic for one output")
    if directory.suffix.lower() in (".zarr", ".tif", ".tiff", ".hdr"):
        raise InputError(directory, "looks like one output file, but a batch job writes one output per flight",
                         "give --out DIR (outputs DIR/<id>.<format>), or add --mosaic")
    if args.quicklook:
        raise InputError("--quicklook", "only one quicklook per command", "add --mosaic, or leave it out")
    outputs = []
    for src in args.sources:
        name = Path(src).name if Path(src).is_dir() else str(src)
        out = Output(directory / f"{name}.{getattr(args, 'format', 'zarr')}", overwrite=bool(args.overwrite))
        out.check()
        outputs.append(out)
    return outputs


def _task_budget(client) -> int:
    """Bytes of rendered values one render task may hold: TASK_VALUES_BYTES, or a tenth of the
    smallest worker memory limit when that is less (small workers get smaller band groups)."""
    from archive.graph.build import TASK_VALUES_BYTES

    limits = [int(w.get("memory_limit") or 0) for w in client.scheduler_info().get("workers", {}).values()]
    limits = [m for m in limits if m > 0]
    return min([TASK_VALUES_BYTES] + [m // 10 for m in limits])


@dataclass
class _Job:
    """One output of a command: its Output, plan, store and graph."""

    output: Output
    sources: list
    plan: object = None
    store: object = None
    graph: object = None
    wavelengths: list | None = None


def render(args: argparse.Namespace) -> dict:
    """Run ``archive render`` for parsed ``args``; returns a summary dict. Raises ArchiveError.

    One output (``--out PATH``), or in batch mode (``--query-*`` without ``--mosaic``) one output
    per flight (``--out DIR``): then the summary holds ``outputs``, one summary per flight. Every
    output's tasks run in one graph.
    """
    from archive.graph.build import RenderGraph, build_render_graph, with_task_groups
    from archive.graph.plan import cube_meshes, plan_render
    from archive.outputs import MosaicStore

    started = time.perf_counter()
    quiet = bool(getattr(args, "quiet", False))

    def say(text: str) -> None:
        if not quiet:
            print(text, file=sys.stderr)

    _resolve_query(args)
    output, nav = _check_args(args)
    mosaic = output is not None
    outputs = [output] if mosaic else _flight_outputs(args)
    client = cluster = None
    jobs: list[_Job] = []
    try:
        inputs = _open_inputs(args, nav, say, mosaic=mosaic)
        p = inputs.params
        members = [list(range(len(inputs.sources)))] if mosaic else [[i] for i in range(len(inputs.sources))]
        client, cluster = _cluster(args, say)
        budget = _task_budget(client)
        for out, idx in zip(outputs, members):
            sources = [inputs.sources[i] for i in idx]
            bands = [inputs.bands[i] for i in idx]
            ground = inputs.grounds[idx[0]]
            meshes = [cube_meshes(s, nav.fov_deg, ground) for s in sources]
            plan = with_task_groups(plan_render(sources, meshes, bands, p.gsd), budget)
            check_size(plan, p.gsd)
            wavelengths = sources[0].wavelengths
            out_wl = None if wavelengths is None else [wavelengths[b] for b in bands[0]]
            attrs = {
                "mode": p.mode, "gsd_m": p.gsd, "fov_deg": nav.fov_deg, "ground_height_m": ground,
                "sync_offset_s": nav.sync_offset, "overlap": p.overlap,
                "sources": [str(getattr(s, "directory", s.id)) for s in sources],
            }
            store = MosaicStore.create(out.store_path, plan.grid, out_wl, bands[0], variable_for_mode(p.mode), attrs)
            graph = build_render_graph(plan, sources, store, mode=p.mode, overlap=p.overlap,
                                       mesh_spec=(nav, ground))
            jobs.append(_Job(out, sources, plan, store, graph, out_wl))
        graph = RenderGraph(tuple(w for j in jobs for w in j.graph.writes), sum(j.graph.renders for j in jobs),
                            sum(j.graph.assemblies for j in jobs))
        if len(graph):
            _execute(client, graph, quiet, shared=cluster is None)
        for job in jobs:
            job.output.finalize(job.store)
    finally:
        if client is not None:
            client.close()
        if cluster is not None:
            cluster.close()  # stops the worker processes, with any task still writing
        for out in outputs:
            out.cleanup()
    seconds = time.perf_counter() - started
    summaries = []
    for job in jobs:
        g = job.plan.grid
        summaries.append({
            "out": str(job.output.path) if not mosaic else str(args.out), "width": g.width, "height": g.height,
            "gsd": g.gsd, "epsg": g.epsg, "bands": job.plan.nbands, "wavelengths": job.wavelengths,
            "mode": p.mode, "cubes": len(job.plan.jobs), "sources": len(job.sources),
            "renders": job.graph.renders, "seconds": seconds,
        })
    if mosaic:
        return summaries[0]
    return {"outputs": summaries, "seconds": seconds, "renders": graph.renders}


def _describe(s: dict) -> str:
    wl = s["wavelengths"]
    span = f" ({min(wl):.1f}-{max(wl):.1f} nm)" if wl else ""
    return (f"{s['out']}: {s['width']} x {s['height']} px at {s['gsd']:g} m, "
            f"EPSG:{s['epsg']}, {s['bands']} band{'s' if s['bands'] != 1 else ''}{span}, {s['mode']}, "
            f"{s['cubes']} cube{'s' if s['cubes'] != 1 else ''} from {s['sources']} source"
            f"{'s' if s['sources'] != 1 else ''}")


def run(args: argparse.Namespace) -> int:
    """CLI entry point of ``archive render`` (see :func:`render`); prints a one-paragraph summary
    (batch mode: one line per output, then the total)."""
    s = render(args)
    if "outputs" in s:
        for one in s["outputs"]:
            print(f"archive render: wrote {_describe(one)}.")
        n = len(s["outputs"])
        print(f"archive render: {n} output{'s' if n != 1 else ''} in {s['seconds']:.1f} s.")
        return 0
    print(f"archive render: wrote {_describe(s)} in {s['seconds']:.1f} s.")
    return 0
