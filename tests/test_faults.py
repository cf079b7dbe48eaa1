"""Faults of the machine, not of the input (issue 30, finding 6), through the real CLI: a full disk
under a batch's --out DIR and under an archive's store or catalog (small tmpfs mounts: needs root,
skipped otherwise), a worker process killed while the local cluster starts (a Dask worker preload,
given through Dask's own DASK_* configuration, that SIGKILLs its worker). Every one is one line on
stderr and a non-zero exit, never a traceback; a rerun with space completes.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from archive.cli import main
from helpers import FOV



@pytest.fixture
def small_disk():
    """``mount(path, size)``: a tmpfs of ``size`` (e.g. '64k') mounted at ``path``; ``resize(path,
    size)``; all unmounted at the end."""
    mounts: list[Path] = []

    def mount(path: Path, size: str) -> Path:
        path.mkdir(parents=True, exist_ok=True)
        done = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)], capture_output=True,
                              text=True)
        if done.returncode:
            pytest.skip(f"cannot mount a small tmpfs here (root needed): {done.stderr.strip()}")
        mounts.append(path)
        return path

    def resize(path: Path, size: str) -> None:
        subprocess.run(["mount", "-o", f"remount,size={size}", str(path)], check=True)

    mount.resize = resize
    yield mount
    for path in reversed(mounts):
        subprocess.run(["umount", "-l", str(path)], capture_output=True)


def fill(folder: Path) -> None:
    """Fill the file system of ``folder`` to the last byte."""
    with open(folder / "filler", "wb", buffering=0) as f:
        try:
            while True:
                f.write(b"\0" * 4096)
        except OSError:
            pass


def cli(*args: str, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "archive", *args], capture_output=True, text=True, timeout=600,
                          env={**os.environ, **(env or {})})


def one_line(stderr: str) -> str:
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in stderr, stderr
    return lines[0]


def batch_args(arc: Path, out: Path, *extra: str) -> list[str]:
    return ["render", "--archive", str(arc), "--query-bbox", "-180,-90,180,90", "--gsd", "0.1", "--out", str(out),
            "--format", "tif", "--quiet", "--workers", "1", *extra]


def test_batch_into_a_full_disk(small_archive, tmp_path, small_disk):
    """--out DIR on a full disk: one line naming DIR and the cause, exit 2 (before: a traceback from
    writing report.json)."""
    arc, _ = small_archive
    out = small_disk(tmp_path / "out", "64k")
    fill(out)
    done = cli(*batch_args(arc, out))
    line = one_line(done.stderr)
    assert done.returncode == 2 and str(out) in line and "No space left on device" in line, line
    assert sorted(p.name for p in out.iterdir()) == ["filler"]


def test_batch_outputs_on_a_small_disk(small_archive, tmp_path, small_disk):
    """Room for the report but not the outputs: each flight fails on its own with one line, the
    report says so, exit 1, no traceback; with room, --resume completes the batch."""
    arc, cid = small_archive
    out = small_disk(tmp_path / "out", "48k")
    done = cli(*batch_args(arc, out))
    assert done.returncode == 1 and "Traceback" not in done.stderr, done.stderr
    doc = json.loads((out / "report.json").read_text())
    assert doc["complete"] and doc["failed"] == 1 and "space" in doc["outputs"][0]["error"], doc
    failed = [line for line in done.stdout.splitlines() if " failed " in line]
    assert failed[0].startswith(f"archive render: failed {cid}:"), done.stdout
    small_disk.resize(out, "64m")
    done = cli(*batch_args(arc, out, "--resume"))
    assert done.returncode == 0, done.stderr
    assert json.loads((out / "report.json").read_text())["done"] == 1


def test_ingest_into_a_full_disk(small_flight, tmp_path, small_disk):
    """The collection store's disk fills while ingesting: one line (the disk is full, rerun resumes),
    exit 2, no collection under its final name; with room, the same ingest completes and verifies."""
    from archive.catalog.root import create_archive

    arc = tmp_path / "arc"
    create_archive(arc)
    collections = small_disk(arc / "collections", "96k")
    args = ["ingest", str(small_flight), "--archive", str(arc), "--fov", str(FOV), "--quiet"]
    done = cli(*args)
    line = one_line(done.stderr)
    assert done.returncode == 2 and "the disk is full while ingesting" in line and "run the same ingest again" in line
    assert not [p for p in collections.iterdir() if p.name.endswith(".zarr")]
    small_disk.resize(collections, "64m")
    done = cli(*args)
    assert done.returncode == 0, done.stderr
    assert main(["verify", "--archive", str(arc), "--quiet"]) == 0


def test_ingest_with_a_full_catalog_disk(small_flight, tmp_path, small_disk):
    """The catalog's disk (Items, SQLite index) is full: one line, exit 2; with room, the rerun
    catalogs the flight it had stored."""
    from archive.catalog.root import create_archive

    arc = tmp_path / "arc"
    create_archive(arc)
    catalog = small_disk(arc / "catalog", "64k")
    (catalog / "items").mkdir()
    fill(catalog)
    args = ["ingest", str(small_flight), "--archive", str(arc), "--fov", str(FOV), "--quiet"]
    done = cli(*args)
    line = one_line(done.stderr)
    assert done.returncode == 2 and "the disk is full while ingesting" in line, line
    (catalog / "filler").unlink()
    small_disk.resize(catalog, "64m")
    done = cli(*args)
    assert done.returncode == 0, done.stderr
    assert "already ingested" in done.stdout
    listed = cli("catalog", "list", "--archive", str(arc))
    assert done.stdout.split(":")[0] in listed.stdout, listed


def preload(tmp_path: Path, once: bool) -> dict:
    """Environment of a Dask worker preload that SIGKILLs the worker while it starts (``once``: only
    the first worker process, noted in a marker file)."""
    marker = tmp_path / "killed-once"
    script = tmp_path / "kill_worker.py"
    script.write_text(
        "import os, signal\n"
        "from pathlib import Path\n\n\n"
        "def dask_setup(worker):\n"
        f"    marker = Path({str(marker)!r})\n"
        f"    if {not once!r} or not marker.exists():\n"
        "        marker.write_text('killed')\n"
        "        os.kill(os.getpid(), signal.SIGKILL)\n")
    return {"DASK_DISTRIBUTED__WORKER__PRELOAD": json.dumps([str(script)])}


def test_a_worker_killed_while_the_cluster_starts_is_started_again(small_archive, tmp_path):
    arc, _ = small_archive
    out = tmp_path / "out"
    done = cli(*batch_args(arc, out), env=preload(tmp_path, once=True))
    assert done.returncode == 0, done.stderr
    assert (tmp_path / "killed-once").exists() and json.loads((out / "report.json").read_text())["done"] == 1


def test_workers_that_always_die_at_start_are_one_line(small_archive, tmp_path):
    """(Before: Dask's ~56-line traceback, 'Nanny failed to start'.)"""
    arc, cid = small_archive
    out = tmp_path / "out"
    done = cli(*batch_args(arc, out), env=preload(tmp_path, once=False))
    line = one_line(done.stderr)
    assert done.returncode == 2 and "the local Dask cluster did not start, 2 times: a worker process died" in line
    doc = json.loads((out / "report.json").read_text())
    assert doc["failed"] == 1 and "did not start" in doc["outputs"][0]["error"]


def test_a_full_disk_line_names_the_path_and_the_flights_done_before(small_flight, tmp_path, small_disk):
    """Issue 50: the line of an ingest stopped by a full disk names where the disk is full, and the flights of
    the same command that were ingested before it."""
    from archive.catalog.root import create_archive

    other = tmp_path / "other"
    done = cli("simulate", str(other), "--cubes", "1", "--lines", "200", "--samples", "64", "--bands", "8",
               "--start", "2024-07-01T10:00:00Z", "--quiet")
    assert done.returncode == 0, done.stderr
    arc = tmp_path / "arc"
    create_archive(arc)
    collections = small_disk(arc / "collections", "8m")
    first = cli("ingest", str(small_flight), "--archive", str(arc), "--fov", str(FOV), "--quiet")
    assert first.returncode == 0, first.stderr
    cid = first.stdout.split(":")[0]
    fill(collections)
    done = cli("ingest", str(small_flight), str(other), "--archive", str(arc), "--fov", str(FOV), "--quiet")
    line = one_line(done.stderr)
    assert done.returncode == 2 and "the disk is full while ingesting" in line, line
    assert line.split(": ")[2].startswith(str(collections)), line   # where: a path on the full disk
    assert f"ingested before it: {cid} (already ingested)" in line, line
