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
