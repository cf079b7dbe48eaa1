"""Exclusive jobs across processes and hosts (issue 30, findings 2 and 6): concurrent ingests of one
flight, the lock files behind them, two batches into one --out DIR, temporaries of other hosts.

Real CLI processes on real files; "another host" is a lock file or temporary that names another
host, as a process on a shared file system would leave it.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from archive.cli import main
from archive.files import FileLock, LockHeldError, host_name
from helpers import FOV



def archive_cmd(*args: str) -> list[str]:
    return [sys.executable, "-m", "archive", *args]


def test_ten_concurrent_ingests_of_one_flight(small_flight, tmp_path):
    """Ten `archive ingest` of the same flight into one new archive at once: one ingests it, the
    others wait (saying so in one line) and find it ingested; one intact collection, cataloged once,
    nothing left beside it. (Before the lock, they shared one partial store: 3 of 10 runs left a
    collection without dn/time/navigation under its final name.)"""
    arc = tmp_path / "arc"
    procs = [subprocess.Popen(archive_cmd("ingest", str(small_flight), "--archive", str(arc), "--fov", str(FOV), "--quiet",
                                          "--workers", "1"),
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for _ in range(10)]
    results = [(p.wait(timeout=600), p.stdout.read(), p.stderr.read()) for p in procs]
    for code, _, err in results:
        assert code == 0, err
        assert all(line.startswith("archive ingest: waiting: collection ") and " is locked, ingest of " in line
                   for line in err.splitlines()), err
    statuses = sorted(out.split(": ", 1)[1].split(" (")[0] for _, out, _ in results)
    assert statuses == ["already ingested"] * 9 + ["ingested"], statuses
    cid = results[0][1].split(":")[0]
    assert main(["verify", "--archive", str(arc)]) == 0
    assert sorted(p.name for p in (arc / "collections").iterdir()) == [f"{cid}.zarr"]   # no lock, no partial
    from archive.catalog.index import search

    assert [row.id for row in search(arc / "catalog" / "index.sqlite")] == [cid]
    # and the collection renders
    assert main(["render", cid, "--archive", str(arc), "--gsd", "0.2", "--out", str(tmp_path / "o.tif"),
                 "--quiet"]) == 0


def _lock_file(path: Path, host: str, pid: int, age: float = 0.0) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"host": host, "pid": pid, "process_start": None, "since": "2026-01-01T00:00:00+00:00",
                                "purpose": "ingest of X"}))
    if age:
        t = time.time() - age
        os.utime(path, (t, t))


def test_lock_judges_dead_owners_by_host(tmp_path):
    """A lock whose owner is a dead PID of THIS host is taken over; one of another host is respected
    while its lease runs (whatever its PID means here), and taken over once it has run out."""
    path = tmp_path / "x.lock"
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    _lock_file(path, host_name(), dead.pid)
    lock = FileLock(path, "test")
    lock.acquire()
    assert json.loads(path.read_text())["pid"] == os.getpid()
    lock.release()
    assert not path.exists()

    # another host's live lock: its PID means nothing here (dead here, or ours)
    for pid in (dead.pid, os.getpid()):
        _lock_file(path, "some-other-node", pid)
        with pytest.raises(LockHeldError, match=rf"ingest of X by PID {pid} on some-other-node since "):
            FileLock(path, "test", lease=60).acquire(wait=0.3)
        assert json.loads(path.read_text())["host"] == "some-other-node"
    _lock_file(path, "some-other-node", 1, age=120)   # no heartbeat for 120 s > the lease
    lock = FileLock(path, "test", lease=60)
    lock.acquire()
    assert json.loads(path.read_text())["host"] == host_name()
    lock.release()


def test_lock_heartbeat_keeps_the_lease(tmp_path):
    """A held lock's file is touched every heartbeat, so that another host never sees it expire."""
    path = tmp_path / "x.lock"
    lock = FileLock(path, "test", lease=1.0, heartbeat=0.1)
    lock.acquire()
    try:
        os.utime(path, (time.time() - 100, time.time() - 100))
        deadline = time.monotonic() + 10
        while time.time() - path.stat().st_mtime > 50 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert time.time() - path.stat().st_mtime < 50
    finally:
        lock.release()


def test_a_waiting_ingest_takes_over_from_a_killed_one(small_flight, tmp_path):
    """An ingest killed while holding the lock (its lock file and partial store left behind, its PID
    dead on this host): the next ingest takes the lock over and resumes."""
    arc = tmp_path / "arc"
    first = subprocess.run(archive_cmd("ingest", str(small_flight), "--archive", str(arc), "--fov", str(FOV), "--quiet"),
                           capture_output=True, text=True)
    assert first.returncode == 0, first.stderr
    cid = first.stdout.split(":")[0]
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    _lock_file(arc / "collections" / f"{cid}.zarr.lock", host_name(), dead.pid)
    again = subprocess.run(archive_cmd("ingest", str(small_flight), "--archive", str(arc), "--fov", str(FOV), "--quiet",
                                       "--overwrite"), capture_output=True, text=True, timeout=300)
    assert again.returncode == 0, again.stderr
    assert "waiting" not in again.stderr and not (arc / "collections" / f"{cid}.zarr.lock").exists()


# ---------------------------------------------------------------------------------------------
# Batches: one per output folder; temporaries of other hosts
# ---------------------------------------------------------------------------------------------
def batch_cmd(arc: Path, out: Path, *extra: str) -> list[str]:
    return archive_cmd("render", "--archive", str(arc), "--query-bbox", "-180,-90,180,90", "--gsd", "0.2", "--out",
                       str(out), "--format", "tif", "--quiet", "--workers", "1", *extra)


def test_a_second_batch_into_the_same_folder_says_who_holds_it(small_archive, tmp_path):
    """Two batches into one --out DIR: the second stops at once, naming the first (PID, host, since),
    and touches nothing; once the first is killed, a --resume takes the folder over and completes it.
    (Before: both ran, did the work twice, and the last report marked complete outputs failed.)"""
    import signal

    arc, cid = small_archive
    out = tmp_path / "out"
    first = subprocess.Popen(batch_cmd(arc, out), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                             start_new_session=True, env={**os.environ, "ARCHIVE_TEST_HOLD_AFTER": "0"})
    try:
        deadline = time.monotonic() + 120
        while not (out / "report.json").exists() and time.monotonic() < deadline and first.poll() is None:
            time.sleep(0.05)
        assert first.poll() is None and (out / "report.json").exists()   # held, holding the folder
        report = (out / "report.json").read_bytes()
        second = subprocess.run(batch_cmd(arc, out, "--resume"), capture_output=True, text=True, timeout=300)
        assert second.returncode == 2
        assert second.stderr.count("\n") == 1 and "Traceback" not in second.stderr
        assert f"output folder {out} is locked: a batch render by PID {first.pid} on {host_name()} since " \
            in second.stderr and "choose another --out" in second.stderr
        assert (out / "report.json").read_bytes() == report
    finally:
        os.killpg(first.pid, signal.SIGKILL)
        first.wait(timeout=30)
    third = subprocess.run(batch_cmd(arc, out, "--resume"), capture_output=True, text=True, timeout=300)
    assert third.returncode == 0, third.stderr
    doc = json.loads((out / "report.json").read_text())
    assert doc["complete"] and doc["done"] == 1
    assert sorted(p.name for p in out.iterdir()) == sorted([f"{cid}.tif", f"{cid}.tif.json", "report.json"])


def test_temporaries_of_other_hosts_are_left_alone(small_archive, tmp_path):
    """A killed run's temporaries are removed only when made on THIS host by a dead process; another
    host's (its PID means nothing here; on a shared file system it may be writing them now) stay."""
    arc, cid = small_archive
    out = tmp_path / "out"
    assert subprocess.run(batch_cmd(arc, out), capture_output=True, text=True, timeout=300).returncode == 0
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    ours = out / f".{cid}.tif.partial-{dead.pid}@{host_name()}.tiles"
    theirs = out / f".{cid}.tif.partial-{dead.pid}@some-other-node.tiles"
    live = out / f".{cid}.tif.partial-{os.getpid()}@{host_name()}"
    for p in (ours, theirs, live):
        p.write_bytes(b"x")
    done = subprocess.run(batch_cmd(arc, out, "--resume"), capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert not ours.exists() and theirs.exists() and live.exists()
