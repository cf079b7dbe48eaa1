"""Post-processed trajectories written by an independent writer (numpy's structured records, the csv
module and pyproj, not :mod:`archive.simulator.postprocessed`) from a simulated flight's error-free
INS path, rendered over a flight whose ``.lcf`` carries an undeclared real-time bias (issue 46):
the render from the trajectory has no gap and no shift against the simulator's truth, the render
from the ``.lcf`` fails the same test."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pyproj
import pytest
from helpers import eroded_dilated

from archive.params import NavigationParams
from tests.test_render_truth import render_shifts

BIAS = (1.5, -1.1, 0.8)   # E, N, up metres: the recorder's real-time solution is off by this
BAND = 2
WEEK = 604800.0
#: An SBET record as PDAL's reader names its 17 little-endian doubles.
SBET = np.dtype([(name, "<f8") for name in (
    "GpsTime", "Y", "X", "Z", "XVelocity", "YVelocity", "ZVelocity", "Roll", "Pitch", "PlatformHeading",
    "WanderAngle", "XBodyAccel", "YBodyAccel", "ZBodyAccel", "XBodyAngRate", "YBodyAngRate", "ZBodyAngRate")])
#: A Qinertia-like export: its own column names, given with --navigation-columns.
COLUMNS = ("GPS Time (s)", "Latitude (deg)", "Longitude (deg)", "Ellipsoidal Height (m)", "Roll (deg)",
           "Pitch (deg)", "Heading (deg)")
MAPPING = {"time": COLUMNS[0], "lat": COLUMNS[1], "lon": COLUMNS[2], "height": COLUMNS[3], "roll": COLUMNS[4],
           "pitch": COLUMNS[5], "heading": COLUMNS[6]}


def _true_path(truth, rate: float = 200.0):
    """(GPS seconds, lon, lat, height, roll, pitch, true heading): the INS's true path (radians),
    from a second before the first line to a second after the last, at ``rate`` Hz."""
    first = min(float(c.line_time[0]) for c in truth.cubes) - 1.0
    last = max(float(c.line_time[-1]) for c in truth.cubes) + 1.0
    t = np.arange(first, last, 1.0 / rate)
    pos, att = truth.ins_trajectory(t)   # UTM E, N, ellipsoidal height; body -> NED about GRID north
    to_geo = pyproj.Transformer.from_crs(truth.epsg, 4326, always_xy=True)
    lon, lat = to_geo.transform(pos[:, 0], pos[:, 1])
    # the grid azimuth of true north at each point, from a step along the meridian
    to_grid = pyproj.Transformer.from_crs(4326, truth.epsg, always_xy=True)
    e1, n1 = to_grid.transform(lon, lat + 1e-4)
    north = np.arctan2(e1 - pos[:, 0], n1 - pos[:, 1])
    yaw, pitch, roll = att.as_euler("ZYX").T
    heading = np.mod(yaw - north, 2 * np.pi)
    return t, np.radians(lon), np.radians(lat), pos[:, 2], roll, pitch, heading


def _write_sbet(truth, path: Path) -> Path:
    t, lon, lat, h, roll, pitch, heading = _true_path(truth)
    rec = np.zeros(t.size, SBET)
    rec["GpsTime"], rec["Y"], rec["X"], rec["Z"] = np.mod(t, WEEK), lat, lon, h
    rec["Roll"], rec["Pitch"], rec["PlatformHeading"] = roll, pitch, heading   # wander angle 0
    rec.tofile(path)
    return path


def _write_csv(truth, path: Path) -> Path:
    t, lon, lat, h, roll, pitch, heading = _true_path(truth, rate=100.0)
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(COLUMNS)
        for row in zip(np.mod(t, WEEK), np.degrees(lat), np.degrees(lon), h, np.degrees(roll), np.degrees(pitch),
                       np.degrees(heading)):
            writer.writerow([f"{row[0]:.4f}", f"{row[1]:.9f}", f"{row[2]:.9f}", f"{row[3]:.3f}",
                             *(f"{v:.5f}" for v in row[4:])])
    return path


@pytest.fixture(scope="module")
def biased(tmp_path_factory):
    from archive.simulator.command import simulate_flight

    base = tmp_path_factory.mktemp("ppk-truth")
    truth = simulate_flight(base / "flight", cubes=2, bands=4, samples=128, lines=200, cubes_per_pass=2, seed=5,
                            gnss_bias_m=BIAS)
    return base / "flight", truth, {"sbet": _write_sbet(truth, base / "flight.sbet"),
                                    "csv": _write_csv(truth, base / "qinertia.csv")}


def _sizes(shifts: np.ndarray) -> np.ndarray:
    assert len(shifts) >= 15, len(shifts)
    return np.hypot(shifts[:, 0], shifts[:, 1])


@pytest.mark.parametrize("kind", ["sbet", "csv"])
def test_an_independent_trajectory_renders_where_the_truth_is(biased, kind):
    from archive.sources.raw import RawFlightSource

    directory, truth, files = biased
    columns = MAPPING if kind == "csv" else None
    source = RawFlightSource(directory, NavigationParams(), navigation=files[kind], navigation_columns=columns)
    size = _sizes(render_shifts(source, truth, truth.ground_height, BAND))
    assert np.median(size) <= 0.1 and np.percentile(size, 95) <= 0.3, (np.median(size), np.percentile(size, 95))
    lcf = RawFlightSource(directory, NavigationParams())
    biased_size = _sizes(render_shifts(lcf, truth, truth.ground_height, BAND)) if kind == "sbet" else None
    if biased_size is not None:   # the recorder's navigation: tens of pixels off
        assert np.median(biased_size) > 3, np.median(biased_size)


def test_the_rendered_trajectory_has_no_gap(biased, tmp_path):
    """``archive render --navigation SBET`` through the pipeline: every pixel inside the true footprint
    (eroded by 1.5 px) has a value, none outside it (dilated)."""
    import subprocess
    import sys

    import xarray as xr

    from archive.grid import Grid

    directory, truth, files = biased
    out = tmp_path / "m.zarr"
    done = subprocess.run([sys.executable, "-m", "archive", "render", str(directory), "--fov", str(truth.fov_deg),
                           "--gsd", str(truth.nominal_gsd), "--navigation", str(files["sbet"]),
                           "--ground-height", str(truth.ground_height), "--out", str(out), "--quiet"],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    ds = xr.open_zarr(out, decode_coords="all")
    values = ds["radiance"].isel(band=0).values
    x, y = ds["x"].values, ds["y"].values
    gsd = float(x[1] - x[0])
    grid = Grid(epsg=truth.epsg, gsd=gsd, x0=float(x[0]) - gsd / 2, y0=float(y[0]) + gsd / 2,
                width=values.shape[1], height=values.shape[0])
    eroded, dilated = eroded_dilated(truth.covered, grid, 1.5)   # the simulator's own footprint test
    has = np.isfinite(values)
    assert eroded.sum() > 2000
    assert not (eroded & ~has).any(), f"{(eroded & ~has).sum()} gaps inside the footprint"
    assert not (has & ~dilated).any(), f"{(has & ~dilated).sum()} values outside the footprint"


def test_the_lever_arm_applies_to_the_trajectory_as_to_the_lcf(tmp_path):
    """Both the ``.lcf`` and an SBET give the INS's (the IMU's) position, so the camera's lever arm
    (body frame, x forward, y right, z down) is added to either the same way (``--lever-arm``; the
    GNSS antenna's offset is the post-processing software's, already in the SBET): with it, both
    renders pass the truth test; without it, the trajectory's render is off by the lever arm."""
    from archive.simulator.command import simulate_flight
    from archive.sources.raw import RawFlightSource

    arm = (0.6, -0.5, 0.4)
    truth = simulate_flight(tmp_path / "flight", cubes=2, bands=4, samples=128, lines=200, cubes_per_pass=2,
                            seed=6, lever_arm_m=arm)
    sbet = _write_sbet(truth, tmp_path / "flight.sbet")
    for navigation in (None, sbet):
        source = RawFlightSource(tmp_path / "flight", NavigationParams(lever_arm_m=arm), navigation=navigation)
        size = _sizes(render_shifts(source, truth, truth.ground_height, BAND))
        assert np.median(size) <= 0.1 and np.percentile(size, 95) <= 0.3, (navigation, np.median(size))
    without = RawFlightSource(tmp_path / "flight", NavigationParams(), navigation=sbet)
    assert np.median(_sizes(render_shifts(without, truth, truth.ground_height, BAND))) > 1
