"""The library API under ``archive render``, ``bench/`` and the web viewer::

    import archive
    arc = archive.open_archive("demo/archive")
    ids = arc.search(bbox=(-90, 35, -89.9, 35.2), datetime="2024-06/2024-07", wavelength=650)
    ds = archive.mosaic(ids, archive="demo/archive", gsd=0.25, wavelengths=[650, 550, 450])  # lazy
    ds.radiance.sel(wavelength=650, method="nearest").compute()    # renders only that band's group
    archive.render(["demo/flight"], "demo/mosaic.zarr", gsd=0.25, fov=47.5)  # what the CLI does

Keyword names are the options of ``archive render`` (``--ground-height`` is ``ground_height``);
values may be Python values or the CLI's text (``wavelengths="650,550"``, ``bands="2,4"``). Errors
are :class:`~archive.errors.ArchiveError` subclasses with the CLI's one-line messages.

:func:`run_render` is the ``archive render`` command: it turns the parsed options into these
keywords once and calls :func:`render` (batch jobs over the catalog too).
"""

from __future__ import annotations

import argparse
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass

from archive.catalog.root import ArchiveRoot
from archive.errors import InputError

__all__ = ["Archive", "mosaic", "open_archive", "plan", "render", "render_keywords", "run_render"]

Source = str | os.PathLike


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
    from archive.catalog.root import open_archive as open_root

    return Archive(open_root(path).path)


# ---------------------------------------------------------------------------------------------
# Rendering
# ---------------------------------------------------------------------------------------------
#: The keywords of :func:`plan`, :func:`mosaic` and :func:`render` that make the render request.
REQUEST_KEYWORDS = ("gsd", "archive", "fov", "calibration", "ground_height", "wavelengths", "bands", "mode",
                    "white_reference", "sync_offset", "boresight", "lever_arm", "overlap", "crs",
                    "max_view_angle", "dem", "dem_datum")


def _request(sources, values: dict):
    """The :class:`~archive.pipeline.RenderRequest` of an API call's ``values`` (its ``locals()``)."""
    from archive.pipeline import RenderRequest

    keywords = {name: values[name] for name in REQUEST_KEYWORDS}
    if isinstance(keywords.get("archive"), ArchiveRoot):
        keywords["archive"] = keywords["archive"].path
    return RenderRequest.create(sources, **keywords)


def plan(sources: Source | Sequence[Source], *, gsd: float, archive: Source | None = None,
         fov: float | None = None, calibration: Source | None = None, ground_height: float | str = "auto",
         wavelengths=None, bands="all", mode: str | None = None, white_reference: Source | None = None,
         sync_offset: float | None = None, boresight=None, lever_arm=None, overlap: str = "last",
         crs=None, max_view_angle: float = 40.0, dem: Source | None = None, dem_datum: str | None = None,
         band_group: int | None = None, quiet: bool = True):
    """The plan of a mosaic of ``sources`` (:class:`archive.pipeline.OutputPlan`: opened sources,
    grid, cube meshes and windows, band groups), from metadata only: no pixel read, no GL.
    Keywords as :func:`mosaic`."""
    from archive import pipeline

    request = _request(sources, locals())
    return pipeline.plan(request, band_group=band_group, quiet=quiet)


def mosaic(sources: Source | Sequence[Source], *, gsd: float, archive: Source | None = None,
           fov: float | None = None, calibration: Source | None = None, ground_height: float | str = "auto",
           wavelengths=None, bands="all", mode: str | None = None, white_reference: Source | None = None,
           sync_offset: float | None = None, boresight=None, lever_arm=None, overlap: str = "last",
           crs=None, max_view_angle: float = 40.0, dem: Source | None = None, dem_datum: str | None = None,
           band_group: int | None = None, quiet: bool = True):
    """A lazy ``xarray.Dataset`` of the mosaic of ``sources``: nothing is rendered until computed.

    sources: raw flight directories and/or collection ids of ``archive`` (one, or a list); gsd:
    output pixel size, m; fov: field of view, degrees (required for raw directories; a collection's
    is the one ingested); calibration: .icp for raw sources; ground_height: m above the ellipsoid or
    'auto'; wavelengths: nm (nearest bands), else bands: 'all' or 0-based indices; mode: 'raw' |
    'relative' | 'radiance' | 'reflectance' (None: radiance, raw DN without calibration);
    white_reference: (nm, radiance) text file for reflectance; sync_offset (s), boresight (roll,
    pitch, yaw deg), lever_arm (x, y, z m): None means as ingested for a collection, else 0;
    overlap: 'last' (the later line wins), 'nadir' (the line seen closest to nadir wins) or 'mean';
    crs: the output's projected CRS ('EPSG:32616', an int...; default:
    the UTM zone holding most of the flights, others rendered into it); max_view_angle: degrees
    off nadir at the field-of-view edge beyond which lines are left out (turns); dem: a DEM GeoTIFF
    (any CRS) the meshes follow instead of flat ground (exclusive with a numeric ground_height; ground
    no line sees is NaN); dem_datum: 'ellipsoid' | 'egm96' | 'egm2008', required when the DEM's CRS
    does not declare its vertical datum; band_group: bands per render task and per band chunk (default sized
    to the task memory budget); quiet: no notes on stderr.

    The data variable is named by mode ('radiance', 'dn', 'relative', 'reflectance'), (band, y, x)
    float32 with NaN where no line covers a pixel, a dask array chunked (band group, 1024, 1024) like
    the output tiles; ``saturated`` (y, x) uint8 is lazy too; coordinates x/y (pixel centres, m),
    ``band`` (source band index) and ``wavelength`` (nm, indexed: ``.sel(wavelength=650,
    method="nearest")``); ``.rio.crs`` is set. Computing it runs the render graph's task bodies
    (GL in the computing threads, each with its own context; on the active distributed Client if
    there is one) and gives the values ``archive render`` writes, bit for bit. Computing some bands
    renders only their band groups.
    """
    from archive import pipeline

    request = _request(sources, locals())
    return pipeline.mosaic(request, band_group=band_group, quiet=quiet)


def render(sources: Source | Sequence[Source], out: Source, *, gsd: float, archive: Source | None = None,
           fov: float | None = None, calibration: Source | None = None, ground_height: float | str = "auto",
           wavelengths=None, bands="all", mode: str | None = None, white_reference: Source | None = None,
           sync_offset: float | None = None, boresight=None, lever_arm=None, overlap: str = "last",
           crs=None, max_view_angle: float = 40.0, dem: Source | None = None, dem_datum: str | None = None,
           quicklook: Source | None = None, scheduler: str | None = None, workers: int | None = None,
           overwrite: bool = False, quiet: bool = True, per_flight: bool = False, format: str = "zarr",
           threads: int | None = None, provenance: bool = False) -> dict:
    """Render ``sources`` into ``out`` (.zarr, .tif or .hdr) exactly as ``archive render``; returns
    its summary (out, width, height, gsd, epsg, bands, wavelengths, mode, cubes, sources, renders,
    assemblies, seconds, graph_seconds).

    Keywords as :func:`mosaic`, plus: quicklook: also write an RGB .png; scheduler: a Dask
    scheduler address (default: a local cluster of ``workers`` processes, 1, of ``threads`` threads
    each, default the cores); overwrite: replace an
    existing output; quiet: no progress bar or notes; per_flight: one output per source,
    ``out/<name>.<format>`` (then the summary holds ``outputs``); provenance: also write the
    per-pixel provenance layers (:mod:`archive.provenance`: variables of a Zarr output, a sibling
    ``<stem>_provenance.tif`` / ``.hdr`` beside a COG / ENVI output; needs overlap 'last' or
    'nadir'). Nothing is left at ``out`` when anything fails.
    """
    import dataclasses

    from archive import pipeline

    request = dataclasses.replace(_request(sources, locals()), provenance=bool(provenance))
    return pipeline.render(request, out, quicklook=quicklook, overwrite=overwrite, scheduler=scheduler,
                           workers=workers, quiet=quiet, per_flight=per_flight, format=format, threads=threads)


# ---------------------------------------------------------------------------------------------
# The command
# ---------------------------------------------------------------------------------------------
def _query_ids(args: argparse.Namespace) -> list[str] | None:
    """Collection ids of ``--archive`` matching the ``--query-*`` filters (None when none is given)."""
    bbox, when = args.query_bbox, args.query_datetime
    wavelength = args.query_wavelength
    if bbox is None and when is None and wavelength is None:
        return None
    if not args.archive:
        raise InputError("--query-*", "a catalog query needs the archive to search", "pass --archive ARCHIVE")
    if wavelength is not None and not (math.isfinite(wavelength) and wavelength > 0):
        raise InputError("--query-wavelength", f"{wavelength} is not a positive wavelength in nm")
    ids = open_archive(args.archive).search(bbox=bbox, datetime=when, wavelength=wavelength)
    if not ids:
        asked = ", ".join(f"{k} {v}" for k, v in (("--query-bbox", bbox), ("--query-datetime", when),
                                                   ("--query-wavelength", wavelength)) if v is not None)
        raise InputError(args.archive, f"no flight in the catalog matches {asked}",
                         "check the filters with 'archive catalog search'")
    return ids


def render_keywords(args: argparse.Namespace) -> dict:
    """The :func:`render` keywords of parsed ``archive render`` options (catalog queries resolved:
    matching ids added to the sources; one output per flight unless ``--mosaic``)."""
    keywords = {
        "sources": list(args.sources or []), "out": args.out, "gsd": args.gsd, "archive": args.archive,
        "fov": args.fov, "calibration": args.calibration, "ground_height": args.ground_height,
        "wavelengths": args.wavelengths, "bands": args.bands, "mode": args.mode,
        "white_reference": args.white_reference, "sync_offset": args.sync_offset, "boresight": args.boresight,
        "lever_arm": args.lever_arm, "overlap": args.overlap, "crs": args.crs,
        "max_view_angle": args.max_view_angle, "dem": args.dem, "dem_datum": args.dem_datum,
        "quicklook": args.quicklook,
        "scheduler": args.scheduler, "workers": args.workers, "overwrite": args.overwrite, "quiet": args.quiet,
        "format": args.format, "threads": getattr(args, "threads", None),
        "provenance": getattr(args, "provenance", False),
    }
    ids = _query_ids(args)
    if ids is not None:
        keywords["sources"] += [i for i in ids if i not in keywords["sources"]]
        keywords["per_flight"] = not args.mosaic
    return keywords


def run_render(args: argparse.Namespace) -> int:
    """``archive render``: :func:`render` with the parsed options; prints a one-paragraph summary
    (batch mode: one line per output, then the total)."""
    from archive.pipeline import describe

    s = render(**render_keywords(args))
    if "outputs" in s:
        for one in s["outputs"]:
            print(f"archive render: wrote {describe(one)}.")
        n = len(s["outputs"])
        print(f"archive render: {n} output{'s' if n != 1 else ''} in {s['seconds']:.1f} s.")
        return 0
    print(f"archive render: wrote {describe(s)} in {s['seconds']:.1f} s.")
    return 0

