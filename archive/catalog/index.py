"""SQLite index of an archive's STAC Items: bbox (R*Tree), time range and wavelength range.

The index is a cache of ``<ARCHIVE>/catalog/items/*.json``: :func:`rebuild_index` recreates it from
those files. Every statement is parameterised. The schema is :data:`SCHEMA`, read from
``catalogs/schema.sql`` (shipped as the package ``archive.catalogs``).
"""

from __future__ import annotations

import importlib.resources

import json
import os
import sqlite3
from collections.abc import Iterable, Sequence
from contextlib import closing
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from archive.catalog.root import ArchiveRoot
from archive.errors import FormatError, InputError

SCHEMA_VERSION = "1"

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


def connect(path: str | os.PathLike) -> sqlite3.Connection:
    """Open (creating if needed) an index database and make sure its schema exists."""
    con = sqlite3.connect(str(path), timeout=30.0)
    try:
        con.executescript(SCHEMA)
        with con:
            con.execute("INSERT OR IGNORE INTO meta (key, value) VALUES (?, ?)", ("schema_version", SCHEMA_VERSION))
        found = con.execute("SELECT value FROM meta WHERE key = ?", ("schema_version",)).fetchone()[0]
    except sqlite3.DatabaseError as exc:
        con.close()
        raise FormatError(path, f"not a catalog index: {exc}", "run 'archive catalog rebuild'") from exc
    if found != SCHEMA_VERSION:
        con.close()
        raise FormatError(path, f"index schema version {found}, expected {SCHEMA_VERSION}",
                          "run 'archive catalog rebuild'")
    return con


def row_from_item(item: dict, item_path: str) -> IndexRow:
    """The index row of a STAC Item dict (as written by archive.catalog.stac.make_item)."""
    from archive.catalog.stac import item_summary

    s = item_summary(item, where=item_path)
    return IndexRow(s["id"], s["start_time"], s["end_time"], s["start_iso"], s["end_iso"], s["bands"],
                    s["min_wavelength"], s["max_wavelength"], tuple(s["bbox"]), s["sensor"], s["gsd"],
                    item_path)


def _insert(con: sqlite3.Connection, row: IndexRow) -> None:
    old = con.execute("SELECT rowid FROM items WHERE id = ?", (row.id,)).fetchone()
    if old is not None:
        con.execute("DELETE FROM items_bbox WHERE id = ?", (old[0],))
        con.execute("DELETE FROM items WHERE rowid = ?", (old[0],))
    w, s, e, n = row.bbox
    cur = con.execute(
        f"INSERT INTO items ({_COLUMNS}) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
        (row.id, row.start_time, row.end_time, row.start_iso, row.end_iso, row.bands, row.min_wavelength,
         row.max_wavelength, w, s, e, n, row.sensor, row.gsd, row.item_path))
    con.execute("INSERT INTO items_bbox (id, west, east, south, north) VALUES (?, ?, ?, ?, ?)",
                (cur.lastrowid, _f32_down(w), _f32_up(e), _f32_down(s), _f32_up(n)))


def add_rows(path: str | os.PathLike, rows: Iterable[IndexRow]) -> int:
    """Insert or replace rows (by id) in one transaction; returns how many."""
    count = 0
    longest = 0.0
    with closing(connect(path)) as con, con:
        for row in rows:
            _insert(con, row)
            longest = max(longest, row.end_time - row.start_time)
            count += 1
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


def rebuild_index(root: ArchiveRoot) -> int:
    """Recreate ``catalog/index.sqlite`` from the Item files (written to a temporary file, then
    renamed over the old index). Returns the number of Items indexed."""
    root.index_path.parent.mkdir(parents=True, exist_ok=True)
    tmp = root.index_path.with_name(root.index_path.name + ".tmp")
    tmp.unlink(missing_ok=True)
    rows = []
    if root.items.is_dir():
        for path in sorted(root.items.glob("*.json")):
            rel = path.relative_to(root.path).as_posix()
            rows.append(row_from_item(read_item_file(path), rel))
    add_rows(tmp, rows)
    os.replace(tmp, root.index_path)
    return len(rows)


def ensure_index(root: ArchiveRoot) -> Path:
    """The index path, rebuilt from the Items first when it does not exist."""
    if not root.index_path.exists():
        rebuild_index(root)
    return root.index_path


def search(path: str | os.PathLike, bbox: tuple[float, float, float, float] | None = None,
           start: float | None = None, end: float | None = None, wavelength: float | None = None,
           ids: Sequence[str] | None = None) -> list[IndexRow]:
    """Items whose bbox intersects ``bbox`` (west, south, east, north degrees), whose time range
    [start_time, end_time] intersects [start, end] (epoch s; None = open), and whose wavelength range
    contains ``wavelength`` (nm). Sorted by start time, then id."""
    longest = _longest(path) if start is not None else 0.0
    sql = f"SELECT {', '.join('i.' + c.strip() for c in _COLUMNS.split(','))} FROM items AS i"
    where: list[str] = []
    params: list[object] = []
    if bbox is not None:
        w, s, e, n = (float(v) for v in bbox)
        sql += " JOIN items_bbox AS r ON r.id = i.rowid"
        where += ["r.west <= ?", "r.east >= ?", "r.south <= ?", "r.north >= ?",
                  "i.west <= ?", "i.east >= ?", "i.south <= ?", "i.north >= ?"]
        params += [_f32_up(e), _f32_down(w), _f32_up(n), _f32_down(s), e, w, n, s]
    if start is not None:
        # end_time >= start, and start_time >= start - longest duration: lets SQLite range-scan the
        # start_time index from both sides instead of reading every later flight.
        where += ["i.end_time >= ?", "i.start_time >= ?"]
        params += [float(start), float(start) - longest - 1.0]
    if end is not None:
        where.append("i.start_time <= ?")
        params.append(float(end))
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
    with closing(connect(path)) as con:
        return [_row(r) for r in con.execute(sql, params)]


def _longest(path) -> float:
    """Longest flight duration in the index, s (recorded by add_rows; computed if absent)."""
    with closing(connect(path)) as con:
        found = con.execute("SELECT value FROM meta WHERE key = 'max_duration'").fetchone()
        if found is None:
            found = con.execute("SELECT max(end_time - start_time) FROM items").fetchone()
    return float(found[0]) if found and found[0] is not None else 0.0


def parse_bbox(text: str) -> tuple[float, float, float, float]:
    """``'W,S,E,N'`` degrees -> (west, south, east, north); InputError when malformed."""
    parts = [p.strip() for p in str(text).split(",")]
    fix = "give --bbox W,S,E,N in degrees, e.g. --bbox -90.1,35.0,-89.8,35.3"
    if len(parts) != 4:
        raise InputError("--bbox", f"expected 4 comma-separated numbers, got {text!r}", fix)
    try:
        w, s, e, n = (float(p) for p in parts)
    except ValueError:
        raise InputError("--bbox", f"expected numbers, got {text!r}", fix) from None
    if not all(np.isfinite(v) for v in (w, s, e, n)):
        raise InputError("--bbox", f"values must be finite, got {text!r}", fix)
    if not (-180.0 <= w <= 180.0 and -180.0 <= e <= 180.0 and -90.0 <= s <= 90.0 and -90.0 <= n <= 90.0):
        raise InputError("--bbox", f"out of range in {text!r} (longitude -180..180, latitude -90..90)", fix)
    if w > e:
        raise InputError("--bbox", f"west {w} is east of east {e} (boxes across the antimeridian are not supported)",
                         "split the query in two")
    if s > n:
        raise InputError("--bbox", f"south {s} is north of north {n}", fix)
    return (w, s, e, n)


def _parse_instant(text: str, end: bool) -> float:
    from datetime import UTC, date, datetime, time, timedelta

    fix = "use ISO 8601, e.g. 2023-06-26T09:00:00Z, 2023-06-26 or 2023-06, and '..' for an open end"
    text = text.strip()
    try:
        if len(text) in (4, 7) and text[:4].isdigit():  # a year or a month alone: the whole of it
            year, month = int(text[:4]), int(text[5:7]) if len(text) == 7 else None
            if len(text) == 7 and text[4] != "-":
                raise ValueError(text)
            first = datetime(year, month or 1, 1, tzinfo=UTC)
            if not end:
                return first.timestamp()
            nxt = (datetime(year + 1, 1, 1, tzinfo=UTC) if month in (None, 12)
                   else datetime(year, month + 1, 1, tzinfo=UTC))
            return (nxt - timedelta(microseconds=1)).timestamp()
        if len(text) == 10:  # a date alone: the whole day
            day = date.fromisoformat(text)
            moment = datetime.combine(day, time(0), tzinfo=UTC)
            if end:
                moment += timedelta(days=1) - timedelta(microseconds=1)
        else:
            moment = datetime.fromisoformat(text)
            if moment.tzinfo is None:
                moment = moment.replace(tzinfo=UTC)
    except ValueError:
        raise InputError("--datetime", f"{text!r} is not a date or date-time", fix) from None
    return moment.timestamp()


def parse_datetime_range(text: str) -> tuple[float | None, float | None]:
    """``'A/B'``, ``'../B'``, ``'A/..'`` or a single instant ``'A'`` (ISO 8601; naive times are UTC;
    a date alone means the whole day, a month 'YYYY-MM' or a year 'YYYY' the whole of it) ->
    (start, end) epoch seconds, None for an open end."""
    text = str(text).strip()
    fix = "give --datetime START/END in ISO 8601 with '..' for an open end, e.g. 2023-06-01/.."
    parts = text.split("/")
    if len(parts) == 1:
        if not text or text == "..":
            raise InputError("--datetime", f"expected a date-time or a range, got {text!r}", fix)
        return _parse_instant(text, end=False), _parse_instant(text, end=True)
    if len(parts) != 2:
        raise InputError("--datetime", f"expected START/END, got {text!r}", fix)
    a, b = (p.strip() for p in parts)
    if a in ("", "..") and b in ("", ".."):
        raise InputError("--datetime", f"both ends of {text!r} are open", fix)
    start = None if a in ("", "..") else _parse_instant(a, end=False)
    stop = None if b in ("", "..") else _parse_instant(b, end=True)
    if start is not None and stop is not None and start > stop:
        raise InputError("--datetime", f"start {a} is after end {b}", fix)
    return start, stop
