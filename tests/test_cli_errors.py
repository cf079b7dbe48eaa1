"""Bad input never gives a traceback: ``archive info`` on broken copies of a simulated flight exits
non-zero with exactly one line on stderr that names the offending file."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

SIM_ARGS = ["--cubes", "2", "--lines", "60", "--samples", "32", "--bands", "4", "--quiet"]


def _archive(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "archive", *args], capture_output=True, text=True,
                          timeout=timeout)


@pytest.fixture(scope="module")
def flight(tmp_path_factory) -> Path:
    directory = tmp_path_factory.mktemp("cli") / "flight"
    done = _archive("simulate", str(directory), *SIM_ARGS, timeout=300)
    assert done.returncode == 0, done.stderr
    return directory


def _cube(directory: Path, index: int = 0) -> dict[str, Path]:
    """Files of cube ``index`` in name order (the simulator's order is capture order)."""
    data = sorted(directory.glob("*.bil"))[index]
    return {"bil": data, "hdr": data.with_name(data.name + ".hdr"),
            "lcf": data.with_name(data.name[:-4] + ".lcf"), "times": data.with_name(data.name + ".times")}


def _edit_header(path: Path, key: str, value: str) -> None:
    lines = path.read_text().splitlines()
    out = [f"{key} = {value}" if line.split("=")[0].strip().lower() == key else line for line in lines]
    assert out != lines, f"{key} not in {path}"
    path.write_text("\n".join(out) + "\n")


def _lcf_rows(path: Path) -> list[str]:
    return path.read_text().splitlines()


def _write_rows(path: Path, rows: list[str]) -> None:
    path.write_text("\n".join(rows) + "\n")


def _truncate(path: Path, keep: int) -> None:
    data = path.read_bytes()
    path.write_bytes(data[:keep])


def _nan_in_lcf(c):
    rows = _lcf_rows(c["lcf"])
    fields = rows[10].split("\t")
    fields[5] = "nan"
    rows[10] = "\t".join(fields)
    _write_rows(c["lcf"], rows)
    return c["lcf"]


def _few_columns(c):
    rows = _lcf_rows(c["lcf"])
    rows[3] = "\t".join(rows[3].split("\t")[:7])
    _write_rows(c["lcf"], rows)
    return c["lcf"]


def _short_navigation(c):
    rows = _lcf_rows(c["lcf"])
    _write_rows(c["lcf"], rows[: len(rows) // 2])
    return c["lcf"]


def _few_times(c):
    rows = c["times"].read_text().splitlines()
    c["times"].write_text("\n".join(rows[:-5]) + "\n")
    return c["times"]


def _non_monotonic_times(c):
    rows = c["times"].read_text().splitlines()
    rows[20], rows[21] = rows[21], rows[20]
    c["times"].write_text("\n".join(rows) + "\n")
    return c["times"]


def _extra_bytes(c):
    with open(c["bil"], "ab") as f:
        f.write(b"\0" * 64)
    return c["bil"]


def _removed(key):
    def broken(c):
        c[key].unlink()
        return c[key]
    return broken


def _emptied(key):
    def broken(c):
        c[key].write_bytes(b"")
        return c[key]
    return broken


def _bad_header(key, value):
    def broken(c):
        _edit_header(c["hdr"], key, value)
        return c["hdr"]
    return broken


def _truncated_bil(c):
    _truncate(c["bil"], c["bil"].stat().st_size - 100)
    return c["bil"]


def _corrupt_icp(c):
    icp = next(c["bil"].parent.glob("*.icp"))
    icp.write_bytes(b"not a zip file")
    return icp


# name -> breaks a copy of the flight (cube 1 where it matters that it is not the first cube) and
# returns the file the message must name
CASES: dict[str, Callable[[dict[str, Path]], Path]] = {
    "missing lcf": _removed("lcf"),
    "missing times": _removed("times"),
    "truncated bil": _truncated_bil,
    "extra bytes in bil": _extra_bytes,
    "unknown data type": _bad_header("data type", "99"),
    "unknown interleave": _bad_header("interleave", "xyz"),
    "fewer times than lines": _few_times,
    "non-monotonic times": _non_monotonic_times,
    "lcf with NaN": _nan_in_lcf,
    "lcf with too few columns": _few_columns,
    "navigation does not cover the cube": _short_navigation,
    "empty bil": _emptied("bil"),
    "empty lcf": _emptied("lcf"),
    "empty times": _emptied("times"),
    "corrupt calibration": _corrupt_icp,
}


def _run_case(flight: Path, root: Path, name: str) -> tuple[Path, subprocess.CompletedProcess]:
    copy = root / name.replace(" ", "_")
    shutil.copytree(flight, copy)
    offending = CASES[name](_cube(copy, 1))
    return offending, _archive("info", str(copy))


@pytest.fixture(scope="module")
def results(flight, tmp_path_factory) -> dict[str, tuple[Path, subprocess.CompletedProcess]]:
    """Run every case at once (each is a separate process)."""
    root = tmp_path_factory.mktemp("broken")
    with ThreadPoolExecutor(max_workers=4) as pool:
        futures = {name: pool.submit(_run_case, flight, root, name) for name in CASES}
        return {name: f.result() for name, f in futures.items()}


def _assert_one_line_error(done: subprocess.CompletedProcess, name: str) -> str:
    assert done.returncode != 0, f"exit code 0 for broken input; stdout: {done.stdout[:300]}"
    assert "Traceback" not in done.stderr, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr
    assert name in lines[0], lines[0]
    assert lines[0].startswith("archive info: error: ")
    return lines[0]


def test_good_flight_summary(flight):
    done = _archive("info", str(flight))
    assert done.returncode == 0, done.stderr
    assert done.stderr == ""
    assert "EPSG:32616" in done.stdout
    done = _archive("info", str(flight), "--json")
    assert done.returncode == 0, done.stderr
    summary = json.loads(done.stdout)
    assert summary["cubes"] == 2 and summary["lines"] == 120
    assert summary["samples"] == 32 and summary["bands"] == 4
    assert summary["epsg"] == 32616
    assert [c["lines"] for c in summary["cube_list"]] == [60, 60]
    # simulator: ~10 m/s, ~40 m above the ground
    assert 8.0 < summary["mean_speed_m_s"] < 12.0
    assert summary["start_utc"].startswith("20")
    assert summary["calibration"] is not None


def test_missing_directory(tmp_path):
    missing = tmp_path / "no_such_flight"
    _assert_one_line_error(_archive("info", str(missing)), missing.name)


@pytest.mark.parametrize("name", list(CASES))
def test_broken_flight(results, name):
    offending, done = results[name]
    _assert_one_line_error(done, offending.name)


def test_sync_offset_beyond_navigation(flight):
    done = _archive("info", str(flight), "--sync-offset", "5")
    line = _assert_one_line_error(done, ".lcf")
    assert "navigation covers" in line
