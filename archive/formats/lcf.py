"""Resonon ``.lcf`` navigation files and GPS time conversion.

Columns (whitespace separated, usually tabs, >= 10 of them; extra columns ignored):
1 time (s, GPS time scale), 2 roll (rad, positive = right wing up), 3 pitch (rad, positive = nose
up), 4 yaw (rad from true North, clockwise), 5 longitude (deg), 6 latitude (deg), 7 altitude (m
above the WGS-84 ellipsoid), 8-9 unused, 10 use flag, 11+ vendor columns.

Column 10 is Resonon's "message to GeoReg" (lcf_spec.txt): 5 = use this row for
georectification, 0 = do not use (every real file here has 5). Rows flagged 0 are kept in
:class:`LcfData` (the first row's time still anchors the line times) but marked in ``use``;
navigation leaves them out and interpolates over them, and their positions are not range-checked.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from pathlib import Path

import numpy as np

from archive.errors import FormatError, InputError, MissingInputError
from archive.files import write_atomic

__all__ = ["GPS_EPOCH", "LcfData", "fix_gps_week", "gps_seconds_to_datetime", "read_lcf",
           "write_lcf"]

GPS_EPOCH = datetime(1980, 1, 6, tzinfo=UTC)
WEEK_S = 604800.0
ROLLOVER_S = 1024 * WEEK_S  #: one GPS week-number rollover, s

# (first UTC instant of the offset, GPS - UTC in s), newest first.
_LEAP_SECONDS: tuple[tuple[datetime, int], ...] = tuple(
    (datetime(y, m, 1, tzinfo=UTC), n) for y, m, n in (
        (2017, 1, 18), (2015, 7, 17), (2012, 7, 16), (2009, 1, 15), (2006, 1, 14), (1999, 1, 13),
        (1997, 7, 12), (1996, 1, 11), (1994, 7, 10), (1993, 7, 9), (1992, 7, 8), (1991, 1, 7),
        (1990, 1, 6), (1988, 1, 5), (1985, 7, 4), (1983, 7, 3), (1982, 7, 2), (1981, 7, 1)))

_NAMES = ("time", "roll", "pitch", "yaw", "lon", "lat", "alt")


@dataclass(frozen=True, eq=False)
class LcfData:
    """Navigation samples of one ``.lcf`` file; every array has shape ``(n,)``.

    ``time`` s on the file's GPS time scale (no week fix); ``roll`` rad, positive = right wing up
    (Resonon sign, opposite of aerospace); ``pitch`` rad, positive = nose up; ``yaw`` rad from
    TRUE north, clockwise (pi/2 = East); ``lon``/``lat`` degrees; ``alt`` m above the WGS-84
    ellipsoid.
    """

    path: Path | None
    time: np.ndarray
    roll: np.ndarray
    pitch: np.ndarray
    yaw: np.ndarray
    lon: np.ndarray
    lat: np.ndarray
    alt: np.ndarray
    use: np.ndarray | None = None  #: (n,) bool, False for rows flagged 'do not use'; None: all used

    def __len__(self) -> int:
        return len(self.time)


def read_lcf(path: str | os.PathLike) -> LcfData:
    """Read an ``.lcf`` file. Blank lines and lines starting with ``#`` are skipped.

    Raises :class:`FormatError` naming the file and line for a row with fewer than 10 columns,
    a non-numeric field among the first 10, a NaN/inf value, a time that does not increase, or a
    file without rows.
    """
    path = Path(path)
    if not path.is_file():
        raise MissingInputError(path, "navigation file (.lcf)")
    text = path.read_bytes().decode("utf-8-sig", errors="replace")
    rows: list[list[float]] = []
    numbers: list[int] = []  # file line number of each row
    previous = -math.inf
    for number, line in enumerate(text.splitlines(), start=1):
        fields = line.split()
        if not fields or fields[0].startswith("#"):
            continue
        if len(fields) < 10:
            raise FormatError(path, f"line {number}: {len(fields)} columns, expected at least 10",
                              "time roll pitch yaw lon lat alt 0 0 use-flag")
        values: list[float] = []
        for column, field in enumerate(fields[:10], start=1):
            try:
                value = float(field)
            except ValueError:
                raise FormatError(path, f"line {number}, column {column}: {field!r} is not a "
                                  "number") from None
            if not math.isfinite(value):
                raise FormatError(path, f"line {number}, column {column}: value {field!r} is not "
                                  "finite")
            values.append(value)
        if values[0] <= previous:
            raise FormatError(path, f"line {number}: time {fields[0]} does not increase (previous "
                              f"{previous!r})", "lcf rows must be in time order without repeats")
        previous = values[0]
        rows.append(values[:7] + [0.0 if values[9] == 0.0 else 1.0])  # column 10: 0 = do not use
        numbers.append(number)
    if not rows:
        raise FormatError(path, "no navigation rows (empty file)")
    table = np.array(rows, dtype=np.float64)
    use = table[:, 7] != 0.0
    if not use.any():
        raise FormatError(path, f"every one of the {len(use)} navigation rows is flagged 'do not use' (column 10 = 0)")
    for column, name, limit in ((5, "longitude", 180.0), (6, "latitude", 90.0)):
        bad = np.flatnonzero(use & (np.abs(table[:, column - 1]) > limit))
        if bad.size:
            row = int(bad[0])
            raise FormatError(path, f"line {numbers[row]}, column {column} ({name}): {table[row, column - 1]:g} "
                              f"is outside [-{limit:g}, {limit:g}] degrees ({bad.size} such rows)",
                              "columns are: time roll pitch yaw longitude latitude altitude, angles of "
                              "position in degrees")
    return LcfData(path, *(np.ascontiguousarray(table[:, k]) for k in range(7)), use=None if use.all() else use)


def write_lcf(path: str | os.PathLike, data: LcfData) -> None:
    """Write ``data`` as an 11-column tab-separated ``.lcf`` (columns 8, 9 = 0, 10 = 5, 11 = 4),
    floats with ``repr`` (full precision). Written to a temporary name, then renamed."""
    path = Path(path)
    columns = [np.asarray(getattr(data, name), dtype=np.float64) for name in _NAMES]
    n = len(columns[0])
    for name, column in zip(_NAMES, columns, strict=True):
        if column.shape != (n,):
            raise InputError(path, f"lcf column '{name}' has shape {column.shape}, expected ({n},)")
    if n == 0:
        raise InputError(path, "no navigation rows to write")
    lines = ["\t".join([*(repr(float(c[i])) for c in columns), "0", "0", "5", "4"])
             for i in range(n)]
    write_atomic(path, ("\n".join(lines) + "\n").encode("ascii"))


def fix_gps_week(t: float, near: datetime | None = None) -> float:
    """GPS seconds since 1980-01-06 with a truncated week number repaired.

    Old Resonon software wrote the GPS week modulo 1024, so its times are below 1024 weeks. Without
    ``near`` one rollover (1024 weeks) is added to such times (right for 1999-08..2019-04 data).
    With ``near`` (e.g. the header timestamp) the number of rollovers that brings the time closest
    to ``near`` is chosen. Times of 1024 weeks or more are returned unchanged.
    """
    t = float(t)
    if t >= ROLLOVER_S or t < 0:
        return t
    if near is None:
        return t + ROLLOVER_S
    if near.tzinfo is None:
        near = near.replace(tzinfo=UTC)
    target = (near - GPS_EPOCH).total_seconds()
    k = max(0, round((target - t) / ROLLOVER_S))
    return t + k * ROLLOVER_S


def gps_seconds_to_datetime(t: float, near: datetime | None = None) -> datetime:
    """UTC-aware datetime of GPS time ``t`` (s since 1980-01-06), leap seconds removed and a
    week-mod-1024 time repaired (see :func:`fix_gps_week`)."""
    gps = GPS_EPOCH + timedelta(seconds=fix_gps_week(t, near))
    for start, offset in _LEAP_SECONDS:
        utc = gps - timedelta(seconds=offset)
        if utc >= start:
            return utc
    return gps
