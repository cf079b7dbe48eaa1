"""``archive info --navigation`` (issue 46): a raw flight checked and summarised with a post-processed
trajectory instead of its ``.lcf``, a trajectory that leaves lines without a pose refused in one line, and a
collection summarised from ``lcf`` or its stored track, the summary naming the source and listing them.

The flight's ``.lcf`` carries an undeclared real-time bias (``gnss_bias_m``: 0.8 m up among others); the
trajectories are written here by an independent writer (numpy's structured records, the csv module and
pyproj, not :mod:`archive.simulator.postprocessed`) from the simulator's error-free INS path, so a summary
from the trajectory sits 0.8 m below the ``.lcf``'s.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from helpers import TINY_FLIGHT, ingest_each
from trajectory_writer import COLUMNS, KEYS, write_csv, write_sbet
from trajectory_writer import true_path as _true_path

from archive.cli import main

BIAS = (1.5, -1.1, 0.8)   # E, N, up metres: the .lcf is off by this
MAPPING = ",".join(f"{k}={c}" for k, c in zip(KEYS, COLUMNS))


@pytest.fixture(scope="module")
def ppk(simulated, tmp_path_factory):
    """(flight, {kind: trajectory file}, truth): a tiny flight with a biased .lcf and its trajectories:
    whole (SBET, CSV), cut short at the middle of the second cube, and with a 0.5 s gap in the first cube."""
    flight, truth = simulated(seed=7, gnss_bias_m=BIAS, **TINY_FLIGHT)
    base = tmp_path_factory.mktemp("info-ppk")
    rows = _true_path(truth)
    t = rows[0]
    second = truth.cubes[1].line_time
    first = truth.cubes[0].line_time
    cut = t < float(second[len(second) // 2])
    hole = (t < float(first[5])) | (t > float(first[5]) + 0.5)
    files = {"sbet": write_sbet(base / "ppk.sbet", rows), "csv": write_csv(base / "qinertia.csv", rows),
             "short": write_sbet(base / "short.out", [r[cut] for r in rows]),
             "gap": write_sbet(base / "gap.out", [r[hole] for r in rows])}
    return flight, files, truth


def _info(capsys, *argv: str) -> dict:
    capsys.readouterr()
    assert main(["info", *argv, "--json"]) == 0
    return json.loads(capsys.readouterr().out)


def _text(capsys, *argv: str) -> str:
    capsys.readouterr()
    assert main(["info", *argv]) == 0
    return capsys.readouterr().out


def test_info_without_the_option_reads_the_lcf_as_before(ppk, capsys):
    flight, _, _ = ppk
    summary = _info(capsys, str(flight))
    assert summary["navigation"] == "lcf" and summary["navigation_sources"] == ["lcf"]
    assert all(c["lcf_rows"] == c["navigation_rows"] for c in summary["cube_list"])
    assert "navigation " not in _text(capsys, str(flight))   # no new line for a flight with only its .lcf
    assert _info(capsys, str(flight), "--navigation", "lcf") == summary


@pytest.mark.parametrize("kind", ["sbet", "csv"])
def test_info_summarises_the_flight_from_a_covering_trajectory(ppk, capsys, kind):
    flight, files, _ = ppk
    extra = ["--navigation-columns", MAPPING] if kind == "csv" else []
    lcf = _info(capsys, str(flight))
    summary = _info(capsys, str(flight), "--navigation", str(files[kind]), *extra)
    used = str(files[kind].absolute())
    assert summary["navigation"] == used and summary["navigation_sources"] == ["lcf", used]
    assert summary["navigation_default"] == "lcf"
    # the same flight (id, lines, times), its track from the trajectory: the .lcf's 0.8 m bias up is gone
    for key in ("id", "cubes", "strips", "lines", "start_gps_s", "end_gps_s", "epsg"):
        assert summary[key] == lcf[key], key
    assert lcf["mean_altitude_m"] - summary["mean_altitude_m"] == pytest.approx(BIAS[2], abs=0.05)
    assert summary["track_length_m"] == pytest.approx(lcf["track_length_m"], rel=0.1)
    for c, lc in zip(summary["cube_list"], lcf["cube_list"]):
        # the .lcf's rows as recorded; the trajectory's epochs over the cube's lines (and two beyond each end)
        span = (c["end_s"] - c["start_s"]) * 200.0
        assert c["lcf_rows"] == lc["lcf_rows"] and span < c["navigation_rows"] <= span + 6, (c, span)
        assert lc["mean_altitude_m"] - c["mean_altitude_m"] == pytest.approx(BIAS[2], abs=0.05)
    text = _text(capsys, str(flight), "--navigation", str(files[kind]), *extra)
    assert f"navigation {used} " in text and f"sources: lcf (default), {used}" in text


@pytest.mark.parametrize("kind, says", [("short", "covers "), ("gap", "with 1 gaps over 0.1 s")])
def test_a_trajectory_leaving_lines_uncovered_is_refused_in_one_line(ppk, kind, says):
    flight, files, _ = ppk
    done = subprocess.run([sys.executable, "-m", "archive", "info", str(flight), "--navigation", str(files[kind])],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode != 0 and done.stdout == ""
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr
    line = lines[0]
    assert line.startswith("archive info: error: ") and "Traceback" not in done.stderr
    assert str(files[kind]) in line and says in line, line
    assert "have no pose" in line and " lines " in line and ".lcf needs " in line, line   # the cube, its lines


def test_info_on_a_collection_picks_lcf_or_its_track(ppk, tmp_path, capsys):
    flight, files, _ = ppk
    archive = str(tmp_path / "archive")
    (cid,) = ingest_each([flight], archive, navigation=str(files["sbet"]))
    name = files["sbet"].stem
    raw_lcf = _info(capsys, str(flight))
    raw_ppk = _info(capsys, str(flight), "--navigation", str(files["sbet"]))
    default = _info(capsys, cid, "--archive", archive)
    assert default["navigation"] == name == default["navigation_default"]
    assert default["navigation_sources"] == ["lcf", name]
    on_lcf = _info(capsys, cid, "--archive", archive, "--navigation", "lcf")
    on_track = _info(capsys, cid, "--archive", archive, "--navigation", name)
    assert on_lcf["navigation"] == "lcf" and on_lcf["navigation_sources"] == ["lcf", name]
    assert on_track == default
    # the collection from each source summarises as the raw flight from the same one
    for key in ("track_length_m", "mean_altitude_m", "min_altitude_m", "max_altitude_m", "lines", "start_gps_s"):
        assert on_lcf[key] == raw_lcf[key] and on_track[key] == raw_ppk[key], key
    assert on_lcf["mean_altitude_m"] - on_track["mean_altitude_m"] == pytest.approx(BIAS[2], abs=0.05)
    assert [c["lcf_rows"] for c in on_track["cube_list"]] == [c["lcf_rows"] for c in raw_lcf["cube_list"]]
    text = _text(capsys, cid, "--archive", archive, "--navigation", "lcf")
    assert "navigation lcf " in text and f"sources: lcf, {name} (default)" in text
    # a name it does not have, or a file: refused, naming what it has
    capsys.readouterr()
    assert main(["info", cid, "--archive", archive, "--navigation", "nope"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "'nope'" in err and f"(it has: lcf, {name})" in err, err
    assert main(["info", cid, "--archive", archive, "--navigation", str(files["sbet"])]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--navigation lcf or a track's name" in err, err


def test_navigation_columns_without_navigation_is_refused(ppk, capsys):
    flight, _, _ = ppk
    capsys.readouterr()
    assert main(["info", str(flight), "--navigation-columns", MAPPING]) == 2
    err = capsys.readouterr().err
    assert err.startswith("archive info: error: --navigation-columns:") and "no --navigation" in err, err
