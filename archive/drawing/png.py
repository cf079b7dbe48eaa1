"""Tiles as the browser reads them: PNGs of rendered values and band-value tiles (little-endian
float32 planes). The tile grids themselves are :mod:`archive.grid`'s (:func:`~archive.grid.tile_grid`).
No OpenGL here."""

from __future__ import annotations

import io
from functools import lru_cache

import numpy as np

from archive.grid import TILE

__all__ = ["encode_png", "encode_values", "transparent_png"]
def encode_png(values: np.ndarray, ranges, compress_level: int = 3) -> bytes:
    """A PNG of rendered values: (3, h, w) -> RGBA, (1, h, w) -> grey + alpha.

    ranges: per band (low, high), mapped linearly to 0..255 (clipped); alpha 255 where every band
    is finite, 0 (transparent) where any is NaN (no line covers the pixel).
    """
    from PIL import Image

    values = np.asarray(values, np.float32)
    if values.ndim != 3 or values.shape[0] not in (1, 3):
        raise ValueError(f"expected (1 or 3, h, w) values, got {values.shape}")
    k, h, w = values.shape
    finite = np.isfinite(values).all(axis=0)
    out = np.zeros((h, w, k + 1), np.uint8)
    for b in range(k):
        lo, hi = (float(v) for v in ranges[b])
        scale = 255.0 / (hi - lo) if hi > lo else 0.0
        with np.errstate(invalid="ignore"):
            channel = np.clip((values[b] - lo) * scale + 0.5, 0, 255)
        out[..., b] = np.where(finite, channel, 0).astype(np.uint8)
    out[..., k] = np.where(finite, 255, 0)
    buffer = io.BytesIO()
    Image.fromarray(out, "RGBA" if k == 3 else "LA").save(buffer, "PNG", compress_level=compress_level)
    return buffer.getvalue()


def encode_values(values: np.ndarray, key: np.ndarray | None = None) -> bytes:
    """A band-value tile as the browser reads it: the (k, n, n) float32 planes, then the (n, n)
    key plane if any, little-endian, row-major (north row first), NaN where no line covers."""
    planes = [np.asarray(values, "<f4")]
    if key is not None:
        planes.append(np.asarray(key, "<f4")[None])
    return b"".join(np.ascontiguousarray(p).tobytes() for p in planes)


@lru_cache(maxsize=1)
def transparent_png() -> bytes:
    """A fully transparent 256 x 256 PNG (tiles away from every line)."""
    return encode_png(np.full((1, TILE, TILE), np.nan, np.float32), [(0.0, 1.0)], 9)


