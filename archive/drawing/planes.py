"""A viewed flight's band planes: every (line, sample) of a band of a cube in a mode, calibrated
once and kept, and the same box-filtered for overview zooms; made on worker threads.

A plane holds the float32 values ``archive render`` gives those pixels:
:func:`archive.render.gather.calibrate_plane`, the calibration of the CPU pass 2 of ``archive
render`` on software GL (bit for bit llvmpipe's band pass), once per (line, sample) instead of per
output pixel. A tile is then a gather through its lookup (:class:`archive.drawing.flight.ViewedFlight`). No
OpenGL here: planes are made on any thread.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import Executor, Future

import numpy as np

from archive.drawing.cache import ByteLRU

__all__ = ["BandPlanes", "RADIOMETRY_KEPT"]

#: (cube, bands, mode) radiometric terms kept per flight.
RADIOMETRY_KEPT = 256


class BandPlanes:
    """The band planes of one flight (served as ``cid``): ``source()`` gives its source (sync offset
    as ingested: the values do not depend on it), ``cubes`` its cubes' info; planes live in the
    shared byte-bounded ``cache``; ``workers`` make several at once (:meth:`prepare`; None: one
    after the other, on the caller's thread)."""

    def __init__(self, cid: str, source: Callable[[], object], cubes: Sequence, cache: ByteLRU,
                 workers: Executor | None = None):
        self.id = cid
        self.source = source
        self.cubes = cubes
        self.cache = cache
        self.workers = workers
        self._radiometry: OrderedDict = OrderedDict()
        self._lock = threading.RLock()   # a future done already runs its callback (_forget) at once, here
        self._making: dict[tuple, Future] = {}   # (cube, band, mode, size) -> a plane being made

    @property
    def radiometry_kept(self) -> dict:
        """The radiometric terms kept (:meth:`radiometry`), by (cube, bands, mode): what a flight is
        charged for them."""
        return dict(self._radiometry)

    def radiometry(self, cube: int, bands: Sequence[int], mode: str):
        """The source's radiometric terms of ``bands`` of ``cube`` in ``mode`` (None: raw DN), kept."""
        key = (cube, tuple(bands), mode)
        found = self._radiometry.get(key)
        if found is None:
            found = self._radiometry[key] = self.source().radiometry(cube, list(bands), mode)
            while len(self._radiometry) > RADIOMETRY_KEPT:
                self._radiometry.popitem(last=False)
        return found

    def plane(self, cube: int, band: int, mode: str) -> np.ndarray:
        """(lines * samples + 1,) float32 values of one band of one cube in ``mode`` for every (line,
        sample), row-major, the last element NaN (what an uncovered pixel shows): the values
        ``archive render`` gives those pixels (:meth:`_calibrate`). Cached (the bands cache)."""
        def make():
            info = self.cubes[cube]
            out = np.empty(info.lines * info.samples + 1, np.float32)
            self._calibrate(cube, band, mode, out[:-1].reshape(info.lines, info.samples))
            out[-1] = np.nan
            return out, out.nbytes
        return self.cache.get_or_make((self.id, cube, band, mode), make)

    def filtered(self, cube: int, band: int, mode: str, size: int) -> np.ndarray:
        """(lines * samples + 1,) float32 like :meth:`plane`, each value the mean of the finite values
        of the size x size block of lines x samples centred on its (line, sample) (from index - size
        // 2, cut at the cube's edges), NaN where none is; ``size`` 1: the plane itself. The
        flight's pixels box-filtered for overview zooms; a tile then gathers from it as from the
        plane. Cached per size (the bands cache): one plane's worth of memory per level shown."""
        if size == 1:
            return self.plane(cube, band, mode)

        def make():
            from scipy.ndimage import uniform_filter

            info = self.cubes[cube]
            plane = self.plane(cube, band, mode)[:-1].reshape(info.lines, info.samples)
            out = np.empty(info.lines * info.samples + 1, np.float32)
            out[-1] = np.nan
            mean = out[:-1].reshape(info.lines, info.samples)
            # uniform_filter's window for even sizes starts at index - size // 2, as wanted; zeros
            # beyond the edges, so a mean there is rescaled by the share of the block inside
            if np.isfinite(np.add.reduce(plane, axis=None, dtype=np.float64)):   # every value finite (one pass)
                uniform_filter(plane, size=size, mode="constant", cval=0.0, output=mean)
                h = size // 2
                for axis, n in ((0, info.lines), (1, info.samples)):
                    edge = np.r_[0:min(h, n), max(h, n - (size - h - 1)):n]
                    i = np.arange(n)[edge]
                    share = ((np.minimum(i - h + size, n) - np.maximum(i - h, 0)) / size).astype(np.float32)
                    if axis == 0:
                        mean[edge] /= share[:, None]
                    else:
                        mean[:, edge] /= share[None, :]
                return out, out.nbytes
            finite = np.isfinite(plane)
            sums = uniform_filter(np.where(finite, plane, np.float32(0)), size=size, mode="constant", cval=0.0,
                                  output=np.float32)
            count = uniform_filter(finite.astype(np.float32), size=size, mode="constant", cval=0.0)
            with np.errstate(invalid="ignore", divide="ignore"):
                np.divide(sums, count, out=mean)
            mean[count < 0.5 / (size * size)] = np.nan
            return out, out.nbytes
        return self.cache.get_or_make((self.id, cube, band, mode, "filtered", int(size)), make)

    def prepare(self, cubes: Iterable[int], bands: Sequence[int], mode: str, size: int = 1,
                ahead: Iterable[int] = ()) -> None:
        """Make the :meth:`filtered` planes of these cubes and bands that are not cached yet, on the
        worker threads when there are several (reading, checking, calibrating and filtering a plane
        release the GIL: a new band of 8 cubes in about half the time on 2 cores), and wait for
        them. ``ahead``: more cubes whose planes are made too, after those, without waiting (what
        the next requests will need). A plane already being made is waited for, not made again."""
        def missing(among):
            return [(int(c), int(b)) for c in among for b in bands
                    if (self.id, int(c), int(b), mode, "filtered", int(size)) not in self.cache
                    and (size > 1 or (self.id, int(c), int(b), mode) not in self.cache)]
        now, later = missing(cubes), missing(ahead)
        if self.workers is None:
            return
        if len(now) + len(later) < 2:   # one plane: the caller makes it, unless a worker is making it now
            with self._lock:
                busy = [self._making.get((c, b, mode, int(size))) for c, b in now]
            for future in busy:
                if future is not None:
                    future.result()
            return
        self.source()
        for c in {c for c, _ in now + later}:
            self.band_radiometry(c, 0, mode)   # shared per cube and mode: made here, not by two threads
        waits = [self._making_on_workers((c, b, mode, int(size))) for c, b in now]
        for c, b in later:
            self._making_on_workers((c, b, mode, int(size)))
        for future in waits:
            future.result()

    def _making_on_workers(self, key: tuple):
        """The future of :meth:`filtered` ``(*key)`` on the workers (one per key at a time)."""
        with self._lock:
            future = self._making.get(key)
            if future is None:
                future = self.workers.submit(self.filtered, *key)
                self._making[key] = future
                future.add_done_callback(lambda _, k=key: self._forget(k))
            return future

    def _forget(self, key: tuple) -> None:
        with self._lock:
            self._making.pop(key, None)

    def block_means(self, cube: int, band: int, mode: str, size: int, line: np.ndarray,
                    sample: np.ndarray) -> np.ndarray:
        """float32 (shape of ``line``): at each (line, sample), the mean of the finite values of the
        band in the size x size block of lines x samples centred there (:meth:`filtered`); NaN where
        ``line`` < 0 (not covered) or no value is finite."""
        info = self.cubes[cube]
        line, sample = np.asarray(line), np.asarray(sample)
        index = np.where(line >= 0, line * info.samples + sample, info.lines * info.samples)
        return self.filtered(cube, band, mode, size).take(index.astype(np.int64))

    def _calibrate(self, cube: int, band: int, mode: str, plane: np.ndarray | None = None) -> np.ndarray:
        """(lines, samples) float32 (into ``plane`` when given): every pixel of one band of one cube
        in ``mode``, by :func:`archive.render.gather.calibrate_plane` (what ``archive render``'s CPU
        band pass computes, ``((DN - dark) * gain) / response`` in float32), so the very values
        ``archive render`` writes; once per (line, sample), without its lookup and saturation work."""
        from archive.render.gather import calibrate_plane
        from archive.render.renderer import dn_texture_format, radiometry_arrays

        info = self.cubes[cube]
        dn = self.source().read_bands(cube, [band])
        dark, gain, resp, _ = radiometry_arrays(self.band_radiometry(cube, band, mode), 1, info.lines, info.samples)
        if plane is None:
            plane = np.empty((info.lines, info.samples), np.float32)
        return calibrate_plane(dn_texture_format(dn)[0][0], dark[0], gain[0], resp, plane)

    def band_radiometry(self, cube: int, band: int, mode: str):
        """The radiometric terms of one band of ``cube`` (None: raw DN), cut from those of every band
        (read once per cube and mode: a new band reads no calibration)."""
        from archive.sources.base import Radiometry

        every = self.radiometry(cube, tuple(range(self.cubes[cube].bands)), mode)
        if every is None:
            return None
        return Radiometry(every.dark[band:band + 1], every.gain[band:band + 1], every.response, every.saturation)
