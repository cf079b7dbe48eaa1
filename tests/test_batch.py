"""Batch reprocessing at archive scale (issue 19), through the real CLI on real files: every DN chunk
read from a collection is checked against its recorded digest (BLAKE3) (render, archive.mosaic, the viewer);
one output per flight, each flight failing alone (report.json, exit 1); --resume after SIGKILL.

Archives of small simulated flights (2 cubes x 100 lines x 64 samples x 4 bands), one per seed
(each seed starts a minute later: distinct ids).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
import shutil

import numcodecs
import numpy as np
import pytest

from archive.cli import main
from archive.collection import CheckedDn, CorruptChunkError, chunk_path
from helpers import FOV, ingest_each

GSD = "0.1"


@pytest.fixture(scope="module")
def flights(small_flights, tmp_path_factory):
    """(raw directories, archive, ids) of four small flights (seeds 0-3, conftest) ingested into one archive."""
    dirs = [small_flights(seed) for seed in range(4)]
    archive = tmp_path_factory.mktemp("batch") / "archive"
    return dirs, archive, ingest_each(dirs, archive)


def copy_archive(archive: Path, to: Path) -> Path:
    shutil.copytree(archive, to)
    return to


def store_of(archive: Path, cid: str) -> Path:
    return archive / "collections" / f"{cid}.zarr"


def _codec():
    return numcodecs.Blosc(cname="zstd", clevel=3, shuffle=numcodecs.Blosc.BITSHUFFLE)


def flip_value(store: Path, band: int, chunk: int) -> None:
    """Silent corruption: one DN of chunk (band, chunk) changed, re-encoded (the codec still decodes it)."""
    path = chunk_path(store, band, chunk)
    values = np.frombuffer(_codec().decode(path.read_bytes()), "<u2").copy()
    values[values.size // 2] ^= 0x10
    path.write_bytes(_codec().encode(values))


def truncate(store: Path, band: int, chunk: int) -> None:
    path = chunk_path(store, band, chunk)
    path.write_bytes(path.read_bytes()[:40])


# ---------------------------------------------------------------------------------------------
# Integrity on every read
# ---------------------------------------------------------------------------------------------
def test_checked_reads_name_collection_band_and_lines(flights, tmp_path):
    _, archive, ids = flights
    archive = copy_archive(archive, tmp_path / "archive")
    store = store_of(archive, ids[1])
    intact = CheckedDn(store).read(2, 50, 150)
    assert np.array_equal(intact, CheckedDn(store).array[2, 50:150])
    flip_value(store, 2, 1)
    truncate(store, 3, 0)
    dn = CheckedDn(store)
    assert np.array_equal(dn.read(2, 0, 100), dn.array[2, 0:100])  # the other chunks read fine
    with pytest.raises(CorruptChunkError, match=rf"collection {ids[1]}: array dn, band 2, lines 100-199: chunk "
                                                r"does not match its recorded blake3.*archive verify"):
        dn.read(2, 50, 150)
    with pytest.raises(CorruptChunkError, match=r"band 3, lines 0-99: chunk cannot be decoded.*re-ingest"):
        dn.read(3, 0, 10)
    chunk_path(store, 1, 0).unlink()
    with pytest.raises(CorruptChunkError, match=r"band 1, lines 0-99: chunk file is missing"):
        dn.read(1, 0, 100)


def test_render_mosaic_and_viewer_refuse_a_corrupt_chunk(flights, tmp_path, capsys):
    import archive as api

    _, archive, ids = flights
    archive = copy_archive(archive, tmp_path / "archive")
    cid = ids[0]
    for k in (0, 1):
        flip_value(store_of(archive, cid), 0, k)
    expected = rf"collection {cid}: array dn, band 0, lines \d+-\d+: chunk does not match its recorded blake3"
    out = tmp_path / "one.tif"
    import re

    assert main(["render", cid, "--archive", str(archive), "--gsd", GSD, "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "archive verify" in err
    assert re.search(expected, err), err
    assert not out.exists() and not list(tmp_path.glob(".one.tif*"))

    ds = api.mosaic(cid, archive=archive, gsd=float(GSD), bands=[0])
    with pytest.raises(CorruptChunkError, match=expected):
        ds.radiance.compute(scheduler="threads")

    from archive.view.registry import FlightRegistry
    from archive.view.server import create_app
    from starlette.testclient import TestClient

    item = json.loads((archive / "catalog" / "items" / f"{cid}.json").read_text())
    lon = (item["bbox"][0] + item["bbox"][2]) / 2
    lat = (item["bbox"][1] + item["bbox"][3]) / 2
    with TestClient(create_app(FlightRegistry(archive))) as client:
        got = client.get(f"/api/collections/{cid}/point", params={"lon": repr(lon), "lat": repr(lat)})
    assert got.status_code == 400, got.text
    assert re.search(expected, got.json()["error"]) and "archive verify" in got.json()["error"]


# ---------------------------------------------------------------------------------------------
# Batch jobs: each flight on its own, the report, --resume
# ---------------------------------------------------------------------------------------------
def read_values(path: Path) -> np.ndarray:
    import rasterio

    with rasterio.open(path) as src:
        return src.read()


def render_batch(archive: Path, out: Path, *extra: str, wait: bool = True, env: dict | None = None):
    """``archive render --archive A --query-bbox (everything) --out DIR --format tif`` as a process
    of its own session (so that SIGKILL of the group is a killed job: command and workers); ``env``:
    variables added to its environment (test hooks)."""
    args = [sys.executable, "-m", "archive", "render", "--archive", str(archive), "--query-bbox", "-180,-90,180,90",
            "--gsd", GSD, "--out", str(out), "--format", "tif", "--quiet", "--workers", "1", *extra]
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
                            env={**os.environ, **(env or {})})
    if not wait:
        return proc
    stdout, stderr = proc.communicate(timeout=300)
    return proc.returncode, stdout, stderr


def report(out: Path) -> dict:
    return json.loads((out / "report.json").read_text())


@pytest.fixture(scope="module")
def singles(flights, tmp_path_factory):
    """Each flight rendered alone (``archive render ID --archive A --out ID.tif``): id -> values."""
    _, archive, ids = flights
    root = tmp_path_factory.mktemp("singles")
    values = {}
    for cid in ids:
        assert main(["render", cid, "--archive", str(archive), "--gsd", GSD, "--out", str(root / f"{cid}.tif"),
                     "--quiet"]) == 0
        values[cid] = read_values(root / f"{cid}.tif")
    return values


def test_a_bad_flight_costs_only_itself(flights, singles, tmp_path):
    _, archive, ids = flights
    archive = copy_archive(archive, tmp_path / "archive")
    flip_value(store_of(archive, ids[1]), 2, 1)     # silent corruption: decodes, wrong values
    truncate(store_of(archive, ids[3]), 3, 0)       # does not decode
    out = tmp_path / "out"
    code, stdout, stderr = render_batch(archive, out)
    assert code == 1, stderr
    lines = [line for line in stdout.splitlines() if line.startswith("archive render: ") and ":" in line[16:]]
    by_id = {line.split()[3].rstrip(":"): line.split()[2] for line in lines if line.split()[2] in
             ("done", "failed", "skipped")}
    assert by_id == {ids[0]: "done", ids[1]: "failed", ids[2]: "done", ids[3]: "failed"}, stdout
    failed = {line.split()[3].rstrip(":"): line for line in lines if " failed " in line}
    assert f"collection {ids[1]}: array dn, band 2, lines 100-199: chunk does not match its recorded blake3" \
        in failed[ids[1]] and "archive verify" in failed[ids[1]]
    assert f"collection {ids[3]}: array dn, band 3, lines 0-99: chunk cannot be decoded" in failed[ids[3]]
    doc = report(out)
    assert doc["complete"] and (doc["done"], doc["failed"], doc["skipped"], doc["pending"]) == (2, 2, 0, 0)
    entries = {o["id"]: o for o in doc["outputs"]}
    assert {k: v["status"] for k, v in entries.items()} == by_id
    assert "band 2, lines 100-199" in entries[ids[1]]["error"] and entries[ids[0]]["error"] is None
    assert all(o["seconds"] >= 0 and o["path"] == str(out / f"{o['id']}.tif") for o in doc["outputs"])
    # nothing of the failed flights anywhere in DIR; the others complete and equal to single renders
    assert sorted(p.name for p in out.iterdir()) == sorted(
        [f"{ids[i]}.tif{x}" for i in (0, 2) for x in ("", ".json")] + ["report.json"])
    for i in (0, 2):
        assert np.array_equal(read_values(out / f"{ids[i]}.tif"), singles[ids[i]], equal_nan=True)


def _kill_when(proc, out: Path, done: int, timeout: float = 300.0) -> None:
    """SIGKILL the batch (its whole session) once its report shows ``done`` finished flights. The
    batch runs with ARCHIVE_TEST_HOLD_AFTER=done: it holds there until killed, so the kill lands at
    that moment however loaded the machine (a batch left free finished all four flights before the
    kill arrived on a loaded CI machine)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and proc.poll() is None:
        try:
            if report(out)["done"] >= done:
                break
        except (OSError, ValueError, KeyError):
            pass
        time.sleep(0.05)
    assert proc.poll() is None, f"the batch ended before it could be killed: {proc.returncode} {proc.communicate()}"
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait(timeout=30)


@pytest.mark.parametrize("moment", [0, 1, 3])
def test_resume_after_sigkill(flights, singles, tmp_path, moment):
    """SIGKILL at three moments (report written, nothing done; one flight done; three done); --resume
    completes the batch, skips every flight finished before the kill (not rendered again: same
    files), and gives the outputs of single-flight renders."""
    _, archive, ids = flights
    out = tmp_path / "out"
    _kill_when(render_batch(archive, out, wait=False, env={"ARCHIVE_TEST_HOLD_AFTER": str(moment)}), out, moment)
    before = report(out)
    assert not before["complete"] and (before["done"], before["pending"]) == (moment, len(ids) - moment), before
    # held right after the report's rewrite: the report says exactly what is complete on disk
    reported = {o["id"] for o in before["outputs"] if o["status"] == "done"}
    finished = {cid for cid in ids if (out / f"{cid}.tif.json").exists()}
    assert reported == finished and len(finished) == moment
    stamps = {cid: (out / f"{cid}.tif").stat().st_mtime_ns for cid in finished}
    code, stdout, stderr = render_batch(archive, out, "--resume")
    assert code == 0, stderr
    doc = report(out)
    assert doc["complete"] and doc["failed"] == 0 and doc["pending"] == 0
    assert {o["id"] for o in doc["outputs"] if o["status"] == "skipped"} == finished
    assert doc["done"] == len(ids) - len(finished)
    assert stdout.count("archive render: skipped ") == len(finished)
    for cid in finished:
        assert (out / f"{cid}.tif").stat().st_mtime_ns == stamps[cid]
    assert sorted(p.name for p in out.iterdir()) == sorted(
        [f"{cid}.tif{x}" for cid in ids for x in ("", ".json")] + ["report.json"])
    for cid in ids:
        assert np.array_equal(read_values(out / f"{cid}.tif"), singles[cid], equal_nan=True)


def test_resume_redoes_incomplete_outputs_and_refuses_another_recipe(flights, tmp_path, capsys):
    _, archive, ids = flights
    out = tmp_path / "out"
    code, _, stderr = render_batch(archive, out)
    assert code == 0, stderr
    # killed between the rename and the Item: data without Item; and a dead run's temporary
    (out / f"{ids[1]}.tif.json").unlink()
    (out / f".{ids[2]}.tif.partial-999999999").mkdir()
    (out / f"{ids[2]}.tif.json.0123abcd.partial").write_text("{")
    (out / "report.json.0123abcd.partial").write_text("{")   # killed while the report was rewritten
    stamp = (out / f"{ids[0]}.tif").stat().st_mtime_ns
    code, stdout, stderr = render_batch(archive, out)   # without --resume: refused, nothing touched
    assert code == 2 and "output exists already" in stderr and "--resume" in stderr
    code, stdout, stderr = render_batch(archive, out, "--resume")
    assert code == 0, stderr
    doc = report(out)
    assert {o["id"]: o["status"] for o in doc["outputs"]} == {ids[0]: "skipped", ids[1]: "done",
                                                            ids[2]: "skipped", ids[3]: "skipped"}
    assert (out / f"{ids[0]}.tif").stat().st_mtime_ns == stamp and (out / f"{ids[1]}.tif.json").is_file()
    assert not list(out.glob(".*")) and not list(out.glob("*.partial"))
    # another recipe: refused before anything starts, unless --overwrite
    args = ["render", "--archive", str(archive), "--query-bbox", "-180,-90,180,90", "--gsd", "0.2", "--out",
            str(out), "--format", "tif", "--quiet", "--resume"]
    capsys.readouterr()
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "was made with another recipe (gsd 0.1 there, 0.2 now)" in err and "--overwrite" in err
    assert (out / f"{ids[0]}.tif").stat().st_mtime_ns == stamp


# ---------------------------------------------------------------------------------------------
# Waves: the tasks the scheduler holds do not grow with the batch
# ---------------------------------------------------------------------------------------------
def _peak_tasks(dirs: list[Path], out: Path) -> tuple[int, dict]:
    """Peak number of tasks the scheduler holds while a batch of ``dirs`` runs (a scheduler plugin)."""
    import logging

    import archive as api
    from distributed import LocalCluster
    from distributed.diagnostics.plugin import SchedulerPlugin

    class Peak(SchedulerPlugin):
        name = "peak-tasks"

        def __init__(self, scheduler):
            self.peak, self.scheduler = 0, scheduler

        def transition(self, key, start, finish, *args, **kwargs):
            self.peak = max(self.peak, len(self.scheduler.tasks))

    with LocalCluster(n_workers=1, threads_per_worker=2, processes=False, resources={"GPU": 2},
                      dashboard_address=":0", silence_logs=logging.CRITICAL) as cluster:
        plugin = Peak(cluster.scheduler)
        cluster.scheduler.add_plugin(plugin)
        summary = api.georectify(dirs, out, per_flight=True, format="zarr", fov=FOV, gsd=0.2,
                                 scheduler=cluster.scheduler_address)
    return plugin.peak, summary


def test_waves_keep_the_scheduler_flat(tiny_flights, tmp_path):
    """40 flights hold no more tasks in the scheduler at once than a wave of single flights (as 4 do)."""
    dirs = [tiny_flights(seed) for seed in range(40)]
    peak1, one = _peak_tasks(dirs[:1], tmp_path / "one")
    peak4, four = _peak_tasks(dirs[:4], tmp_path / "four")
    peak40, forty = _peak_tasks(dirs, tmp_path / "forty")
    assert one["done"] == 1 and four["done"] == 4 and forty["done"] == 40 and forty["failed"] == 0
    assert forty["wave"] == four["wave"] < 40
    # the bound does not grow with the batch: at most a wave of flights, each holding what one flight
    # alone holds (how close a batch comes to it depends on whether planning keeps ahead of rendering)
    bound = forty["wave"] * peak1
    assert 0 < peak4 <= bound and 0 < peak40 <= bound, (peak1, forty["wave"], peak4, peak40)
    assert forty["peak_tasks"] <= forty["wave"] * one["peak_tasks"]


def test_futures_followed_on_the_commands_client(flights, tmp_path, monkeypatch):
    """With another Client of the process as the default (a notebook's), a batch and a single render
    follow their futures on their own client's event loop: ``as_completed`` without a loop used the
    default client's, where the completions arrived late (20 flights: 21 s instead of 5 s)."""
    import logging

    import distributed
    from distributed import Client, LocalCluster

    import archive as api

    loops = []

    class Spy(distributed.as_completed):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            loops.append(self.loop)

    monkeypatch.setattr(distributed, "as_completed", Spy)
    dirs, archive, ids = flights
    with LocalCluster(n_workers=1, threads_per_worker=2, processes=False, resources={"GPU": 2},
                      dashboard_address=":0", silence_logs=logging.CRITICAL) as cluster:
        with Client(cluster.scheduler_address) as notebook:   # the default client, not the command's
            batch = api.georectify(ids[:2], tmp_path / "batch", archive=archive, gsd=0.2, per_flight=True,
                                   scheduler=cluster.scheduler_address)
            api.georectify(ids[:1], tmp_path / "one.zarr", archive=archive, gsd=0.2,
                           scheduler=cluster.scheduler_address)
            assert distributed.default_client() is notebook
    assert batch["done"] == 2 and (tmp_path / "one.zarr").is_dir()
    assert len(loops) == 2 and all(loop is not notebook.loop for loop in loops)


def test_a_cluster_that_does_not_close_is_a_warning_after_a_batch(flights, scheduler, tmp_path, capsys, monkeypatch):
    """A batch whose client's close fails once every flight was published (Dask's TimeoutError on a
    loaded machine) keeps its outcome: its flights done, one warning line naming the output folder,
    no temporary left. The close's error used to be the batch's, and skipped that clean-up."""
    import archive as api
    from archive.run import cluster

    close = cluster.close_client

    def late(client, cluster) -> None:
        close(client, cluster)
        raise TimeoutError()

    monkeypatch.setattr(cluster, "close_client", late)
    _, archive, ids = flights
    out = tmp_path / "batch"
    capsys.readouterr()
    summary = api.georectify(ids[:2], out, archive=archive, gsd=float(GSD), per_flight=True, scheduler=scheduler)
    err = capsys.readouterr().err.strip().splitlines()
    assert summary["done"] == 2 and summary["failed"] == 0, summary
    assert err == [f"archive render: warning: {out}: the Dask cluster did not close cleanly (TimeoutError)"], err
    assert sorted(p.name for p in out.iterdir()) == sorted(
        [f"{i}.zarr{x}" for i in ids[:2] for x in ("", ".json")] + ["report.json"])
