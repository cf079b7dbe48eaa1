"""The library API under ``archive render``, ``bench/`` and the web viewer::

    import archive
    arc = archive.open_archive("demo/archive")
    ids = arc.search(bbox=(-90, 35, -89.9, 35.2), datetime="2024-06/2024-07", wavelength=650)
    ds = archive.mosaic(ids, archive="demo/archive", gsd=0.25, wavelengths=[650, 550, 450])  # lazy
    ds.radiance.sel(wavelength=650, method="nearest").compute()    # renders only that band's group
    archive.georectify(["demo/flight"], "demo/mosaic.zarr", gsd=0.25, fov=47.5)  # what `archive render` does

Render options are keywords named as the options of ``archive render`` (``--ground-height`` is
``ground_height``; every name of :data:`archive.run.options.KEYWORDS`), made into one
:class:`~archive.run.options.RenderOptions` (values may be Python values or the CLI's text:
``wavelengths="650,550"``, ``bands="2,4"``). Errors are :class:`~archive.errors.ArchiveError`
subclasses with the CLI's one-line messages. The command itself is :mod:`archive.run.command`.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

from archive.api_errors import python_errors
from archive.catalog.root import ArchiveRoot
from archive.errors import InputError

if TYPE_CHECKING:
    from archive.run.cluster import SlurmJobs

__all__ = ["Archive", "georectify", "mosaic", "open_archive", "plan", "stack"]

Source = str | os.PathLike


def _render_keywords(*more: str):
    """The keywords of a rendering function: the render options and ``more``."""
    def valid() -> tuple[str, ...]:
        from archive.run.options import KEYWORDS

        return (*KEYWORDS, "band_group", "quiet", *more)
    return valid


# ---------------------------------------------------------------------------------------------
# Archives
# ---------------------------------------------------------------------------------------------
def _bbox_text(bbox) -> str:
    """'W,S,E,N' from a string or four numbers (checked by the catalog's parser afterwards)."""
    if isinstance(bbox, str):
        return bbox
    try:
        values = [float(v) for v in bbox]
    except (TypeError, ValueError):
        raise InputError("--bbox", f"expected four numbers (west, south, east, north), got {bbox!r}") from None
    return ",".join(repr(v) for v in values)


def _datetime_text(when) -> str:
    """'A/B' from a string (ISO 8601, '..' for an open end), or a (start, end) pair of ISO strings,
    dates or datetimes (None for an open end)."""
    if isinstance(when, str):
        return when
    if isinstance(when, (tuple, list)) and len(when) == 2:
        return "/".join(".." if w is None else (w if isinstance(w, str) else w.isoformat()) for w in when)
    if hasattr(when, "isoformat"):
        return when.isoformat()
    raise InputError("--datetime", f"expected 'START/END' (ISO 8601) or a (start, end) pair, got {when!r}")


@dataclass(frozen=True)
class Archive(ArchiveRoot):
    """An opened archive: its paths and collections (:class:`~archive.catalog.root.ArchiveRoot`)
    and its catalog's queries."""

    @python_errors("Archive.search", lambda: ("bbox", "datetime", "wavelength"))
    def search(self, bbox=None, datetime=None, wavelength: float | None = None) -> list[str]:
        """Ids of the collections matching every given filter, sorted by start time then id (what
        ``archive catalog search`` lists).

        bbox: (west, south, east, north) degrees or 'W,S,E,N'; datetime: 'A/B' in ISO 8601 ('..':
        an open end; a date alone is the whole day) or a (start, end) pair; wavelength: nm, a
        wavelength the flight's bands must span.
        """
        from archive.catalog.index import ensure_index, parse_bbox, parse_datetime_range, search

        box = None if bbox is None else parse_bbox(_bbox_text(bbox))
        start, end = (None, None) if datetime is None else parse_datetime_range(_datetime_text(datetime))
        if wavelength is not None:
            try:
                wavelength = float(wavelength)
            except (TypeError, ValueError):
                raise InputError("--wavelength", f"{wavelength!r} is not a wavelength in nm") from None
            if not (math.isfinite(wavelength) and 0 < wavelength < 1e6):
                raise InputError("--wavelength", f"{wavelength} is not a positive wavelength in nm")
        rows = search(ensure_index(self), bbox=box, start=start, end=end, wavelength=wavelength)
        return [row.id for row in rows]


def open_archive(path: Source) -> Archive:
    """Open an existing archive (a directory made by ``archive ingest``); MissingInputError or
    InputError when ``path`` is not one."""
    from archive.catalog.root import open_root

    return Archive(open_root(path).path)


# ---------------------------------------------------------------------------------------------
# Rendering
# ---------------------------------------------------------------------------------------------
def _options(sources, options: dict):
    """The :class:`~archive.run.options.RenderOptions` of an API call (an opened :class:`Archive` stands
    for its path). TypeError for a keyword that is no render option."""
    from archive.run.options import RenderOptions

    if isinstance(options.get("archive"), ArchiveRoot):
        path = options["archive"].path
        options = {**options, "archive": str(path) if options["archive"].is_url else path}   # s3://: the URL
    return RenderOptions.create(sources, **options)


@python_errors("archive.plan", _render_keywords())
def plan(sources: Source | Sequence[Source], *, band_group: int | None = None, quiet: bool = True, **options):
    """The plan of a mosaic of ``sources`` (:class:`archive.run.pipeline.OutputPlan`: opened sources,
    grid, cube meshes and windows, band groups), from metadata only: no pixel read, no GL.
    Keywords as :func:`mosaic`."""
    from archive.run import pipeline

    return pipeline.plan(_options(sources, options), band_group=band_group, quiet=quiet)


@python_errors("archive.mosaic", _render_keywords())
def mosaic(sources: Source | Sequence[Source], *, band_group: int | None = None, quiet: bool = True, **options):
    """A lazy ``xarray.Dataset`` of the mosaic of ``sources``: nothing is rendered until computed.

    sources: raw flight directories and/or collection ids of ``archive`` (one, or a list).
    Render options (:class:`~archive.run.options.RenderOptions`, the names of ``archive render``'s
    options): gsd (required): output pixel size, m; archive: the archive of the collection ids (a
    path or an opened :class:`Archive`); fov: field of view, degrees (required for raw directories;
    a collection's is the one ingested); calibration: .icp for raw sources; ground_height: m above
    the ellipsoid or 'auto'; wavelengths: nm (nearest bands), else bands: 'all' or 0-based indices;
    mode: 'raw' | 'relative' | 'radiance' | 'reflectance' (None: radiance, raw DN without
    calibration); white_reference: (nm, radiance) text file for reflectance; sync_offset (s),
    boresight (roll, pitch, yaw deg), lever_arm (x, y, z m): None means as ingested for a
    collection, else 0; overlap: 'last' (the later line wins), 'nadir' (the line seen closest to
    nadir wins) or 'mean'; crs: the output's projected CRS ('EPSG:32616', an int...; default: the
    UTM zone holding most of the flights, others rendered into it); max_view_angle: degrees off
    nadir at the field-of-view edge beyond which lines are left out (turns; default
    :data:`~archive.params.DEFAULT_MAX_VIEW_ANGLE`); dem: a DEM GeoTIFF (any CRS) the meshes follow
    instead of flat ground (exclusive with a numeric ground_height; ground no line sees is NaN);
    dem_datum: 'ellipsoid' | 'egm96' | 'egm2008', required when the DEM's CRS does not declare its
    vertical datum; bounds: (west, south, east, north) metres in the output CRS, the grid's extent
    (top-left corner exactly there); align: with bounds, pixel edges snapped outward to multiples of
    the GSD (``gdalwarp -tap``); like: an existing output (.zarr, a stack too, .tif, .hdr) whose CRS,
    GSD, corner and size the grid takes (gsd may then be left out). And: band_group: bands per render
    task and per band chunk (default sized to the task memory budget); quiet: no notes on stderr.

    The data variable is named by mode ('radiance', 'dn', 'relative', 'reflectance'), (band, y, x)
    float32 with NaN where no line covers a pixel, a dask array chunked (band group, 1024, 1024) like
    the output tiles; ``saturated`` (y, x) uint8 is lazy too; coordinates x/y (pixel centres, m),
    ``band`` (source band index) and ``wavelength`` (nm, indexed: ``.sel(wavelength=650,
    method="nearest")``); ``.rio.crs`` is set. Computing it runs the render graph's task bodies
    (GL in the computing threads, each with its own context; on the active distributed Client if
    there is one) and gives the values :func:`georectify` writes, bit for bit. Computing some bands
    renders only their band groups.
    """
    from archive.run import pipeline

    return pipeline.mosaic(_options(sources, options), band_group=band_group, quiet=quiet)


def _stack_sources(ids_or_query, options: dict) -> list:
    """The flights of :func:`stack`: ids / directories as given, or the ids of ``archive`` matching a
    query dict (keys bbox, datetime, wavelength as :meth:`Archive.search`)."""
    if isinstance(ids_or_query, dict):
        where = options.get("archive")
        if where is None:
            raise InputError("archive", "a catalog query needs the archive to search", "pass archive=...")
        unknown = set(ids_or_query) - {"bbox", "datetime", "wavelength"}
        if unknown:
            raise InputError("query", f"unknown keys {sorted(unknown)}", "use bbox, datetime, wavelength")
        arc = where if isinstance(where, Archive) else open_archive(where)
        ids = arc.search(**ids_or_query)
        if not ids:
            raise InputError(arc.path, f"no flight in the catalog matches {ids_or_query}",
                             "check the query with archive.open_archive(...).search(...)")
        return ids
    return ids_or_query


@python_errors("archive.stack", _render_keywords())
def stack(ids_or_query, *, band_group: int | None = None, quiet: bool = True, **options):
    """The time stack of flights as a lazy ``xarray.DataArray`` (time, band, y, x): nothing rendered
    until computed.

    ids_or_query: collection ids (and/or raw flight directories), or a query dict ({"bbox": ...,
    "datetime": ..., "wavelength": ...}, as :meth:`Archive.search`) of ``archive``. Render options as
    :func:`mosaic` (gsd required unless like; bounds, like, crs: the grid). The grid is the one
    ``archive render ... --stack`` gives: aligned, the union of the flights' footprints (or bounds,
    or like's); each time step is one flight rendered alone from its raw lines onto it (the same
    values as the Zarr stack and as ``archive render ID --like X.zarr``, bit for bit); ``time`` is
    each flight's first line (UTC, datetime64[ns]) in time order, ``flight`` its id. Computing a
    window (``.sel(x=slice(...), y=slice(...))``, one ``time``) renders only its tiles.
    ``.archive.index("NDVI")`` (or ``"NAME=EXPR"``) is a spectral index of it, as lazy (time, y, x)
    (:func:`archive.analysis.indices.stack_index`).
    """
    from archive.analysis.indices import register_accessor
    from archive.run.stacks import stack as lazy_stack

    register_accessor()   # .archive.index("NDVI") on the stack

    return lazy_stack(_options(_stack_sources(ids_or_query, options), options), band_group=band_group,
                      quiet=quiet)


@python_errors("archive.georectify", _render_keywords(
    "quicklook", "scheduler", "workers", "threads", "overwrite", "per_flight", "format", "resume", "tell", "stack",
    "tiles"))
def georectify(sources: Source | Sequence[Source], out: Source, *, quicklook: Source | None = None,
               scheduler: str | SlurmJobs | None = None, workers: int | None = None, threads: int | None = None,
               overwrite: bool = False, quiet: bool = True, per_flight: bool = False, format: str = "zarr",
               resume: bool = False, tell=None, stack: bool = False, tiles: float | None = None, **options) -> dict:
    """Georectify ``sources`` into ``out`` (.zarr, .tif or .hdr) exactly as ``archive render``;
    returns its summary (out, width, height, gsd, epsg, bands, wavelengths, mode, cubes, sources,
    renders, assemblies, seconds, graph_seconds, left_out, provenance).

    Render options as :func:`mosaic`, plus provenance: also write the per-pixel provenance layers
    (:mod:`archive.geometry.provenance`: variables of a Zarr output, a sibling ``<stem>_provenance.tif`` /
    ``.hdr`` beside a COG / ENVI output; needs overlap 'last' or 'nadir'). And: quicklook: also
    write an RGB .png; scheduler: a Dask scheduler address, or an :class:`archive.run.cluster.SlurmJobs`
    (workers as Slurm jobs, ``--cluster slurm``) (default: a local cluster of ``workers`` processes, 1,
    of ``threads`` threads each, default the cores); overwrite: replace an existing
    output; quiet: no progress bar or notes; per_flight: one output per source,
    ``out/<name>.<format>`` (then the summary holds ``outputs``, and ``out/report.json`` the batch
    report; each flight succeeds or fails alone, :mod:`archive.run.batch`); resume: skip per-flight
    outputs that are complete with the same recipe (with ``stack``: add the flights the stack lacks);
    tell: called with one line per finished flight; stack: one Zarr ``out`` (time, band, y, x) of
    all sources on one aligned grid (:mod:`archive.run.stacks`; the summary holds ``flights``,
    ``added``, ``skipped``, ``left_out``; with ``index``/``expression`` its bands are the indices);
    tiles: a tile side in metres: one output per tile of the
    output CRS that a source touches, ``out/<EPSG>_<E0>_<N0>.<format>``, each the mosaic of its
    sources, tiles as the units of a batch (:mod:`archive.run.tiling`).
    Nothing is left at ``out`` when anything fails; the output's STAC Item, ``<out>.json``, is
    written last.
    """
    from archive.run.runner import OutputKind, run

    return run(OutputKind.of(per_flight=per_flight, stack=stack, tiles=tiles), _options(sources, options), out,
               quicklook=quicklook, format=format, overwrite=overwrite, resume=resume, scheduler=scheduler,
               workers=workers, threads=threads, quiet=quiet, tell=tell)
