"""No tracebacks where people pipe and script (issue 36, item 5).

Every command that prints is run with a stdout whose reader is gone (``archive ... | head``): it stops
without a traceback and without "Exception ignored" noise. Also: a flight given twice to ``ingest``,
batch lines printed past the progress bar on lines of their own (``tqdm.write``), and Python API errors
naming the function and keyword the caller used, not ``RenderOptions.create()`` or CLI flags.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import archive
from archive.api_errors import KeywordError
from archive.errors import InputError
from helpers import FOV

SIM_ARGS = ["--cubes", "2", "--lines", "60", "--samples", "32", "--bands", "4", "--quiet"]
FIRST, SECOND = "Pika-L-SIM_20240612T160000", "Pika-L-SIM_20240612T160100"


def _archive(*args: str, cwd: Path, timeout: float = 180, **kw) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    return subprocess.run([sys.executable, "-m", "archive", *args], cwd=cwd, text=True, timeout=timeout, env=env,
                          **({"capture_output": True} | kw))


@pytest.fixture(scope="module")
def work(tmp_path_factory) -> Path:
    """Two small flights (f0, f1) ingested into arc/."""
    d = tmp_path_factory.mktemp("pipes")
    for k in (0, 1):
        done = _archive("simulate", f"f{k}", *SIM_ARGS, "--seed", str(k), cwd=d)
        assert done.returncode == 0, done.stderr
    done = _archive("ingest", "f0", "f1", "--archive", "arc", "--fov", str(FOV), "--quiet", cwd=d)
    assert done.returncode == 0, done.stderr
    return d


def _closed_stdout(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    """Run ``archive *args`` with a stdout pipe whose read end is already closed."""
    read, write = os.pipe()
    os.close(read)
    try:
        return _archive(*args, cwd=cwd, stdout=write, stderr=subprocess.PIPE, capture_output=False)
    finally:
        os.close(write)


COMMANDS = [
    ["--help"],
    ["simulate", "g", *SIM_ARGS[:-1], "--seed", "5"],
    ["info", "f0", "--fov", str(FOV)],
    ["info", FIRST, "--archive", "arc", "--json"],
    ["ingest", "f0", "--archive", "arc", "--fov", str(FOV), "--quiet"],
    ["verify", "--archive", "arc"],
    ["catalog", "search", "--archive", "arc", "--json"],
    ["catalog", "search", "--archive", "arc"],
    ["catalog", "list", "--archive", "arc"],
    ["catalog", "rebuild", "--archive", "arc"],
    ["catalog", "validate", "--archive", "arc"],
    ["render", "f0", "--fov", str(FOV), "--gsd", "0.5", "--out", "one.tif", "--quiet", "--overwrite"],
    ["catalog", "add", "one.tif.json", "--archive", "arc"],
    ["render", "--archive", "arc", "--query-datetime", "2024-06-12", "--gsd", "0.5", "--out", "batch",
     "--format", "tif", "--quiet", "--overwrite"],
    ["view", "--archive", "arc", "--port", "0"],
    ["calibrate", "f0", "--fov", str(FOV), "--json", "--quiet"],
    ["doctor", "--json"],
]


@pytest.mark.parametrize("args", COMMANDS, ids=lambda a: " ".join(a[:2]))
def test_closed_stdout_no_traceback(work, args):
    if args[0] == "catalog" and args[1] == "add" and not (work / "one.tif.json").exists():
        assert _archive("render", *COMMANDS[11][1:], cwd=work).returncode == 0
    done = _closed_stdout(args, work)
    assert "Traceback" not in done.stderr, done.stderr
    assert "Exception ignored" not in done.stderr, done.stderr
    assert "BrokenPipe" not in done.stderr, done.stderr
    # a closed stdout is SIGPIPE's exit code; a command that fails for its own reason says it in one line
    assert done.returncode == 141 or len(done.stderr.strip().splitlines()) <= 1, done.stderr


def test_same_flight_twice_in_one_ingest(work, tmp_path):
    again = _archive("ingest", "f1", "f1", "--archive", str(tmp_path / "a"), "--fov", str(FOV), "--quiet", cwd=work)
    assert again.returncode == 0, again.stderr
    assert again.stdout.splitlines() == [f"{SECOND}: ingested ({tmp_path / 'a' / 'collections' / SECOND}.zarr)"]
    shutil.copytree(work / "f1", tmp_path / "copy")
    both = _archive("ingest", "f1", str(tmp_path / "copy"), "--archive", "arc", "--fov", str(FOV), "--quiet",
                    cwd=work)
    assert both.returncode == 2 and "Traceback" not in both.stderr, both.stderr
    line, = both.stderr.strip().splitlines()
    assert "same flight as f1" in line and SECOND in line


def test_batch_lines_past_the_progress_bar(work):
    """stdout and stderr on one stream, as on a terminal: each 'done' line starts a line of its own
    (the bar is cleared first), never glued behind the bar's carriage-return text."""
    done = _archive("render", "--archive", "arc", "--query-datetime", "2024-06-12", "--gsd", "0.5", "--out",
                    "bars", "--format", "tif", "--overwrite", cwd=work, stdout=subprocess.PIPE,
                    stderr=subprocess.STDOUT, capture_output=False)
    assert done.returncode == 0, done.stdout
    pieces = [p.strip() for p in re.split(r"[\r\n]", done.stdout) if "archive render: done" in p]
    assert len(pieces) == 2, done.stdout
    assert all(p.startswith("archive render: done") for p in pieces), done.stdout


def test_python_errors_name_the_function_and_keyword(work):
    os.chdir(work)
    with pytest.raises(KeywordError) as bad:
        archive.mosaic(["f0"], gsd=0.5, fov=FOV, groundheight=3)
    assert isinstance(bad.value, TypeError)
    assert str(bad.value) == "archive.mosaic(): no keyword 'groundheight' (did you mean ground_height=?)"
    with pytest.raises(InputError) as bad:
        archive.mosaic(["f0"], gsd=-1, fov=FOV)
    assert str(bad.value).startswith("archive.mosaic(gsd=...): ") and "--" not in str(bad.value)
    with pytest.raises(InputError) as bad:
        archive.mosaic(["f0"], gsd=0.5)
    assert "archive.mosaic(fov=...)" in str(bad.value) and "fov=DEG" in str(bad.value)
    with pytest.raises(InputError) as bad:
        archive.open_archive("arc").search(bbox=(1, 2))
    assert str(bad.value).startswith("Archive.search(bbox=...): ") and "--" not in str(bad.value)
    with pytest.raises(KeywordError, match=r"Archive.search\(\): no keyword 'bbx' \(did you mean bbox=\?\)"):
        archive.open_archive("arc").search(bbx=(1, 2, 3, 4))
    with pytest.raises(KeywordError, match=r"archive.georectify\(\): no keyword 'overwite'"):
        archive.georectify(["f0"], "x.tif", gsd=0.5, fov=FOV, overwite=True)
