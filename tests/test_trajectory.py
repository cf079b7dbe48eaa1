"""Post-processed trajectories (issue 46): SBET and CSV exports read, put on the flight's clock and used
instead of the recorder's ``.lcf`` (``render --navigation``), checked against the simulator's truth.

The flight's ``.lcf`` records every position 1.5 m / -1.1 m / 0.8 m off the truth (an undeclared real-time
bias, ``--gnss-bias``); its trajectory files hold the true INS path (:mod:`archive.simulator.postprocessed`).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers import FOV

from archive.errors import ArchiveError, FormatError, InputError, NavigationError
from archive.params import NavigationParams

BIAS = (1.5, -1.1, 0.8)


@pytest.fixture(scope="module")
def biased(tmp_path_factory):
    """(directory, truth, {kind: trajectory file}) of a small flight whose .lcf carries BIAS."""
    from archive.simulator.command import simulate_flight
    from archive.simulator.postprocessed import write_trajectory

    base = tmp_path_factory.mktemp("ppk")
    truth = simulate_flight(base / "flight", cubes=2, bands=4, samples=64, lines=100, cubes_per_pass=2, seed=4,
                            gnss_bias_m=BIAS)
    files = {"sbet": write_trajectory(truth, base / "flight.out"),
             "csv": write_trajectory(truth, base / "flight_ie.txt"),
             "full": write_trajectory(truth, base / "flight_full.csv", full_seconds=True)}
    return base / "flight", truth, files


def _position_error(source, truth) -> np.ndarray:
    """(lines, 3) camera position minus truth at every line's exposure start (E, N, up metres)."""
    out = []
    for k in range(len(source.cubes)):
        e, n, alt = source.frame.from_ned(source.poses(k).position)
        want, _ = truth.trajectory(truth.cubes[k].line_time)
        out.append(np.column_stack([e - want[:, 0], n - want[:, 1], alt - want[:, 2]]))
    return np.concatenate(out)


@pytest.mark.parametrize("kind", ["sbet", "csv", "full"])
def test_the_trajectory_puts_every_line_where_the_truth_is(biased, kind):
    from archive.sources.raw import RawFlightSource

    directory, truth, files = biased
    lcf = _position_error(RawFlightSource(directory, NavigationParams()), truth)
    np.testing.assert_allclose(np.median(lcf, axis=0), BIAS, atol=0.05)   # the recorder's real-time bias
    ppk = _position_error(RawFlightSource(directory, NavigationParams(), navigation=files[kind]), truth)
    assert np.abs(ppk).max() < (0.005 if kind == "sbet" else 0.02), np.abs(ppk).max(axis=0)


def test_sbet_fields_as_pdal_reads_them(biased):
    """Field order and units as PDAL's readers.sbet documents them: time, lat, lon (rad), height, velocities,
    roll, pitch, platform heading, wander angle...; true heading = platform heading - wander angle."""
    from archive.formats.trajectory import read_trajectory

    _, truth, files = biased
    rec = np.fromfile(files["sbet"], "<f8").reshape(-1, 17)
    traj = read_trajectory(files["sbet"])
    assert traj.week_seconds and traj.time.size == rec.shape[0]
    np.testing.assert_allclose(traj.lat, np.degrees(rec[:, 1]))
    np.testing.assert_allclose(traj.heading, np.mod(rec[:, 9] - rec[:, 10], 2 * np.pi))
    csv = read_trajectory(files["csv"])
    np.testing.assert_allclose(csv.lat, traj.lat, atol=1e-9)
    np.testing.assert_allclose(np.unwrap(csv.heading), np.unwrap(traj.heading), atol=1e-6)


def test_a_flight_across_a_gps_week_boundary(tmp_path):
    """Seconds of week start again from 0 inside the flight: unwrapped, and the week comes from the .lcf."""
    from archive.formats.lcf import GPS_EPOCH, gps_seconds_to_datetime
    from archive.simulator.command import simulate_flight, start_gps
    from archive.simulator.postprocessed import write_trajectory
    from archive.sources.raw import RawFlightSource

    boundary = 2322 * 604800.0   # a GPS week's start (2024-07-14)
    probe = simulate_flight(tmp_path / "probe", cubes=2, bands=2, samples=16, lines=100, cubes_per_pass=2, seed=1)
    first, last = probe.cubes[0].line_time[0], probe.cubes[-1].line_time[-1]
    start = boundary - ((first + last) / 2 - start_gps(None, seed=1))   # the boundary mid-flight
    when = gps_seconds_to_datetime(start)
    truth = simulate_flight(tmp_path / "f", cubes=2, bands=2, samples=16, lines=100, cubes_per_pass=2, seed=1,
                            start=when, gnss_bias_m=BIAS)
    assert truth.cubes[0].line_time[0] < boundary < truth.cubes[-1].line_time[-1], (when, GPS_EPOCH)
    path = write_trajectory(truth, tmp_path / "f.sbet")
    raw = np.fromfile(path, "<f8").reshape(-1, 17)[:, 0]
    assert raw.max() > 604000 and raw.min() < 100   # it wraps
    err = _position_error(RawFlightSource(tmp_path / "f", NavigationParams(), navigation=path), truth)
    assert np.abs(err).max() < 0.005


def test_render_navigation_from_the_command_line(biased, tmp_path):
    directory, truth, files = biased
    out = tmp_path / "ppk.tif"
    done = subprocess.run([sys.executable, "-m", "archive", "render", str(directory), "--fov", str(FOV),
                           "--gsd", "0.5", "--navigation", str(files["sbet"]), "--out", str(out), "--quiet"],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    item = json.loads(Path(str(out) + ".json").read_text())
    recipe = item["properties"]["archive:recipe"]
    assert f"--navigation {files['sbet']}" in recipe["command"]
    assert any(e.get("option") == "navigation" for e in recipe["inputs"])   # --resume sees it change


def _damaged(src: Path, dest: Path, edit) -> Path:
    lines = src.read_text().splitlines()
    dest.write_text("\n".join(edit(lines)) + "\n")
    return dest


def test_bad_trajectories_are_refused_by_name(biased, tmp_path):
    from archive.formats.trajectory import parse_columns, read_trajectory
    from archive.sources.raw import RawFlightSource

    directory, truth, files = biased
    csv = files["csv"]
    short = _damaged(csv, tmp_path / "short.csv", lambda ls: ls[: len(ls) // 2])   # stops mid-flight
    with pytest.raises(NavigationError, match=r"short\.csv: covers .* lines \d+-\d+ of that cube have no pose"):
        RawFlightSource(directory, NavigationParams(), navigation=short)
    gap = _damaged(csv, tmp_path / "gap.csv", lambda ls: ls[:300] + ls[500:])   # a second of epochs missing
    with pytest.raises(NavigationError, match=r"gap\.csv: covers .*with 1 gaps"):
        RawFlightSource(directory, NavigationParams(), navigation=gap)
    nan = _damaged(csv, tmp_path / "nan.csv", lambda ls: ls[:10] + [ls[10].replace(ls[10].split(",")[1], "nan")]
                   + ls[11:])
    with pytest.raises(FormatError, match=r"nan\.csv: line 11: a value is not a number"):
        read_trajectory(nan)
    back = _damaged(csv, tmp_path / "back.csv", lambda ls: ls[:10] + [ls[12], ls[11]] + ls[13:])
    with pytest.raises(FormatError, match=r"back\.csv: line 12: .*not monotonic"):
        read_trajectory(back)
    other = _damaged(csv, tmp_path / "qinertia.csv",
                     lambda ls: ["GPS Time;Latitude;Longitude;Altitude Ellipsoid;Roll;Pitch;Yaw"]
                     + [x.replace(",", ";") for x in ls[1:]])
    with pytest.raises(FormatError, match="has no column 'GPSTime'.*--navigation-columns"):
        read_trajectory(other)
    cols = parse_columns("time=GPS Time,lat=Latitude,lon=Longitude,height=Altitude Ellipsoid,roll=Roll,"
                         "pitch=Pitch,heading=Yaw")
    np.testing.assert_allclose(read_trajectory(other, cols).lat, read_trajectory(csv).lat)
    with pytest.raises(InputError, match="--navigation-columns"):
        parse_columns("time=a,lat=b")
    (tmp_path / "cut.out").write_bytes(files["sbet"].read_bytes()[:1000])
    with pytest.raises(FormatError, match="not a whole number of SBET records"):
        read_trajectory(tmp_path / "cut.out")
    proc = subprocess.run([sys.executable, "-m", "archive", "render", str(directory), "--fov", str(FOV), "--gsd",
                           "0.5", "--navigation", str(short), "--out", str(tmp_path / "x.tif")],
                          capture_output=True, text=True, timeout=300)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode != 0 and len(lines) == 1 and "short.csv" in lines[0], proc.stderr
    assert not (tmp_path / "x.tif").exists()
    assert issubclass(NavigationError, ArchiveError)


def test_a_utc_time_column_gets_the_leap_seconds(biased, tmp_path):
    """``utc=COL``: UTC seconds of week; GPS = UTC + 18 s in 2024: the same poses as the GPS export."""
    from archive.formats.trajectory import parse_columns
    from archive.sources.raw import RawFlightSource

    directory, truth, files = biased
    lines = files["csv"].read_text().splitlines()
    rows = [x.split(",") for x in lines[1:]]
    utc = tmp_path / "utc.csv"
    utc.write_text("UTCTime,Latitude,Longitude,H-Ell,Roll,Pitch,Heading\n"
                   + "".join(",".join([f"{float(r[0]) - 18.0:.5f}", *r[1:]]) + "\n" for r in rows))
    cols = parse_columns("utc=UTCTime,lat=Latitude,lon=Longitude,height=H-Ell,roll=Roll,pitch=Pitch,heading=Heading")
    err = _position_error(RawFlightSource(directory, NavigationParams(), navigation=utc, navigation_columns=cols),
                          truth)
    assert np.abs(err).max() < 0.02
    wrong = parse_columns("time=UTCTime,lat=Latitude,lon=Longitude,height=H-Ell,roll=Roll,pitch=Pitch,heading=Heading")
    with pytest.raises(NavigationError, match="have no pose"):   # read as GPS time: 18 s away from the lines
        RawFlightSource(directory, NavigationParams(), navigation=utc, navigation_columns=wrong)


def _values(path: Path) -> np.ndarray:
    import rasterio

    with rasterio.open(path) as ds:
        return ds.read()


def test_ingest_stores_the_trajectory_as_the_default_source(biased, tmp_path):
    """``ingest --navigation FILE``: a checksummed track beside the .lcf, the collection's default source; a
    render of the collection equals the raw flight's render from the same file, ``--navigation lcf`` the raw
    flight's .lcf render, bit for bit; an unknown source is one line naming the ones there."""
    import zarr

    from archive.collection import verify_store

    directory, truth, files = biased
    archive = tmp_path / "arc"

    def cli(*args):
        done = subprocess.run([sys.executable, "-m", "archive", *args], capture_output=True, text=True, timeout=300)
        return done

    done = cli("ingest", str(directory), "--archive", str(archive), "--fov", str(FOV), "--navigation",
               str(files["sbet"]), "--quiet")
    assert done.returncode == 0, done.stderr
    cid = done.stdout.split(":")[0]
    store = archive / "collections" / f"{cid}.zarr"
    group = zarr.open_group(store, mode="r")
    assert group.attrs["navigation_tracks"]["default"] == "flight" and "track_flight" in group
    assert verify_store(store) == []
    assert any(s["name"] == "flight.out" for s in group.attrs["sources"])   # the file's sha256 recorded
    common = ["--gsd", "0.5", "--quiet"]
    raw_ppk, raw_lcf = tmp_path / "raw_ppk.tif", tmp_path / "raw_lcf.tif"
    assert cli("render", str(directory), "--fov", str(FOV), "--navigation", str(files["sbet"]), "--out", str(raw_ppk),
               *common).returncode == 0
    assert cli("render", str(directory), "--fov", str(FOV), "--like", str(raw_ppk), "--out", str(raw_lcf),
               *common).returncode == 0
    col, col_lcf = tmp_path / "col.tif", tmp_path / "col_lcf.tif"
    assert cli("render", cid, "--archive", str(archive), "--like", str(raw_ppk), "--out", str(col),
               *common).returncode == 0
    done = cli("render", cid, "--archive", str(archive), "--navigation", "lcf", "--like", str(raw_ppk),
               "--out", str(col_lcf), *common)
    assert done.returncode == 0, done.stderr
    np.testing.assert_array_equal(_values(col), _values(raw_ppk))
    np.testing.assert_array_equal(_values(col_lcf), _values(raw_lcf))
    assert not np.array_equal(_values(col), _values(col_lcf), equal_nan=True)   # the bias shows
    done = cli("render", cid, "--archive", str(archive), "--navigation", "rtk", "--gsd", "0.5",
               "--out", str(tmp_path / "x.tif"))
    lines = done.stderr.strip().splitlines()
    assert done.returncode != 0 and len(lines) == 1 and "has no navigation source 'rtk'" in lines[0], done.stderr
    assert "lcf, flight" in lines[0]
    # the ingest again without the trajectory: refused, not silently kept
    done = cli("ingest", str(directory), "--archive", str(archive), "--fov", str(FOV), "--quiet")
    assert done.returncode != 0 and "another navigation source" in done.stderr, done.stderr


def test_calibrate_estimates_from_the_trajectory(biased, tmp_path):
    """``calibrate --navigation FILE`` opens the flight on the trajectory (every line where the truth
    is, not the .lcf's biased positions); a missing file is one line naming it."""
    from archive.calibrate.command import open_calibration_sources

    directory, truth, files = biased
    (lcf,), _ = open_calibration_sources([str(directory)], fov=FOV)
    np.testing.assert_allclose(np.median(_position_error(lcf, truth), axis=0), BIAS, atol=0.05)
    (ppk,), fov = open_calibration_sources([str(directory)], fov=FOV, navigation=files["sbet"])
    assert fov == FOV and np.abs(_position_error(ppk, truth)).max() < 0.005
    missing = tmp_path / "nowhere.out"
    done = subprocess.run([sys.executable, "-m", "archive", "calibrate", str(directory), "--fov", str(FOV),
                           "--navigation", str(missing)], capture_output=True, text=True, timeout=120)
    lines = done.stderr.strip().splitlines()
    assert done.returncode != 0 and len(lines) == 1 and str(missing) in lines[0], done.stderr
