"""Post-processed trajectories written by an independent writer (numpy's structured records, the csv
module and pyproj, not :mod:`archive.simulator.postprocessed`) from a simulated flight's error-free
INS path, rendered over a flight whose ``.lcf`` carries an undeclared real-time bias (issue 46):
the render from the trajectory has no gap and no shift against the simulator's truth, the render
from the ``.lcf`` fails the same test."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from helpers import eroded_dilated
from trajectory_writer import COLUMNS, KEYS, true_path, write_csv, write_sbet

from archive.params import NavigationParams
from tests.test_render_truth import render_shifts

BIAS = (1.5, -1.1, 0.8)   # E, N, up metres: the recorder's real-time solution is off by this
BAND = 2
MAPPING = dict(zip(KEYS, COLUMNS))


def _write_sbet(truth, path: Path) -> Path:
    return write_sbet(path, true_path(truth))


def _write_csv(truth, path: Path) -> Path:
    return write_csv(path, true_path(truth, rate=100.0))


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
