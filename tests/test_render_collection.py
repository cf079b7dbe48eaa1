"""``archive render ID --archive A`` renders an ingested collection exactly as the raw flight.

Real ingest (Zarr), real CLI, real LocalCluster and EGL: the two Zarr mosaics must be identical
(same grid, same float32 values bit for bit, same saturation flags), and the render reads no raw
file (the raw flight is moved away before rendering the collection).
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import xarray as xr

from archive.cli import main
from helpers import FOV



@pytest.fixture(scope="module")
def raw_and_archive(tmp_path_factory):
    from archive.simulator.command import simulate_flight

    base = tmp_path_factory.mktemp("render_collection")
    flight = base / "flight"
    simulate_flight(flight, cubes=3, bands=5, samples=48, lines=100, cubes_per_pass=2, seed=5)
    archive_dir = base / "archive"
    assert main(["ingest", str(flight), "--archive", str(archive_dir), "--fov", str(FOV)]) == 0
    (item,) = (archive_dir / "catalog" / "items").glob("*.json")
    return flight, archive_dir, item.stem


def test_collection_render_equals_raw_render(raw_and_archive, tmp_path):
    flight, archive_dir, cid = raw_and_archive
    raw_out = tmp_path / "raw.zarr"
    assert main(["render", str(flight), "--fov", str(FOV), "--gsd", "0.1", "--out", str(raw_out), "--quiet"]) == 0
    moved = tmp_path / "moved-away"
    shutil.move(str(flight), moved)  # the collection render must not need the raw files
    try:
        col_out = tmp_path / "collection.zarr"
        # no --fov: the collection keeps the one it was ingested with; ground height 'auto' likewise
        assert main(["render", cid, "--archive", str(archive_dir), "--gsd", "0.1", "--out", str(col_out),
                     "--quiet"]) == 0
    finally:
        shutil.move(str(moved), flight)
    a = xr.open_zarr(raw_out, decode_coords="all")
    b = xr.open_zarr(col_out, decode_coords="all")
    assert a.rio.crs == b.rio.crs
    assert a.rio.transform() == b.rio.transform()
    va, vb = a["radiance"].values, b["radiance"].values
    assert va.shape == vb.shape and np.isfinite(va).sum() > 1000
    np.testing.assert_array_equal(va, vb)  # NaN positions and values identical
    np.testing.assert_array_equal(a["saturated"].values, b["saturated"].values)
    np.testing.assert_array_equal(a["wavelength"].values, b["wavelength"].values)


def test_unknown_collection_and_calibration_refused(raw_and_archive, tmp_path, capsys):
    flight, archive_dir, cid = raw_and_archive
    out = tmp_path / "x.zarr"
    assert main(["render", "no-such-id", "--archive", str(archive_dir), "--gsd", "0.1", "--out", str(out)]) != 0
    assert "no-such-id" in capsys.readouterr().err
    assert main(["render", cid, "--archive", str(archive_dir), "--gsd", "0.1", "--out", str(out),
                 "--calibration", str(flight / "calibration.icp")]) != 0
    assert "--calibration" in capsys.readouterr().err
    assert main(["render", "no-such-id", "--gsd", "0.1", "--out", str(out), "--fov", str(FOV)]) != 0
    assert "--archive" in capsys.readouterr().err
    assert not out.exists()
