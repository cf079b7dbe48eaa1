"""``archive simulate``: write a simulated Resonon flight and its ground truth.

:func:`simulate_flight` is the Python entry point (tests call it); :func:`run` is the CLI handler.
The flight is written into a hidden sibling directory and renamed into place at the end, so a
half-written flight never appears under the requested name.
"""

from __future__ import annotations

import argparse
import math
import os
import shutil
import sys
from collections import deque
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from archive.errors import InputError, OutputExistsError
from archive.formats.icp import Calibration, DarkFrame, write_icp
from archive.formats.lcf import LcfData, write_lcf
from archive.formats.times import write_times
from archive.simulator.layout import layout
from archive.simulator.scene import MATERIALS, Scene, material_spectra, random_waves
from archive.simulator.sensor import (EXPOSURES, GAIN_CAL, SHUTTER_CAL, Radiometry,
                                      make_radiometry, trace_abundance)
from archive.simulator.trajectory import (FRAMERATE, INS_RATE, Trajectory, convergence,
                                          default_wobble, to_lonlat, to_utm, utm_epsg)
from archive.simulator.truth import CubeTruth, Truth, save_truth
from archive.simulator.writer import BilWriter, header_text, size_on_disk

__all__ = ["simulate_flight", "run", "T_START_GPS", "CAMERA_CLOCK_START"]

T_START_GPS = 1402243218.0     #: 2024-06-12 16:00:00 UTC in GPS seconds (GPS - UTC = 18 s)
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


@dataclass(frozen=True, eq=False)
class _CubePlan:
    index: int
    base: str
    pass_index: int
    line_time: np.ndarray      # (lines,) GPS s, lcf scale
    camera_time: np.ndarray    # (lines,) s, camera clock as written in .times
    shutter_ms: float
    gain_db: float


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


def _plan(cubes: int, lines: int, cubes_per_pass: int, traj: Trajectory) -> list[_CubePlan]:
    plans = []
    t_first = traj.record_start(0)
    for c in range(cubes):
        k, j = divmod(c, cubes_per_pass)
        ideal = traj.record_start(k) + (j * lines + np.arange(lines)) / FRAMERATE
        camera = np.round(CAMERA_CLOCK_START + (ideal - t_first), 6)
        # the first line, the first .times value and the first .lcf row are simultaneous
        line_time = ideal[0] + (camera - camera[0])
        shutter, gain = EXPOSURES[c % len(EXPOSURES)]
        plans.append(_CubePlan(c, f"sim_Pika_L_{c + 1}", k, line_time, camera, shutter, gain))
    return plans


def _lcf(traj: Trajectory, plan: _CubePlan, path: Path) -> None:
    t0 = plan.line_time[0]
    rows = int(math.ceil((plan.line_time[-1] + 2.0 / FRAMERATE - t0) * INS_RATE)) + 1
    t = t0 + np.arange(rows) / INS_RATE
    pos = traj.position(t)
    yaw, pitch, roll = traj.euler(t)
    lon, lat = to_lonlat(pos[:, 0], pos[:, 1], traj.epsg)
    yaw_true = yaw - convergence(lon, lat, traj.epsg)
    yaw_true = np.mod(yaw_true + np.pi, 2.0 * np.pi) - np.pi
    write_lcf(path, LcfData(path, t, -roll, pitch, yaw_true, lon, lat, pos[:, 2]))


@dataclass(frozen=True, eq=False)
class _Context:
    scene: Scene
    traj: Trajectory
    radiometry: Radiometry
    spectra_t: np.ndarray      # (bands, materials) float32
    fov_deg: float
    samples: int
    ku: int
    seed: int


def _cube_block(job: tuple[_CubePlan, int, np.ndarray], ctx: _Context) -> np.ndarray:
    """DN (bands, lines, samples) uint16 of the lines ``t`` of one cube, starting at line ``i0``.
    Its noise is seeded by (seed, cube, first line), so the result does not depend on threading."""
    plan, i0, t = job
    a = trace_abundance(ctx.scene, ctx.traj, t, plan.shutter_ms / 1000.0, ctx.fov_deg, ctx.samples,
                        ctx.ku, KT)
    radiance = np.tensordot(ctx.spectra_t, a.astype(np.float32), axes=(1, 0))
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
                    progress: bool = False) -> Truth:
    """Write a simulated flight into ``directory`` and return its :class:`Truth`.

    ``cubes`` cubes of ``lines`` lines x ``samples`` samples x ``bands`` bands (400-1000 nm,
    evenly spaced), ``cubes_per_pass`` of them back to back on each lawn-mower pass; site at
    (``lat``, ``lon``) degrees; camera field of view ``fov_deg`` degrees. Refuses an existing
    non-empty ``directory`` unless ``overwrite`` (:class:`OutputExistsError`).
    """
    _check(cubes, bands, samples, lines, cubes_per_pass, lat, lon, fov_deg)
    directory = Path(directory)
    if (directory.exists() and not (directory.is_dir() and not any(directory.iterdir()))) \
            and not overwrite:
        raise OutputExistsError(directory)
    directory.parent.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)

    epsg = utm_epsg(lon, lat)
    e0, n0 = (float(np.round(v)) for v in to_utm(lon, lat, epsg))
    passes = -(-cubes // cubes_per_pass)
    traj = Trajectory(epsg, e0, n0, HEADING_DEG, SPEED, SPACING, HEIGHT, GROUND_HEIGHT, T_START_GPS,
                      RUN_S, cubes_per_pass * lines / FRAMERATE, passes, default_wobble(rng))
    plans = _plan(cubes, lines, cubes_per_pass, traj)
    spans = [(min(p.line_time[0] for p in plans if p.pass_index == k),
              max(p.line_time[-1] for p in plans if p.pass_index == k)) for k in range(passes)]
    wavelengths = np.round(np.linspace(400.0, 1000.0, bands), 3)
    spectra = material_spectra(wavelengths)
    scene = Scene(e0, n0, int(seed), 1.2, random_waves(rng), tuple(layout(traj, spans, rng)),
                  wavelengths, spectra)
    radiometry = make_radiometry(spectra[MATERIALS.index("white")], wavelengths, samples,
                                 [(p.shutter_ms, p.gain_db) for p in plans], rng)

    pixel = 2.0 * HEIGHT * math.tan(math.radians(fov_deg) / 2.0) / samples
    ku = max(4, int(math.ceil(pixel / SUBSAMPLE_M)))
    block = max(1, min(MAX_POINTS // (KT * samples * ku), MAX_VALUES // (bands * samples)))
    context = _Context(scene, traj, radiometry, spectra.T.astype(np.float32), fov_deg, samples, ku,
                       int(seed))

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
                                  FRAMERATE, plan.line_time[0], plan.base, GROUND_HEIGHT)
                jobs = [(plan, i0, plan.line_time[i0:i0 + block]) for i0 in range(0, lines, block)]
                with BilWriter(tmp / f"{plan.base}.bil", samples, lines, bands, hdr) as out:
                    for dn in _parallel_map(lambda job: _cube_block(job, context), jobs, pool,
                                                workers + 1):
                        out.write(dn)
                        bar.update(dn.shape[1])
                write_times(tmp / f"{plan.base}.bil.times", plan.camera_time)
                _lcf(traj, plan, tmp / f"{plan.base}.lcf")
                position, attitude = traj(plan.line_time)
                cube_truths.append(CubeTruth(plan.base, plan.line_time, position, attitude,
                                             plan.shutter_ms, plan.gain_db, FRAMERATE))
        darks = tuple(DarkFrame(g, s, d) for (g, s), d in sorted(radiometry.darks.items()))
        write_icp(tmp / "calibration.icp", Calibration(None, radiometry.gain, SHUTTER_CAL, GAIN_CAL,
                                                       tuple(float(w) for w in wavelengths), darks))
        truth = Truth(directory, epsg, float(fov_deg), GROUND_HEIGHT, wavelengths, tuple(cube_truths),
                      samples, (float(lon), float(lat)), int(seed), scene, traj)
        save_truth(truth, tmp / "truth")
        _finalize(tmp, directory)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return truth


def summary(truth: Truth) -> str:
    """A short human-readable summary of a simulated flight."""
    lines = sum(c.lines for c in truth.cubes)
    size = size_on_disk(truth.directory)
    lon, lat = truth.site
    return "\n".join([
        f"simulated flight: {truth.directory}",
        f"  cubes {len(truth.cubes)} ({len(truth.strips)} strips), lines {lines} "
        f"({truth.cubes[0].lines} per cube), bands {truth.wavelengths.size} "
        f"({truth.wavelengths[0]:.0f}-{truth.wavelengths[-1]:.0f} nm), samples {truth.samples}",
        f"  size on disk {size / 1e6:.1f} MB",
        f"  site {lat:.5f} N, {lon:.5f} E; EPSG:{truth.epsg}; grid convergence "
        f"{math.degrees(truth.convergence):+.3f} deg",
        f"  nominal GSD {truth.nominal_gsd * 100:.1f} cm across, "
        f"{truth.flight.speed / truth.cubes[0].framerate * 100:.1f} cm along; field of view "
        f"{truth.fov_deg:g} deg; ground {truth.ground_height:g} m (ellipsoid)",
        f"  truth: {truth.directory / 'truth'}",
    ])


def run(args: argparse.Namespace) -> int:
    """CLI handler of ``archive simulate``; returns the exit code."""
    truth = simulate_flight(args.directory, cubes=args.cubes, bands=args.bands, samples=args.samples,
                            lines=args.lines, cubes_per_pass=args.cubes_per_pass, seed=args.seed,
                            lat=args.lat, lon=args.lon, fov_deg=args.fov, overwrite=args.overwrite,
                            progress=not args.quiet)
    print(summary(truth))
    return 0
