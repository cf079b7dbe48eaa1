"""The viewer's band planes (:mod:`archive.drawing.planes`) on a fake source of known DN: a plane is
the DN in float32 (raw mode), a filtered plane the mean of the block around each pixel (cut at the
edges), each plane is read once however many requests ask for it, and planes are made on worker
threads, including those asked ahead, without deadlocking when a worker finishes at once."""

from __future__ import annotations

import threading
import time
from concurrent.futures import Executor, Future, ThreadPoolExecutor
from types import SimpleNamespace

import numpy as np

from archive.drawing.cache import ByteLRU
from archive.drawing.planes import BandPlanes

LINES, SAMPLES, BANDS = 40, 30, 3


class FakeSource:
    """Cubes of (bands, lines, samples) uint16 DN; raw mode only (no radiometric terms)."""

    def __init__(self, cubes: int):
        rng = np.random.default_rng(3)
        self.data = [rng.integers(0, 4000, (BANDS, LINES, SAMPLES)).astype(np.uint16) for _ in range(cubes)]
        self.reads: list[tuple[int, int]] = []
        self._lock = threading.Lock()

    def read_bands(self, cube, bands):
        with self._lock:
            self.reads += [(cube, b) for b in bands]
        return self.data[cube][list(bands)]

    def radiometry(self, cube, bands, mode):
        return None


class AtOnce(Executor):
    """An executor that runs each job in submit (its future is done before submit returns)."""

    def submit(self, fn, *args, **kwargs):
        future: Future = Future()
        future.set_result(fn(*args, **kwargs))
        return future


def _planes(source: FakeSource, workers) -> BandPlanes:
    cubes = [SimpleNamespace(lines=LINES, samples=SAMPLES, bands=BANDS) for _ in source.data]
    return BandPlanes("fake", lambda: source, cubes, ByteLRU(64 << 20), workers)


def _in_thread(fn, seconds: float = 20.0) -> None:
    """Run ``fn`` in a thread; fail (instead of hanging) when it has not returned in ``seconds``."""
    errors: list = []
    t = threading.Thread(target=lambda: errors.append(None) if fn() is None else None, daemon=True)
    t.start()
    t.join(seconds)
    assert not t.is_alive(), "deadlocked"
    assert errors == [None]


def test_planes_hold_the_dn_and_block_means():
    source = FakeSource(2)
    planes = _planes(source, AtOnce())
    _in_thread(lambda: planes.prepare([0, 1], [0, 2], "raw", size=4))   # jobs done before submit returns
    dn = source.data[1][2].astype(np.float32)
    plane = planes.plane(1, 2, "raw")
    assert plane.shape == (LINES * SAMPLES + 1,) and np.isnan(plane[-1])
    assert np.array_equal(plane[:-1].reshape(LINES, SAMPLES), dn)
    filtered = planes.filtered(1, 2, "raw", 4)[:-1].reshape(LINES, SAMPLES)
    # the 4 x 4 block from (line - 2, sample - 2), cut at the edges
    for line, sample in ((10, 10), (0, 0), (LINES - 1, SAMPLES - 1), (1, SAMPLES - 2)):
        block = dn[max(0, line - 2):line + 2, max(0, sample - 2):sample + 2]
        assert np.isclose(filtered[line, sample], block.mean(), rtol=1e-6), (line, sample)
    got = planes.block_means(1, 2, "raw", 4, np.array([10, -1]), np.array([10, 3]))
    assert np.isclose(got[0], filtered[10, 10]) and np.isnan(got[1])
    assert sorted(source.reads) == [(0, 0), (0, 2), (1, 0), (1, 2)]   # each read once


def test_planes_are_made_on_the_workers_ahead_and_once():
    source = FakeSource(4)
    with ThreadPoolExecutor(2) as workers:
        planes = _planes(source, workers)
        planes.prepare([0, 1], [1], "raw", size=2, ahead=[2, 3])
        key = ("fake", 3, 1, "raw", "filtered", 2)
        deadline = time.monotonic() + 20
        while key not in planes.cache:   # made ahead, without being waited for
            assert time.monotonic() < deadline, "the planes asked ahead were not made"
            time.sleep(0.01)
        planes.prepare([0, 1, 2, 3], [1], "raw", size=2)    # all held: nothing made again
        for c in range(4):
            planes.filtered(c, 1, "raw", 2)
    assert sorted(source.reads) == [(c, 1) for c in range(4)]


class SlowCube(FakeSource):
    """A source whose reads of one cube wait for ``release`` (a worker still making it)."""

    def __init__(self, cubes: int, slow: int):
        super().__init__(cubes)
        self.slow, self.release, self.reading = slow, threading.Event(), threading.Event()

    def read_bands(self, cube, bands):
        if cube == self.slow:
            self.reading.set()
            assert self.release.wait(20)
        return super().read_bands(cube, bands)


def test_a_plane_a_worker_is_making_is_waited_for_not_made_again():
    """The last plane missing is being made ahead on a worker: asking for it waits for that worker
    instead of reading the cube a second time (a race the load of CI once showed)."""
    source = SlowCube(4, slow=2)
    with ThreadPoolExecutor(2) as workers:
        planes = _planes(source, workers)
        planes.prepare([0, 1], [1], "raw", size=2, ahead=[2, 3])
        assert source.reading.wait(20)   # cube 2 is being read on a worker
        deadline = time.monotonic() + 20
        while ("fake", 3, 1, "raw", "filtered", 2) not in planes.cache:
            assert time.monotonic() < deadline
            time.sleep(0.01)
        threading.Timer(0.3, source.release.set).start()
        planes.prepare([0, 1, 2, 3], [1], "raw", size=2)   # only cube 2's plane missing: waited for
        for c in range(4):
            planes.filtered(c, 1, "raw", 2)
    assert sorted(source.reads) == [(c, 1) for c in range(4)]
