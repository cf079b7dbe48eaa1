"""Mosaic rules: how the renders of several cubes combine on one output tile.

A rule is a small strategy object: ``feed`` it the cubes' renders in capture order (source order,
then cube order), then take ``result()``. Arrays are ``(band, y, x)`` float32 with NaN where a cube
does not cover a pixel; ``saturated`` is ``(y, x)`` bool (some band of the group was saturated there);
``key`` is ``(y, x)`` float32, the view zenith of the cube's line at each pixel (degrees, NaN where not
covered), fed only to rules that declare they need it.

Every rule declares what it needs besides the renders and what it gives: ``needs`` names the
provenance layer it compares (:mod:`archive.provenance`; the 'nadir' rule: ``view_zenith``, empty
for the others), ``single_source`` says whether each output pixel comes from one raw pixel (then
provenance layers can be written). Graph builders ask :func:`rule_key` instead of testing names.

Rules: 'last' (the later capture wins), 'nadir' (the capture seen closest to nadir wins, the later
one on a tie: NEON's mosaics), 'mean' (mean of the covering captures).

The 'last' rule is written once, as two functions the chunk writer also uses band by band:
:func:`last_values` and :func:`last_saturation`; :class:`LastRule` is their strategy object.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import ClassVar

import numpy as np

from archive.errors import InputError

__all__ = ["LastRule", "MeanRule", "NadirRule", "RULES", "WINNER_RULES", "last_saturation", "last_values",
           "make_rule", "nadir_values", "nadir_winners", "rule_key"]


def last_values(out: np.ndarray, parts: Sequence[tuple[np.ndarray, slice, slice]]) -> np.ndarray:
    """The 'last' rule's values, written into ``out`` (..., H, W) float32 and returned: per value, the
    latest finite value of the ``parts`` covering it, NaN where none is finite.

    parts: (values (..., h, w), rows, cols) in capture order, ``values`` landing at
    ``out[..., rows, cols]``. The first part is copied straight in (NaN only around it, non-finite
    values turned to NaN): one pass instead of a fill and a masked copy.
    """
    if not parts:
        out[...] = np.nan
        return out
    first, rows, cols = parts[0]
    out[..., :rows.start, :] = np.nan
    out[..., rows.stop:, :] = np.nan
    out[..., rows, :cols.start] = np.nan
    out[..., rows, cols.stop:] = np.nan
    target = out[..., rows, cols]
    np.copyto(target, first)
    infinite = np.isinf(target)
    if infinite.any():
        target[infinite] = np.nan
    for values, rows, cols in parts[1:]:
        np.copyto(out[..., rows, cols], values, where=np.isfinite(values))
    return out


def last_saturation(height: int, width: int,
                    parts: Sequence[tuple[np.ndarray, np.ndarray, slice, slice]]) -> np.ndarray:
    """The 'last' rule's saturation mask (height, width) bool: the flag of the last part covering
    the pixel (some band finite there), False where none does.

    parts: (values (band, h, w), saturated (h, w), rows, cols) in capture order. Evaluated only
    where some part is flagged (saturation is rare).
    """
    flagged = np.zeros((height, width), bool)
    for _, part_sat, rows, cols in parts:
        flagged[rows, cols] |= part_sat
    ys, xs = np.nonzero(flagged)
    saturated = np.zeros((height, width), bool)
    if not ys.size:
        return saturated
    result = np.zeros(ys.size, bool)
    for values, part_sat, rows, cols in parts:
        inside = np.flatnonzero((ys >= rows.start) & (ys < rows.stop) & (xs >= cols.start) & (xs < cols.stop))
        r, c = ys[inside] - rows.start, xs[inside] - cols.start
        covered = np.isfinite(values[:, r, c]).any(axis=0)
        result[inside[covered]] = part_sat[r[covered], c[covered]]
    saturated[ys, xs] = result
    return saturated


class LastRule:
    """The later capture wins wherever it covers the pixel (per band: the later finite value wins).

    Renders are only collected by ``feed``; ``result`` combines them with :func:`last_values` and
    :func:`last_saturation`.
    """

    needs: ClassVar[tuple[str, ...]] = ()
    single_source: ClassVar[bool] = True

    def __init__(self, nbands: int, height: int, width: int):
        self.shape = (nbands, height, width)
        self.parts: list[tuple[np.ndarray, np.ndarray, slice, slice]] = []

    def feed(self, values: np.ndarray, saturated: np.ndarray, rows: slice, cols: slice,
             key: np.ndarray | None = None) -> None:
        """Add one render covering ``values[:, rows, cols]`` of the tile (later ones win)."""
        self.parts.append((values, saturated, _bounded(rows, self.shape[1]), _bounded(cols, self.shape[2])))

    def result(self) -> tuple[np.ndarray, np.ndarray]:
        values = last_values(np.empty(self.shape, np.float32), [(v, r, c) for v, _, r, c in self.parts])
        return values, last_saturation(self.shape[1], self.shape[2], self.parts)


def _bounded(s: slice, size: int) -> slice:
    """``s`` with explicit start and stop within 0..size (step 1)."""
    start, stop, step = s.indices(size)
    if step != 1:
        raise ValueError(f"mosaic parts need contiguous slices, got step {step}")
    return slice(start, max(start, stop))


class MeanRule:
    """Mean of the covering captures, leaving saturated samples out (unless all are saturated).

    The saturation flag is the OR over every capture covering the pixel.
    """

    needs: ClassVar[tuple[str, ...]] = ()
    single_source: ClassVar[bool] = False

    def __init__(self, nbands: int, height: int, width: int):
        shape = (nbands, height, width)
        self.total = np.zeros(shape, np.float64)
        self.count = np.zeros(shape, np.uint16)
        self.total_sat = np.zeros(shape, np.float64)   # saturated samples: used only if nothing else
        self.count_sat = np.zeros(shape, np.uint16)
        self.saturated = np.zeros((height, width), bool)

    def feed(self, values: np.ndarray, saturated: np.ndarray, rows: slice, cols: slice,
             key: np.ndarray | None = None) -> None:
        ok = np.isfinite(values)
        good = ok & ~saturated[None]
        bad = ok & saturated[None]
        v = np.where(ok, values, 0.0)
        self.total[:, rows, cols] += np.where(good, v, 0.0)
        self.count[:, rows, cols] += good
        self.total_sat[:, rows, cols] += np.where(bad, v, 0.0)
        self.count_sat[:, rows, cols] += bad
        self.saturated[rows, cols] |= saturated & ok.any(axis=0)

    def result(self) -> tuple[np.ndarray, np.ndarray]:
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = np.where(self.count > 0, self.total / self.count,
                            np.where(self.count_sat > 0, self.total_sat / self.count_sat, np.nan))
        return mean.astype(np.float32), self.saturated


def nadir_winners(height: int, width: int, keys: Sequence[tuple[np.ndarray, slice, slice]]) -> np.ndarray:
    """The 'nadir' rule's choice: (height, width) int32, per pixel the index of the part with the
    smallest key (view zenith), the later one on a tie, -1 where no key is finite.

    keys: (key (h, w) float32, NaN where the part does not cover the pixel; rows, cols) in capture
    order, ``key`` landing at ``[rows, cols]``.
    """
    best = np.full((height, width), np.inf, np.float32)
    winner = np.full((height, width), -1, np.int32)
    for k, (key, rows, cols) in enumerate(keys):
        wins = key <= best[rows, cols]         # NaN (not covered) never wins
        best[rows, cols][wins] = key[wins]
        winner[rows, cols][wins] = k
    return winner


def nadir_values(out: np.ndarray, winner: np.ndarray, parts: Sequence[tuple[np.ndarray, slice, slice]],
                 fill=np.nan) -> np.ndarray:
    """The 'nadir' rule's values, written into ``out`` (..., H, W) and returned: each pixel's value
    from the part :func:`nadir_winners` chose (``winner``), ``fill`` where none.

    parts: (values (..., h, w), rows, cols) in the order of the winners' keys.
    """
    out[...] = fill
    for k, (values, rows, cols) in enumerate(parts):
        np.copyto(out[..., rows, cols], values, where=winner[rows, cols] == k)
    return out


class NadirRule:
    """The capture with the smallest view zenith (``key``) at the pixel wins (all its bands and its
    saturation flag), the later one on a tie; pixels no capture covers (key NaN) stay NaN.

    Renders are only collected by ``feed``; ``result`` picks with :func:`nadir_winners` and
    :func:`nadir_values`.
    """

    needs: ClassVar[tuple[str, ...]] = ("view_zenith",)
    single_source: ClassVar[bool] = True

    def __init__(self, nbands: int, height: int, width: int):
        self.shape = (nbands, height, width)
        self.parts: list[tuple[np.ndarray, np.ndarray, slice, slice, np.ndarray]] = []

    def feed(self, values: np.ndarray, saturated: np.ndarray, rows: slice, cols: slice,
             key: np.ndarray | None = None) -> None:
        if key is None:
            raise ValueError("the 'nadir' rule needs each render's view zenith (key)")
        rows, cols = _bounded(rows, self.shape[1]), _bounded(cols, self.shape[2])
        self.parts.append((values, saturated, rows, cols, key))

    def result(self) -> tuple[np.ndarray, np.ndarray]:
        winner = nadir_winners(self.shape[1], self.shape[2], [(k, r, c) for _, _, r, c, k in self.parts])
        values = nadir_values(np.empty(self.shape, np.float32), winner, [(v, r, c) for v, _, r, c, _ in self.parts])
        saturated = np.zeros(self.shape[1:], bool)
        nadir_values(saturated, winner, [(s, r, c) for _, s, r, c, _ in self.parts], fill=False)
        return values, saturated


RULES = {"last": LastRule, "nadir": NadirRule, "mean": MeanRule}
#: Rules under which every output pixel comes from one raw pixel (provenance layers can be written).
WINNER_RULES = tuple(name for name, rule in RULES.items() if rule.single_source)


def rule_key(name: str) -> str | None:
    """The provenance layer the rule ``name`` compares (fed to it as each render's ``key``), or None
    when it needs none."""
    needs = RULES[name].needs if name in RULES else ()
    return needs[0] if needs else None


def make_rule(name: str, nbands: int, height: int, width: int):
    """A fresh rule ('last' | 'mean') for a tile of ``nbands`` x ``height`` x ``width``."""
    try:
        return RULES[name](nbands, height, width)
    except KeyError:
        raise InputError("--overlap", f"unknown overlap rule {name!r}", f"use one of {', '.join(RULES)}") from None
