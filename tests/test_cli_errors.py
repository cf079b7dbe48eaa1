"""Bad input never gives a traceback: ``archive info`` on broken copies of a simulated flight exits
non-zero with exactly one line on stderr that names the offending file.

Two defects also go through ``archive info``, ``archive ingest`` and ``archive render`` (issue 8): an
``.lcf`` with longitudes or latitudes out of range, and a flight holding a byte copy of one of its
cubes under another name. Each command runs in its own session; it must write nothing, change
nothing (the flight, an existing archive) and leave no process of its session behind.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import psutil
import pytest
from helpers import FOV

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


# --- issue 8: two defects through info, ingest and render, in their own sessions -------------------



@dataclass(frozen=True)
class Finished:
    """A CLI run: exit code, output, and the processes of its session still alive after it exited."""

    args: tuple[str, ...]
    returncode: int
    stdout: str
    stderr: str
    left: tuple[str, ...]


def _session_processes(pid: int, known: dict[int, float]) -> None:
    """Add to ``known`` (pid -> creation time) the live processes of session/group ``pid`` and its
    descendants (a child that left the session is still found through its parent)."""
    try:
        descendants = psutil.Process(pid).children(recursive=True)
    except psutil.Error:
        descendants = []
    candidates = list(descendants)
    for proc in psutil.process_iter(["pid"]):
        try:
            if os.getpgid(proc.pid) == pid or os.getsid(proc.pid) == pid:
                candidates.append(proc)
        except OSError:
            continue
    for proc in candidates:
        try:
            if proc.pid != pid and proc.status() != psutil.STATUS_ZOMBIE:
                known.setdefault(proc.pid, proc.create_time())
        except psutil.Error:
            continue


def _still_alive(known: dict[int, float]) -> list[psutil.Process]:
    """Processes of ``known`` alive (not zombies: those have exited, waiting for init to reap them)."""
    alive = []
    for pid, created in known.items():
        try:
            proc = psutil.Process(pid)
            if proc.create_time() == created and proc.status() != psutil.STATUS_ZOMBIE:
                alive.append(proc)
        except psutil.Error:
            continue
    return alive


def run_in_session(*args: str, timeout: float = 300, grace: float = 5.0, env: dict | None = None) -> Finished:
    """``python -m archive ARGS`` as the leader of a new session (and process group). After it
    exits, wait up to ``grace`` seconds for every process it started (its session and group, and
    descendants seen while it ran) to end; those still alive are listed in ``left`` and killed."""
    proc = subprocess.Popen([sys.executable, "-m", "archive", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True,
                            env=None if env is None else {**os.environ, **env})
    known: dict[int, float] = {}
    with ThreadPoolExecutor(max_workers=1) as pool:
        output = pool.submit(proc.communicate, timeout=timeout)
        while not output.done():
            _session_processes(proc.pid, known)
            time.sleep(0.05)
        try:
            stdout, stderr = output.result()
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
            raise
    _session_processes(proc.pid, known)
    deadline = time.monotonic() + grace
    while (alive := _still_alive(known)) and time.monotonic() < deadline:
        time.sleep(0.1)
    left = []
    for p in alive:
        try:
            left.append(f"{p.pid}: {' '.join(p.cmdline())[:200]}")
            p.kill()  # started by this test's command: do not let it outlive the test
        except psutil.Error:
            continue
    return Finished(tuple(args), proc.returncode, stdout, stderr, tuple(left))


def snapshot(*roots: Path) -> dict[str, str]:
    """Recursive listing of ``roots`` with each file's sha256 (directories as 'dir', links by target)."""
    out = {}
    for root in roots:
        if not root.exists():
            out[str(root)] = "absent"
            continue
        for path in sorted([root, *root.rglob("*")]):
            if path.is_symlink():
                out[str(path)] = f"link {os.readlink(path)}"
            elif path.is_dir():
                out[str(path)] = "dir"
            else:
                out[str(path)] = hashlib.sha256(path.read_bytes()).hexdigest()
    return out


def _set_column(path: Path, column: int, value: str, comment: bool = False) -> None:
    """Set 1-based ``column`` of every row of an .lcf to ``value`` (optionally behind a comment line)."""
    rows = [line.split() for line in path.read_text().splitlines() if line.strip()]
    for row in rows:
        row[column - 1] = value
    text = "\n".join("\t".join(row) for row in rows) + "\n"
    path.write_text(("# time roll pitch yaw lon lat alt 0 0 flag\n" if comment else "") + text)


def _lon_200(directory: Path) -> list[str]:
    c = _cube(directory, 1)
    _set_column(c["lcf"], 5, "200.0")
    return [c["lcf"].name, "line 1,", "column 5", "longitude", "200"]


def _lat_95(directory: Path) -> list[str]:
    c = _cube(directory, 1)
    _set_column(c["lcf"], 6, "95.0", comment=True)  # the first row is on line 2
    return [c["lcf"].name, "line 2,", "column 6", "latitude", "95"]


def _duplicated_cube(directory: Path) -> list[str]:
    c = _cube(directory, 0)
    base = c["bil"].name[:-len(".bil")]
    for path in c.values():  # all four files, byte for byte, under another base name
        shutil.copyfile(path, path.with_name("copy_of_first" + path.name[len(base):]))
    return [base, "copy_of_first"]


DEFECTS: dict[str, Callable[[Path], list[str]]] = {
    "longitude 200": _lon_200,
    "latitude 95": _lat_95,
    "duplicated cube": _duplicated_cube,
}
COMMANDS = ("info", "ingest", "ingest-new", "render")


@dataclass(frozen=True)
class DefectRun:
    run: Finished
    expected: list[str]
    before: dict[str, str]
    after: dict[str, str]
    watched: tuple[Path, ...]


@pytest.fixture(scope="module")
def archive_root(flight, tmp_path_factory) -> tuple[Path, str]:
    """An archive holding the good flight (what the refused commands must leave untouched)."""
    root = tmp_path_factory.mktemp("archive") / "archive"
    done = _archive("ingest", str(flight), "--archive", str(root), "--fov", str(FOV), "--quiet", timeout=300)
    assert done.returncode == 0, done.stderr
    cid = done.stdout.split(":")[0].strip()
    return root, cid


def _defect_run(flight: Path, archive_root: tuple[Path, str], work: Path, defect: str, command: str) -> DefectRun:
    case = work / f"{defect.replace(' ', '_')}-{command}"
    bad = case / "flight"
    shutil.copytree(flight, bad)
    expected = DEFECTS[defect](bad)
    root, cid = archive_root
    out = case / "out"  # does not exist: nothing may create it
    if command == "info":
        args, watched = ("info", str(bad)), (bad, out)
    elif command == "ingest":
        args, watched = ("ingest", str(bad), "--archive", str(root), "--fov", str(FOV), "--quiet"), (bad, root)
    elif command == "ingest-new":
        args, watched = ("ingest", str(bad), "--archive", str(out / "archive"), "--fov", str(FOV), "--quiet"), (bad, out)
    else:  # the good collection first: the archive is read before the bad flight is refused
        args = ("render", cid, str(bad), "--archive", str(root), "--fov", str(FOV), "--gsd", "0.1",
                "--out", str(out / "mosaic.zarr"), "--quicklook", str(out / "look.png"), "--quiet")
        watched = (bad, root, out)
    before = snapshot(*watched)
    run = run_in_session(*args)
    return DefectRun(run, expected, before, snapshot(*watched), watched)


@pytest.fixture(scope="module")
def defect_runs(flight, archive_root, tmp_path_factory) -> dict[tuple[str, str], DefectRun]:
    work = tmp_path_factory.mktemp("defects")
    cases = [(d, c) for d in DEFECTS for c in COMMANDS]
    with ThreadPoolExecutor(max_workers=4) as pool:
        futures = {case: pool.submit(_defect_run, flight, archive_root, work, *case) for case in cases}
        return {case: f.result() for case, f in futures.items()}


@pytest.mark.parametrize("command", COMMANDS)
@pytest.mark.parametrize("defect", list(DEFECTS))
def test_defect_refused_cleanly(defect_runs, defect, command):
    result = defect_runs[defect, command]
    done = result.run
    assert done.returncode != 0, f"exit code 0; stdout: {done.stdout[:300]}"
    assert "Traceback" not in done.stderr, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr
    assert lines[0].startswith(f"archive {done.args[0]}: error: "), lines[0]
    for part in result.expected:
        assert part in lines[0], f"{part!r} not in {lines[0]!r}"
    assert done.stdout == ""
    assert result.after == result.before, "files changed: " + ", ".join(
        sorted(k for k in result.before.keys() | result.after.keys() if result.before.get(k) != result.after.get(k)))
    assert not done.left, f"processes left alive after {done.args[0]} exited: {done.left}"


def test_render_refused_after_its_cluster_started(flight, tmp_path):
    """A render refused after its local Dask cluster started (the output would be too large for
    the GSD: checked once the cube meshes exist) stops the cluster's processes before it exits."""
    out = tmp_path / "out"
    before = snapshot(flight, out)
    done = run_in_session("render", str(flight), "--fov", str(FOV), "--gsd", "0.00001", "--out", str(out / "m.zarr"),
                          "--quiet")
    assert done.returncode != 0 and "Traceback" not in done.stderr, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("archive render: error: --gsd"), done.stderr
    assert snapshot(flight, out) == before
    assert not done.left, f"processes left alive after render exited: {done.left}"


def test_duplicated_cube_with_reformatted_times(flight, tmp_path):
    bad = tmp_path / "flight"
    shutil.copytree(flight, bad)
    c = _cube(bad, 0)
    base = c["bil"].name[:-len(".bil")]
    for key in ("bil", "hdr", "lcf"):
        shutil.copyfile(c[key], c[key].with_name("copy_of_first" + c[key].name[len(base):]))
    values = c["times"].read_text().split()
    (bad / "copy_of_first.bil.times").write_text("\r\n".join(f"{float(v):.9f}" for v in values) + "\r\n")
    done = run_in_session("info", str(bad))
    assert done.returncode != 0 and len(done.stderr.strip().splitlines()) == 1, done.stdout
    assert base in done.stderr and "copy_of_first" in done.stderr
    assert not done.left


FAILING_READS = """\
import os
if os.environ.get("ARCHIVE_TEST_FAIL_READS"):
    import archive.sources.raw
    from archive.errors import InputError

    def read_bands(self, cube, bands):
        raise InputError(self.label, "injected read failure")

    archive.sources.raw.RawFlightSource.read_bands = read_bands
"""


def test_render_failing_on_a_worker(flight, tmp_path):
    """A render task that fails on a worker of the command's own cluster (pixel reads made to fail in
    every process through a ``sitecustomize`` on PYTHONPATH: the spawned workers load it too): one
    line naming the flight and cube, nothing written, no process left."""
    (tmp_path / "inject").mkdir()
    (tmp_path / "inject" / "sitecustomize.py").write_text(FAILING_READS)
    out = tmp_path / "out"
    before = snapshot(flight, out)
    done = run_in_session("render", str(flight), "--fov", str(FOV), "--gsd", "0.05", "--out", str(out / "m.zarr"),
                          "--quiet", env={"PYTHONPATH": os.pathsep.join(filter(None, [str(tmp_path / "inject"),
                                                                           os.environ.get("PYTHONPATH")])),
                               "ARCHIVE_TEST_FAIL_READS": "1"})
    assert done.returncode != 0 and "Traceback" not in done.stderr, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr
    assert lines[0].startswith(f"archive render: error: {flight} cube "), lines[0]
    assert lines[0].endswith(": injected read failure"), lines[0]
    assert snapshot(flight, out) == before
    assert not done.left, f"processes left alive after render exited: {done.left}"


def test_session_watch_sees_a_process_left_behind():
    """The watch itself: a command whose child outlives it is reported (and the child killed)."""
    code = ("import subprocess, sys; subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(60)']); "
            "print('started')")
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.DEVNULL, start_new_session=True)
    known: dict[int, float] = {}
    proc.wait(timeout=60)
    _session_processes(proc.pid, known)
    alive = _still_alive(known)
    assert len(alive) == 1 and "time.sleep(60)" in " ".join(alive[0].cmdline())
    alive[0].kill()


def test_bounds_in_degrees_are_named_and_converted(flight, tmp_path):
    """``--bounds`` given as longitudes and latitudes (a user's first guess) is one line that says so
    and gives the same box in the output CRS's metres, which then renders."""
    import pyproj

    lon, lat = -89.94, 35.12   # near the simulator's field (archive simulate --help): a box of ~550 x 670 m
    box = f"{lon - 0.003:.6f},{lat - 0.003:.6f},{lon + 0.003:.6f},{lat + 0.003:.6f}"
    out = tmp_path / "o.zarr"
    done = _archive("render", str(flight), "--fov", str(FOV), "--gsd", "0.5", f"--bounds={box}", "--out", str(out),
                    "--quiet")
    lines = done.stderr.strip().splitlines()
    assert done.returncode != 0 and len(lines) == 1 and "these look like degrees" in lines[0], done.stderr
    assert not out.exists()
    metres = lines[0].rsplit(": ", 1)[1].rstrip(")")
    w, s, e, n = (float(v) for v in metres.split(","))
    to = pyproj.Transformer.from_crs(4326, int(lines[0].split("(EPSG:")[1].split(")")[0]), always_xy=True)
    x, y = to.transform(lon, lat)
    assert w < x < e and s < y < n and 400 < e - w < 700 and 500 < n - s < 800, (metres, x, y)
