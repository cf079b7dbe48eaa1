"""A viewed flight's geometry (its meshes at one ground height and sync offset) and the small
array helpers its drawing uses (:mod:`archive.drawing.flight`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Geometry", "PosesKept", "bounds_intersect", "plane_index", "slice_radiometry"]


@dataclass(frozen=True, eq=False)
class Geometry:
    """A flight's meshes at one ground height, sync offset, navigation source and boresight.

    source: the opened flight source; ground_height: m above the ellipsoid (resolved);
    epsg: the UTM zone ``archive render`` uses for this flight; utm / mercator: per cube, its mesh
    in ``epsg`` / EPSG:3857; bounds: (cubes, 4) W, S, E, N EPSG:3857 metres of each cube's mesh
    (NaN for a cube without a drawable mesh).
    """

    source: object
    ground_height: float
    epsg: int
    utm: tuple
    mercator: tuple
    bounds: np.ndarray
    gsd: float | None = None   #: terrain meshes: the output pixel they were built for (m); None: flat
    #: (sync offset, navigation source, boresight) as asked (:meth:`ViewedFlight.pose_key`): the caches' key
    pose: tuple = ()

    def union(self, cubes: range) -> tuple[float, float, float, float] | None:
        """W, S, E, N (EPSG:3857 m) of the cubes' meshes, None when none is drawable."""
        b = self.bounds[list(cubes)]
        b = b[np.isfinite(b).all(axis=1)]
        if not len(b):
            return None
        return (float(b[:, 0].min()), float(b[:, 1].min()), float(b[:, 2].max()), float(b[:, 3].max()))


def bounds_intersect(a, b) -> bool:
    """Whether two (west, south, east, north) boxes overlap (touching edges do not)."""
    return a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]


def slice_radiometry(radiometry, lines: slice, samples: slice):
    """The radiometric terms of some lines and samples of a cube (None stays None: raw DN)."""
    from archive.sources.base import Radiometry

    if radiometry is None:
        return None
    return Radiometry(radiometry.dark[:, samples], radiometry.gain[:, samples], radiometry.response[lines],
                      radiometry.saturation)


def plane_index(lookup) -> np.ndarray:
    """(height * width,) int32 index into a band plane (:meth:`ViewedFlight.plane`) of the (line, sample)
    each pixel of ``lookup`` sees; the plane's last (NaN) element where none."""
    index = lookup.line * np.int32(lookup.samples) + lookup.sample
    return np.where(lookup.line >= 0, index, lookup.lines * lookup.samples).astype(np.int32).reshape(-1)


class PosesKept:
    """A flight source whose per-cube poses are computed once: they do not depend on the ground
    height, so a ground-height change (a slider being dragged) rebuilds only the meshes. Everything
    else is the source's own."""

    def __init__(self, source):
        self.source = source
        self._poses: dict = {}

    def poses(self, cube: int, delay: float = 0.0):
        key = (cube, delay)
        if key not in self._poses:
            self._poses[key] = self.source.poses(cube, delay)
        return self._poses[key]

    def __getattr__(self, name):
        return getattr(self.source, name)
