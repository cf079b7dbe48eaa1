"""Mosaic rules: how the renders of several cubes combine on one output tile.

A rule is a small strategy object: ``feed`` it the cubes' renders in capture order (source order,
then cube order), then take ``result()``. Arrays are ``(band, y, x)`` float32 with NaN where a cube
does not cover a pixel; ``saturated`` is ``(y, x)`` bool (some band of the group was saturated there).
"""

from __future__ import annotations

import numpy as np

__all__ = ["LastRule", "MeanRule", "RULES", "make_rule"]


class LastRule:
    """The later capture wins wherever it covers the pixel (per band: later non-NaN wins)."""

    def __init__(self, nbands: int, height: int, width: int):
        self.values = np.full((nbands, height, width), np.nan, np.float32)
        self.saturated = np.zeros((height, width), bool)

    def feed(self, values: np.ndarray, saturated: np.ndarray, rows: slice, cols: slice) -> None:
        """Combine one render covering ``values[:, rows, cols]`` of the tile."""
        ok = np.isfinite(values)
        target = self.values[:, rows, cols]
        np.copyto(target, values, where=ok)
        covered = ok.any(axis=0)
        self.saturated[rows, cols] = np.where(covered, saturated, self.saturated[rows, cols])

    def result(self) -> tuple[np.ndarray, np.ndarray]:
        return self.values, self.saturated


class MeanRule:
    """Mean of the covering captures, leaving saturated samples out (unless all are saturated).

    The saturation flag is the OR over every capture covering the pixel.
    """

    def __init__(self, nbands: int, height: int, width: int):
        shape = (nbands, height, width)
        self.total = np.zeros(shape, np.float64)
        self.count = np.zeros(shape, np.uint16)
        self.total_sat = np.zeros(shape, np.float64)   # saturated samples: used only if nothing else
        self.count_sat = np.zeros(shape, np.uint16)
        self.saturated = np.zeros((height, width), bool)

    def feed(self, values: np.ndarray, saturated: np.ndarray, rows: slice, cols: slice) -> None:
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


RULES = {"last": LastRule, "mean": MeanRule}


def make_rule(name: str, nbands: int, height: int, width: int):
    """A fresh rule ('last' | 'mean') for a tile of ``nbands`` x ``height`` x ``width``."""
    try:
        return RULES[name](nbands, height, width)
    except KeyError:
        from archive.errors import InputError

        raise InputError("--overlap", f"unknown overlap rule {name!r}", f"use one of {', '.join(RULES)}") from None
