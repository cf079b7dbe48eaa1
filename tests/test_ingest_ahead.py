"""DN chunks encoded ahead of an ingest, cube by cube (``archive watch``, issue 47; archive/ingest/ahead.py):
an ingest with ``prewritten=`` moves in exactly the chunks that are its own and writes the rest, so its
collection equals a plain ingest's (every array, every attribute) whatever was written ahead."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from helpers import FOV

FLIGHT = dict(cubes=4, bands=5, samples=48, lines=120, cubes_per_pass=2, seed=11)


@pytest.fixture(scope="module")
def flight(tmp_path_factory) -> Path:
    from archive.simulator.command import simulate_flight

    folder = tmp_path_factory.mktemp("ahead") / "flight"
    simulate_flight(folder, **FLIGHT)
    return folder


def _same_store(a: Path, b: Path) -> None:
    import zarr

    mine, theirs = (zarr.open_group(str(p), mode="r") for p in (a, b))
    assert dict(mine.attrs) == dict(theirs.attrs)
    names = sorted(k for k, _ in theirs.arrays())
    assert sorted(k for k, _ in mine.arrays()) == names
    for name in names:
        np.testing.assert_array_equal(mine[name][...], theirs[name][...], err_msg=name)


def test_place_guesses_one_line_chunk_per_cube():
    from archive.watch.ahead import place

    cubes = [("s_1", 100), ("s_2", 100), ("s_10", 60), ("s_3", 100)]
    assert [place(cubes, b) for b, _ in cubes] == [(0, 100), (1, 100), (3, 100), (2, 100)]   # name order: 1 2 3 10
    odd = [("s_1", 100), ("s_2", 60), ("s_3", 100), ("s_4", 100)]
    assert place(odd, "s_2") == (1, 100) and place(odd, "s_3") is None   # offset 160: not a chunk's start
    assert place([("s_1", 100), ("s_2", 150), ("s_3", 150)], "s_1") == (0, 150)   # the common length leads
    assert place([("s_1", 100), ("s_2", 150), ("s_3", 150)], "s_2") is None


def test_prewritten_chunks_are_moved_in_only_where_they_are_the_ingests(flight, tmp_path):
    from archive.collection import verify_store
    from archive.collection.layout import chunk_path
    from archive.formats.flight import discover_flight
    from archive.ingest.ahead import read_records, record_cube, write_cube_ahead
    from archive.ingest.command import ingest
    from archive.ingest.flight import store_choices
    from archive.watch.cubes import cube_files

    codec, checksum = store_choices(None, None)
    cubes = discover_flight(flight).cubes
    ahead = tmp_path / "ahead"
    lines = FLIGHT["lines"]
    for k, c in enumerate(cubes):
        chunk = {1: 5}.get(k, k)                     # cube 1 guessed at the wrong place
        record = write_cube_ahead(ahead, cube_files(Path(c.data)), chunk, lines, codec, checksum)
        record_cube(ahead, c.base, record)
        assert record["lines"] == lines and len(record["digests"]) == FLIGHT["bands"]
    assert len(read_records(ahead)) == 4
    # cube 2's data file touched since it was encoded: its chunks may be stale, so they are written again
    st = os.stat(cubes[2].data)
    os.utime(cubes[2].data, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000))

    (plain,) = ingest([str(flight)], tmp_path / "plain", FOV, progress=False)
    (mine,) = ingest([str(flight)], tmp_path / "mine", FOV, progress=False, prewritten=ahead)
    assert mine.cid == plain.cid and mine.status == "ingested"
    left = {k for k in range(6) for b in range(FLIGHT["bands"]) if chunk_path(ahead, b, k).exists()}
    assert left == {2, 5}   # the touched cube and the one in the wrong place stay; cubes 0 and 3 moved in
    _same_store(mine.store, plain.store)
    assert verify_store(mine.store) == []


def test_prewritten_is_refused_on_a_cluster(flight, tmp_path):
    from archive.errors import InputError
    from archive.ingest.command import ingest

    with pytest.raises(InputError, match="--prewritten"):
        ingest([str(flight)], tmp_path / "a", FOV, progress=False, prewritten=tmp_path, workers=2)
