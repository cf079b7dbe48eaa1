"""The ENVI cube reader without memory maps (``archive.formats.pread``): the same values as a
``np.memmap`` of the file for every interleave, byte order and data type, for any band selection
(order, repeats, gaps, whole cube), across staging blocks; no file left open and no mapping of it."""

from __future__ import annotations

import os
import pickle
from pathlib import Path

import numpy as np
import pytest

from archive.errors import FormatError
from archive.formats import pread
from archive.formats.envi import EnviCube, write_envi

SELECTIONS = [[0], [5], [2, 3, 4, 5], [5, 4, 3], [1, 1, 6, 1], [0, 7, 13], [12, 0, 6, 3, 9],
              list(range(14)), [13, 2, 2, 8, 9, 10]]


def _memmap_bands(cube: EnviCube, idx) -> np.ndarray:
    """What the reader did before: map the file, view it as (band, line, sample), copy the bands."""
    h = cube.header
    file_shape = {"bsq": (h.bands, h.lines, h.samples), "bil": (h.lines, h.bands, h.samples),
                  "bip": (h.lines, h.samples, h.bands)}[h.interleave]
    mm = np.memmap(cube.path, dtype=h.dtype, mode="r", offset=h.header_offset, shape=file_shape)
    order = {"bsq": (0, 1, 2), "bil": (1, 0, 2), "bip": (2, 0, 1)}[h.interleave]
    view = mm.transpose(order)
    out = np.stack([np.ascontiguousarray(view[b], dtype=h.dtype.newbyteorder("=")) for b in idx])
    del view, mm
    return out


def _data(dtype: str, shape=(14, 9, 11), seed=3) -> np.ndarray:
    rng = np.random.default_rng(seed)
    if np.dtype(dtype).kind == "f":
        data = rng.normal(0, 1000, shape).astype(dtype)
        data.flat[::17] = np.nan
        return data
    info = np.iinfo(dtype)
    return rng.integers(info.min, info.max, shape, endpoint=True).astype(dtype)


def _open_fds_on(path: Path) -> list[str]:
    fds = []
    for fd in os.listdir("/proc/self/fd"):
        try:
            if os.readlink(f"/proc/self/fd/{fd}") == str(path):
                fds.append(fd)
        except OSError:
            pass
    return fds


def _mapped(path: Path) -> bool:
    return str(path) in Path("/proc/self/maps").read_text()


@pytest.mark.parametrize("interleave", ["bil", "bip", "bsq"])
@pytest.mark.parametrize("dtype", ["uint16", "int16", "int32", "uint32", "float32", "float64", "uint8"])
@pytest.mark.parametrize("byte_order", [0, 1])
@pytest.mark.parametrize("stage", [None, 1])
def test_same_values_as_the_memory_map(tmp_path, monkeypatch, interleave, dtype, byte_order, stage):
    if stage is not None:   # one line (or less) per staging block: every block boundary exercised
        monkeypatch.setattr(pread, "STAGE_BYTES", stage)
    data = _data(dtype)
    path = write_envi(tmp_path / f"c.{interleave}", data, interleave=interleave, byte_order=byte_order,
                      header_offset=96)
    cube = EnviCube(path)
    for idx in SELECTIONS:
        got = cube.bands(idx)
        want = _memmap_bands(cube, idx)
        assert got.dtype == np.dtype(dtype) and got.dtype.isnative and got.flags.c_contiguous
        assert got.shape == (len(idx), 9, 11)
        assert got.tobytes() == want.tobytes()          # bit for bit, NaN payloads included
        assert got.tobytes() == data[idx].tobytes()
    assert cube.read().tobytes() == data.tobytes()
    for b in (0, 6, 13):
        assert cube.band(b).tobytes() == data[b].tobytes()


@pytest.mark.parametrize("gap", [0, 10**9])
def test_bil_segments_merge_or_split_alike(tmp_path, monkeypatch, gap):
    # gaps read through (one call per line for [0, 13]) or skipped (a call per band): same values
    monkeypatch.setattr(pread, "GAP_BYTES", gap)
    data = _data("uint16")
    cube = EnviCube(write_envi(tmp_path / "g.bil", data, interleave="bil"))
    for idx in SELECTIONS:
        np.testing.assert_array_equal(cube.bands(idx), data[idx])


def test_segments():
    assert pread._segments([1, 2, 3, 7], per_band=pread.GAP_BYTES // 2) == [(1, 4), (7, 8)]
    assert pread._segments([1, 2, 3, 6], per_band=pread.GAP_BYTES // 2) == [(1, 7)]
    assert pread._segments([4], per_band=1) == [(4, 5)]


@pytest.mark.parametrize("interleave", ["bil", "bip", "bsq"])
def test_no_file_left_open_or_mapped(tmp_path, interleave):
    data = _data("uint16")
    path = write_envi(tmp_path / f"o.{interleave}", data, interleave=interleave)
    cube = EnviCube(path)
    arrays = [cube.bands([3, 4, 5]), cube.band(2), cube.read()]   # results kept alive while we look
    assert not _open_fds_on(path) and not _mapped(path)
    clone = pickle.loads(pickle.dumps(cube))
    np.testing.assert_array_equal(clone.bands([3, 4, 5]), arrays[0])
    assert not _open_fds_on(path) and not _mapped(path)
    for a in arrays:   # own memory, not a view of a file
        assert a.base is None or not isinstance(a.base, np.memmap)


def test_file_truncated_after_opening_says_so(tmp_path):
    data = _data("uint16")
    path = write_envi(tmp_path / "t.bil", data, interleave="bil")
    cube = EnviCube(path)
    os.truncate(path, path.stat().st_size // 2)
    with pytest.raises(FormatError, match=r"t\.bil: data file ended at byte"):
        cube.bands([12, 13])
    assert not _open_fds_on(path)


def _evict(path: Path, start: int = 0, length: int = 0) -> None:
    """Drop the file's pages (all, or ``length`` bytes from ``start``) from the page cache, as the
    kernel does to pages nobody touched (written back first: dirty pages are not dropped)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
        os.posix_fadvise(fd, start, length, os.POSIX_FADV_DONTNEED)
    finally:
        os.close(fd)


def _nowait_refused(path: Path) -> bool:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.preadv(fd, [bytearray(1)], 0, os.RWF_NOWAIT)
    except BlockingIOError:
        return False
    except OSError:
        return True
    finally:
        os.close(fd)
    return False


@pytest.mark.parametrize("evicted", ["all", "middle"])
def test_bil_lines_not_in_the_page_cache_are_asked_together(tmp_path, monkeypatch, evicted):
    """A BIL cube whose pages left the page cache (all of them, or a range cutting lines in two):
    the lines the cache lacks are asked of the disk together (one WILLNEED each, for the part not
    read yet) before any is read whole, and the values are the file's bit for bit."""
    data = _data("uint16", shape=(64, 300, 128))   # 16 KiB lines: many pages, several staging blocks
    path = write_envi(tmp_path / "cold.bil", data, interleave="bil", header_offset=96)
    if not hasattr(os, "RWF_NOWAIT") or _nowait_refused(path):
        pytest.skip(f"{tmp_path}: the file system reads only blocking (RWF_NOWAIT refused)")
    monkeypatch.setattr(pread, "STAGE_BYTES", 100 * 10 * 128 * 2)   # 100 lines of 10 bands per block
    cube = EnviCube(path)
    record = 64 * 128 * 2
    advised: list[tuple[int, int]] = []
    fadvise = os.posix_fadvise

    def spy(fd, offset, length, advice):
        if advice == os.POSIX_FADV_WILLNEED:
            advised.append((offset, length))
        return fadvise(fd, offset, length, advice)

    monkeypatch.setattr(os, "posix_fadvise", spy)
    if evicted == "all":
        _evict(path)
    else:   # bytes 0.5-4.5 MiB of 4.9 (lines 31-288): the page cache's folios wholly inside go,
        _evict(path, 1 << 19, 1 << 22)   # at least the 2 MiB-aligned one (folios are 2 MiB at most)
    got = cube.bands(list(range(20, 30)))
    assert got.tobytes() == data[20:30].tobytes()
    segment = 96 + 20 * 128 * 2   # where bands 20-29 start in line 0
    if evicted == "all":   # every line asked, whole
        assert sorted(advised) == [(segment + i * record, 10 * 128 * 2) for i in range(300)]
    else:   # some lines of the evicted range, each from where the page cache's part of it ended
        lines = sorted({(off - segment) // record for off, _ in advised})
        assert lines and 31 <= lines[0] and lines[-1] <= 288, lines
        assert all(0 < length <= 10 * 128 * 2 and off + length == segment + (off - segment) // record * record
                   + 10 * 128 * 2 for off, length in advised)


def test_bil_on_a_file_system_without_rwf_nowait(tmp_path):
    """tmpfs refuses RWF_NOWAIT (EOPNOTSUPP): the lines are read one by one, the values the file's."""
    shm = Path("/dev/shm")
    if not shm.is_dir() or not os.access(shm, os.W_OK):
        pytest.skip("no writable /dev/shm")
    data = _data("int16", shape=(20, 40, 16))
    folder = shm / f"archive-test-{os.getpid()}-{tmp_path.name}"
    folder.mkdir()
    try:
        path = write_envi(folder / "t.bil", data, interleave="bil")
        assert _nowait_refused(path)
        for idx in SELECTIONS:
            assert EnviCube(path).bands(idx).tobytes() == data[idx].tobytes()
    finally:
        import shutil

        shutil.rmtree(folder)
