"""What bounds a render's memory whatever the flight's length (issue 20): cubes rendered in the order
that holds the fewest renders, band groups sized from the renders a group holds at once, and
lookups held packed."""

from __future__ import annotations

import gc
import pickle

import numpy as np

from archive.graph.build import (HELD_VALUES_BYTES, LOOKUP_BYTES, RENDERS_AHEAD, live_renders, render_order,
                                 renders_held, shared_lookup_bytes, task_group_size)
from archive.graph.plan import CubeJob, RenderPlan, band_groups
from archive.graph.tasks import VALUES_POOL, PackedLookup, ValuesPool, unpacked
from archive.grid import Grid
from archive.render.gather import gather_lookup
from archive.render.renderer import Lookup

TILE = 1024


def lawn_mower(cubes_per_pass: int, passes: int = 2) -> RenderPlan:
    """Cubes of one tile each; pass p flies its tiles left to right (even p) or back (odd p), all
    passes over the same row of tiles (full overlap: the worst case)."""
    grid = Grid(32616, 0.04, 500000.0, 3900000.0, TILE * cubes_per_pass, TILE)
    jobs = []
    for p in range(passes):
        for c in range(cubes_per_pass):
            col = c if p % 2 == 0 else cubes_per_pass - 1 - c
            box = (0, col * TILE, TILE, TILE)
            jobs.append(CubeJob(0, len(jobs), None, box, grid.window(*box)))
    return RenderPlan(grid, tuple(jobs), (tuple(range(300)),), band_groups(300))


def test_live_renders_follow_the_passes_and_groups_shrink_to_fit():
    assert live_renders(lawn_mower(4, passes=1)) == 1     # each tile written as soon as its cube is drawn
    # two passes in capture order: the first pass's renders wait for the second pass to come back
    # over their tiles (a whole pass: grows with the flight's length)
    capture = range(8)
    assert live_renders(lawn_mower(4), order=capture) == 5
    assert live_renders(lawn_mower(8), order=range(16)) == 9
    # the graph's order sweeps along the passes: a tile is complete once both passes crossed it,
    # whatever the length (the renders of its two cubes)
    for n in (4, 8, 16):
        order = render_order(lawn_mower(n))
        assert sorted(order) == list(range(2 * n))
        assert live_renders(lawn_mower(n), order=order) == live_renders(lawn_mower(n)) == 2
    assert render_order(lawn_mower(4, passes=1)) == tuple(range(4))   # capture order when it is as good
    sizes = [task_group_size(lawn_mower(n)) for n in (2, 4, 8, 16)]
    assert sizes == sorted(sizes, reverse=True) and sizes[-1] >= 4
    for n, size in zip((2, 4, 8, 16), sizes):   # all renders held at once fit the budget (or 4 bands)
        held = renders_held(lawn_mower(n))
        assert held == min(live_renders(lawn_mower(n)) + RENDERS_AHEAD, 2 * n) + VALUES_POOL.keep
        # the lookups the groups share are held all run: they count in the same budget
        lookups = shared_lookup_bytes(lawn_mower(n))
        assert lookups == 2 * n * TILE * TILE * 8 // 8
        assert held * size * TILE * TILE * 4 + lookups <= HELD_VALUES_BYTES or size == 4
    # a flight of fewer cubes than live + ahead holds at most its cubes: bigger groups, the same bytes
    assert renders_held(lawn_mower(2)) == 4 + VALUES_POOL.keep < live_renders(lawn_mower(2)) + RENDERS_AHEAD + VALUES_POOL.keep
    # bigger cube windows: as many bands as fit, not a multiple of 4 (what is held stays near the
    # budget, flat, as the flights get longer and more renders are alive at once)
    big = lawn_mower(4, passes=1)
    side = 2 * TILE
    grid = Grid(32616, 0.04, 500000.0, 3900000.0, side * 4, side)
    jobs = tuple(CubeJob(0, c, None, (0, c * side, side, side), grid.window(0, c * side, side, side)) for c in range(4))
    big = RenderPlan(grid, jobs, big.bands, big.groups)
    per_band = side * side * 4
    held = renders_held(big)
    assert held == min(live_renders(big) + RENDERS_AHEAD, 4) + VALUES_POOL.keep == 4 + VALUES_POOL.keep
    assert task_group_size(big) == (HELD_VALUES_BYTES - shared_lookup_bytes(big)) // held // per_band == 6
    # lookups too big to share are made per group (held like renders): not taken off the budget
    many = lawn_mower(LOOKUP_BYTES // (TILE * TILE) + 2, passes=1)
    assert shared_lookup_bytes(many) == 0


def test_packed_lookup_gives_the_lookup_back():
    grid = Grid(32616, 0.04, 500000.0, 3900000.0, 300, 200)
    rows, cols = np.mgrid[0:200, 0:300]
    line = np.where(cols > 20, rows * 3 // 2, -1).astype(np.int32)
    sample = np.where(line >= 0, cols % 128, -1).astype(np.int32)
    count = (line >= 0).astype(np.uint16)
    for lookup in (Lookup(grid, line, sample, 300, 128), Lookup(grid, line, sample, 300, 128, count)):
        packed = pickle.loads(pickle.dumps(PackedLookup(lookup)))
        assert packed.nbytes < line.nbytes / 4
        back = unpacked(packed)
        assert back.grid == grid and (back.lines, back.samples) == (300, 128)
        np.testing.assert_array_equal(back.line, line)
        np.testing.assert_array_equal(back.sample, sample)
        if lookup.count is None:
            assert back.count is None
        else:
            np.testing.assert_array_equal(back.count, count)
        assert unpacked(back) is back
        # the flat index a render gathers through, decoded in one step: the same values as the lookup's
        dn = (np.arange(3 * 300 * 128) % 4093).reshape(3, 300, 128).astype(np.uint16)
        want, got = gather_lookup(lookup, dn, None), gather_lookup(packed.gather_index(), dn, None)
        assert np.array_equal(want.values.view(np.uint32), got.values.view(np.uint32))
        np.testing.assert_array_equal(got.covered, lookup.covered)
    # a lookup pass 1 never makes (a sample without its line): kept as it is
    odd = Lookup(grid, line, np.where(cols % 7 == 0, -1, sample).astype(np.int32), 300, 128)
    back = unpacked(pickle.loads(pickle.dumps(PackedLookup(odd))))
    np.testing.assert_array_equal(back.line, odd.line)
    np.testing.assert_array_equal(back.sample, odd.sample)


def test_values_pool_reuses_a_buffer_only_once_no_view_of_it_is_left():
    pool = ValuesPool(keep=2)
    values = pool.take((2, 3, 4))
    values[...] = 1.0
    part = values[1][:, 1:]          # what a writer slices out of a render
    buffer = values.base.base.obj   # the pool's buffer behind it (holding it keeps no view alive)
    del values
    gc.collect()
    assert pool.free == [] and (part == 1.0).all()   # still in use: not handed out again
    del part
    gc.collect()
    assert len(pool.free) == 1 and pool.free[0] is buffer
    again = pool.take((2, 3, 4))
    assert pool.free == [] and again.base.base.obj is buffer and again.flags.writeable and again.flags.c_contiguous
    assert pickle.loads(pickle.dumps(again)).shape == (2, 3, 4)
    assert pool.take((4, 3, 4)).size == 48             # too big for any free buffer: a new one
    for shape in ((5,), (6,), (7,)):
        pool.take(shape)                               # released at once
    gc.collect()
    assert len(pool.free) == 2                         # at most ``keep`` wait free


def _pool_keeps(shape: tuple[int, ...]) -> int:
    """In a worker's task: how many free buffers a fresh pool keeps after one render's values die."""
    pool = ValuesPool(keep=2)
    values = pool.take(shape)
    values[...] = 0.0
    del values
    gc.collect()
    return len(pool.free)


def test_values_pool_keeps_no_more_than_its_share_of_a_workers_memory():
    """A worker with a small memory limit keeps no free buffer (a paused worker cannot release it:
    a 500 MB test worker stayed paused for good); a larger one keeps it."""
    from distributed import Client, LocalCluster

    shape = (2, 1000, 1000)   # 8 MB of float32
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, memory_limit="100MB",
                      dashboard_address=None) as small, Client(small) as client:
        assert client.submit(_pool_keeps, shape, pure=False).result() == 0      # cap 5 MB
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, memory_limit="1GB",
                      dashboard_address=None) as large, Client(large) as client:
        assert client.submit(_pool_keeps, shape, pure=False).result() == 1      # cap 50 MB
    assert _pool_keeps(shape) == 1                                              # no worker: no cap


_GIVEN_BACK = """
import gc, pickle
from archive.graph.tasks import ValuesPool


def mapping(address):
    with open("/proc/self/maps") as maps:
        for line in maps:
            start, end = (int(x, 16) for x in line.split()[0].split("-"))
            if start <= address < end:
                return start, end


pool = ValuesPool(keep=0)
values = pool.take((3, 1024, 1024))    # 12 MiB: under the workers' 32 MiB mmap threshold
values[...] = 2.0
address, before = values.ctypes.data, mapping(values.ctypes.data)
assert before is not None and before[1] - before[0] >= values.nbytes, before   # a mapping of its own
assert float(values.sum()) == 2.0 * values.size
assert pickle.loads(pickle.dumps(values[1:])).shape == (2, 1024, 1024)
del values
gc.collect()
assert pool.free == [] and mapping(address) != before, "not unmapped"   # (the range may be reused)
assert pool.take((4, 4)).size == 16    # small ones come from numpy as before
print("ok")
"""


def test_values_pool_gives_large_buffers_back_to_the_system():
    """Buffers of a render's size are memory maps of their own: once the pool drops one, its pages
    are unmapped, whatever glibc's mmap threshold (our workers': 32 MiB; glibc's heaps keep freed
    memory: a worker holding renders under the threshold grew 0.1 GB on the 40-cube flight). Run
    in a process started with the workers' threshold."""
    import os
    import subprocess
    import sys

    from archive.run.cluster import MALLOC_MMAP_THRESHOLD

    env = {**os.environ, "MALLOC_MMAP_THRESHOLD_": str(MALLOC_MMAP_THRESHOLD)}
    done = subprocess.run([sys.executable, "-c", _GIVEN_BACK], env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and done.stdout.strip() == "ok", done.stderr[-2000:]
