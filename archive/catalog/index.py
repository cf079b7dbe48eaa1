"""SQLite index of an archive's STAC Items: bbox (R*Tree), footprint, time range and wavelength range.

The index is a cache of ``<ARCHIVE>/catalog/items/*.json``: :func:`rebuild_index` recreates it from
those files. :func:`ensure_index` checks it before every use (:func:`index_problem`: an SQLite header,
this schema, an intact database, and the Items and collection stores it was built from are the ones
on disk, row count included) and rebuilds it when not; an archive that cannot be written (a
published archive, a read-only mount) gets its index in the user's cache folder instead
(:func:`cache_index_path`). Readers open it read-only (:func:`connect_readonly`). Items that cannot
be read, and collections without an Item, are recorded as damaged (:func:`damaged_flights`): each
costs only its own flight. Every statement is parameterised. The schema is :data:`SCHEMA`, read from ``catalogs/schema.sql`` (shipped
as the package ``archive.catalogs``).

Spatial queries are exact: the R*Tree (float32 boxes rounded outward) picks candidates, the exact
bbox keeps those inside the query box, and the footprint itself (WKB, tested with shapely in the
SQL function ``archive_intersects``) decides the rest. Every connection made by :func:`connect` has
that function.
"""

from __future__ import annotations

import importlib.resources

import json
import os
import sqlite3
from collections.abc import Iterable, Sequence
from contextlib import closing
from dataclasses import dataclass
from dataclasses import field as dataclass_field
from functools import lru_cache
from pathlib import Path

import numpy as np

from archive import storage
from archive.catalog.arguments import parse_bbox, parse_datetime_range  # noqa: F401 - re-exported
from archive.catalog.root import ArchiveRoot, cache_index_path  # cache_index_path: re-exported
from archive.collection import is_complete
from archive.errors import FormatError, InputError

SCHEMA_VERSION = "2"

# The schema lives in catalogs/schema.sql (the agreed place for it), shipped as archive.catalogs.
SCHEMA = (importlib.resources.files("archive.catalogs") / "schema.sql").read_text(encoding="utf-8")


@dataclass(frozen=True)
class IndexRow:
    """One indexed Item. Times in epoch seconds (UTC) and ISO 8601; wavelengths nm; bbox degrees
    (west, south, east, north); item_path relative to the archive root."""

    id: str
    start_time: float
    end_time: float
    start_iso: str
    end_iso: str
    bands: int
    min_wavelength: float | None
    max_wavelength: float | None
    bbox: tuple[float, float, float, float]
    sensor: str | None
    gsd: float | None
    item_path: str
    geometry: bytes | None = dataclass_field(default=None, repr=False, compare=False)  # footprint, WKB


_COLUMNS = ("id, start_time, end_time, start_iso, end_iso, bands, min_wavelength, max_wavelength, "
            "west, south, east, north, sensor, gsd, item_path")


def _row(values: Sequence) -> IndexRow:
    (cid, t0, t1, i0, i1, bands, wl0, wl1, w, s, e, n, sensor, gsd, path) = values
    return IndexRow(cid, t0, t1, i0, i1, bands, wl0, wl1, (w, s, e, n), sensor, gsd, path)


def _f32_down(x: float) -> float:
    v = np.float32(x)
    return float(v if float(v) <= x else np.nextafter(v, np.float32(-np.inf)))


def _f32_up(x: float) -> float:
    v = np.float32(x)
    return float(v if float(v) >= x else np.nextafter(v, np.float32(np.inf)))


@lru_cache(maxsize=64)
def _prepared(wkb: bytes):
    """A query geometry from its WKB, prepared for repeated predicates (cached: one per query)."""
    import shapely

    geom = shapely.from_wkb(wkb)
    shapely.prepare(geom)
    return geom


def _intersects(footprint: bytes | None, query: bytes) -> int:
    """SQL function ``archive_intersects(footprint WKB, query WKB)``: 1 when they intersect (touching
    counts); a row without a footprint counts as its bbox, which the caller has already tested."""
    if footprint is None:
        return 1
    import shapely

    return int(_prepared(query).intersects(shapely.from_wkb(footprint)))


def geometry_wkb(geometry: dict) -> bytes:
    """WKB of a GeoJSON geometry (lon/lat degrees); InputError when it is not one."""
    import shapely

    try:
        geom = shapely.geometry.shape(geometry)
    except Exception as exc:  # shapely raises several kinds for malformed GeoJSON
        raise InputError("geometry", f"not a GeoJSON geometry: {exc}") from None
    if geom.is_empty:
        raise InputError("geometry", "the geometry is empty")
    return shapely.to_wkb(geom)


def box_wkb(bbox: Sequence[float]) -> bytes:
    """WKB of the polygon of a (west, south, east, north) box in degrees."""
    import shapely

    return shapely.to_wkb(shapely.box(*(float(v) for v in bbox)))


def spatial_clause(bbox: Sequence[float], wkb: bytes | None = None, alias: str = "i") -> tuple[str, list]:
    """SQL (and its parameters) true for the rows of ``items AS alias`` whose footprint intersects
    the geometry ``wkb`` whose bbox is ``bbox`` (W, S, E, N degrees; ``wkb`` None: the box itself).
    Uses the R*Tree; the caller joins nothing."""
    w, s, e, n = (float(v) for v in bbox)
    query = box_wkb((w, s, e, n)) if wkb is None else wkb
    a = alias
    sql = (f"{a}.rowid IN (SELECT id FROM items_bbox WHERE west <= ? AND east >= ? AND south <= ? AND north >= ?)"
           f" AND {a}.west <= ? AND {a}.east >= ? AND {a}.south <= ? AND {a}.north >= ?")
    params: list = [_f32_up(e), _f32_down(w), _f32_up(n), _f32_down(s), e, w, n, s]
    if wkb is None:
        # a footprint whose bbox lies inside the query box meets it: no geometry test needed
        sql += (f" AND (({a}.west >= ? AND {a}.east <= ? AND {a}.south >= ? AND {a}.north <= ?)"
                f" OR archive_intersects({a}.geometry, ?))")
        params += [w, e, s, n, query]
    else:
        sql += f" AND archive_intersects({a}.geometry, ?)"
        params.append(query)
    return f"({sql})", params


def connect(path: str | os.PathLike) -> sqlite3.Connection:
    """Open (creating if needed) an index database for writing and make sure its schema exists."""
    con = sqlite3.connect(str(path), timeout=30.0)
    con.create_function("archive_intersects", 2, _intersects, deterministic=True)
    try:
        con.executescript(SCHEMA)
        with con:
            con.execute("INSERT OR IGNORE INTO meta (key, value) VALUES (?, ?)", ("schema_version", SCHEMA_VERSION))
        found = con.execute("SELECT value FROM meta WHERE key = ?", ("schema_version",)).fetchone()[0]
    except sqlite3.DatabaseError as exc:
        con.close()
        raise FormatError(path, f"not a catalog index: {exc}",
                          "it is a cache of the Items: delete it, the next search rebuilds it") from exc
    if found != SCHEMA_VERSION:
        con.close()
        raise FormatError(path, f"index schema version {found}, expected {SCHEMA_VERSION}",
                          "it is a cache of the Items: delete it, the next search rebuilds it")
    return con


def connect_readonly(path: str | os.PathLike) -> sqlite3.Connection:
    """Open an existing index read-only (nothing is written: the archive may be a read-only mount)."""
    con = sqlite3.connect(f"file:{Path(path).absolute()}?mode=ro", uri=True, timeout=30.0,
                          check_same_thread=False)
    con.create_function("archive_intersects", 2, _intersects, deterministic=True)
    return con


def row_from_item(item: dict, item_path: str) -> IndexRow:
    """The index row of a STAC Item dict (as written by archive.catalog.stac.make_item)."""
    from archive.catalog.stac import item_summary

    s = item_summary(item, where=item_path)
    geometry = item.get("geometry")
    try:
        wkb = geometry_wkb(geometry) if geometry else None
    except InputError as exc:
        raise FormatError(item_path, f"bad Item geometry: {exc}", "re-ingest its flight") from None
    return IndexRow(s["id"], s["start_time"], s["end_time"], s["start_iso"], s["end_iso"], s["bands"],
                    s["min_wavelength"], s["max_wavelength"], tuple(s["bbox"]), s["sensor"], s["gsd"],
                    item_path, wkb)


def _insert(con: sqlite3.Connection, row: IndexRow) -> None:
    old = con.execute("SELECT rowid FROM items WHERE id = ?", (row.id,)).fetchone()
    if old is not None:
        con.execute("DELETE FROM items_bbox WHERE id = ?", (old[0],))
        con.execute("DELETE FROM items WHERE rowid = ?", (old[0],))
    w, s, e, n = row.bbox
    cur = con.execute(
        f"INSERT INTO items ({_COLUMNS}, geometry) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
        (row.id, row.start_time, row.end_time, row.start_iso, row.end_iso, row.bands, row.min_wavelength,
         row.max_wavelength, w, s, e, n, row.sensor, row.gsd, row.item_path, row.geometry))
    con.execute("INSERT INTO items_bbox (id, west, east, south, north) VALUES (?, ?, ?, ?, ?)",
                (cur.lastrowid, _f32_down(w), _f32_up(e), _f32_down(s), _f32_up(n)))


def _meta_json(con: sqlite3.Connection, key: str):
    found = con.execute("SELECT value FROM meta WHERE key = ?", (key,)).fetchone()
    return None if found is None else json.loads(found[0])


def _set_meta_json(con: sqlite3.Connection, key: str, value) -> None:
    con.execute("INSERT INTO meta (key, value) VALUES (?, ?) ON CONFLICT(key) DO UPDATE SET value = excluded.value",
                (key, json.dumps(value)))


def add_rows(path: str | os.PathLike, rows: Iterable[IndexRow]) -> int:
    """Insert or replace rows (by id) in one transaction; returns how many. Each id also counts
    as an Item and a collection store on disk (a flight is indexed once both exist) and is no
    longer damaged."""
    count = 0
    longest = 0.0
    with closing(connect(path)) as con, con:
        seen_items, seen_stores = _meta_json(con, "items"), _meta_json(con, "stores")
        damaged = _meta_json(con, "damaged") or {}
        for row in rows:
            _insert(con, row)
            longest = max(longest, row.end_time - row.start_time)
            count += 1
            damaged.pop(row.id, None)
            for seen in (seen_items, seen_stores):
                if seen is not None and row.id not in seen:
                    seen.append(row.id)
        for key, value in (("items", seen_items), ("stores", seen_stores)):
            if value is not None:
                _set_meta_json(con, key, sorted(value))
        _set_meta_json(con, "damaged", damaged)
        # The longest flight bounds start_time from below in time queries (see search).
        con.execute("INSERT INTO meta (key, value) VALUES ('max_duration', ?) ON CONFLICT(key) DO UPDATE "
                    "SET value = max(CAST(value AS REAL), CAST(excluded.value AS REAL))", (repr(longest),))
    return count


def remove(path: str | os.PathLike, cid: str) -> bool:
    """Remove the row of ``cid``; returns whether there was one."""
    with closing(connect(path)) as con, con:
        old = con.execute("SELECT rowid FROM items WHERE id = ?", (cid,)).fetchone()
        if old is None:
            return False
        con.execute("DELETE FROM items_bbox WHERE id = ?", (old[0],))
        con.execute("DELETE FROM items WHERE rowid = ?", (old[0],))
    return True


def read_item_file(path: Path) -> dict:
    try:
        item = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise FormatError(path, f"unreadable STAC Item: {exc}", "remove it or re-ingest its flight") from exc
    if not isinstance(item, dict):
        raise FormatError(path, "a STAC Item must be a JSON object")
    return item


@dataclass(frozen=True)
class Damaged:
    """A flight the catalog cannot describe: its id, why (one line), how to fix it, and the kind:
    ``item`` (its Item cannot be read), ``no-item`` (a store without an Item), ``no-store`` (an
    Item whose store is gone), ``incomplete`` (an Item whose store lacks its completion marker)."""

    id: str
    reason: str
    fix: str = "run 'archive catalog rebuild' (it recreates a collection's Item from the collection)"
    kind: str = "item"

    def as_dict(self) -> dict:
        return {"id": self.id, "reason": self.reason, "fix": self.fix}

    def __str__(self) -> str:
        return f"{self.id}: {self.reason} ({self.fix})"


def item_names(root: ArchiveRoot) -> list[str]:
    """Ids of the Item files ``catalog/items/<id>.json`` (sorted; temporaries left out)."""
    if root.is_url:
        return sorted(name[:-5] for name, is_dir, _ in storage.list_names(root.items)
                      if not is_dir and name.endswith(".json") and not name.startswith("."))
    try:
        return sorted(e.name[:-5] for e in os.scandir(root.items)
                      if e.name.endswith(".json") and not e.name.startswith("."))
    except FileNotFoundError:
        return []


def store_names(root: ArchiveRoot) -> list[str]:
    """Ids of the collection stores ``collections/<id>.zarr`` on disk (sorted; partial ones left out;
    in object storage every ``<id>.zarr/`` prefix: complete or not, as on disk)."""
    if root.is_url:
        return sorted(name[:-5] for name, is_dir, _ in storage.list_names(root.collections)
                      if is_dir and name.endswith(".zarr") and not name.startswith("."))
    try:
        return sorted(e.name[:-5] for e in os.scandir(root.collections)
                      if e.name.endswith(".zarr") and not e.name.startswith(".") and e.is_dir())
    except FileNotFoundError:
        return []


def item_etags(root: ArchiveRoot) -> dict[str, str]:
    """{id: ETag} of the Item objects of an archive in object storage, from one LIST: what the
    local index cache of such an archive records, so that an Item rewritten elsewhere (same name,
    new content) makes the cache stale."""
    return {name[:-5]: str((meta or {}).get("e_tag")) for name, is_dir, meta in storage.list_names(root.items)
            if not is_dir and name.endswith(".json") and not name.startswith(".")}


def scan_catalog(root: ArchiveRoot) -> tuple[list[IndexRow], list[Damaged], list[str], list[str]]:
    """Read every Item of the archive: (index rows of the readable ones, damaged flights, Item ids,
    store ids). Damaged: an Item that cannot be read or is not a valid flight Item, a completed
    store without an Item, an Item whose store is gone (also indexed: its metadata is intact)."""
    items, stores = item_names(root), store_names(root)
    rows: list[IndexRow] = []
    damaged: list[Damaged] = []
    for cid in items:
        path = root.items / f"{cid}.json"
        rel = path.relative_to(root.path).as_posix()
        try:
            row = row_from_item(read_item_file(path), rel)
        except (InputError, KeyError, TypeError, ValueError) as exc:
            damaged.append(Damaged(cid, f"STAC Item {rel} is damaged: {_one_line(exc)}"))
            continue
        rows.append(row)
        if cid not in stores:
            damaged.append(Damaged(cid, f"collection store collections/{cid}.zarr is missing",
                                   "re-ingest the flight, or delete its Item", "no-store"))
        elif not root.is_url and not is_complete(root.collections / f"{cid}.zarr"):
            damaged.append(Damaged(cid, f"collection store collections/{cid}.zarr is incomplete (no completion "
                                        "marker: an update of it was interrupted by an older version)",
                                   f"re-ingest it from its raw files: archive ingest RAW_DIR --archive {root.path} "
                                   "--overwrite", "incomplete"))
    known = set(items)
    for cid in stores:
        if cid not in known:
            if is_complete(root.collections / f"{cid}.zarr"):
                damaged.append(Damaged(cid, f"collection collections/{cid}.zarr has no STAC Item (an ingest may be "
                                            "under way)", kind="no-item"))
            else:   # a killed ingest's (in object storage its partial store has its final name): rebuild cannot help
                damaged.append(Damaged(cid, f"collection collections/{cid}.zarr is not complete (an ingest of it is "
                                            "under way, or was killed)", "run the same 'archive ingest' again: it "
                                       "resumes where it stopped", kind="no-item"))
    return rows, damaged, items, stores


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return text if len(text) <= 300 else text[:297] + "..."


def rebuild_index(root: ArchiveRoot, dest: str | os.PathLike | None = None) -> int:
    """Recreate the index from the Item files (written to a temporary file, then renamed over
    ``dest``, by default ``catalog/index.sqlite``). Unreadable Items cost only their flight: they
    are recorded as damaged (:func:`damaged_flights`). Returns the number of Items indexed."""
    dest = Path(dest) if dest is not None else root.index_path
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = dest.with_name(f"{dest.name}.tmp-{os.getpid()}")
    tmp.unlink(missing_ok=True)
    etags = item_etags(root) if root.is_url else None   # before the scan: a later change shows as stale
    rows, damaged, items, stores = scan_catalog(root)
    try:
        add_rows(tmp, rows)
        with closing(connect(tmp)) as con, con:
            if etags is not None:
                _set_meta_json(con, "item_etags", etags)
            _set_meta_json(con, "items", items)
            _set_meta_json(con, "stores", stores)
            _set_meta_json(con, "damaged", {d.id: [d.reason, d.fix, d.kind] for d in damaged})
        os.replace(tmp, dest)
    finally:
        tmp.unlink(missing_ok=True)
    return len(rows)


_REQUIRED_COLUMNS = {"id", "start_time", "end_time", "start_iso", "end_iso", "bands", "min_wavelength",
                     "max_wavelength", "west", "south", "east", "north", "sensor", "gsd", "item_path", "geometry"}
_SQLITE_HEADER = b"SQLite format 3\x00"


def index_problem(path: str | os.PathLike, root: ArchiveRoot) -> str | None:
    """Why the index file ``path`` cannot answer for the archive ``root`` (None: it can). Checks,
    reading only: the file exists and has an SQLite header, its schema version and columns, the
    database's integrity (``PRAGMA quick_check``), and that it was built from the Item files and
    collection stores now on disk, with one row per readable Item."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            header = f.read(100)
    except FileNotFoundError:
        return "missing"
    except OSError as exc:
        return f"unreadable ({exc.strerror or exc})"
    if len(header) < 100 or not header.startswith(_SQLITE_HEADER):
        return f"not an SQLite database ({path.stat().st_size} bytes)"
    try:
        with closing(connect_readonly(path)) as con:
            version = con.execute("SELECT value FROM meta WHERE key = 'schema_version'").fetchone()
            if version is None or version[0] != SCHEMA_VERSION:
                return f"schema version {version[0] if version else None}, expected {SCHEMA_VERSION}"
            columns = {r[1] for r in con.execute("PRAGMA table_info(items)")}
            if not _REQUIRED_COLUMNS <= columns:
                return f"wrong schema (items lacks {', '.join(sorted(_REQUIRED_COLUMNS - columns))})"
            check = con.execute("PRAGMA quick_check(1)").fetchone()
            if check is None or check[0] != "ok":
                return f"damaged ({check[0] if check else 'no answer'})"
            seen_items, seen_stores = _meta_json(con, "items"), _meta_json(con, "stores")
            damaged = _meta_json(con, "damaged") or {}
            etags = _meta_json(con, "item_etags") if root.is_url else None
            count = con.execute("SELECT count(*) FROM items").fetchone()[0]
            bbox_count = con.execute("SELECT count(*) FROM items_bbox").fetchone()[0]
    except (sqlite3.DatabaseError, ValueError, TypeError) as exc:
        return f"damaged ({_one_line(exc)})"
    if seen_items is None or seen_stores is None:
        return "built by an older version (no record of the Items it holds)"
    if root.is_url:   # the local cache of an archive in object storage: the Items' ETags, one LIST
        if etags != item_etags(root):
            return "out of date: the Item objects have changed since it was built"
    elif seen_items != item_names(root):
        return "out of date: the Item files have changed since it was built"
    if seen_stores != store_names(root):
        return "out of date: the collection stores have changed since it was built"
    unreadable = sum(1 for cid, entry in damaged.items() if entry[2:] == ["item"] and cid in seen_items)
    if count != len(seen_items) - unreadable or bbox_count != count:
        return f"{count} rows for {len(seen_items) - unreadable} readable Items"
    return None


def unwritable(exc: BaseException) -> bool:
    """Whether ``exc`` (an OSError or sqlite3.OperationalError) says the archive cannot be written
    (read-only file system or database, permission denied)."""
    import errno

    if isinstance(exc, sqlite3.OperationalError):
        text = str(exc).lower()
        return "readonly" in text or "read-only" in text or "unable to open" in text
    return isinstance(exc, OSError) and exc.errno in (errno.EACCES, errno.EPERM, errno.EROFS)


def schema_version(path: str | os.PathLike) -> str | None:
    """The schema version an index file records (None: no such file, or no version in it)."""
    if not Path(path).exists():
        return None
    try:
        with closing(sqlite3.connect(f"file:{Path(path).absolute()}?mode=ro", uri=True, timeout=30.0)) as con:
            found = con.execute("SELECT value FROM meta WHERE key = 'schema_version'").fetchone()
    except sqlite3.DatabaseError:
        return "unreadable"
    return found[0] if found else None


def ensure_index(root: ArchiveRoot) -> Path:
    """The path of an index that answers for the archive's Items now: the archive's own
    ``catalog/index.sqlite`` when :func:`index_problem` finds nothing wrong with it, else that file
    rebuilt from the Items (under the catalog lock), else, when the archive cannot be written, an
    index in the user's cache folder (:func:`cache_index_path`), rebuilt there when needed.
    Nothing is written to a read-only archive."""
    own = root.index_path
    problem = index_problem(own, root)
    if problem is None:
        return own
    try:
        from archive.catalog.root import locked

        with locked(root):
            if index_problem(own, root) is not None:  # another process may have rebuilt it meanwhile
                rebuild_index(root)
        return own
    except (OSError, sqlite3.OperationalError) as exc:
        if not unwritable(exc):
            raise
    cache = cache_index_path(root)
    if index_problem(cache, root) is None:
        return cache
    try:
        rebuild_index(root, cache)
    except (OSError, sqlite3.OperationalError) as exc:
        if not unwritable(exc):
            raise
        raise InputError(own, f"the catalog index is {problem}, the archive cannot be written and neither can "
                              f"the cache folder {cache.parent} ({_one_line(exc)})",
                         "set XDG_CACHE_HOME to a writable folder") from None
    return cache


def damaged_flights(root: ArchiveRoot, index: str | os.PathLike | None = None) -> list[Damaged]:
    """The flights the catalog cannot describe (recorded when the index was built; ``index``: a
    path from :func:`ensure_index`, found when None), sorted by id."""
    path = ensure_index(root) if index is None else Path(index)
    with closing(connect_readonly(path)) as con:
        found = _meta_json(con, "damaged") or {}
    return [Damaged(cid, *entry) for cid, entry in sorted(found.items())]


def search(path: str | os.PathLike, bbox: tuple[float, float, float, float] | None = None,
           start: float | None = None, end: float | None = None, wavelength: float | None = None,
           ids: Sequence[str] | None = None) -> list[IndexRow]:
    """Items whose bbox intersects ``bbox`` (west, south, east, north degrees), whose time range
    [start_time, end_time] intersects [start, end] (epoch s; None = open), and whose wavelength range
    contains ``wavelength`` (nm). Sorted by start time, then id.

    bbox: the footprint (not only its bbox) must meet the box (touching counts)."""
    sql = f"SELECT {', '.join('i.' + c.strip() for c in _COLUMNS.split(','))} FROM items AS i"
    where: list[str] = []
    params: list[object] = []
    if bbox is not None:
        clause, more = spatial_clause(bbox)
        where.append(clause)
        params += more
    if start is not None or end is not None:
        clause, more = time_clause(path, start, end)
        where.append(clause)
        params += more
    if wavelength is not None:
        where += ["i.min_wavelength <= ?", "i.max_wavelength >= ?"]
        params += [float(wavelength), float(wavelength)]
    if ids is not None:
        if not ids:
            return []
        where.append(f"i.id IN ({', '.join('?' for _ in ids)})")
        params += list(ids)
    if where:
        sql += " WHERE " + " AND ".join(where)
    sql += " ORDER BY i.start_time, i.id"
    try:
        with closing(connect_readonly(path)) as con:
            return [_row(r) for r in con.execute(sql, params)]
    except sqlite3.DatabaseError as exc:
        root = _archive_of(path)
        if root is None:
            raise FormatError(path, f"not a usable catalog index ({_one_line(exc)})",
                              "it is a cache of an archive's Items: 'archive catalog rebuild' recreates it") from None
        with closing(connect_readonly(ensure_index(root))) as con:  # the archive's own, damaged: healed first
            return [_row(r) for r in con.execute(sql, params)]


def collection_summary(path: str | os.PathLike) -> dict:
    """What the archive's STAC Collection says of its Items, asked of the index in SQL (no row object
    per Item: an ingest rewrites the Collection, and at 10,000 Items that was most of its cost):
    ``bbox`` (west, south, east, north degrees; None when empty), ``start_iso`` of the first Item and
    ``end_iso`` of the one ending last (ties as :func:`search` orders them), ``sensors`` (sorted),
    ``gsd`` (min, max m; None when none is known) and ``links``: (id, item_path) sorted by start time,
    then id."""
    with closing(connect_readonly(path)) as con:
        w, s, e, n, g0, g1 = con.execute("SELECT MIN(west), MIN(south), MAX(east), MAX(north), MIN(gsd), MAX(gsd) "
                                         "FROM items").fetchone()
        first = con.execute("SELECT start_iso FROM items ORDER BY start_time, id LIMIT 1").fetchone()
        last = con.execute("SELECT end_iso FROM items ORDER BY end_time DESC, start_time, id LIMIT 1").fetchone()
        sensors = [r[0] for r in con.execute("SELECT DISTINCT sensor FROM items WHERE sensor IS NOT NULL AND "
                                             "sensor != '' ORDER BY sensor")]
        links = con.execute("SELECT id, item_path FROM items ORDER BY start_time, id").fetchall()
    return {"bbox": None if first is None else (w, s, e, n), "start_iso": first and first[0],
            "end_iso": last and last[0], "sensors": sensors, "gsd": None if g0 is None else (float(g0), float(g1)),
            "links": links}


def _archive_of(index: str | os.PathLike) -> ArchiveRoot | None:
    """The archive whose own index ``index`` is (``<ARCHIVE>/catalog/index.sqlite``), else None."""
    path = Path(index)
    root = path.parent.parent
    if path.name == "index.sqlite" and path.parent.name == "catalog" and (root / "archive.json").is_file():
        return ArchiveRoot(root)
    return None


def time_clause(source, start: float | None, end: float | None, alias: str = "i") -> tuple[str, list]:
    """SQL (and parameters) true for the rows whose [start_time, end_time] meets [start, end]
    (epoch s, None = open); source: the index (path or open connection)."""
    where, params = [], []
    if start is not None:
        # end_time >= start, and start_time >= start - longest duration: lets SQLite range-scan the
        # start_time index from both sides instead of reading every later flight.
        where += [f"{alias}.end_time >= ?", f"{alias}.start_time >= ?"]
        params += [float(start), float(start) - _longest(source) - 1.0]
    if end is not None:
        where.append(f"{alias}.start_time <= ?")
        params.append(float(end))
    return "(" + (" AND ".join(where) or "1") + ")", params


def _longest(source) -> float:
    """Longest flight duration in the index (a path or an open connection), s (recorded by
    add_rows; computed if absent)."""
    if not isinstance(source, sqlite3.Connection):
        with closing(connect_readonly(source)) as con:
            return _longest(con)
    found = source.execute("SELECT value FROM meta WHERE key = 'max_duration'").fetchone()
    if found is None:
        found = source.execute("SELECT max(end_time - start_time) FROM items").fetchone()
    return float(found[0]) if found and found[0] is not None else 0.0
