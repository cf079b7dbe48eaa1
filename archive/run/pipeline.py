"""Georectify flights on Dask: open -> plan -> build -> run -> publish, for every kind of output.

A render is asked for by :class:`~archive.run.options.RenderOptions` (checked once, before anything starts:
:meth:`~archive.run.options.RenderOptions.check`) and goes through the same steps whatever comes out:

1. open (:func:`open_inputs`): open the sources (:func:`archive.sources.open_source`), select the
   bands, settle the radiometric mode, and decide once how the meshes are built, the
   :class:`~archive.params.MeshSpec` (field of view, ground height or DEM, view-angle limit, CRS);
2. plan (:func:`plan_output`): cube meshes, output grid and cube windows (metadata only, no GL;
   the graph's tasks build the meshes again on the workers: the plan keeps only the windows);
3. build (:func:`build_output`): the output's sink under a temporary name
   (:mod:`archive.outputs`) and the render graph that writes it (:mod:`archive.graph.build`);
4. run (:func:`archive.run.cluster.execute`): on a local cluster or ``scheduler`` (:mod:`archive.run.cluster`);
5. publish (:func:`publish`): finish the output (ENVI header, COG layout), rename it into place,
   then write its STAC Item, last (an Item says the output is complete).

:func:`georectify` runs all five (nothing is left at ``out`` when anything fails); :func:`mosaic`
stops after planning and gives the plan as a lazy ``xarray.Dataset`` (:mod:`archive.graph.lazy`)
computed on demand. Batch jobs (one output per source, each flight a job of its own, submitted in
waves) are :mod:`archive.run.batch`'s, built from these steps. Band groups are sized from the workers'
memory limits (:func:`archive.run.cluster.task_budget`).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from archive import storage
from archive.run.cluster import active_client, check_gpu_workers, execute, task_budget
from archive.errors import InputError
from archive.formats.trajectory import parse_columns
from archive.files import wait_while_exists
from archive.grid import GridRequest
from archive.geometry.navigation import projected_epsg
from archive.run.options import RenderOptions, grid_request
from archive.run.session import Job, RenderSummary, Session, render_summary
from archive.outputs.bandmath import bind_indices
from archive.outputs.base import variable_for_mode
from archive.outputs.indexed import IndexSink, index_properties
from archive.outputs.publish import Output
from archive.outputs.zarr import mosaic_dataset
from archive.params import MeshSpec, NavigationParams, RenderParams
from archive.sources.select import check_same_bands, read_white_reference, resolve_ground_height, select_bands

if TYPE_CHECKING:
    from archive.graph.plan import RenderPlan

__all__ = ["OUTPUT_BUDGET", "TASK_BUDGET_BYTES", "Inputs", "OutputPlan", "build_output", "check_size", "client_budget",
           "describe", "field_of_view", "georectify", "mosaic", "open_inputs", "plan", "plan_output", "planned_dataset",
           "progress_lines", "publish"]

#: Largest render task: cube window x 4 bands x float32 (plus its flags), bytes.
TASK_BUDGET_BYTES = 2 * 1024**3
#: Largest output, in pixels x bands.
OUTPUT_BUDGET = 4e10


# ---------------------------------------------------------------------------------------------
# Open and plan
# ---------------------------------------------------------------------------------------------
def _nice(x: float) -> float:   # rounded up to 1, 2 or 5 x 10^k
    k = 10 ** math.floor(math.log10(x))
    return next(m * k for m in (1, 2, 5, 10) if m * k >= x)


def check_size(plan, gsd: float) -> None:
    """InputError when the output or a render task would be absurdly large for this GSD."""
    grid = plan.grid
    total = grid.width * grid.height * plan.nbands
    group = max(b1 - b0 for b0, b1 in plan.groups)
    biggest = max((job.window.width * job.window.height for job in plan.jobs), default=0)
    task = biggest * (group * 4 + 2)
    limits = ((total, OUTPUT_BUDGET, f"{gsd:g} m gives a {grid.width} x {grid.height} px x {plan.nbands}-band output "
               f"({total:.3g} pixel-bands, {total * 4 / 1024**4:.1f} TiB), over the {OUTPUT_BUDGET:.0e} limit",
               ", or fewer --wavelengths"),
              (task, TASK_BUDGET_BYTES, f"{gsd:g} m makes one cube cover {biggest:.3g} px ({task / 1024**3:.1f} GiB "
               f"per {group}-band render task, limit {TASK_BUDGET_BYTES / 1024**3:.0f} GiB)", ""))
    for size, limit, problem, also in limits:
        if size > limit:
            raise InputError("--gsd", problem, f"use --gsd {_nice(gsd * math.sqrt(size / limit)):g} or larger{also}")


@dataclass(frozen=True, eq=False)
class Inputs:
    """The opened sources of a request: bands (per source, the source band of each output band),
    params (gsd, mode as settled, overlap, navigation), mesh_specs (per source, the
    :class:`~archive.params.MeshSpec` its cube meshes are built from: field of view, flat ground or
    DEM, view-angle limit, ``--crs``; in a mosaic one and the same for every source)."""

    sources: tuple
    bands: tuple[tuple[int, ...], ...]
    params: RenderParams
    mesh_specs: tuple[MeshSpec, ...]
    meshes: tuple | None = None  #: with a DEM: each source's terrain meshes (built here: DEM errors come early)
    grid: GridRequest = GridRequest()  #: what the output grid is asked to be (--bounds, --align, --like)
    indices: tuple | None = None  #: --index/--expression: per source, its BoundIndex of each output band


def _quiet(text: str) -> None:
    pass


def field_of_view(options: RenderOptions) -> float:
    """The field of view (deg) the meshes of ``options`` are built with: ``--fov``, else the one the
    collections of ``options`` were ingested with (their records read here; they must agree)."""
    if options.fov is not None:
        return float(options.fov)
    from archive.sources.open import collection_fov

    return float(collection_fov(options.archive, options.sources))


def open_inputs(options: RenderOptions, nav: NavigationParams, say=_quiet, mosaic: bool = True,
                fov: float | None = None) -> Inputs:
    """Open and check the sources of ``options`` (``nav`` from :meth:`~archive.run.options.RenderOptions.check`)
    and decide, once, the :class:`~archive.params.MeshSpec` their meshes are built from.

    mosaic: all sources go into one output (same bands, one ground height); else each source is
    an output of its own. ``say(text)`` tells notes (a source without calibration renders raw DN).
    fov: the field of view (deg) when the caller decided it for several requests (a stack's or
    tiles' flights, each opened alone), else :func:`field_of_view` of ``options``.
    With a DEM, the sources' terrain meshes are built here (metadata and DEM only, no pixel, no GL),
    so that a DEM that does not cover the flights, or has holes under them, fails before any
    cluster starts.
    """
    from archive.graph.plan import spec_meshes
    from archive.sources import open_source

    from archive.terrain.dem import DemSpec
    from archive.sources.ground import sources_dem

    grid = grid_request(options)   # --like read once, before the sources
    fov = field_of_view(options) if fov is None else float(fov)
    mesh = functools.partial(MeshSpec, fov, max_view_angle=float(options.max_view_angle),
                             epsg=None if options.crs is None else projected_epsg(options.crs))
    given_dem = None if options.dem is None else DemSpec.create(options.dem, options.dem_datum)
    terrain = None if given_dem is None else given_dem.open()   # opened once, here: its errors before the sources'
    # absolute paths: workers (maybe on another machine sharing the file system) open them again
    archive = None if options.archive is None else \
        (options.archive if storage.is_url(options.archive) else Path(options.archive).absolute())

    def opened(src, white=None):
        return open_source(Path(src).absolute() if Path(src).is_dir() else src, nav, calibration=options.calibration,
                           white_reference=white, archive=archive, irradiance_calibration=options.irradiance_calibration,
                           navigation=options.navigation, navigation_columns=parse_columns(options.navigation_columns))

    sources = [opened(src) for src in options.sources]
    if options.white_reference:   # interpolated to each source's wavelengths: opened again with it
        sources = [opened(src, read_white_reference(options.white_reference, s.wavelengths))
                   for s, src in zip(sources, options.sources)]
    specs = options.indices()   # --index/--expression: the bands they read, chosen by wavelength
    bound = [tuple(bind_indices(specs, s.wavelengths, str(s.label))) if specs else None for s in sources]
    bands = [select_bands(s, options.wavelengths, options.bands) if b is None else
             select_bands(s, sorted({nm for i in b for nm in i.wavelengths})) for s, b in zip(sources, bound)]
    if mosaic:
        check_same_bands(sources, bands)
    mode = options.mode or "radiance"
    uncalibrated = [s for s in sources if not s.has_calibration]
    if mode == "radiance" and uncalibrated and not options.calibration:
        say(f"archive render: {uncalibrated[0].label} has no radiometric calibration (*.icp): rendering raw DN")
        mode = "raw"
    if options.panels:   # the empirical line, fitted per flight on its selected bands (issue 34)
        from archive.render.empirical_line import panelled

        flat = [mesh(float(resolve_ground_height(options.ground_height, [s]))) for s in sources]
        sources = [panelled(s, dict(enumerate(spec_meshes(s, spec))), b, options.panels)
                   for s, spec, b in zip(sources, flat, bands)]
    for s, b in zip(sources, bands):
        s.radiometry(0, b[:1], mode)  # mode problems (calibration, white reference) surface now
    if given_dem is not None:   # the DEM gives the ground: no flat height to settle
        dem = given_dem
    elif str(options.ground_height).strip().lower() == "auto":   # collections ingested with --dem: theirs
        dem = sources_dem(sources)
        terrain = None if dem is None else dem.open()
    else:
        dem = None
    meshes = None
    if dem is not None:
        specs = [mesh(dem=dem, gsd=float(options.gsd))] * len(sources)
        meshes = tuple(spec_meshes(s, spec, terrain) for s, spec in zip(sources, specs))
    elif mosaic:
        specs = [mesh(float(resolve_ground_height(options.ground_height, sources)))] * len(sources)
    else:
        specs = [mesh(float(resolve_ground_height(options.ground_height, [s]))) for s in sources]
    params = RenderParams(gsd=float(options.gsd), mode=mode, bands=tuple(bands[0]), overlap=options.overlap,
                          navigation=nav)
    return Inputs(tuple(sources), tuple(tuple(b) for b in bands), params, tuple(specs), meshes, grid,
                  tuple(bound) if bound and bound[0] is not None else None)


@dataclass(frozen=True, eq=False)
class OutputPlan:
    """One output, planned (metadata only): its sources, the :class:`~archive.graph.plan.RenderPlan`
    (grid, cube jobs, band groups), the processing parameters, the
    :class:`~archive.params.MeshSpec` of its meshes (field of view, flat ground or DEM, view-angle
    limit, the grid's EPSG code), the wavelength (nm) of each output band (None when the cubes have
    none) and its spectral full width at half maximum (``fwhm``, nm; None when the cubes have none)."""

    sources: tuple
    plan: RenderPlan
    params: RenderParams
    mesh_spec: MeshSpec
    wavelengths: list[float] | None
    left_out: dict | None = None  #: lines left out of the meshes, by reason ('no navigation', 'view angle')
    fwhm: list[float] | None = None
    indices: tuple | None = None  #: an index output's BoundIndex per output band (the rendered bands: its inputs)

    @property
    def variable(self) -> str:
        """Name of the data variable ('radiance', 'dn', ...; 'index' for an index output)."""
        return "index" if self.indices else variable_for_mode(self.params.mode)

    def layers_spec(self, rule_only: bool = False):
        """The :class:`~archive.geometry.provenance.ProvenanceSpec` of this output: every provenance layer,
        or with ``rule_only`` only the layer the overlap rule compares (:attr:`~archive.overlap.OverlapRule.key`)."""
        from archive.geometry.provenance import provenance_spec

        return provenance_spec(self.plan, self.sources, self.mesh_spec,
                               (self.params.overlap.key,) if rule_only else None)

    @property
    def attrs(self) -> dict:
        """The output's attributes (mode, gsd, fov, ground height or DEM, sync offset, overlap, sources)."""
        offsets = list(dict.fromkeys(float(s.params.sync_offset) for s in self.sources))
        mesh = self.mesh_spec
        ground = ({"ground_height_m": mesh.ground_height} if mesh.dem is None else
                  {"dem": mesh.dem.path, "dem_datum": mesh.dem.datum or "declared"})
        return {"mode": self.params.mode, "gsd_m": self.params.gsd, "fov_deg": mesh.fov_deg,
                **ground, "sync_offset_s": offsets[0] if len(offsets) == 1 else offsets,
                "overlap": self.params.overlap.name, "sources": [str(s.label) for s in self.sources],
                **({"indices": index_properties(self.indices)} if self.indices else {})}


def plan_output(inputs: Inputs, members: Sequence[int] | None = None, *, budget: int | None = None,
                band_group: int | None = None) -> OutputPlan:
    """Plan one output of ``inputs`` (the sources at ``members``, default all): cube meshes, output
    grid, cube windows and band groups (``band_group`` bands per render task, default sized to
    ``budget`` bytes of values per task; see :func:`archive.graph.build.with_task_groups`).
    InputError when the output or a task would be absurdly large."""
    from archive.graph.build import TASK_VALUES_BYTES, with_task_groups
    from archive.graph.plan import band_groups, plan_render, spec_meshes

    idx = list(range(len(inputs.sources))) if members is None else list(members)
    p = inputs.params
    sources = [inputs.sources[i] for i in idx]
    bands = [inputs.bands[i] for i in idx]
    spec = inputs.mesh_specs[idx[0]]
    if inputs.meshes is None:
        meshes = [spec_meshes(s, spec) for s in sources]
    else:   # terrain meshes, built by open_inputs
        meshes = [list(inputs.meshes[i]) for i in idx]
    plan = plan_render(sources, meshes, bands, p.gsd, crs=spec.epsg, grid=inputs.grid)
    # the graph builds the meshes again in tasks on the workers (DESIGN 9: shipped from here, a
    # terrain flight's meshes made graphs of MBs); the plan keeps their windows only
    spec = spec.with_epsg(plan.grid.epsg)
    plan = plan.without_meshes(spec)
    indices = None if inputs.indices is None else inputs.indices[idx[0]]
    if indices is not None:   # one band group: each tile's indices are computed from all the bands they read
        plan = dataclasses.replace(plan, groups=band_groups(plan.nbands, plan.nbands))
    elif band_group is None:
        plan = with_task_groups(plan, TASK_VALUES_BYTES if budget is None else budget)
    else:
        if isinstance(band_group, bool) or not isinstance(band_group, (int, np.integer)) or band_group <= 0:
            raise InputError("band_group", f"expected a positive number of bands, got {band_group!r}")
        plan = dataclasses.replace(plan, groups=band_groups(plan.nbands, int(band_group)))
    check_size(plan, p.gsd)
    wavelengths = sources[0].wavelengths
    out_wl = None if wavelengths is None else [wavelengths[b] for b in bands[0]]
    fwhm = getattr(sources[0], "fwhm", None)
    out_fwhm = None if fwhm is None else [fwhm[b] for b in bands[0]]
    left_out: dict[str, int] = {}
    for ms in meshes:
        for m in ms:
            for reason, n in (m.dropped or {}).items():
                left_out[reason] = left_out.get(reason, 0) + int(n)
    return OutputPlan(tuple(sources), plan, p, spec, out_wl, left_out, out_fwhm, indices)


def build_output(output: OutputPlan, target: Output):
    """(sink, graph): create ``target``'s sink for ``output`` under its temporary names (metadata
    only) and build (never compute) the render graph that writes it (its provenance layers too,
    when ``target`` asks for them, and the layer the overlap rule compares)."""
    from archive.graph.build import build_render_graph
    from archive.outputs.base import OutputMeta

    p, plan = output.params, output.plan
    meta = OutputMeta(plan.grid, tuple(plan.bands[0]), None if output.wavelengths is None else tuple(output.wavelengths),
                      output.variable, output.attrs, fwhm=None if output.fwhm is None else tuple(output.fwhm),
                      zarr_format=target.zarr_format, compression=target.compression)
    if output.indices:   # one band per index, named by it; the graph writes the bands they read through IndexSink
        meta = dataclasses.replace(meta, band_indices=tuple(range(len(output.indices))), wavelengths=None, fwhm=None,
                                   names=tuple(i.name for i in output.indices))
    sink = graph_sink = target.sink(meta)
    if output.indices:
        graph_sink = IndexSink(sink, tuple(output.wavelengths), tuple(output.indices))
    layers = layers_sink = None
    if target.provenance or p.overlap.key is not None:
        layers = output.layers_spec(rule_only=not target.provenance)
    if target.provenance:
        layers_sink = target.layers_sink(layers)
    graph = build_render_graph(plan, list(output.sources), graph_sink, mode=p.mode, overlap=p.overlap,
                               layers=layers, layers_sink=layers_sink)
    return sink, graph


# ---------------------------------------------------------------------------------------------
# Run and publish
# ---------------------------------------------------------------------------------------------
def _file_stamp(path: str | os.PathLike) -> dict:
    try:
        st = os.stat(path)
    except OSError:
        return {"path": str(path), "missing": True}
    return {"path": str(path), "size": st.st_size, "mtime_ns": st.st_mtime_ns}


def input_versions(options, source: str) -> list[dict]:
    """What the output of ``source`` depends on beyond ``options`` (``archive:recipe.inputs``): for a
    collection id, its navigation parameters, ground height and content version
    (:func:`archive.collection.content_version`); for a raw flight directory, its files' names,
    sizes and modification times (the navigation sidecar included); then every file the options
    name (calibration, white reference, DEM), by size and modification time."""
    import hashlib
    import json

    from archive.collection import content_version

    entries: list[dict] = []
    if Path(source).is_dir():
        files = sorted((p for p in Path(source).iterdir() if p.is_file()), key=lambda p: p.name)
        stamps = [[p.name, *(lambda st: (st.st_size, st.st_mtime_ns))(p.stat())] for p in files]
        sidecar = Path(source) / "navigation_params.json"
        try:
            nav = json.loads(sidecar.read_text()) if sidecar.is_file() else None
        except (OSError, ValueError):
            nav = "unreadable"
        entries.append({"source": str(Path(source).absolute()), "navigation_params": nav,
                        "version": hashlib.sha256(json.dumps(stamps).encode()).hexdigest()})
    elif options.archive is not None:
        store = storage.location(options.archive) / "collections" / f"{source}.zarr"
        entries.append({"source": str(source), **(content_version(store) or {"version": None})})
    for name in ("calibration", "white_reference", "dem", "irradiance_calibration", "panels", "navigation"):
        value = getattr(options, name, None)
        if value:
            entries.append({"option": name, **_file_stamp(value)})
    return json.loads(json.dumps(entries, default=str))


def recipe_inputs(options) -> list[dict]:
    """``archive:recipe.inputs`` of an output rendered from ``options``: :func:`input_versions` of
    each source, a file the options name listed once whatever the number of sources."""
    inputs = [entry for src in options.sources for entry in input_versions(options, str(src))]
    return [e for k, e in enumerate(inputs) if "option" not in e or e not in inputs[:k]]


def worker_renderers(client) -> list[dict]:
    """The GL renderers the workers of ``client`` opened (one dict per worker and context: worker,
    EGL device, why that device, renderer and vendor strings, and the band pass its render tasks
    took: {method, reason} or None), for the output's Item; [] when none is known. Makes no GL
    context (:func:`archive.render.context.opened_renderers`, :func:`archive.graph.tasks.decided_band_pass`)."""
    try:
        found = client.run(_worker_gl_facts)
    except Exception:   # a worker gone since: the metadata is a record, not a condition of the output
        return []
    return [{"worker": str(worker), **o, "band_pass": facts["band_pass"]}
            for worker, facts in sorted(found.items()) for o in facts["opened"]]


def _worker_gl_facts() -> dict:
    """On a worker: the GL contexts it opened and the band pass its render tasks took (no GL)."""
    from archive.graph.tasks import decided_band_pass
    from archive.render.context import opened_renderers

    return {"opened": opened_renderers(), "band_pass": decided_band_pass()}


def product_item(planned: OutputPlan, output: Output, options: RenderOptions,
                 renderers: list | None = None) -> dict:
    """The STAC Item of a written output (:func:`archive.catalog.product.product_item`): grid, bands,
    processing attributes, time span of its lines, and the recipe (the command that renders it
    again)."""
    from archive.catalog.product import product_item as item, render_command
    from archive.formats.lcf import gps_seconds_to_datetime

    plan = planned.plan
    first = min(float(planned.sources[j.source].line_times(j.cube)[0]) for j in plan.jobs)
    last = max(float(planned.sources[j.source].line_times(j.cube)[-1]) for j in plan.jobs)
    command = render_command(options, output.path, quicklook=output.quicklook, provenance=output.provenance)
    idx = planned.indices
    doc = item(output.path, fmt=output.format, grid=plan.grid, band_indices=range(len(idx)) if idx else plan.bands[0],
                wavelengths=None if idx else planned.wavelengths, fwhm=None if idx else planned.fwhm,
                variable=planned.variable,
                attrs=planned.attrs, start=gps_seconds_to_datetime(first), end=gps_seconds_to_datetime(last),
                sources=list(options.sources), command=command, request=options,
                provenance=(output.provenance_path or output.path) if output.provenance else None)
    if idx:   # an index output: the camera bands rendered for its indices, and which band each symbol took
        doc["properties"].update({"archive:source_bands": [int(b) for b in plan.bands[0]],
                                  "archive:wavelengths": [float(w) for w in planned.wavelengths or ()]})
        doc["properties"]["archive:recipe"]["indices"] = index_properties(idx)
    if renderers:
        # which GL renderer drew it (a GPU, or llvmpipe with the CPU band gather): a record of the
        # run, kept out of archive:recipe.request so that a resume on other hardware is the same recipe
        doc["properties"]["archive:renderers"] = renderers
        doc["properties"]["archive:recipe"]["renderers"] = sorted({str(r.get("renderer")) for r in renderers})
    if planned.params.mode == "reflectance":   # what it was divided by, and the sky's QA (issue 34)
        from archive.sources.downwelling import reflectance_record

        doc["properties"]["archive:reflectance"] = reflectance_record(planned.sources, options.white_reference,
                                                                     options.panels)
    return doc


#: Test-only: ``ARCHIVE_TEST_HOLD_PUBLISH=PATH`` makes a render wait before publishing its output while
#: the file PATH exists (touching ``PATH.reached``): a test kills it after its writes and before its
#: publication at a moment it controls, however loaded the machine (never set outside tests).
TEST_HOLD_PUBLISH = "ARCHIVE_TEST_HOLD_PUBLISH"


def publish(job: Job, inputs: list[dict] | None = None, properties: dict | None = None) -> None:
    """Finish a job's output (ENVI header, COG layout), rename it into place (its old Item removed
    first), then write its STAC Item beside it, ``<out>.json``, last: an Item says the output is
    complete. The Item's recipe records ``inputs`` (default :func:`recipe_inputs` of the job's
    options: what ``--resume`` compares besides the request); ``properties``: more of its properties
    (a batch tile's)."""
    from archive.catalog.stac import write_item

    job.output.finalize(job.sink)
    item = product_item(job.planned, job.output, job.options, job.renderers)
    item["properties"]["archive:recipe"]["inputs"] = recipe_inputs(job.options) if inputs is None else inputs
    item["properties"].update(properties or {})
    write_item(job.output.item_path, item)


def progress_lines(quiet: bool):
    """A ``say(text)`` for a command's progress lines: each on stderr on a line of its own (through
    ``tqdm.write``: a progress bar being drawn is drawn again below it), nothing when ``quiet``."""
    def say(text: str) -> None:
        if not quiet:
            from tqdm import tqdm

            tqdm.write(text, file=sys.stderr)

    return say


def client_budget() -> int | None:
    """The render task budget (:func:`archive.run.cluster.task_budget`) of the active distributed Client
    (its workers checked for the GPU resource), None without one: what a lazy mosaic or stack is
    planned with."""
    client = active_client()
    if client is None:
        return None
    check_gpu_workers(client, f"the active Dask client ({client.scheduler.address})")
    return task_budget(client)


def georectify(options: RenderOptions, out: str | os.PathLike, *, quicklook: str | os.PathLike | None = None,
               overwrite: bool = False, scheduler: str | None = None, workers: int | None = None,
               quiet: bool = True, threads: int | None = None) -> RenderSummary:
    """Georectify ``options`` into ``out`` (.zarr, .tif or .hdr); returns a summary dict. Raises ArchiveError.

    One output at ``out`` (batch jobs, one output per flight, are :func:`archive.run.batch.run_batch`'s).
    The tasks run on ``scheduler`` (an address) or on a local cluster of ``workers`` processes of
    ``threads`` threads each (default: the cores). The graph's tile tasks write every format
    directly; :func:`publish` finishes each output and moves it into place.
    """
    started = time.perf_counter()
    say = progress_lines(quiet)
    nav = options.check()
    remote = None
    if storage.is_url(out):   # rendered in a local staging folder, uploaded once, its Item last
        from archive.outputs.publish import RemoteOutput

        remote = RemoteOutput(str(out), overwrite=bool(overwrite), zarr_format=options.zarr_format,
                              compression=options.compression,
                              quicklook=None if not quicklook else str(Path(quicklook).absolute()),
                              provenance=options.provenance)
        remote.check()
        output = remote.local
    else:
        output = Output(Path(out).absolute(), overwrite=bool(overwrite), zarr_format=options.zarr_format,
                        compression=options.compression,
                        quicklook=None if not quicklook else Path(quicklook).absolute(),
                        provenance=options.provenance)
    output.check()
    job = None
    graph_seconds = 0.0
    try:
        inputs = open_inputs(options, nav, say, mosaic=True)
        # a failed run's close stops the worker processes, with any task still writing; the close
        # begun once every task had ended runs while we publish: neither hides the run's outcome
        with Session(scheduler, workers, threads, say, what=str(out)) as session:
            planned = plan_output(inputs, budget=session.budget)
            sink, graph = build_output(planned, output)
            job = Job(output, planned, sink, options, graph)
            t = time.perf_counter()
            if len(graph):
                execute(session.client, graph, quiet, shared=session.shared)
            graph_seconds = time.perf_counter() - t
            job.renderers = worker_renderers(session.client)
            session.close_early()   # every task ended: the workers stop while we publish
            if os.environ.get(TEST_HOLD_PUBLISH):
                wait_while_exists(os.environ[TEST_HOLD_PUBLISH])
            publish(job)
            if remote is not None:
                remote.upload()
    finally:
        output.cleanup()
        if remote is not None:
            remote.cleanup()
    return render_summary(job.planned, job.output, job.graph, seconds=time.perf_counter() - started,
                          graph_seconds=graph_seconds) | {"out": str(out)}


def describe(s: dict) -> str:
    """One line about an output from its :func:`georectify` summary."""
    wl = s["wavelengths"]
    span = f" ({min(wl):.1f}-{max(wl):.1f} nm)" if wl else ""
    return (f"{s['out']}: {s['width']} x {s['height']} px at {s['gsd']:g} m, "
            f"EPSG:{s['epsg']}, {s['bands']} band{'s' if s['bands'] != 1 else ''}{span}, {s['mode']}, "
            f"{s['cubes']} cube{'s' if s['cubes'] != 1 else ''} from {s['sources']} source"
            f"{'s' if s['sources'] != 1 else ''}{_left_out_text(s.get('left_out'))}")


def _left_out_text(left_out: dict | None) -> str:
    """'; 12 lines left out (3 without navigation, 9 beyond the view-angle limit)' or ''."""
    left_out = {k: v for k, v in (left_out or {}).items() if v}
    if not left_out:
        return ""
    names = {"no navigation": "without navigation", "view angle": "beyond the view-angle limit"}
    parts = ", ".join(f"{n} {names.get(k, k)}" for k, n in left_out.items())
    total = sum(left_out.values())
    return f"; {total} line{'s' if total != 1 else ''} left out ({parts})"


# ---------------------------------------------------------------------------------------------
# Lazy mosaics
# ---------------------------------------------------------------------------------------------
def plan(options: RenderOptions, *, band_group: int | None = None, budget: int | None = None,
         quiet: bool = True, grid: GridRequest | None = None) -> OutputPlan:
    """Check, open and plan ``options`` as one mosaic (metadata only: no pixel is read, no GL);
    ``grid``: the output grid asked for instead of the options' (a stack's grid, :mod:`archive.stack`)."""
    nav = options.check()
    inputs = open_inputs(options, nav, progress_lines(quiet), mosaic=True)
    if grid is not None:
        inputs = dataclasses.replace(inputs, grid=grid)
    return plan_output(inputs, budget=budget, band_group=band_group)


def mosaic(options: RenderOptions, *, band_group: int | None = None, quiet: bool = True):
    """``options`` as a lazy ``xarray.Dataset`` (nothing rendered until computed).

    The data variable (named by mode: 'dn', 'relative', 'radiance', 'reflectance') is (band, y, x)
    float32, NaN where no line covers a pixel, a dask array chunked (band group, 1024, 1024): one
    block per output tile and band group (``band_group`` bands, default sized to the task memory
    budget, the active distributed Client's workers' when there is one), rendered by the render
    graph's task bodies (:mod:`archive.graph.lazy`). ``saturated`` (y, x) uint8 is lazy too. The
    coordinates are those of the Zarr output (x/y pixel centres in metres, ``band``: source band
    index, ``wavelength`` in nm, indexed for ``.sel(wavelength=..., method="nearest")``), with the
    CRS set (rioxarray ``spatial_ref``).
    """
    return planned_dataset(plan(options, band_group=band_group, budget=client_budget(), quiet=quiet))


def planned_dataset(planned: OutputPlan):
    """The lazy ``xarray.Dataset`` of a planned output (:func:`mosaic`'s, from its plan)."""
    from archive.graph.lazy import mosaic_arrays

    p, grid = planned.params, planned.plan.grid
    if planned.indices:
        raise InputError("--index", "a lazy mosaic holds the bands", "take the index of it with "
                         "archive.analysis.indices.stack_index(ds[variable], 'NDVI'), or write it with georectify")
    values, saturated = mosaic_arrays(planned.plan, list(planned.sources), mode=p.mode, overlap=p.overlap,
                                      layers=planned.layers_spec(rule_only=True)
                                      if p.overlap.key is not None else None)
    ds = mosaic_dataset(grid, values, saturated, planned.plan.bands[0], planned.wavelengths, planned.fwhm,
                        planned.variable, planned.attrs)
    if planned.wavelengths is not None and len(set(planned.wavelengths)) == len(planned.wavelengths):
        ds = ds.set_xindex("wavelength")
    return ds
