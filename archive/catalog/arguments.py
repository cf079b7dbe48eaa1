"""The catalog's query arguments as users type them: a bbox in degrees and a datetime range
(``--query-bbox``/``--bbox``, ``--query-datetime``/``--datetime``, the STAC API's ``datetime``),
parsed into numbers or refused in one line naming the option."""

from __future__ import annotations

import numpy as np

from archive.errors import InputError

__all__ = ["parse_bbox", "parse_datetime_range"]


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
