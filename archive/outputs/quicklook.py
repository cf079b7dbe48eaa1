"""The RGB quicklook PNG of an output: bands nearest 640 / 550 / 460 nm, 2 %/98 % stretch."""

from __future__ import annotations

import math
import os
from collections.abc import Sequence

import numpy as np

from archive.grid import Grid

__all__ = ["quicklook_bands", "quicklook_png"]

# Quicklook targets (nm) for red, green, blue.
_RGB_NM = (640.0, 550.0, 460.0)


def quicklook_bands(wavelengths: Sequence[float] | None, nbands: int) -> tuple[int, int, int]:
    """Output band positions for (red, green, blue).

    The bands nearest 640 / 550 / 460 nm when those lie within the bands' range; else the last /
    middle / first band (which for ascending wavelengths keeps long wavelengths red).
    """
    if wavelengths is not None and len(wavelengths) == nbands and nbands > 0:
        wl = np.asarray(wavelengths, dtype=float)
        half = (wl.max() - wl.min()) / max(nbands - 1, 1) / 2 if nbands > 1 else 0.0
        if all(wl.min() - half <= t <= wl.max() + half for t in _RGB_NM):
            return tuple(int(np.argmin(np.abs(wl - t))) for t in _RGB_NM)  # type: ignore[return-value]
    return (nbands - 1, nbands // 2, 0)


def quicklook_png(read_band, grid: Grid, wavelengths, nbands: int, path: str | os.PathLike,
                  max_size: int = 2048) -> None:
    """Write an RGBA PNG preview: 2 %/98 % stretch per channel over covered pixels, uncovered transparent.

    ``read_band(b, step)`` returns every ``step``-th pixel of band b (both axes); step is chosen so
    that the longer side is at most ``max_size``.
    """
    from PIL import Image

    step = max(1, math.ceil(max(grid.height, grid.width) / max_size))
    bands = quicklook_bands(wavelengths, nbands)
    channels = [read_band(b, step) for b in bands]
    covered = np.zeros(channels[0].shape, dtype=bool)
    for c in channels:
        covered |= np.isfinite(c)
    rgba = np.zeros(channels[0].shape + (4,), dtype=np.uint8)
    for i, c in enumerate(channels):
        ok = np.isfinite(c)
        if ok.any():
            lo, hi = np.percentile(c[ok], [2.0, 98.0])
            scale = 255.0 / (hi - lo) if hi > lo else 0.0
            stretched = np.clip((np.where(ok, c, lo) - lo) * scale, 0, 255)
            rgba[..., i] = np.where(ok, np.round(stretched), 0).astype(np.uint8)
    rgba[..., 3] = np.where(covered, 255, 0)
    Image.fromarray(rgba, mode="RGBA").save(path, format="PNG")
