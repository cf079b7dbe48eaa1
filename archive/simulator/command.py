"""``archive simulate``: write a simulated Resonon flight and its ground truth.

:func:`simulate_flight` is the Python entry point (tests call it); :func:`run` is the CLI handler.
The flight is written into a hidden sibling directory and renamed into place at the end, so a
half-written flight never appears under the requested name.

Recorder realism (every option defaults to an ideal recorder, whose flight is unchanged byte for byte):
dropped frames at cube switches, shutter steps, a camera-to-navigation sync offset, banked turns
(optionally recorded), a pause inside a cube, a boresight and a lever arm; see :func:`simulate_flight`.
"""

from __future__ import annotations

import argparse
import math
import os
import shutil
import sys
from collections import deque
from collections.abc import Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from archive.errors import InputError, OutputExistsError
from archive.formats.icp import Calibration, DarkFrame, write_icp
from archive.formats.lcf import LcfData, write_lcf
from archive.formats.times import write_times
from archive.simulator.clouds import Clouds, write_downwelling
from archive.simulator.layout import layout
from archive.simulator.mount import Mount, camera_path
from archive.simulator.scene import MATERIALS, Scene, material_spectra, random_waves
from archive.simulator.sensor import (EXPOSURES, GAIN_CAL, SHUTTER_CAL, Radiometry, band_fwhm,
                                      make_radiometry, trace_abundance)
from archive.simulator.summary import summary
from archive.simulator.terrain import DEM_NAME, TERRAINS, Terrain, make_terrain, write_dem
from archive.simulator.trajectory import (FRAMERATE, INS_RATE, Trajectory, convergence,
                                          Wobble, default_wobble, to_lonlat, to_utm, utm_epsg)
from archive.simulator.turns import RAMP_S, banked_turn
from archive.simulator.truth import CubeTruth, Truth, load_truth, save_truth
from archive.simulator.writer import BilWriter, header_text

__all__ = ["simulate_flight", "run", "T_START_GPS", "CAMERA_CLOCK_START", "SEED_START_STEP_S", "start_gps"]

T_START_GPS = 1402243218.0     #: 2024-06-12 16:00:00 UTC in GPS seconds (GPS - UTC = 18 s)
#: s between the default starts of consecutive seeds: seed k starts at 2024-06-12 16:00 UTC + k
#: minutes, so flights of different seeds get different collection ids (seed 0 keeps 16:00:00)
SEED_START_STEP_S = 60.0
CAMERA_CLOCK_START = 263.873396  #: s, camera clock (not GPS) at the first line of the flight
SPEED = 10.0                   #: m/s
HEIGHT = 40.0                  #: m above ground
GROUND_HEIGHT = 80.0           #: m above the ellipsoid
SPACING = 25.0                 #: m between passes
HEADING_DEG = 20.0             #: grid heading of even passes
RUN_S = 0.5                    #: s of straight flight before and after recording on each pass
KT = 3                         #: time points per exposure
SUBSAMPLE_M = 0.03             #: target spacing (m) of the across-track sub-samples of a sample
MAX_POINTS = 1 << 19           #: ground points traced per block (memory bound)
MAX_VALUES = 1 << 22           #: DN values (bands x lines x samples) per block (memory bound)
SHUTTER_STEPS = (3.0, 1.5, 3.9, 2.2)  #: ms, shutters cycled over cubes by ``shutter_steps`` (gain 0 dB)
MAX_BANK_DEG = 70.0
MIN_BANK_DEG = 10.0
DEM_RESOLUTION = 0.1           #: m, its pixel side
DEM_MARGIN = 10.0              #: m of DEM around the footprint's bounding box
RECORD_TURN_FRACTION = 0.8     #: at most this fraction of a pass's recording is flown in the turn


@dataclass(frozen=True, eq=False)
class _CubePlan:
    index: int
    base: str
    pass_index: int
    line_time: np.ndarray      # (lines,) true GPS s of exposure start
    camera_time: np.ndarray    # (lines,) s, camera clock as written in .times
    shutter_ms: float
    gain_db: float
    lcf_t0: float              # GPS s of the first .lcf row (= line_time[0] - sync offset)


@dataclass(frozen=True)
class _Recorder:
    """The recorder options of :func:`simulate_flight` (see there), checked."""

    dropped_frames: int = 0
    exposures: tuple[tuple[float, float], ...] = EXPOSURES
    sync_offset: float = 0.0
    bank_deg: float = 0.0
    record_turns: bool = False
    pause_s: float = 0.0
    pause_cube: int = 0
    mount: Mount = field(default_factory=Mount)

    def pause_at(self, lines: int) -> tuple[int, int] | None:
        """(cube, line) before which the recorder pauses, or None."""
        return (self.pause_cube, lines // 2) if self.pause_s else None


def _check(cubes: int, bands: int, samples: int, lines: int, cubes_per_pass: int, lat: float,
           lon: float, fov_deg: float) -> None:
    for name, value, low in (("cubes", cubes, 1), ("bands", bands, 1), ("samples", samples, 2),
                             ("lines", lines, 2), ("cubes per pass", cubes_per_pass, 1)):
        if int(value) != value or value < low:
            raise InputError("simulate", f"{name} = {value}, expected an integer >= {low}")
    if not -80.0 <= lat <= 84.0:
        raise InputError("simulate", f"latitude {lat} is outside the UTM range -80..84 degrees")
    if not -180.0 <= lon <= 180.0:
        raise InputError("simulate", f"longitude {lon} is outside -180..180 degrees")
    if not 1.0 <= fov_deg <= 120.0:
        raise InputError("simulate", f"field of view {fov_deg} degrees, expected 1..120")


def start_gps(start, seed: int = 0) -> float:
    """GPS seconds of a flight's start (its first line follows :data:`RUN_S` later): ``start`` (an ISO 8601 text, 'Z' or an offset for the
    zone, UTC without one; or a datetime), else the seed's default (:data:`T_START_GPS` +
    ``seed`` x :data:`SEED_START_STEP_S`). InputError for an unreadable or implausible time."""
    from datetime import UTC, datetime, timedelta

    from archive.formats.lcf import GPS_EPOCH, gps_seconds_to_datetime

    if start is None:
        return T_START_GPS + int(seed) * SEED_START_STEP_S
    when = start
    if isinstance(start, str):
        try:
            when = datetime.fromisoformat(start.strip().replace("z", "Z").replace("Z", "+00:00"))
        except ValueError:
            raise InputError("--start", f"{start!r} is not an ISO 8601 time", "e.g. 2024-06-12T16:00:00Z") from None
    if not isinstance(when, datetime):
        raise InputError("--start", f"expected an ISO 8601 time or a datetime, got {start!r}")
    when = when.replace(tzinfo=UTC) if when.tzinfo is None else when.astimezone(UTC)
    if not datetime(2000, 1, 1, tzinfo=UTC) <= when < datetime(2100, 1, 1, tzinfo=UTC):
        raise InputError("--start", f"{start} is outside 2000..2099 (GPS week numbers)")
    base = (when - GPS_EPOCH).total_seconds()
    t = base
    for _ in range(3):   # add the leap seconds in force at that instant (GPS - UTC)
        t = base + ((GPS_EPOCH + timedelta(seconds=t)) - gps_seconds_to_datetime(t)).total_seconds()
    return t


def _triple(name: str, value) -> tuple[float, float, float]:
    try:
        out = tuple(float(v) for v in value)
    except (TypeError, ValueError):
        out = ()
    if len(out) != 3 or not all(math.isfinite(v) for v in out):
        raise InputError("simulate", f"{name} = {value!r}, expected three finite numbers")
    return out  # type: ignore[return-value]


def _recorder(cubes: int, lines: int, dropped_frames: int, shutters, gains, shutter_steps: bool,
              sync_offset: float, bank_deg: float | None, record_turns: bool, pause_s: float,
              pause_cube: int, boresight_deg, lever_arm_m) -> _Recorder:
    def fail(message: str) -> None:
        raise InputError("simulate", message)

    if int(dropped_frames) != dropped_frames or not 0 <= dropped_frames <= 10:
        fail(f"dropped frames = {dropped_frames}, expected an integer 0..10")
    exposures = EXPOSURES
    if shutters is not None or gains is not None or shutter_steps:
        if shutters is not None and shutter_steps:
            fail("give either shutters or shutter_steps, not both")
        if shutter_steps:
            shutter_list = [float(v) for v in SHUTTER_STEPS]
        elif shutters is not None:
            shutter_list = [float(v) for v in shutters]
        else:
            shutter_list = [e[0] for e in EXPOSURES]
        gain_list = [float(v) for v in (gains if gains is not None else [0.0])]
        if not shutter_list or not gain_list:
            fail("shutters and gains need at least one value each")
        for v in shutter_list:
            if not (math.isfinite(v) and 0.01 <= v <= 1000.0 / FRAMERATE):
                fail(f"shutter {v} ms, expected 0.01..{1000.0 / FRAMERATE:.3f} (the frame interval)")
        for v in gain_list:
            if not (math.isfinite(v) and 0.0 <= v <= 24.0):
                fail(f"gain {v} dB, expected 0..24")
        exposures = tuple((shutter_list[c % len(shutter_list)], gain_list[c % len(gain_list)])
                          for c in range(max(len(shutter_list), len(gain_list))))
    if not (math.isfinite(sync_offset) and abs(sync_offset) <= 10.0):
        fail(f"sync offset {sync_offset} s, expected -10..10")
    bank = 0.0 if bank_deg is None else float(bank_deg)
    if bank and not MIN_BANK_DEG <= bank <= MAX_BANK_DEG:
        fail(f"bank {bank_deg} degrees, expected {MIN_BANK_DEG:g}..{MAX_BANK_DEG:g}")
    if not (math.isfinite(pause_s) and 0.0 <= pause_s <= 600.0):
        fail(f"pause {pause_s} s, expected 0..600")
    if pause_s and not (int(pause_cube) == pause_cube and 0 <= pause_cube < cubes):
        fail(f"pause cube {pause_cube}, expected 0..{cubes - 1}")
    if pause_s and lines < 4:
        fail(f"a pause needs cubes of at least 4 lines, got {lines}")
    boresight = _triple("boresight", boresight_deg)
    lever = _triple("lever arm", lever_arm_m)
    if max(abs(v) for v in boresight) > 90.0:
        fail(f"boresight {boresight} degrees, expected angles within +-90")
    if max(abs(v) for v in lever) > 20.0:
        fail(f"lever arm {lever} m, expected components within +-20")
    return _Recorder(int(dropped_frames), exposures, float(sync_offset), bank, bool(record_turns),
                     float(pause_s), int(pause_cube), Mount(boresight, lever))


def _plan(cubes: int, lines: int, cubes_per_pass: int, traj: Trajectory,
          recorder: _Recorder = _Recorder()) -> list[_CubePlan]:
    plans = []
    t_first = traj.record_start(0)
    pause = recorder.pause_at(lines)
    for c in range(cubes):
        k, j = divmod(c, cubes_per_pass)
        ideal = traj.record_start(k) + (j * (lines + recorder.dropped_frames) + np.arange(lines)) / FRAMERATE
        if pause is not None and divmod(pause[0], cubes_per_pass)[0] == k and pause[0] <= c:
            # the recorder stops pause_s before line pause[1] of cube pause[0]; later lines follow
            ideal = ideal + np.where(np.arange(lines) >= (pause[1] if pause[0] == c else 0),
                                     recorder.pause_s, 0.0)
        camera = np.round(CAMERA_CLOCK_START + (ideal - t_first), 6)
        # the first line, the first .times value and the first .lcf row are simultaneous (up to the
        # recorder's sync offset: the first .lcf row is at line_time[0] - sync_offset)
        line_time = ideal[0] + (camera - camera[0])
        shutter, gain = recorder.exposures[c % len(recorder.exposures)]
        lcf_t0 = line_time[0] - recorder.sync_offset if recorder.sync_offset else line_time[0]
        plans.append(_CubePlan(c, f"sim_Pika_L_{c + 1}", k, line_time, camera, shutter, gain, lcf_t0))
    return plans


def _lcf(traj: Trajectory, plan: _CubePlan, path: Path, bias=(0.0, 0.0, 0.0)) -> None:
    """The INS (body) samples at 200 Hz from the cube's first .lcf row to 2 frames past its last line,
    on the .lcf scale (no sync offset) and in true time (with it), whichever is later; positions
    recorded ``bias`` (dE, dN, dU metres) off the truth (a GNSS bias)."""
    t0 = plan.lcf_t0
    last = plan.line_time[-1]
    if t0 != plan.line_time[0]:
        last = max(last, t0 + (plan.line_time[-1] - plan.line_time[0]))
    rows = int(math.ceil((last + 2.0 / FRAMERATE - t0) * INS_RATE)) + 1
    t = t0 + np.arange(rows) / INS_RATE
    pos = traj.position(t) + np.asarray(bias, float)[None, :]
    yaw, pitch, roll = traj.euler(t)
    lon, lat = to_lonlat(pos[:, 0], pos[:, 1], traj.epsg)
    yaw_true = yaw - convergence(lon, lat, traj.epsg)
    yaw_true = np.mod(yaw_true + np.pi, 2.0 * np.pi) - np.pi
    write_lcf(path, LcfData(path, t, -roll, pitch, yaw_true, lon, lat, pos[:, 2]))


@dataclass(frozen=True, eq=False)
class _Context:
    scene: Scene
    camera: object             # camera path: the Trajectory, or a MountedCamera
    radiometry: Radiometry
    spectra_t: np.ndarray      # (bands, materials) float32
    fov_deg: float
    samples: int
    ku: int
    seed: int
    terrain: Terrain | None = None
    clouds: object = None      # archive.simulator.clouds.Clouds, or None (clear sky)


def _cube_block(job: tuple[_CubePlan, int, np.ndarray], ctx: _Context) -> np.ndarray:
    """DN (bands, lines, samples) uint16 of the lines ``t`` of one cube, starting at line ``i0``.
    Its noise is seeded by (seed, cube, first line), so the result does not depend on threading."""
    plan, i0, t = job
    a = trace_abundance(ctx.scene, ctx.camera, t, plan.shutter_ms / 1000.0, ctx.fov_deg, ctx.samples,
                        ctx.ku, KT, ctx.terrain)
    radiance = np.tensordot(ctx.spectra_t, a.astype(np.float32), axes=(1, 0))
    if ctx.clouds is not None:   # the sky's brightness at each line's exposure start
        radiance *= ctx.clouds.field(t, ctx.scene.wavelengths).T.astype(np.float32)[:, :, None]
    rng = np.random.default_rng([ctx.seed, plan.index, i0])
    return ctx.radiometry.dn(radiance, plan.shutter_ms, plan.gain_db, rng)


def _workers() -> int:
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return max(1, min(cpus, 8))


def _parallel_map(func, items: list, pool: ThreadPoolExecutor, ahead: int) -> Iterator:
    """``map(func, items)`` in order, at most ``ahead`` results in flight (memory bound); numpy
    releases the GIL in the heavy element-wise work, so threads give real parallelism."""
    pending: deque = deque()
    for item in items:
        pending.append(pool.submit(func, item))
        if len(pending) >= ahead:
            yield pending.popleft().result()
    while pending:
        yield pending.popleft().result()


def _finalize(tmp: Path, directory: Path) -> None:
    if directory.exists() or directory.is_symlink():
        if directory.is_dir() and not directory.is_symlink() and not any(directory.iterdir()):
            directory.rmdir()
        else:
            old = directory.with_name(f".{directory.name}.old-{os.getpid()}")
            os.replace(directory, old)
            os.replace(tmp, directory)
            if old.is_dir() and not old.is_symlink():
                shutil.rmtree(old)
            else:
                old.unlink()
            return
    os.replace(tmp, directory)


def simulate_flight(directory: str | os.PathLike, cubes: int = 4, bands: int = 8, samples: int = 128,
                    lines: int = 250, cubes_per_pass: int = 2, seed: int = 0, lat: float = 35.12,
                    lon: float = -89.94, fov_deg: float = 47.5, overwrite: bool = False,
                    progress: bool = False, *, dropped_frames: int = 0,
                    shutters: Sequence[float] | None = None, gains: Sequence[float] | None = None,
                    shutter_steps: bool = False, sync_offset: float = 0.0,
                    bank_deg: float | None = None, record_turns: bool = False, pause_s: float = 0.0,
                    pause_cube: int = 0, boresight_deg: Sequence[float] = (0.0, 0.0, 0.0),
                    lever_arm_m: Sequence[float] = (0.0, 0.0, 0.0), terrain: str | None = None,
                    heading_deg: float = HEADING_DEG, wobble: bool = True, start=None,
                    scene_seed: int | None = None, clouds: bool = False, cloud_colour: float = 0.0,
                    gnss_bias_m: Sequence[float] = (0.0, 0.0, 0.0), scene_from: str | os.PathLike | None = None,
                    ground_changes: float = 0.0) -> Truth:
    """Write a simulated flight into ``directory`` and return its :class:`Truth`.

    ``cubes`` cubes of ``lines`` lines x ``samples`` samples x ``bands`` bands (400-1000 nm,
    evenly spaced), ``cubes_per_pass`` of them back to back on each lawn-mower pass; site at
    (``lat``, ``lon``) degrees (the UTM zone of the site is the truth's ``epsg``, even where passes
    cross into the next zone); camera field of view ``fov_deg`` degrees. Refuses an existing
    non-empty ``directory`` unless ``overwrite`` (:class:`OutputExistsError`).

    Recorder realism, each off by default (then the flight is exactly the ideal one):

    - ``dropped_frames`` (0..10): at each cube switch within a pass the recorder drops that many
      frames: the next cube's first line starts ``dropped_frames + 1`` frame intervals after the
      previous cube's last line (true times and the camera clock alike).
    - ``shutters`` (ms) / ``gains`` (dB): exposures cycled over cubes (a list not given: shutters
      as by default, gains 0 dB); ``shutter_steps``: shutters :data:`SHUTTER_STEPS` at 0 dB. By default
      (shutter, gain) already cycles over cubes through ``EXPOSURES``.
    - ``sync_offset`` (s): the true camera-to-navigation error. Each cube's ``.lcf`` starts at its
      first line's true time minus ``sync_offset``, so that ``lcf_t0 + (times[i] - times[0]) +
      sync_offset`` is line i's true time; the truth keeps true times and poses.
    - ``bank_deg`` (10..70): coordinated banked turns between passes with this sustained bank
      (None: flat half-circle turns); ``record_turns``: each pass's recording (but the last's) goes on
      into the following turn, until the bank of a banked turn starts rolling out (half the turn for
      flat turns), capped at 80 % of the pass's recording; those lines have huge view angles.
    - ``pause_s`` (s): the recorder stops that long before the middle line (``lines // 2``) of cube
      ``pause_cube`` and carries on in the same file: its ``.times`` jump by ``pause_s`` plus a frame
      interval there, its ``.lcf`` is continuous. Every pass's straight segment is ``pause_s`` longer.
    - ``boresight_deg`` (roll, pitch, yaw) and ``lever_arm_m`` (x, y, z, body frame): the true camera
      mounting (DESIGN 3); the ``.lcf`` records the INS, the camera sees through the mount.

    ``terrain`` ('hills' | 'ridge', :mod:`archive.simulator.terrain`; None: flat ground): every sample's
    rays are traced to their first hit on an analytic height field about the ground height (the
    camera still flies ``HEIGHT`` above ``GROUND_HEIGHT``), and the flight directory gets
    ``dem.tif``: the heights above the ellipsoid every ``DEM_RESOLUTION`` m over the footprint (in
    the site's UTM zone, its 3-D CRS declaring ellipsoidal heights). The truth knows which ground no
    line sees (:meth:`Truth.visible`).

    ``heading_deg``: grid heading of the even passes (degrees clockwise from grid north; odd passes
    fly the opposite way).

    ``wobble``: False flies the passes without attitude, height or lateral wobble (straight, level, at
    constant speed: the case where pitch and a sync offset cannot be told apart); the scene is the
    one the same seed gives with wobble.

    ``start``: UTC time the flight starts, its first line :data:`RUN_S` later (ISO 8601 text or a datetime; :func:`start_gps`); the
    default depends on the seed (2024-06-12T16:00:00Z plus ``seed`` minutes), so flights of
    different seeds get different collection ids (``<sensor>_<start>``) and can share an archive.

    ``scene_seed``: the seed of the ground (the scene's textures and targets) and of the camera's
    radiometry (its gain and dark frames), None: ``seed``. Flights of one ``scene_seed`` (and one
    site, heading, cubes, lines and recorder) fly over the same ground, each with its own wobble,
    noise and (by default) start: the same field flown again on another day. A flight whose
    ``scene_seed`` equals its ``seed`` is the flight of that seed, byte for byte.

    ``gnss_bias_m`` (dE, dN, dU metres, each within +-20): the ``.lcf`` records every position this
    far off the truth (a GNSS bias of a kit without RTK, constant over the flight); the truth keeps
    the true poses and the bias.

    ``scene_from``: a flight directory written by this simulator (or its ``truth`` folder): fly over
    exactly its ground (its scene: texture, targets, spectra), whatever this flight's heading, cubes
    or seed (``scene_seed`` gives the same ground only to flights of the same shape). Its bands must
    match. ``ground_changes`` (0..0.9): then paint this fraction of the ground under the flight
    with new homogeneous material patches (1.5-5 m rectangles, drawn from ``seed``): what changes
    between two days (new material, moved objects).

    ``clouds``: the sky's brightness drifts 30 % within cubes (:mod:`archive.simulator.clouds`); the
    directory gets the kit's downwelling spectra (one per cube) and ``downwelling.dcp``, the truth
    ``clouds.json``. ``cloud_colour``: the sky's spectrum also changes shape (every other spectrum
    tilted by this fraction per 300 nm; 0: grey).
    """
    if not math.isfinite(heading_deg):
        raise InputError("simulate", f"heading must be a finite number of degrees, got {heading_deg!r}")
    _check(cubes, bands, samples, lines, cubes_per_pass, lat, lon, fov_deg)
    t_start = start_gps(start, seed)
    if terrain is not None and terrain not in TERRAINS:
        raise InputError("simulate", f"terrain {terrain!r}, expected one of {', '.join(TERRAINS)}")
    recorder = _recorder(cubes, lines, dropped_frames, shutters, gains, shutter_steps, sync_offset,
                         bank_deg, record_turns, pause_s, pause_cube, boresight_deg, lever_arm_m)
    bias = _triple("GNSS bias", gnss_bias_m)
    if max(abs(v) for v in bias) > 20.0:
        raise InputError("simulate", f"GNSS bias {bias} m, expected components within +-20")
    if not (math.isfinite(ground_changes) and 0.0 <= ground_changes <= 0.9):
        raise InputError("simulate", f"ground changes {ground_changes}, expected a fraction 0..0.9")
    base_scene = None
    if scene_from is not None:
        base_scene = load_truth(scene_from).scene
        if base_scene.wavelengths.size != bands:
            raise InputError(scene_from, f"its scene has {base_scene.wavelengths.size} bands, this flight {bands}",
                             "simulate with the same --bands")
    directory = Path(directory)
    if (directory.exists() and not (directory.is_dir() and not any(directory.iterdir()))) \
            and not overwrite:
        raise OutputExistsError(directory)
    directory.parent.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)

    epsg = utm_epsg(lon, lat)
    e0, n0 = (float(np.round(v)) for v in to_utm(lon, lat, epsg))
    passes = -(-cubes // cubes_per_pass)
    record_s = (cubes_per_pass * lines + (cubes_per_pass - 1) * recorder.dropped_frames) / FRAMERATE
    if recorder.pause_s:
        record_s += recorder.pause_s
    into_turn = 0.0
    if recorder.record_turns and passes > 1:
        if recorder.bank_deg:
            turn = banked_turn(float(SPEED), float(SPACING), recorder.bank_deg)
            into_turn = turn.peak_end_s + 0.5 * RAMP_S
        else:
            into_turn = 0.5 * math.pi * (SPACING / 2.0) / SPEED
        into_turn = min(into_turn, RECORD_TURN_FRACTION * record_s)
    motion = default_wobble(rng)     # drawn either way: the same seed gives the same scene
    if scene_seed is not None and int(scene_seed) != int(seed):
        # the ground (and camera) of flight ``scene_seed``: its generator, past its wobble draws
        rng = np.random.default_rng(int(scene_seed))
        default_wobble(rng)
    ground_seed = int(seed) if scene_seed is None else int(scene_seed)
    if not wobble:
        motion = {name: Wobble() for name in motion}
    traj = Trajectory(epsg, e0, n0, float(heading_deg), SPEED, SPACING, HEIGHT, GROUND_HEIGHT, t_start,
                      RUN_S, record_s, passes, motion, bank_deg=recorder.bank_deg,
                      record_into_turn_s=into_turn)
    camera = camera_path(traj, recorder.mount)
    relief = None if terrain is None else make_terrain(
        terrain, GROUND_HEIGHT, e0, n0, float(heading_deg), [float(traj.pass_c(k)) for k in range(passes)])
    plans = _plan(cubes, lines, cubes_per_pass, traj, recorder)
    spans = [(min(p.line_time[0] for p in plans if p.pass_index == k),
              max(p.line_time[-1] for p in plans if p.pass_index == k)) for k in range(passes)]
    if into_turn:   # targets go on the straight part of each pass only
        spans = [(t0, min(t1, traj.segment_end(k)) if k < passes - 1 else t1)
                 for k, (t0, t1) in enumerate(spans)]
    wavelengths = np.round(np.linspace(400.0, 1000.0, bands), 3)
    fwhm = band_fwhm(wavelengths)
    spectra = material_spectra(wavelengths)
    scene = Scene(e0, n0, ground_seed, 1.2, random_waves(rng), tuple(layout(traj, spans, rng)),
                  wavelengths, spectra)
    if base_scene is not None:
        scene = base_scene
    if ground_changes:
        scene = changed_ground(scene, traj, spans, fov_deg, ground_changes, np.random.default_rng([int(seed), 33]))
    radiometry = make_radiometry(spectra[MATERIALS.index("white")], wavelengths, samples,
                                 [(p.shutter_ms, p.gain_db) for p in plans], rng)

    pixel = 2.0 * HEIGHT * math.tan(math.radians(fov_deg) / 2.0) / samples
    ku = max(4, int(math.ceil(pixel / SUBSAMPLE_M)))
    block = max(1, min(MAX_POINTS // (KT * samples * ku), MAX_VALUES // (bands * samples)))
    sky = Clouds.for_cubes([p.line_time[0] for p in plans], float(cloud_colour)) if clouds else None
    context = _Context(scene, camera, radiometry, spectra.T.astype(np.float32), fov_deg, samples, ku,
                       int(seed), relief, sky)

    workers = _workers()
    tmp = directory.with_name(f".{directory.name}.simulate-{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    try:
        cube_truths = []
        with tqdm(total=cubes * lines, unit="line", desc="simulate", disable=not progress,
                  file=sys.stderr) as bar, ThreadPoolExecutor(workers) as pool:
            for plan in plans:
                hdr = header_text(samples, lines, bands, wavelengths, plan.shutter_ms, plan.gain_db,
                                  FRAMERATE, plan.lcf_t0, plan.base, GROUND_HEIGHT, fwhm=fwhm)
                jobs = [(plan, i0, plan.line_time[i0:i0 + block]) for i0 in range(0, lines, block)]
                with BilWriter(tmp / f"{plan.base}.bil", samples, lines, bands, hdr) as out:
                    for dn in _parallel_map(lambda job: _cube_block(job, context), jobs, pool,
                                                workers + 1):
                        out.write(dn)
                        bar.update(dn.shape[1])
                write_times(tmp / f"{plan.base}.bil.times", plan.camera_time)
                _lcf(traj, plan, tmp / f"{plan.base}.lcf", bias)
                position, attitude = camera(plan.line_time)
                cube_truths.append(CubeTruth(plan.base, plan.line_time, position, attitude,
                                             plan.shutter_ms, plan.gain_db, FRAMERATE))
        darks = tuple(DarkFrame(g, s, d) for (g, s), d in sorted(radiometry.darks.items()))
        write_icp(tmp / "calibration.icp", Calibration(None, radiometry.gain, SHUTTER_CAL, GAIN_CAL,
                                                       tuple(float(w) for w in wavelengths), darks))
        pause = recorder.pause_at(lines)
        truth = Truth(directory, epsg, float(fov_deg), GROUND_HEIGHT, wavelengths, tuple(cube_truths),
                      samples, (float(lon), float(lat)), int(seed), scene, traj,
                      sync_offset=recorder.sync_offset, mount=recorder.mount,
                      dropped_frames=recorder.dropped_frames,
                      pause_cube=None if pause is None else pause[0],
                      pause_line=None if pause is None else pause[1],
                      pause_s=recorder.pause_s, record_turns=bool(into_turn), terrain=relief,
                      gnss_bias_m=bias, ground_changes=float(ground_changes))
        save_truth(truth, tmp / "truth")
        if sky is not None:
            write_downwelling(tmp, [p.base for p in plans], sky)
        if relief is not None:
            write_dem(tmp / DEM_NAME, relief, epsg, dem_bounds(truth))
        _finalize(tmp, directory)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return truth


def changed_ground(scene: Scene, traj: Trajectory, spans, fov_deg: float, fraction: float,
                   rng: np.random.Generator) -> Scene:
    """``scene`` with about ``fraction`` of the ground under the passes (their ``spans`` of GPS
    times, swath of ``fov_deg`` at :data:`HEIGHT`) covered by new homogeneous patches: rectangles
    of 1.5-5 m sides, materials drawn from the scene's (glint excluded), painted over everything."""
    half = HEIGHT * math.tan(math.radians(fov_deg) / 2.0) + 2.0
    pts = []
    for t0, t1 in spans:
        e, n = traj.position(np.linspace(t0, t1, 64))[:, :2].T
        pts.append(np.column_stack([e, n]))
    pts = np.concatenate(pts)
    w, s = pts.min(axis=0) - half
    e, n = pts.max(axis=0) + half
    sides = rng.uniform(1.5, 5.0, size=(100000, 2))
    mean_area = float(np.mean(sides[:, 0] * sides[:, 1]))
    count = int(math.ceil(-math.log(1.0 - fraction) * (e - w) * (n - s) / mean_area))
    choices = [k for k, name in enumerate(scene.materials) if name != "glint"]
    shapes = []
    for k in range(count):
        we, hn = rng.uniform(1.5, 5.0, size=2)
        ce, cn = rng.uniform(w, e), rng.uniform(s, n)
        shapes.append({"kind": "rect", "name": f"change{k}", "material": int(rng.choice(choices)),
                       "bounds": [ce - we / 2, cn - hn / 2, ce + we / 2, cn + hn / 2], "changed": True})
    return Scene(scene.origin_e, scene.origin_n, scene.seed, scene.cell, scene.waves,
                 tuple(scene.shapes) + tuple(shapes), scene.wavelengths, scene.spectra, scene.materials)


def dem_bounds(truth: Truth, margin: float = DEM_MARGIN) -> tuple[float, float, float, float]:
    """(west, south, east, north) UTM metres a flight's DEM covers: the footprint's box + ``margin``."""
    rings = np.concatenate(truth.footprint())
    return (float(rings[:, 0].min() - margin), float(rings[:, 1].min() - margin),
            float(rings[:, 0].max() + margin), float(rings[:, 1].max() + margin))




def run(args: argparse.Namespace) -> int:
    """CLI handler of ``archive simulate``; returns the exit code."""
    def opt(name: str, default):
        value = getattr(args, name, None)
        return default if value is None else value

    truth = simulate_flight(args.directory, cubes=args.cubes, bands=args.bands, samples=args.samples,
                            lines=args.lines, cubes_per_pass=args.cubes_per_pass, seed=args.seed,
                            lat=args.lat, lon=args.lon, fov_deg=args.fov, overwrite=args.overwrite,
                            progress=not args.quiet, dropped_frames=opt("dropped_frames", 0),
                            shutters=opt("shutters", None), gains=opt("gains", None),
                            shutter_steps=bool(opt("shutter_steps", False)),
                            sync_offset=opt("sync_offset", 0.0), bank_deg=opt("bank_deg", None),
                            record_turns=bool(opt("record_turns", False)), pause_s=opt("pause", 0.0),
                            pause_cube=opt("pause_cube", 0),
                            boresight_deg=opt("boresight", (0.0, 0.0, 0.0)),
                            lever_arm_m=opt("lever_arm", (0.0, 0.0, 0.0)), terrain=opt("terrain", None),
                            start=opt("start", None), scene_seed=opt("scene_seed", None),
                            clouds=bool(opt("clouds", False)), gnss_bias_m=opt("gnss_bias", (0.0, 0.0, 0.0)),
                            scene_from=opt("scene_from", None), ground_changes=opt("ground_changes", 0.0),
                            heading_deg=opt("heading", HEADING_DEG))
    print(summary(truth))
    return 0
