"""An archive root: a directory marked by ``archive.json``, holding collections and a catalog.

Layout::

    <ARCHIVE>/archive.json                   {"format": "archive", "version": 1}
    <ARCHIVE>/collections/<id>.zarr          completed collections (Zarr v3)
    <ARCHIVE>/collections/<id>.zarr.partial  an ingest in progress (never listed)
    <ARCHIVE>/catalog.json                   STAC Catalog, the root (links to the Collection)
    <ARCHIVE>/catalog/collection.json        STAC Collection of the archive (links to every Item)
    <ARCHIVE>/catalog/items/<id>.json        one STAC Item per completed collection
    <ARCHIVE>/catalog/index.sqlite           the query index, rebuildable from the Items

An archive may also be an ``s3://bucket/prefix`` URL (:mod:`archive.storage`): the same layout as
objects, except that a store is written under its final prefix (no ``.partial``: S3 has no rename;
its ``zarr.json`` says complete only at the end) and the SQLite index is a local cache
(:func:`cache_index_path`), rebuilt from the Items when it is missing or stale.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import threading
from dataclasses import dataclass
from pathlib import Path

from archive import storage
from archive.collection import is_complete
from archive.errors import InputError, MissingInputError
from archive.files import FileLock, write_atomic

MARKER = "archive.json"
FORMAT = "archive"
VERSION = 1

# Collection ids are file names: letters, digits, '-', '_' and '.', not starting with '.'.
_ID = re.compile(r"^[A-Za-z0-9_-][A-Za-z0-9_.-]{0,127}$")


def check_collection_id(cid: str) -> str:
    """Return ``cid`` if it is a valid collection id (safe as a file name), else raise InputError."""
    if not isinstance(cid, str) or not _ID.match(cid) or cid.endswith(".partial"):
        raise InputError(None, f"{cid!r} is not a valid collection id",
                         "ids use letters, digits, '-', '_' and '.', e.g. Pika-L-536_20230626T090301")
    return cid


@dataclass(frozen=True)
class ArchiveRoot:
    """Paths inside one archive directory (no I/O in the constructor); ``path`` is a UPath for an
    archive in object storage (:attr:`is_url`)."""

    path: Path

    @property
    def is_url(self) -> bool:
        """Whether the archive is in object storage (``s3://``)."""
        return storage.is_url(self.path)

    @property
    def collections(self) -> Path:
        return self.path / "collections"

    @property
    def items(self) -> Path:
        return self.path / "catalog" / "items"

    @property
    def index_path(self) -> Path:
        """The SQLite index: ``catalog/index.sqlite`` on disk; for an archive in object storage a
        local cache file (SQLite needs a local file; see :func:`cache_index_path`)."""
        if self.is_url:
            return cache_index_path(self)
        return self.path / "catalog" / "index.sqlite"

    @property
    def catalog_path(self) -> Path:
        """The root STAC Catalog, ``<ARCHIVE>/catalog.json``."""
        return self.path / "catalog.json"

    @property
    def collection_path(self) -> Path:
        """The archive's STAC Collection, ``<ARCHIVE>/catalog/collection.json``."""
        return self.path / "catalog" / "collection.json"

    def store(self, cid: str) -> Path:
        """Path of the completed collection store ``<id>.zarr``."""
        return self.collections / f"{check_collection_id(cid)}.zarr"

    def partial(self, cid: str) -> Path:
        """Path of the store while it is being written (renamed to :meth:`store` when complete; in
        object storage the store itself, which its completion marker publishes)."""
        if self.is_url:
            return self.store(cid)
        return self.collections / f"{check_collection_id(cid)}.zarr.partial"

    def item_path(self, cid: str) -> Path:
        return self.items / f"{check_collection_id(cid)}.json"

    def collection_ids(self) -> list[str]:
        """Ids of the completed stores on disk (a ``.zarr`` directory whose group says complete)."""
        if self.is_url:
            ids = [name[: -len(".zarr")] for name, is_dir, _ in storage.list_names(self.collections)
                   if is_dir and name.endswith(".zarr")]
            return sorted(cid for cid in ids if is_complete(self.collections / f"{cid}.zarr"))
        if not self.collections.is_dir():
            return []
        ids = [p.name[: -len(".zarr")] for p in self.collections.iterdir()
               if p.name.endswith(".zarr") and p.is_dir()]
        return sorted(cid for cid in ids if is_complete(self.collections / f"{cid}.zarr"))

    def incomplete_ids(self) -> list[str]:
        """Ids of the stores ``collections/<id>.zarr`` on disk that lack their completion marker (an
        update interrupted by an older version; partial ingests, ``<id>.zarr.partial``, are not these).
        Local archives only (in object storage an ingest under way looks the same): [] for a URL."""
        if self.is_url or not self.collections.is_dir():
            return []
        ids = [p.name[: -len(".zarr")] for p in self.collections.iterdir()
               if p.name.endswith(".zarr") and not p.name.startswith(".") and p.is_dir()]
        return sorted(cid for cid in ids if not is_complete(self.collections / f"{cid}.zarr"))

    def require_collection(self, cid: str) -> Path:
        """Path of a completed collection, or MissingInputError naming the id and the archive."""
        store = self.store(cid)
        if not is_complete(store):
            known = self.collection_ids()
            hint = ("known ids: " + ", ".join(known[:10]) + (" ..." if len(known) > 10 else "")) if known \
                else "the archive holds no collection yet: run 'archive ingest'"
            raise MissingInputError(store, f"collection {cid!r}", hint)
        return store


def cache_index_path(root: ArchiveRoot) -> Path:
    """Where the index of an archive that cannot be written lives: ``$XDG_CACHE_HOME`` (else
    ``~/.cache``) ``/archive/catalog/<name>-<hash of the archive's absolute path>/index.sqlite``."""
    import hashlib

    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    where = str(root.path) if root.is_url else str(Path(root.path).absolute())
    digest = hashlib.sha256(where.encode("utf-8", "surrogateescape")).hexdigest()[:16]
    name = "".join(c if c.isalnum() or c in "-_." else "_" for c in where.rstrip("/").rsplit("/", 1)[-1])[:40] \
        or "archive"
    return Path(base) / "archive" / "catalog" / f"{name}-{digest}" / "index.sqlite"


def open_root(path: str | os.PathLike) -> ArchiveRoot:
    """Open an existing archive; MissingInputError if ``path`` does not exist, InputError if it is
    not an archive (no readable ``archive.json``) or has a newer format version."""
    root = storage.location(path)
    url = storage.is_url(root)
    if not url and not root.exists():
        raise MissingInputError(root, "archive directory", "create one with 'archive ingest RAW_DIR --archive PATH'")
    marker = root / MARKER
    if not storage.exists(marker):
        if url:
            raise MissingInputError(marker, "archive marker",
                                    "check the URL, AWS_ENDPOINT_URL and the credentials, or create the archive "
                                    "with 'archive ingest RAW_DIR --archive URL'")
        raise InputError(root, f"not an archive (no {MARKER})",
                         "point --archive at a directory made by 'archive ingest'")
    try:
        info = json.loads(storage.read_bytes(marker))
    except (OSError, ValueError) as exc:
        raise InputError(marker, f"unreadable archive marker: {exc}", "restore it: {\"format\": \"archive\", \"version\": 1}") from exc
    if not isinstance(info, dict) or info.get("format") != FORMAT:
        raise InputError(marker, "not an archive marker (expected \"format\": \"archive\")")
    version = info.get("version")
    if not isinstance(version, int) or version > VERSION:
        raise InputError(marker, f"archive format version {version!r} is not supported (this software reads {VERSION})",
                         "upgrade archive")
    return ArchiveRoot(root)


def create_archive(path: str | os.PathLike) -> ArchiveRoot:
    """Open the archive at ``path``, creating it (directories and ``archive.json``) when ``path``
    does not exist or is an empty directory. A non-empty directory that is not an archive is
    refused, so that an ingest never scatters files into an unrelated folder. In object storage,
    likewise: a prefix that holds objects but no ``archive.json`` is refused; the marker is created with
    a conditional PUT (two ingests creating one archive both succeed)."""
    root = storage.location(path)
    if storage.is_url(root):
        if storage.exists(root / MARKER):
            return open_root(root)
        # another ingest creating this archive puts its marker first, before any other object: a prefix
        # found non-empty is an archive when the marker is there now (it may have appeared since the check)
        if any(True for _ in storage.list_names(root)) and not storage.exists(root / MARKER):
            raise InputError(root, f"holds objects but no {MARKER}, so it is not an archive",
                             "choose a new or empty prefix for --archive")
        storage.put_if_absent(root / MARKER, (json.dumps({"format": FORMAT, "version": VERSION}, indent=2)
                                              + "\n").encode())
        return open_root(root)
    if (root / MARKER).exists():
        return open_root(root)
    if root.exists():
        if not root.is_dir():
            raise InputError(root, "exists and is not a directory", "choose another --archive path")
        if any(root.iterdir()):
            raise InputError(root, f"is a non-empty directory without {MARKER}, so not an archive",
                             "choose a new or empty directory for --archive")
    root.mkdir(parents=True, exist_ok=True)
    (root / "collections").mkdir(exist_ok=True)
    (root / "catalog" / "items").mkdir(parents=True, exist_ok=True)
    write_atomic(root / MARKER, json.dumps({"format": FORMAT, "version": VERSION}, indent=2) + "\n")
    return ArchiveRoot(root)


_HELD = threading.local()


@contextlib.contextmanager
def locked(root: ArchiveRoot):
    """An exclusive lock on the archive's catalog (so that two ingests never interleave their
    read of the index and their writes); none where fcntl does not exist. Reentrant within a
    thread (a flock taken twice by one process through two files would wait for itself).
    OSError when the lock file cannot be opened (a read-only archive)."""
    try:
        import fcntl
    except ImportError:  # not POSIX
        yield
        return
    held = getattr(_HELD, "paths", None)
    if held is None:
        held = _HELD.paths = set()
    key = str(root.path) if root.is_url else str(Path(root.path).absolute())
    if key in held:
        yield
        return
    if root.is_url:   # a lock object (conditional PUT), see archive.files.FileLock
        lock = FileLock(root.path / "catalog" / ".catalog.lock", "catalog update", what=f"the catalog of {root.path}")
        lock.acquire(wait=float("inf"))
        held.add(key)
        try:
            yield
        finally:
            held.discard(key)
            lock.release()
        return
    root.collection_path.parent.mkdir(parents=True, exist_ok=True)
    with open(root.collection_path.parent / ".catalog.lock", "a") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        held.add(key)
        try:
            yield
        finally:
            held.discard(key)
            fcntl.flock(f, fcntl.LOCK_UN)
