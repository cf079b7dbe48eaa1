"""``archive stats`` and ``archive.zonal_stats``: the zone x flight x index table of
:mod:`archive.analysis.zonal`, from the command line's options or Python keywords, written to CSV
or (Geo)Parquet under a temporary name and renamed when complete."""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence
from pathlib import Path

from typing import TYPE_CHECKING

from archive.api_errors import python_errors
from archive.errors import InputError, OutputExistsError

if TYPE_CHECKING:
    import pandas as pd

__all__ = ["TABLE_SUFFIXES", "check_out", "run", "write_table", "zonal_stats"]

#: The table formats, by suffix.
TABLE_SUFFIXES = (".csv", ".parquet")
#: Render options ``archive stats`` passes on (the parser's destinations of the same names).
_RENDER = ("gsd", "archive", "fov", "mode", "white_reference", "ground_height", "dem", "dem_datum", "crs",
           "overlap", "like")


def check_out(out: str | os.PathLike, overwrite: bool, geometry: bool) -> Path:
    """``--out`` checked before anything is computed: a .csv or .parquet path, not there unless
    ``overwrite``, Parquet when geometries are kept."""
    path = Path(out)
    suffix = path.suffix.lower()
    if suffix not in TABLE_SUFFIXES:
        raise InputError("--out", f"{out}: a table is written as .csv or .parquet, not {suffix or 'no suffix'}",
                         "e.g. --out fields.csv")
    if geometry and suffix != ".parquet":
        raise InputError("--geometry", "geometries are kept in GeoParquet", f"write --out {path.with_suffix('.parquet')}")
    if path.exists() and not overwrite:
        raise OutputExistsError(path)
    if not path.parent.is_dir():
        raise InputError("--out", f"{path.parent} is not a folder", "create it first")
    return path


def write_table(frame: pd.DataFrame, out: str | os.PathLike) -> None:
    """``frame`` to ``out`` (.csv: ``datetime`` ISO 8601 UTC; .parquet: GeoParquet for a
    GeoDataFrame), written under a temporary name and renamed over ``out`` when complete."""
    from archive.files import atomic_path

    path = Path(out)
    with atomic_path(path) as tmp:
        if path.suffix.lower() == ".csv":
            frame.to_csv(tmp, index=False, date_format="%Y-%m-%dT%H:%M:%S.%fZ")
        else:
            frame.to_parquet(tmp, index=False)


def _sources(ids_or_query, archive) -> list[str]:
    """The flights of a call: ids / directories as given, or the ids of ``archive`` matching a query
    dict (bbox, datetime, wavelength as :meth:`archive.api.Archive.search`)."""
    from archive.api import Archive, open_archive

    if isinstance(ids_or_query, (str, os.PathLike)):
        return [os.fspath(ids_or_query)]
    if isinstance(ids_or_query, dict):
        if archive is None:
            raise InputError("archive", "a catalog query needs the archive to search", "pass archive=...")
        unknown = set(ids_or_query) - {"bbox", "datetime", "wavelength"}
        if unknown:
            raise InputError("query", f"unknown keys {sorted(unknown)}", "use bbox, datetime, wavelength")
        arc = archive if isinstance(archive, Archive) else open_archive(archive)
        ids = arc.search(**ids_or_query)
        if not ids:
            raise InputError(arc.path, f"no flight in the catalog matches {ids_or_query}",
                             "check the query with archive.open_archive(...).search(...)")
        return ids
    return [os.fspath(s) for s in ids_or_query]


def _keywords() -> tuple[str, ...]:
    from archive.run.options import KEYWORDS

    return (*KEYWORDS, "index", "expression", "zone_id", "geometry", "scheduler", "workers", "threads", "quiet")


@python_errors("archive.zonal_stats", _keywords)
def zonal_stats(ids_or_query, zones, index: str | Sequence[str] = (), expression: str | Sequence[str] = (), *,
                zone_id: str | None = None, geometry: bool = False, scheduler: str | None = None,
                workers: int | None = None, threads: int | None = None, quiet: bool = True, mode: str = "reflectance",
                **options) -> pd.DataFrame:
    """The zone x flight x index statistics of ``zones`` over the time stack of ``ids_or_query``
    (``archive stats``): a ``pandas.DataFrame`` of :data:`archive.analysis.zonal.COLUMNS`, a
    ``geopandas.GeoDataFrame`` with ``geometry``.

    ids_or_query: collection ids / raw flight directories, or a query dict ({"bbox", "datetime",
    "wavelength"}) of ``archive``; zones: a .geojson/.gpkg/.shp path (any CRS); index: catalogue
    names ('NDVI', or a list); expression: 'NAME=EXPR' band math (``R<nm>``; or a list); zone_id: the property naming the
    zones; mode: what indices are computed from (default 'reflectance'); scheduler: a Dask scheduler
    address (default a local cluster of ``workers`` x ``threads``). Render options as
    :func:`archive.stack` (gsd or like required; fov for raw flights; crs, ground_height, dem,
    white_reference...): the grid is the stack's. Errors: :class:`~archive.errors.ArchiveError`
    with the command's one-line messages.
    """
    from archive.analysis.indices import parse_indices
    from archive.analysis.zonal import check_options, zonal_table
    from archive.analysis.zones import read_zones
    from archive.run.options import RenderOptions

    names = [index] if isinstance(index, str) else list(index)
    texts = [expression] if isinstance(expression, str) else list(expression)
    specs = parse_indices(names, texts)
    found = read_zones(zones, zone_id)
    where = options.get("archive")
    if where is not None and hasattr(where, "path"):
        options["archive"] = str(where.path)
    request = RenderOptions.create(_sources(ids_or_query, where), mode=mode, **options)
    check_options(request)
    return zonal_table(request, found, specs, geometry=geometry, scheduler=scheduler, workers=workers,
                       threads=threads, quiet=quiet)


def run(args: argparse.Namespace) -> int:
    """``archive stats``: the table written to ``--out``; prints one line (zones, flights, indices,
    rows, seconds)."""
    from archive.analysis.indices import parse_indices
    from archive.analysis.zonal import check_options, zonal_table
    from archive.analysis.zones import read_zones
    from archive.run.command import query_ids
    from archive.run.options import RenderOptions

    out = check_out(args.out, args.overwrite, args.geometry)
    specs = parse_indices(args.index, args.expression)   # unknown names: one line, before anything is opened
    zones = read_zones(args.zones, args.zone_id)
    sources = list(args.sources or [])
    ids = query_ids(args)
    if ids is not None:
        sources += [i for i in ids if i not in sources]
    if not sources:
        raise InputError("SOURCE", "no flight to compute statistics of",
                         "give collection ids or flight directories, or --archive A with --query-*")
    request = RenderOptions.create(sources, **{name: getattr(args, name) for name in _RENDER})
    check_options(request)

    def say(text: str) -> None:
        if not args.quiet:
            print(text, file=sys.stderr)

    frame = zonal_table(request, zones, specs, geometry=args.geometry, scheduler=args.scheduler,
                        workers=args.workers, threads=args.threads, quiet=args.quiet, say=say)
    write_table(frame, out)
    flights = frame["flight"].nunique()
    print(f"archive stats: wrote {out}: {len(zones)} zones x {flights} flight{'s' if flights != 1 else ''} x "
          f"{len(specs)} ind{'ices' if len(specs) != 1 else 'ex'} = {len(frame)} rows in {frame.attrs['seconds']:.1f} s.")
    return 0
