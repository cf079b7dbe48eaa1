"""Flight sources: one shared suite for every implementation, plus raw-directory specifics."""

from __future__ import annotations

import pickle
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from archive.errors import InputError, MissingInputError, NavigationError
from archive.formats.envi import EnviCube
from archive.formats.icp import read_icp, response
from archive.params import NavigationParams
from archive.sources import (
    MODES,
    CubeInfo,
    FlightSource,
    MemoryFlightSource,
    Radiometry,
    RawFlightSource,
    open_source,
)

SIM_ARGS = ["--cubes", "2", "--lines", "40", "--samples", "24", "--bands", "5", "--quiet"]
PARAMS = NavigationParams(fov_deg=47.5)


@pytest.fixture(scope="module")
def flight(tmp_path_factory) -> Path:
    directory = tmp_path_factory.mktemp("source") / "flight"
    done = subprocess.run([sys.executable, "-m", "archive", "simulate", str(directory), *SIM_ARGS],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    return directory


@pytest.fixture(scope="module")
def raw(flight) -> RawFlightSource:
    return RawFlightSource(flight, PARAMS)


@pytest.fixture(scope="module")
def memory(raw) -> MemoryFlightSource:
    """The same flight held in memory (dark/gain of the calibration, responses of each cube)."""
    nb = raw.cubes[0].bands
    all_bands = list(range(nb))
    rad = [raw.radiometry(i, all_bands, "radiance") for i in range(len(raw.cubes))]
    return MemoryFlightSource(
        [raw.read_bands(i, all_bands) for i in range(len(raw.cubes))],
        [raw.poses(i) for i in range(len(raw.cubes))],
        id="memory-flight", wavelengths=raw.wavelengths, dark=rad[0].dark, gain=rad[0].gain,
        responses=[r.response for r in rad], bit_depth=raw.cubes[0].bit_depth,
        white_reference=np.linspace(100.0, 200.0, nb))


@pytest.fixture(params=["raw", "memory"])
def source(request) -> FlightSource:
    return request.getfixturevalue(request.param)


# --- the shared suite ---------------------------------------------------------------------------

def test_protocol_and_cubes(source):
    assert isinstance(source, FlightSource)
    assert re.fullmatch(r"[A-Za-z0-9._-]+", source.id)
    assert len(source.cubes) == 2
    for i, info in enumerate(source.cubes):
        assert isinstance(info, CubeInfo) and info.index == i
        assert (info.lines, info.samples, info.bands) == (40, 24, 5)
    assert source.cubes[0].first_time < source.cubes[1].first_time
    assert source.wavelengths is not None and len(source.wavelengths) == 5


def test_poses(source):
    for info in source.cubes:
        poses = source.poses(info.index)
        assert poses.position.shape == (info.lines, 3) and len(poses.attitude) == info.lines
        assert poses.frame == source.frame
        assert poses.time[0] == pytest.approx(info.first_time, abs=1e-6)
        assert np.all(np.diff(poses.time) > 0)
        # the simulator flies ~40 m above flat ground at ~10 m/s, 249 lines/s
        step = np.linalg.norm(np.diff(poses.position[:, :2], axis=0), axis=1)
        assert np.all((step > 0.03) & (step < 0.05))
    # a delay of a whole line period lands on the next line's pose
    p = source.poses(0)
    dt = float(p.time[1] - p.time[0])
    later = source.poses(0, delay=dt)
    np.testing.assert_allclose(later.position[:-1], p.position[1:], atol=2e-3)
    assert np.all((p.attitude[1:].inv() * later.attitude[:-1]).magnitude() < np.radians(0.01))


def test_read_bands(source):
    data = source.read_bands(1, [4, 0])
    assert data.shape == (2, 40, 24)
    assert data.dtype == np.uint16
    both = source.read_bands(1, [0, 4])
    np.testing.assert_array_equal(data[::-1], both)
    assert data.max() > 0
    with pytest.raises(InputError, match="band 5"):
        source.read_bands(0, [5])
    with pytest.raises(InputError, match="cube 2"):
        source.read_bands(2, [0])


def test_radiometry_modes(source):
    bands = [3, 1]
    raw = source.radiometry(0, bands, "raw")
    assert isinstance(raw, Radiometry)
    assert raw.dark.shape == raw.gain.shape == (2, 24) and raw.response.shape == (40,)
    assert raw.dark.dtype == raw.gain.dtype == raw.response.dtype == np.float32
    assert np.all(raw.dark == 0) and np.all(raw.gain == 1) and np.all(raw.response == 1)
    assert raw.saturation == 4095.0
    rel = source.radiometry(0, bands, "relative")
    assert np.all(rel.gain == 1) and np.all(rel.response > 0)
    rad = source.radiometry(0, bands, "radiance")
    assert rad.gain.shape == (2, 24) and np.all(rad.gain > 0) and np.all(rad.dark >= 0)
    full = source.radiometry(0, [1, 3], "radiance")
    np.testing.assert_array_equal(full.gain[::-1], rad.gain)
    white = np.linspace(100.0, 200.0, 5)
    refl = source.radiometry(0, bands, "reflectance", white_reference=white)
    np.testing.assert_allclose(refl.gain, rad.gain / white[bands][:, None], rtol=1e-6)
    np.testing.assert_array_equal(refl.dark, rad.dark)
    with pytest.raises(InputError, match="white reference has 3 values for 5 bands"):
        source.radiometry(0, bands, "reflectance", white_reference=np.ones(3))
    with pytest.raises(InputError, match="unknown radiometric mode"):
        source.radiometry(0, bands, "dn")
    assert set(MODES) == {"raw", "relative", "radiance", "reflectance"}


def test_pickle_round_trip(source):
    copy = pickle.loads(pickle.dumps(source))
    assert copy.id == source.id and copy.frame == source.frame and copy.cubes == source.cubes
    np.testing.assert_array_equal(copy.read_bands(1, [2]), source.read_bands(1, [2]))
    np.testing.assert_array_equal(copy.poses(1).position, source.poses(1).position)
    a = copy.radiometry(1, [0, 2], "radiance")
    b = source.radiometry(1, [0, 2], "radiance")
    np.testing.assert_array_equal(a.gain, b.gain)
    np.testing.assert_array_equal(a.response, b.response)


# --- raw directories ----------------------------------------------------------------------------

def test_raw_reads_equal_the_bil(raw, flight):
    for i, info in enumerate(raw.cubes):
        cube = EnviCube(flight / f"{info.base}.bil")
        np.testing.assert_array_equal(raw.read_bands(i, [0, 2, 4]), cube.read()[[0, 2, 4]])
        assert info.framerate == cube.header.framerate and info.shutter_ms == cube.header.shutter
        assert info.gain_db == cube.header.gain and info.wavelengths == cube.header.wavelengths


def test_raw_radiometry_values(raw, flight):
    cal = read_icp(next(flight.glob("*.icp")))
    header = raw.header(1)
    dark, gain = cal.for_cube(header)
    rad = raw.radiometry(1, [0, 4], "radiance")
    np.testing.assert_allclose(rad.dark, dark[[0, 4]], rtol=1e-6)
    np.testing.assert_allclose(rad.gain, gain[[0, 4]], rtol=1e-6)
    expected = response(header.shutter, header.gain, cal.shutter_cal, cal.gain_cal)
    np.testing.assert_allclose(rad.response, expected, rtol=1e-6)
    rel = raw.radiometry(1, [0, 4], "relative")
    np.testing.assert_allclose(rel.dark, dark[[0, 4]], rtol=1e-6)
    np.testing.assert_allclose(rel.response, header.shutter * 10 ** (header.gain / 20), rtol=1e-6)
    with pytest.raises(InputError, match="white reference"):
        raw.radiometry(1, [0], "reflectance")
    with_white = RawFlightSource(flight, PARAMS, white_reference=np.full(5, 50.0))
    np.testing.assert_allclose(with_white.radiometry(1, [0, 4], "reflectance").gain, rad.gain / 50.0, rtol=1e-6)


def test_raw_without_calibration(flight, tmp_path):
    copy = tmp_path / "nocal"
    shutil.copytree(flight, copy)
    for icp in copy.glob("*.icp"):
        icp.unlink()
    src = RawFlightSource(copy, PARAMS)
    assert src.calibration() is None
    rel = src.radiometry(0, [0], "relative")
    assert np.all(rel.dark == 0)
    with pytest.raises(InputError, match="--calibration") as info:
        src.radiometry(0, [0], "radiance")
    assert "--mode raw" in str(info.value)
    # an explicit calibration file elsewhere
    explicit = RawFlightSource(copy, PARAMS, calibration=next(flight.glob("*.icp")))
    assert explicit.radiometry(0, [0], "radiance").gain.mean() > 0
    with pytest.raises(MissingInputError):
        RawFlightSource(copy, PARAMS, calibration=tmp_path / "none.icp")


def test_open_source(flight, tmp_path):
    src = open_source(flight, PARAMS)
    assert isinstance(src, RawFlightSource) and src.id.startswith("flight-")
    with pytest.raises(MissingInputError, match="nothing_here"):
        open_source(tmp_path / "nothing_here", PARAMS)


def test_raw_sync_offset_and_lever_arm(raw, flight):
    shifted = RawFlightSource(flight, NavigationParams(fov_deg=47.5, sync_offset=0.008))
    assert shifted.cubes[0].first_time == pytest.approx(raw.cubes[0].first_time + 0.008)
    np.testing.assert_allclose(shifted.poses(0).position[:-2], raw.poses(0).position[2:], atol=2e-3)
    levered = RawFlightSource(flight, NavigationParams(fov_deg=47.5, lever_arm_m=(0.0, 0.0, 1.0)))
    # 1 m down in the body: ~1 m lower (D larger), tilted by the few degrees of roll/pitch
    delta = levered.poses(0).position - raw.poses(0).position
    np.testing.assert_allclose(np.linalg.norm(delta, axis=1), 1.0, atol=1e-9)
    assert np.all(delta[:, 2] > 0.99)
    with pytest.raises(NavigationError, match=r"\.lcf"):
        RawFlightSource(flight, NavigationParams(fov_deg=47.5, sync_offset=1.0))
