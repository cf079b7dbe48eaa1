"""The viewer's query parameters, checked and normalised once (a hashable value: the tile cache key).

Every problem is an :class:`~archive.errors.InputError` naming the parameter, which the server
turns into a 400 answer with that message. Values are bounded before they are parsed (a 10,000-entry
list is refused by its length, not read).
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from dataclasses import dataclass

from archive.errors import InputError
from archive.overlap import RULES
from archive.sources.base import MODES

__all__ = ["MAX_TEXT", "OVERLAPS", "OverlapChoice", "Stretch", "ViewQuery", "overlap_choice", "parse_bbox",
           "parse_number", "parse_query"]

#: Longest accepted parameter value, characters.
MAX_TEXT = 200
#: Wavelengths a tile or stats request may name (RGB).
MAX_CHANNELS = 3
#: Band indices one band-value tile or stats request may name.
MAX_BANDS = 16
#: Ground heights (m, ellipsoid) and sync offsets (s) outside these are refused outright.
MAX_HEIGHT = 10_000.0
MAX_SYNC_OFFSET = 10.0
#: Boresight angles (deg, roll, pitch, yaw) outside +-this are refused outright.
MAX_BORESIGHT = 45.0
#: A navigation source's name: 'lcf' or a stored track's (letters, digits, '.', '_', '-').
NAVIGATION_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}")


@dataclass(frozen=True)
class OverlapChoice:
    """An overlap rule the viewer offers, as the page needs it to compose flights (``/api/collections``
    serves the list; the page branches on ``key`` and ``wins``, never on the name).

    name: the rule's name (``overlap=`` of the API, ``archive render --overlap``); label: words for the
    page's list; key: the per-pixel plane the values come with and the rule compares (None: none);
    wins: which capture a pixel shows, 'last' (the latest drawn) or 'lowest' (the lowest ``key``).
    """

    name: str
    label: str
    key: str | None
    wins: str

    def as_dict(self) -> dict:
        return {"name": self.name, "label": self.label, "key": self.key, "wins": self.wins}


#: Overlap rules between captures (cubes, flights), the first the default: the rules of ``archive render
#: --overlap`` (:data:`archive.overlap.RULES`) that pick one capture per pixel ('mean' is not offered: it
#: mixes pixels, and the browser composes flights by picking one). The one list the server and the page read.
OVERLAPS = tuple(OverlapChoice(rule.name, rule.label, rule.key, rule.wins) for rule in RULES.values() if rule.single_source)


def overlap_choice(name: str) -> OverlapChoice:
    """The :data:`OVERLAPS` entry named ``name``; InputError naming ``overlap`` if there is none."""
    for choice in OVERLAPS:
        if choice.name == name:
            return choice
    raise InputError("overlap", f"unknown overlap rule {name!r}",
                     f"use one of {', '.join(c.name for c in OVERLAPS)}")


def _text(params: Mapping[str, str], name: str) -> str | None:
    value = params.get(name)
    if value is None or value.strip() == "":
        return None
    if len(value) > MAX_TEXT:
        count = value.count(",") + 1
        raise InputError(name, f"value of {len(value)} characters ({count} comma-separated values) is too long",
                         f"give at most {MAX_TEXT} characters")
    return value.strip()


def parse_number(params: Mapping[str, str], name: str, low: float | None = None, high: float | None = None,
                 default: float | None = None) -> float | None:
    """A finite float parameter within [low, high], ``default`` when absent."""
    text = _text(params, name)
    if text is None:
        return default
    try:
        value = float(text)
    except ValueError:
        raise InputError(name, f"expected a number, got {text!r}") from None
    if not math.isfinite(value):
        raise InputError(name, f"expected a finite number, got {text!r}")
    if (low is not None and value < low) or (high is not None and value > high):
        raise InputError(name, f"{value:g} is out of range {low:g}..{high:g}")
    return value


def _numbers(params: Mapping[str, str], name: str, limit: int) -> tuple[float, ...] | None:
    text = _text(params, name)
    if text is None:
        return None
    parts = [p.strip() for p in text.split(",")]
    if len(parts) > limit:
        raise InputError(name, f"{len(parts)} values given, at most {limit} accepted")
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        raise InputError(name, f"expected comma-separated numbers, got {text!r}") from None
    if not all(math.isfinite(v) for v in values):
        raise InputError(name, f"expected finite numbers, got {text!r}")
    return values


def parse_bbox(params: Mapping[str, str], name: str = "bbox") -> tuple[float, float, float, float] | None:
    """'W,S,E,N' degrees (longitudes -180..180, latitudes -90..90, west <= east, south <= north)."""
    values = _numbers(params, name, 4)
    if values is None:
        return None
    if len(values) != 4:
        raise InputError(name, f"expected 4 numbers W,S,E,N in degrees, got {len(values)}")
    w, s, e, n = values
    if not (-180 <= w <= e <= 180 and -90 <= s <= n <= 90):
        raise InputError(name, f"{w:g},{s:g},{e:g},{n:g} is not a box W,S,E,N of longitudes -180..180 and "
                         "latitudes -90..90 with W <= E and S <= N")
    return values


@dataclass(frozen=True)
class Stretch:
    """How values map to 0..255: ``percentiles`` (low, high) of the whole flight, or fixed
    ``ranges``: one (low, high) shared by every channel, or one per channel."""

    percentiles: tuple[float, float] | None = (2.0, 98.0)
    ranges: tuple[tuple[float, float], ...] | None = None

    @classmethod
    def parse(cls, text: str | None, channels: int) -> Stretch:
        if text is None:
            return cls()
        parts = [p.strip() for p in text.split(",")]
        if len(parts) == 2 and all(p[:1] in ("p", "P") for p in parts):
            try:
                lo, hi = (float(p[1:]) for p in parts)
            except ValueError:
                raise InputError("stretch", f"expected pLOW,pHIGH percentiles, got {text!r}") from None
            if not (0 <= lo < hi <= 100):
                raise InputError("stretch", f"percentiles {lo:g}, {hi:g} must satisfy 0 <= low < high <= 100")
            return cls((lo, hi), None)
        try:
            values = [float(p) for p in parts]
        except ValueError:
            raise InputError("stretch", f"expected pLOW,pHIGH or LOW,HIGH numbers (one pair, or one per "
                             f"channel), got {text!r}") from None
        if len(values) not in (2, 2 * channels) or not all(math.isfinite(v) for v in values):
            raise InputError("stretch", f"expected 2 or {2 * channels} finite numbers for {channels} "
                             f"channel(s), got {len(values)}")
        pairs = tuple((values[i], values[i + 1]) for i in range(0, len(values), 2))
        if any(hi <= lo for lo, hi in pairs):
            raise InputError("stretch", f"each range needs low < high, got {text!r}")
        return cls(None, pairs * channels if len(pairs) == 1 else pairs)


@dataclass(frozen=True)
class ViewQuery:
    """What to render, as requested (band choices are resolved against the flight later).

    wavelengths: nm of the channels (1 = grey, 3 = RGB), or band: one 0-based band index (grey),
    or bands: 0-based band indices (band-value tiles and stats); none: the flight's default. mode: radiometric mode (None: radiance, raw DN without a
    calibration). stretch: :class:`Stretch`. cubes: (first, last) 0-based inclusive, None = all.
    ground_height: m above the ellipsoid (None: as ingested / the headers'). sync_offset: s (None:
    as ingested, else 0). overlap: how cubes that cover the same pixel combine (a name of :data:`OVERLAPS`).
    navigation: the navigation source ('lcf' or a stored track's name; None: the viewer's default for
    the flight). boresight: (roll, pitch, yaw) degrees, aerospace signs (None: as ingested).
    """

    wavelengths: tuple[float, ...] | None = None
    band: int | None = None
    bands: tuple[int, ...] | None = None
    mode: str | None = None
    stretch: Stretch = Stretch()
    cubes: tuple[int, int] | None = None
    ground_height: float | None = None
    sync_offset: float | None = None
    overlap: str = "last"
    navigation: str | None = None
    boresight: tuple[float, float, float] | None = None

    @property
    def channels(self) -> int:
        if self.band is not None:
            return 1
        if self.bands is not None:
            return len(self.bands)
        return 3 if self.wavelengths is None else len(self.wavelengths)


def _cubes(params: Mapping[str, str]) -> tuple[int, int] | None:
    text = _text(params, "cubes")
    if text is None:
        return None
    first, sep, last = text.partition("-")
    try:
        a = int(first)
        b = int(last) if sep else a
    except ValueError:
        raise InputError("cubes", f"expected FIRST-LAST (0-based cube indices), got {text!r}") from None
    if a < 0:
        raise InputError("cubes", f"expected 0-based cube indices (cube 1, as the files are numbered, is 0), "
                         f"got {text!r}")
    if b < a:
        raise InputError("cubes", f"first cube {a + 1} comes after last cube {b + 1} (numbered from 1, as the cube "
                         "files are)", "give a first cube at or before the last")
    return (a, b)


def _band_indices(params: Mapping[str, str]) -> tuple[int, ...] | None:
    values = _numbers(params, "bands", MAX_BANDS)
    if values is None:
        return None
    if not all(v == int(v) and 0 <= v < 1e6 for v in values):
        raise InputError("bands", f"expected 0-based band indices, got {params.get('bands')!r}")
    return tuple(int(v) for v in values)


def parse_query(params: Mapping[str, str], channels: bool = True) -> ViewQuery:
    """The :class:`ViewQuery` of request parameters (``wavelengths``, ``band``, ``bands``, ``mode``,
    ``stretch``, ``cubes``, ``ground_height``, ``sync_offset``, ``overlap``, ``navigation``, ``boresight``
    (roll,pitch,yaw degrees)). channels: whether wavelengths /
    band / stretch are read (tiles and stats) or left out (point: every band)."""
    wavelengths = band = indices = None
    stretch = Stretch()
    if channels:
        wavelengths = _numbers(params, "wavelengths", MAX_CHANNELS)
        if wavelengths is not None and len(wavelengths) not in (1, 3):
            raise InputError("wavelengths",
                             f"give 1 (grey) or 3 (red, green, blue) wavelengths, got {len(wavelengths)}")
        if wavelengths is not None and not all(0 < w < 1e5 for w in wavelengths):
            raise InputError("wavelengths", "wavelengths are nm, between 0 and 100000")
        b = parse_number(params, "band", 0, 1e6)
        if b is not None:
            if wavelengths is not None:
                raise InputError("band", "give either band (one grey band) or wavelengths, not both")
            if b != int(b):
                raise InputError("band", f"expected a 0-based band index, got {b:g}")
            band = int(b)
        indices = _band_indices(params)
        if indices is not None and (band is not None or wavelengths is not None):
            raise InputError("bands", "give one of bands, band or wavelengths")
        count = 1 if band is not None else (len(indices) if indices is not None else
                                            3 if wavelengths is None else len(wavelengths))
        stretch = Stretch.parse(_text(params, "stretch"), count)
    mode = _text(params, "mode")
    if mode is not None and mode not in MODES:
        raise InputError("mode", f"unknown radiometric mode {mode!r}", f"use one of {', '.join(MODES)}")
    overlap = overlap_choice(_text(params, "overlap") or OVERLAPS[0].name).name
    return ViewQuery(
        wavelengths=wavelengths, band=band, bands=indices if channels else None, mode=mode, stretch=stretch,
        cubes=_cubes(params), overlap=overlap,
        ground_height=parse_number(params, "ground_height", -MAX_HEIGHT, MAX_HEIGHT),
        sync_offset=parse_number(params, "sync_offset", -MAX_SYNC_OFFSET, MAX_SYNC_OFFSET),
        navigation=_navigation(params), boresight=_boresight(params))


def _navigation(params: Mapping[str, str]) -> str | None:
    text = _text(params, "navigation")
    if text is not None and not NAVIGATION_NAME.fullmatch(text):
        raise InputError("navigation", f"{text!r} is not a navigation source's name",
                         "give lcf or the name of one of the flight's stored trajectories")
    return text


def _boresight(params: Mapping[str, str]) -> tuple[float, float, float] | None:
    values = _numbers(params, "boresight", 3)
    if values is None:
        return None
    if len(values) != 3:
        raise InputError("boresight", f"expected 3 numbers ROLL,PITCH,YAW in degrees, got {len(values)}")
    if not all(abs(v) <= MAX_BORESIGHT for v in values):
        raise InputError("boresight", f"{','.join(f'{v:g}' for v in values)} is out of range: each angle within "
                         f"+-{MAX_BORESIGHT:g} degrees")
    return (float(values[0]), float(values[1]), float(values[2]))
