"""What an ingest checks against the archive before and after it writes a flight: whether the flight
is ingested already (same files, parameters, DEM, navigation source) and cataloged, two directories
holding one flight, an archive another process is creating right now, and a full disk made one line.
Shared by the local ingest (:mod:`archive.ingest.command`) and the cluster's (:mod:`archive.ingest.cluster`)."""

from __future__ import annotations

import errno
import os
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from archive import storage
from archive.catalog.root import ArchiveRoot, create_archive
from archive.collection import StorePlan, is_complete, read_attrs
from archive.collection.layout import CHECKSUMS, file_digest
from archive.errors import ArchiveError, InputError
from archive.ingest.prepare import dem_of

__all__ = ["DiskFullError", "already_ingested", "cataloged", "check_ingested", "disk_full_is_an_error",
           "distinct_flights", "open_archive_root", "same_sources"]


def same_sources(attrs: dict, plan: StorePlan) -> bool:
    """Whether the store whose attributes are ``attrs`` was ingested from the same files as
    ``plan``: same names and sizes, and the same digest (by the algorithm each record names: blake3, or
    sha256 in older stores) for the small files (headers, times, navigation, calibration); data files are
    not re-hashed, so that a repeated ingest stays a quick no-op."""
    recorded = attrs.get("sources", [])
    if [(s["name"], s["size"]) for s in recorded] != [(plan.attrs["source_names"][p], n) for p, n in plan.sources]:
        return False
    data = set(plan.data_files)

    def same(path: str, record: dict) -> bool:
        algorithm = next((a for a in CHECKSUMS if a in record), None)
        return algorithm is not None and file_digest(path, algorithm) == record[algorithm]

    return all(path in data or same(path, rec) for (path, _), rec in zip(plan.sources, recorded, strict=True))


def cataloged(root: ArchiveRoot, cid: str) -> bool:
    from archive.catalog.index import ensure_index, search

    if root.is_url:   # the index is a local cache, rebuilt from the Items when stale
        return storage.exists(root.item_path(cid)) and storage.exists(root.catalog_path) \
            and bool(search(ensure_index(root), ids=[cid]))
    if not root.item_path(cid).exists() or not root.index_path.exists() or not root.catalog_path.exists():
        return False  # (an archive made before the root catalog.json existed gets one)
    return bool(search(root.index_path, ids=[cid]))


def distinct_flights(directories: list[str], plans: list[StorePlan]) -> list[tuple[str, StorePlan]]:
    """(directory, plan) per flight, a directory given twice taken once; two directories holding
    the same flight id (a copy of a flight) are refused before anything is written."""
    seen: dict[str, str] = {}
    pairs = []
    for directory, plan in zip(directories, plans):
        first = seen.get(plan.cid)
        if first is None:
            seen[plan.cid] = directory
            pairs.append((directory, plan))
        elif os.path.realpath(first) != os.path.realpath(directory):
            raise InputError(directory, f"is the same flight as {first} (both are {plan.cid})",
                             "ingest one of them; remove the copy from the command line")
    return pairs


def open_archive_root(archive_path: str | os.PathLike) -> ArchiveRoot:
    """:func:`create_archive`, tolerating another process creating the same new archive right now
    (its folders exist for a moment before its ``archive.json``; in object storage the marker is a
    conditional PUT, so both succeed)."""
    if storage.is_url(archive_path):
        return create_archive(archive_path)
    deadline = time.monotonic() + 10.0
    while True:
        try:
            return create_archive(archive_path)
        except InputError:
            path = Path(archive_path)
            made = ("collections", "catalog", "archive.json")   # what create_archive makes, marker last
            being_made = path.is_dir() and all(p.name in made or p.name.endswith(".partial") for p in path.iterdir())
            if not being_made or time.monotonic() > deadline:
                raise
            time.sleep(0.05)


def check_ingested(root: ArchiveRoot, plan: StorePlan, directory: str) -> None:
    """InputError unless the existing store of ``plan``'s id is complete and holds this flight, ingested
    with the same navigation parameters and DEM (then a rerun is a no-op)."""
    final = root.store(plan.cid)
    if not is_complete(final):
        raise InputError(final, "exists but has no completion marker", "pass --overwrite to re-ingest")
    attrs = read_attrs(final)
    recorded = attrs.get("navigation_params") or {}
    wanted = plan.attrs["navigation_params"]
    if any(recorded.get(k, 0.0 if k == "sync_offset" else [0.0] * 3) != v for k, v in wanted.items()):
        raise InputError(final, f"was ingested with other navigation parameters ({recorded or 'none'}, "
                         f"now {wanted})", "pass --overwrite to re-ingest with the new ones")
    tracks = (attrs.get("navigation_tracks") or {}).get("default"), \
        (plan.attrs.get("navigation_tracks") or {}).get("default")
    if tracks[0] != tracks[1]:
        raise InputError(final, f"was ingested with another navigation source ({tracks[0] or 'lcf'}, now "
                         f"{tracks[1] or 'lcf'})", "pass --overwrite to re-ingest it so")
    old_dem = dem_of(attrs.get("terrain"))
    if old_dem != dem_of(plan.attrs.get("terrain")):
        new_dem = dem_of(plan.attrs.get("terrain"))
        raise InputError(final, f"was ingested with {'the DEM ' + old_dem[0] if old_dem else 'no DEM'}, "
                         f"now {'the DEM ' + new_dem[0] if new_dem else 'none'}",
                         "pass --overwrite to re-ingest (the catalog footprint follows the DEM)")
    if not same_sources(attrs, plan):
        raise InputError(final, f"holds a different flight than {directory} under the "
                         f"same id {plan.cid} (same sensor, same start second)",
                         "pass --overwrite to replace it")


def already_ingested(root: ArchiveRoot, plan: StorePlan, directory: str) -> bool:
    """Whether ``plan``'s flight is ingested and cataloged as asked (read only, without the lock: a
    rerun after success writes nothing, not even a lock file); False when in any doubt (the locked
    path then decides, and says why)."""
    try:
        if not (is_complete(root.store(plan.cid)) if root.is_url else root.store(plan.cid).exists()):
            return False
        check_ingested(root, plan, directory)
        return cataloged(root, plan.cid)
    except (ArchiveError, OSError, ValueError):
        return False


def _disk_full(exc: BaseException) -> BaseException | None:
    """The error in ``exc``'s chain (``exc`` or what it wraps) that says the disk or the quota is full, if any."""
    import sqlite3

    seen = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        if isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT):
            return exc
        if isinstance(exc, sqlite3.OperationalError) and "full" in str(exc).lower():
            return exc
        exc = exc.__cause__ or exc.__context__
    return None


@contextmanager
def disk_full_is_an_error(root: ArchiveRoot, cid: str) -> Iterator[None]:
    """A full disk (or quota) while writing the store, its checksums or the catalog (SQLite) becomes
    one line naming the full file (else the full folder) and the archive; what was written stays as the partial
    store, which the rerun resumes."""
    try:
        yield
    except Exception as exc:
        full = _disk_full(exc)
        if full is None:
            raise
        where = getattr(full, "filename", None) or _full_folder(root) or root.path   # the full file, else folder
        raise DiskFullError(where, f"the disk is full while ingesting {cid} into {root.path} ({type(exc).__name__}: "
                            f"{' '.join(str(exc).split())})",
                            "free some space, then run the same ingest again: it resumes where it stopped") from None


def _full_folder(root: ArchiveRoot) -> Path | None:
    """The first of the archive's folders (collections, catalog, the archive) whose file system has no
    free block left (a local archive; None when none, or in object storage)."""
    if root.is_url:
        return None
    for folder in (root.collections, root.path / "catalog", root.path):
        try:
            if os.statvfs(folder).f_bavail == 0:
                return folder
        except OSError:
            continue
    return None


class DiskFullError(InputError):
    """An ingest stopped by a full disk or quota (its partial store stays, for the rerun to resume)."""


