"""What bounds a render's memory whatever the flight's length (issue 20): band groups sized from the
renders a group holds at once, and lookups held packed."""

from __future__ import annotations

import pickle

import numpy as np

from archive.graph.build import HELD_VALUES_BYTES, RENDERS_AHEAD, live_renders, task_group_size
from archive.graph.plan import CubeJob, RenderPlan, band_groups
from archive.graph.tasks import PackedLookup, unpacked
from archive.grid import Grid
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
    # two passes: the first pass's renders wait for the second pass to come back over their tiles
    assert live_renders(lawn_mower(4)) == 5
    assert live_renders(lawn_mower(8)) == 9
    sizes = [task_group_size(lawn_mower(n)) for n in (2, 4, 8, 16)]
    assert sizes == sorted(sizes, reverse=True) and sizes[-1] >= 4
    for n, size in zip((2, 4, 8, 16), sizes):   # all renders held at once fit the budget (or 4 bands)
        held = (live_renders(lawn_mower(n)) + RENDERS_AHEAD) * size * TILE * TILE * 4
        assert held <= HELD_VALUES_BYTES or size == 4


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
