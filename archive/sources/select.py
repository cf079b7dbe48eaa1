"""What to take from opened sources: bands, ground height, white reference.

Shared by the render pipeline (:mod:`archive.run.pipeline`), the lazy mosaics and the viewer
(:mod:`archive.drawing.flight`): the same wavelength picks the same band, ``auto`` the same ground
height, wherever a flight is drawn.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from archive.errors import InputError, MissingInputError

__all__ = ["WAVELENGTH_TOLERANCE", "check_same_bands", "parse_bands", "read_white_reference",
           "resolve_ground_height", "select_bands"]


#: A requested wavelength must lie within this many band widths of a band.
WAVELENGTH_TOLERANCE = 1.5


def parse_bands(value) -> str | tuple[int, ...]:
    """'all' (or None), '2,4' (the CLI's text), one index or a sequence of 0-based indices."""
    if value is None or (isinstance(value, str) and value.strip().lower() == "all"):
        return "all"
    if isinstance(value, str):
        try:
            out = tuple(int(b) for b in value.split(",") if b.strip())
        except ValueError:
            raise InputError("--bands", f"expected 'all' or 0-based band indices, got {value!r}") from None
        if not out:
            raise InputError("--bands", f"expected 'all' or 0-based band indices, got {value!r}")
        return out
    items = [value] if isinstance(value, (int, np.integer)) else list(value)
    if not items or not all(isinstance(b, (int, np.integer)) and not isinstance(b, bool) for b in items):
        raise InputError("--bands", f"expected 'all' or 0-based band indices, got {value!r}")
    return tuple(int(b) for b in items)


def select_bands(source, wavelengths: Sequence[float] | None = None,
                 bands: str | Sequence[int] | None = "all") -> list[int]:
    """Source band indices to render: nearest bands to ``wavelengths`` (nm), else ``bands``.

    bands: 'all', comma-separated 0-based indices, or a sequence of them. A wavelength farther than
    1.5 band widths from every band is an InputError naming the source's range.
    """
    nbands = source.cubes[0].bands
    where = source.label
    if wavelengths is not None:
        wl = None if source.wavelengths is None else np.asarray(source.wavelengths, float)
        if wl is None or len(wl) == 0:
            raise InputError(where, "the cubes have no 'wavelength' list", "use --bands all")
        spacing = np.abs(np.gradient(wl)) if len(wl) > 1 else np.array([10.0])
        out: list[int] = []
        for w in wavelengths:
            i = int(np.argmin(np.abs(wl - w)))
            if abs(wl[i] - w) > WAVELENGTH_TOLERANCE * spacing[i]:
                raise InputError(
                    "--wavelengths", f"no band near {w:g} nm in {where} (bands span "
                    f"{wl.min():.1f}-{wl.max():.1f} nm, nearest {wl[i]:.1f} nm)",
                    "choose wavelengths inside the cubes' range",
                )
            if i not in out:
                out.append(i)
        return out
    chosen = parse_bands(bands)
    if chosen == "all":
        return list(range(nbands))
    bad = [b for b in chosen if not 0 <= b < nbands]
    if bad:
        raise InputError("--bands", f"band {bad[0]} out of range 0..{nbands - 1}")
    return list(dict.fromkeys(chosen))


def check_same_bands(sources: Sequence, bands: Sequence[Sequence[int]]) -> None:
    """InputError unless every source renders as many bands, at the same wavelengths (to 1/2 band)."""
    first = sources[0]
    for s, b in zip(sources[1:], bands[1:]):
        if len(b) != len(bands[0]):
            raise InputError(s.label, f"{len(b)} bands selected, but {len(bands[0])} in the first source",
                             "render sources with the same bands together, or pick --wavelengths")
        if first.wavelengths is None or s.wavelengths is None:
            continue
        w0 = np.asarray(first.wavelengths, float)
        tol = 0.5 * float(np.min(np.abs(np.diff(w0)))) if len(w0) > 1 else 1.0
        wa = w0[list(bands[0])]
        wb = np.asarray(s.wavelengths, float)[list(b)]
        worst = int(np.argmax(np.abs(wa - wb)))
        if abs(wa[worst] - wb[worst]) > tol:
            raise InputError(s.label, f"band at {wb[worst]:.1f} nm does not match {wa[worst]:.1f} nm of the "
                             "first source", "render sensors with different bands separately")


def resolve_ground_height(value: str | float | None, sources: Sequence) -> float:
    """A number (metres above the ellipsoid), or 'auto' (:func:`archive.sources.ground.auto_ground_height`:
    a collection's ingest record, else the headers' 'ground elevation'); refused when the camera is
    not plausibly above it."""
    from archive.sources.ground import auto_ground_height, camera_altitudes, check_ground_height

    if value is not None and str(value).strip().lower() != "auto":
        try:
            h = float(value)
        except ValueError:
            raise InputError("--ground-height", f"expected metres or 'auto', got {value!r}") from None
        if not math.isfinite(h):
            raise InputError("--ground-height", f"expected a finite height, got {value!r}")
        for source in sources:
            check_ground_height(h, camera_altitudes(source), source.label, "--ground-height")
        return h
    return auto_ground_height(sources)


def read_white_reference(path: str, wavelengths) -> np.ndarray:
    """(bands,) white radiance from a two-column text file (nm, radiance), interpolated to the bands."""
    p = Path(path)
    if not p.is_file():
        raise MissingInputError(p, "white reference spectrum", "check --white-reference")
    try:
        table = np.loadtxt(p, delimiter=None if "," not in p.read_text()[:200] else ",", ndmin=2)
    except ValueError as exc:
        raise InputError(p, f"cannot read a (wavelength nm, radiance) table: {exc}") from None
    if table.shape[1] < 2 or table.shape[0] < 2:
        raise InputError(p, "expected two columns (wavelength nm, radiance) and at least two rows")
    if wavelengths is None:
        raise InputError(p, "the cubes have no wavelengths to interpolate the white reference to")
    order = np.argsort(table[:, 0])
    wl = np.asarray(wavelengths, float)
    step = float(np.min(np.abs(np.diff(wl)))) if len(wl) > 1 else 1.0
    lo, hi = float(table[order[0], 0]), float(table[order[-1], 0])
    if wl.min() < lo - step / 2 or wl.max() > hi + step / 2:  # np.interp would clamp silently
        raise InputError(p, f"the white reference spans {lo:g}-{hi:g} nm but the bands span "
                         f"{wl.min():g}-{wl.max():g} nm", "give a white reference covering every band")
    return np.interp(wl, table[order, 0], table[order, 1])
