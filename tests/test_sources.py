"""Flight sources: ONE conformance suite run against every implementation of the same simulated
flight, then what is particular to each.

- ``raw``: :class:`RawFlightSource` on the flight directory;
- ``collection``: the flight ingested (``archive.ingest.command.ingest``) and opened by id with
  :func:`open_source`;
- ``memory``: :class:`MemoryFlightSource` built from the raw source's arrays, poses and radiometry.

Every source must give the same content (cubes, headers, wavelengths, line times, poses, pixels,
radiometry) and, for the same defect, the same error (type, problem and fix; only the place named
differs, and it names the source). Poses are compared to 1e-9 m and 1e-12 rad; the memory source
holds given poses, so only they (not navigation-derived behaviour) are compared for it.
"""

from __future__ import annotations

import dataclasses
import pickle
import re
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from dask.base import tokenize

from archive.errors import ArchiveError, InputError, MissingInputError, NavigationError
from archive.formats.envi import EnviCube
from archive.formats.icp import read_icp, response
from archive.ingest.command import ingest
from archive.params import NavigationParams
from archive.simulator.command import simulate_flight
from archive.sources import (
    MODES,
    CollectionSource,
    CubeInfo,
    FlightSource,
    MemoryFlightSource,
    Radiometry,
    RawFlightSource,
    open_source,
)
from helpers import FOV

CUBES, BANDS, SAMPLES, LINES = 2, 4, 48, 80
PARAMS = NavigationParams()
WHITE = np.linspace(100.0, 200.0, BANDS)
KINDS = ("raw", "collection", "memory")
NAVIGATED = ("raw", "collection")  # the sources that compute poses from the flight's navigation
POSITION_ATOL = 1e-9   # m
ANGLE_ATOL = 1e-12     # rad


@dataclasses.dataclass(frozen=True)
class Flight:
    directory: Path
    archive: Path
    cid: str
    ground_height: float


@pytest.fixture(scope="module")
def flight(tmp_path_factory) -> Flight:
    root = tmp_path_factory.mktemp("sources")
    truth = simulate_flight(root / "flight", cubes=CUBES, bands=BANDS, samples=SAMPLES, lines=LINES)
    (result,) = ingest([str(root / "flight")], root / "archive", FOV, progress=False)
    assert result.status == "ingested"
    return Flight(root / "flight", root / "archive", result.cid, truth.ground_height)


def memory_from(raw: RawFlightSource, white: np.ndarray | None = None) -> MemoryFlightSource:
    """The raw flight held in memory: its DN, poses, wavelengths, bit depth and frame rate, the
    dark/gain of its calibration (cube 0's dark: the memory source has one for all cubes) and the
    radiance responses of each cube."""
    all_bands = list(range(BANDS))
    rad = [raw.radiometry(i, all_bands, "radiance") for i in range(len(raw.cubes))]
    return MemoryFlightSource(
        [raw.read_bands(i, all_bands) for i in range(len(raw.cubes))],
        [raw.poses(i) for i in range(len(raw.cubes))],
        id="memory-flight", wavelengths=raw.wavelengths, fwhm=raw.fwhm, dark=rad[0].dark, gain=rad[0].gain,
        responses=[r.response for r in rad], bit_depth=raw.cubes[0].bit_depth,
        framerate=raw.cubes[0].framerate, white_reference=white)


def open_kind(kind: str, flight: Flight, params: NavigationParams = PARAMS,
              white: np.ndarray | None = None) -> FlightSource:
    if kind == "raw":
        return RawFlightSource(flight.directory, params, white_reference=white)
    if kind == "collection":
        return open_source(flight.cid, params, archive=flight.archive, white_reference=white)
    if kind == "memory":
        return memory_from(RawFlightSource(flight.directory, params), white)
    raise ValueError(kind)


@pytest.fixture(scope="module")
def sources(flight) -> dict[str, FlightSource]:
    return {kind: open_kind(kind, flight) for kind in KINDS}


@pytest.fixture(params=KINDS)
def kind(request) -> str:
    return request.param


@pytest.fixture
def source(sources, kind) -> FlightSource:
    return sources[kind]


@pytest.fixture
def raw(sources) -> RawFlightSource:
    return sources["raw"]


def assert_same_poses(a, b, position_atol: float = POSITION_ATOL, angle_atol: float = ANGLE_ATOL) -> None:
    """Same line times, positions (m), attitudes (rotation angle between them, rad), frame and valid mask."""
    np.testing.assert_array_equal(a.time, b.time)
    np.testing.assert_allclose(a.position, b.position, rtol=0, atol=position_atol)
    assert len(a.attitude) == len(b.attitude)
    assert np.max((a.attitude.inv() * b.attitude).magnitude()) <= angle_atol
    assert a.frame == b.frame
    assert (a.valid is None) == (b.valid is None)
    if a.valid is not None:
        np.testing.assert_array_equal(a.valid, b.valid)


def outcome(call: Callable[[], object]) -> tuple:
    """('ok', result) or ('error', type, problem, fix) of an ArchiveError (the place it names aside)."""
    try:
        return ("ok", call())
    except ArchiveError as exc:
        return ("error", type(exc), getattr(exc, "problem", str(exc)), getattr(exc, "fix", None), str(exc))


# --- the shared suite: every source on its own ----------------------------------------------------

def test_protocol_and_cubes(source, kind, flight):
    assert isinstance(source, FlightSource)
    assert re.fullmatch(r"[A-Za-z0-9._-]+", source.id)
    assert isinstance(source.label, str) and source.label
    assert len(source.cubes) == CUBES
    for i, info in enumerate(source.cubes):
        assert isinstance(info, CubeInfo) and info.index == i
        assert (info.lines, info.samples, info.bands) == (LINES, SAMPLES, BANDS)
    assert source.cubes[0].first_time < source.cubes[1].first_time
    assert source.wavelengths is not None and len(source.wavelengths) == BANDS
    assert source.fwhm is not None and len(source.fwhm) == BANDS
    assert source.has_calibration and source.white_reference is None
    if kind in NAVIGATED:  # the memory source's poses are given: its params change nothing
        assert source.params == PARAMS
    recorded = {"raw": (None, None), "collection": (FOV, flight.ground_height), "memory": (None, None)}[kind]
    assert (source.fov_deg, source.ground_height) == recorded


def test_poses(source):
    for info in source.cubes:
        poses = source.poses(info.index)
        assert poses.position.shape == (info.lines, 3) and len(poses.attitude) == info.lines
        assert poses.frame == source.frame
        assert poses.valid is None  # sync offset 0: navigation covers every line
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
    data = source.read_bands(1, [3, 0])
    assert data.shape == (2, LINES, SAMPLES)
    assert data.dtype == np.uint16
    both = source.read_bands(1, [0, 3])
    np.testing.assert_array_equal(data[::-1], both)
    assert data.max() > 0
    assert source.read_bands(0, []).shape == (0, LINES, SAMPLES)
    with pytest.raises(InputError, match=f"band {BANDS}"):
        source.read_bands(0, [BANDS])
    with pytest.raises(InputError, match=f"cube {CUBES}"):
        source.read_bands(CUBES, [0])


def test_radiometry_modes(source):
    bands = [3, 1]
    raw = source.radiometry(0, bands, "raw")
    assert isinstance(raw, Radiometry)
    assert raw.dark.shape == raw.gain.shape == (2, SAMPLES) and raw.response.shape == (LINES,)
    assert raw.dark.dtype == raw.gain.dtype == raw.response.dtype == np.float32
    assert np.all(raw.dark == 0) and np.all(raw.gain == 1) and np.all(raw.response == 1)
    assert raw.saturation == 4095.0
    rel = source.radiometry(0, bands, "relative")
    assert np.all(rel.gain == 1) and np.all(rel.response > 0)
    rad = source.radiometry(0, bands, "radiance")
    assert rad.gain.shape == (2, SAMPLES) and np.all(rad.gain > 0) and np.all(rad.dark >= 0)
    full = source.radiometry(0, [1, 3], "radiance")
    np.testing.assert_array_equal(full.gain[::-1], rad.gain)
    refl = source.radiometry(0, bands, "reflectance", white_reference=WHITE)
    np.testing.assert_allclose(refl.gain, rad.gain / WHITE[bands][:, None], rtol=1e-6)
    np.testing.assert_array_equal(refl.dark, rad.dark)
    np.testing.assert_array_equal(refl.response, rad.response)
    with pytest.raises(InputError, match=f"white reference has 3 values for {BANDS} bands"):
        source.radiometry(0, bands, "reflectance", white_reference=np.ones(3))
    with pytest.raises(InputError, match="unknown radiometric mode"):
        source.radiometry(0, bands, "dn")
    assert set(MODES) == {"raw", "relative", "radiance", "reflectance"}


def test_source_white_reference(flight, kind):
    """A white reference given when opening is the one 'reflectance' uses by default."""
    with_white = open_kind(kind, flight, white=np.full(BANDS, 50.0))
    rad = with_white.radiometry(1, [0, 3], "radiance")
    np.testing.assert_allclose(with_white.radiometry(1, [0, 3], "reflectance").gain, rad.gain / 50.0, rtol=1e-6)
    # one given to the call wins
    np.testing.assert_allclose(with_white.radiometry(1, [0, 3], "reflectance", WHITE).gain,
                               rad.gain / WHITE[[0, 3]][:, None], rtol=1e-6)


def test_tokenize_is_deterministic(source, kind, flight):
    assert tokenize(source) == tokenize(source)
    assert tokenize(source) == tokenize(open_kind(kind, flight))  # the same flight opened again
    assert tokenize(source) != tokenize(open_kind(kind, flight, white=WHITE))  # what reflectance depends on


@pytest.mark.parametrize("kind", NAVIGATED)
def test_tokenize_depends_on_the_sync_offset(flight, kind):
    shifted = open_kind(kind, flight, NavigationParams(sync_offset=0.008))
    again = open_kind(kind, flight, NavigationParams(sync_offset=0.008))
    base = open_kind(kind, flight)
    assert tokenize(shifted) == tokenize(again)
    assert tokenize(shifted) != tokenize(base)
    assert tokenize(open_kind(kind, flight, NavigationParams(sync_offset=0.15))) != tokenize(shifted)


def test_pickle_round_trip(source):
    copy = pickle.loads(pickle.dumps(source))
    assert copy.id == source.id and copy.frame == source.frame and copy.cubes == source.cubes
    assert copy.label == source.label and copy.wavelengths == source.wavelengths
    assert tokenize(copy) == tokenize(source)
    np.testing.assert_array_equal(copy.read_bands(1, [2]), source.read_bands(1, [2]))
    np.testing.assert_array_equal(copy.line_times(1), source.line_times(1))
    np.testing.assert_array_equal(copy.poses(1).position, source.poses(1).position)
    a = copy.radiometry(1, [0, 2], "radiance")
    b = source.radiometry(1, [0, 2], "radiance")
    np.testing.assert_array_equal(a.gain, b.gain)
    np.testing.assert_array_equal(a.response, b.response)


# --- the shared suite: every source against the raw flight ----------------------------------------

def test_same_cubes_and_wavelengths(source, kind, raw):
    assert source.frame == raw.frame
    assert source.wavelengths == raw.wavelengths and source.fwhm == raw.fwhm
    for mine, theirs in zip(source.cubes, raw.cubes, strict=True):
        if kind == "memory":  # named after the source; one exposure for all cubes (none given here)
            theirs = dataclasses.replace(theirs, base=mine.base, shutter_ms=None, gain_db=None)
        assert mine == theirs


def test_same_headers(source, kind, raw):
    for i in range(CUBES):
        mine, theirs = source.header(i), raw.header(i)
        assert (mine.samples, mine.lines, mine.bands) == (theirs.samples, theirs.lines, theirs.bands)
        assert mine.dtype.newbyteorder("=") == theirs.dtype.newbyteorder("=")
        assert mine.wavelengths == theirs.wavelengths and mine.bit_depth == theirs.bit_depth
        assert mine.fwhm == theirs.fwhm
        if kind == "collection":  # every key, as ingested
            assert mine.metadata == theirs.metadata
            assert (mine.shutter, mine.gain, mine.framerate) == (theirs.shutter, theirs.gain, theirs.framerate)


def test_same_line_times_and_poses(source, kind, raw):
    for i in range(CUBES):
        np.testing.assert_array_equal(source.line_times(i), raw.line_times(i))
        assert_same_poses(source.poses(i), raw.poses(i))
        if kind in NAVIGATED:
            # mid-exposure poses, and the INS samples themselves
            half = raw.cubes[i].shutter_ms / 2000.0
            assert_same_poses(source.poses(i, delay=half), raw.poses(i, delay=half))
            mine, theirs = source.track(i), raw.track(i)
            np.testing.assert_array_equal(mine.time, theirs.time)
            np.testing.assert_allclose(mine.position, theirs.position, rtol=0, atol=POSITION_ATOL)
            assert np.max((mine.attitude.inv() * theirs.attitude).magnitude()) <= ANGLE_ATOL


def test_same_pixels(source, raw):
    everything = list(range(BANDS))
    for i in range(CUBES):
        np.testing.assert_array_equal(source.read_bands(i, everything), raw.read_bands(i, everything))
        np.testing.assert_array_equal(source.read_bands(i, [2, 2, 0]), raw.read_bands(i, [2, 2, 0]))


@pytest.mark.parametrize("mode", MODES)
def test_same_radiometry(source, kind, raw, mode):
    bands = [3, 0, 2]
    for i in range(CUBES):
        mine = source.radiometry(i, bands, mode, white_reference=WHITE)
        theirs = raw.radiometry(i, bands, mode, white_reference=WHITE)
        assert mine.saturation == theirs.saturation
        if kind == "memory" and mode == "relative":
            # the memory source has one set of responses (here the radiance ones) for every mode
            np.testing.assert_array_equal(mine.dark, raw.radiometry(0, bands, mode).dark)
            np.testing.assert_array_equal(mine.gain, theirs.gain)
            continue
        if kind == "memory" and mode != "raw" and i > 0:
            # one dark for all cubes (cube 0's), where the calibration matches each cube's exposure
            np.testing.assert_array_equal(mine.gain, theirs.gain)
            np.testing.assert_array_equal(mine.response, theirs.response)
            continue
        np.testing.assert_array_equal(mine.dark, theirs.dark)
        np.testing.assert_array_equal(mine.gain, theirs.gain)
        np.testing.assert_array_equal(mine.response, theirs.response)


# --- the same errors for the same defects ---------------------------------------------------------

DEFECTS: dict[str, Callable[[FlightSource], object]] = {
    "cube out of range: line_times": lambda s: s.line_times(CUBES),
    "cube out of range: poses": lambda s: s.poses(CUBES),
    "cube out of range: track": lambda s: s.track(CUBES),
    "cube out of range: header": lambda s: s.header(CUBES),
    "cube out of range: read_bands": lambda s: s.read_bands(CUBES, [0]),
    "cube out of range: radiometry": lambda s: s.radiometry(CUBES, [0], "raw"),
    "negative cube": lambda s: s.read_bands(-1, [0]),
    "cube given as a bool": lambda s: s.poses(True),
    "cube given as a float": lambda s: s.line_times(1.0),
    "band out of range: read_bands": lambda s: s.read_bands(0, [0, BANDS]),
    "negative band: read_bands": lambda s: s.read_bands(1, [-1]),
    "band out of range: radiometry": lambda s: s.radiometry(0, [BANDS], "radiance"),
    "band given as a bool": lambda s: s.radiometry(1, [True], "raw"),
    "unknown mode": lambda s: s.radiometry(0, [0], "dn"),
    "reflectance without white reference": lambda s: s.radiometry(0, [0], "reflectance"),
    "white reference of the wrong length": lambda s: s.radiometry(0, [0], "reflectance", np.ones(BANDS + 1)),
    "white reference with a zero": lambda s: s.radiometry(0, [1], "reflectance", np.array([1.0, 0.0, 1.0, 1.0])),
}


@pytest.mark.parametrize("defect", list(DEFECTS))
def test_same_errors(sources, defect):
    results = {kind: outcome(lambda: DEFECTS[defect](s)) for kind, s in sources.items()}
    for kind, result in results.items():
        assert result[0] == "error", f"{kind}: no error for {defect}"
        assert issubclass(result[1], InputError), result
    first = results["raw"][1:4]
    assert all(r[1:4] == first for r in results.values()), results
    # the message names the flight (or the file of it)
    for kind, result in results.items():
        if defect not in ("unknown mode",):
            assert sources[kind].label in result[4] or sources[kind].id in result[4], (kind, result[4])


def test_numpy_indices_are_accepted(source):
    np.testing.assert_array_equal(source.read_bands(np.int64(1), [np.int32(2)]), source.read_bands(1, [2]))
    np.testing.assert_array_equal(source.line_times(np.int64(0)), source.line_times(0))


@pytest.mark.parametrize("offset", [0.15, 1.0, -0.15, 0.008, -1.0])
def test_sync_offset_same_from_raw_and_collection(flight, offset):
    """A flight opened with a sync offset behaves the same from its directory and its collection:
    the same poses (valid mask included) or the same error."""
    params = NavigationParams(sync_offset=offset)

    def poses_of(kind):
        src = open_kind(kind, flight, params)
        return src, [src.poses(i) for i in range(CUBES)]

    raw, coll = outcome(lambda: poses_of("raw")), outcome(lambda: poses_of("collection"))
    assert raw[0] == coll[0], (raw, coll)
    if raw[0] == "error":
        assert raw[1:4] == coll[1:4]
        assert raw[1] is NavigationError
        assert ".lcf" in raw[4] and "sim_Pika_L_" in coll[4]  # the raw file, the stored cube
        assert abs(offset) >= 0.5
        return
    (raw_src, raw_poses), (coll_src, coll_poses) = raw[1], coll[1]
    assert raw_src.cubes == coll_src.cubes
    for i, (a, b) in enumerate(zip(raw_poses, coll_poses, strict=True)):
        np.testing.assert_array_equal(raw_src.line_times(i), coll_src.line_times(i))
        assert_same_poses(a, b)
    valid = [p.valid for p in raw_poses]
    if offset == 0.15:  # the last lines lie beyond the end of the navigation: flagged, not an error
        assert valid[0] is None and valid[1] is not None and 0 < valid[1].sum() < LINES and not valid[1][-1]
    if offset == -0.15:  # the first lines lie before its start
        assert valid[1] is None and valid[0] is not None and 0 < valid[0].sum() < LINES and not valid[0][0]
    if offset == 0.008:
        assert valid == [None, None]


@pytest.mark.parametrize("kind", NAVIGATED)
def test_sync_offset_and_lever_arm(flight, sources, kind):
    base = sources[kind]
    shifted = open_kind(kind, flight, NavigationParams(sync_offset=0.008))
    assert shifted.cubes[0].first_time == pytest.approx(base.cubes[0].first_time + 0.008)
    np.testing.assert_allclose(shifted.poses(0).position[:-2], base.poses(0).position[2:], atol=2e-3)
    levered = open_kind(kind, flight, NavigationParams(lever_arm_m=(0.0, 0.0, 1.0)))
    # 1 m down in the body: ~1 m lower (D larger), tilted by the few degrees of roll/pitch
    delta = levered.poses(0).position - base.poses(0).position
    np.testing.assert_allclose(np.linalg.norm(delta, axis=1), 1.0, atol=1e-9)
    assert np.all(delta[:, 2] > 0.99)
    with pytest.raises(NavigationError, match=r"\.lcf" if kind == "raw" else "sim_Pika_L_1"):
        open_kind(kind, flight, NavigationParams(sync_offset=1.0))


# --- raw directories ------------------------------------------------------------------------------

def test_raw_reads_equal_the_bil(raw, flight):
    for i, info in enumerate(raw.cubes):
        cube = EnviCube(flight.directory / f"{info.base}.bil")
        np.testing.assert_array_equal(raw.read_bands(i, [0, 2, 3]), cube.read()[[0, 2, 3]])
        assert info.framerate == cube.header.framerate and info.shutter_ms == cube.header.shutter
        assert info.gain_db == cube.header.gain and info.wavelengths == cube.header.wavelengths


def test_raw_radiometry_values(raw, flight):
    cal = read_icp(next(flight.directory.glob("*.icp")))
    header = raw.header(1)
    dark, gain = cal.for_cube(header)
    rad = raw.radiometry(1, [0, 3], "radiance")
    np.testing.assert_allclose(rad.dark, dark[[0, 3]], rtol=1e-6)
    np.testing.assert_allclose(rad.gain, gain[[0, 3]], rtol=1e-6)
    expected = response(header.shutter, header.gain, cal.shutter_cal, cal.gain_cal)
    np.testing.assert_allclose(rad.response, expected, rtol=1e-6)
    rel = raw.radiometry(1, [0, 3], "relative")
    np.testing.assert_allclose(rel.dark, dark[[0, 3]], rtol=1e-6)
    np.testing.assert_allclose(rel.response, header.shutter * 10 ** (header.gain / 20), rtol=1e-6)
    with pytest.raises(InputError, match="white reference"):
        raw.radiometry(1, [0], "reflectance")
    with_white = RawFlightSource(flight.directory, PARAMS, white_reference=np.full(BANDS, 50.0))
    np.testing.assert_allclose(with_white.radiometry(1, [0, 3], "reflectance").gain, rad.gain / 50.0, rtol=1e-6)


def test_raw_without_calibration(flight, tmp_path):
    copy = tmp_path / "nocal"
    shutil.copytree(flight.directory, copy)
    for icp in copy.glob("*.icp"):
        icp.unlink()
    src = RawFlightSource(copy, PARAMS)
    assert src.calibration() is None and not src.has_calibration
    rel = src.radiometry(0, [0], "relative")
    assert np.all(rel.dark == 0)
    with pytest.raises(InputError, match="--calibration") as info:
        src.radiometry(0, [0], "radiance")
    assert "--mode raw" in str(info.value)
    # an explicit calibration file elsewhere
    explicit = RawFlightSource(copy, PARAMS, calibration=next(flight.directory.glob("*.icp")))
    assert explicit.radiometry(0, [0], "radiance").gain.mean() > 0
    with pytest.raises(MissingInputError):
        RawFlightSource(copy, PARAMS, calibration=tmp_path / "none.icp")


def test_open_source(flight, tmp_path):
    src = open_source(flight.directory, PARAMS)
    assert isinstance(src, RawFlightSource) and src.id.startswith("flight-")
    with pytest.raises(MissingInputError, match="nothing_here"):
        open_source(tmp_path / "nothing_here", PARAMS)


# --- collections ----------------------------------------------------------------------------------

def test_open_source_resolves_collection_ids(flight, sources):
    src = sources["collection"]
    assert isinstance(src, CollectionSource) and src.id == flight.cid
    assert Path(src.label).name == f"{flight.cid}.zarr"
    with pytest.raises(MissingInputError, match="no_such_id"):
        open_source("no_such_id", PARAMS, archive=flight.archive)
    with pytest.raises(InputError, match="carries the calibration"):
        open_source(flight.cid, PARAMS, calibration=next(flight.directory.glob("*.icp")), archive=flight.archive)
    with pytest.raises(MissingInputError, match="--archive"):
        open_source(flight.cid, PARAMS)  # an id without the archive to resolve it
