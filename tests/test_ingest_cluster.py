"""``archive ingest --scheduler`` on a real multi-process Dask cluster (issue 45), and the store's checksums.

A scheduler and two workers are started as processes of their own through Dask's command line
(``dask scheduler`` / ``dask worker --nthreads 1``) on loopback, as docs/deploy.md tells an operator;
``archive ingest`` runs as a subprocess in its own session. Checked: an ingest through the scheduler
equals a local (in-process) ingest byte for byte, every file of each collection and its catalog Item,
and its DN equals the raw cubes'; one corrupt flight among several fails alone (one line, exit 1, the
report); a SIGKILL of the command mid-store, then the same command again, resumes the partial store
(keeps its chunks) and gives the same bytes. Stores of format 1 (sha256, no recorded algorithm) still
read, verify, and are found ingested.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import zarr

from archive.collection import CheckedDn, chunk_path, verify_store
from archive.formats.envi import EnviCube
from archive.formats.flight import discover_flight
from archive.ingest.command import ingest
from archive.simulator.command import simulate_flight
from helpers import FOV

PY = sys.executable
SEEDS = (21, 22, 23)
HOLD_AFTER = 3   # chunks each worker writes before the hold file (if present) stops it


def snapshot(path: Path) -> dict[str, bytes]:
    return {p.relative_to(path).as_posix(): p.read_bytes() for p in sorted(path.rglob("*")) if p.is_file()}


def item(archive: Path, cid: str) -> dict:
    return json.loads((archive / "catalog" / "items" / f"{cid}.json").read_text())


@pytest.fixture(scope="module")
def flights(tmp_path_factory):
    """Three small flights (2 cubes x 100 lines x 64 samples x 6 bands) and a copy of another with a
    truncated cube; the good ones ingested locally (in this process) as the reference."""
    root = tmp_path_factory.mktemp("flights")
    dirs = []
    for seed in SEEDS:
        d = root / f"raw{seed}"
        simulate_flight(d, cubes=2, bands=6, samples=64, lines=100, cubes_per_pass=2, seed=seed)
        dirs.append(d)
    bad = root / "bad"
    simulate_flight(bad, cubes=2, bands=6, samples=64, lines=100, cubes_per_pass=2, seed=29)
    data = bad / "sim_Pika_L_2.bil"
    data.write_bytes(data.read_bytes()[:-640])
    local = root / "local"
    results = ingest([str(d) for d in dirs], local, FOV, ground_height=80.0, threads=2, progress=False)
    assert [r.status for r in results] == ["ingested"] * 3
    return dirs, bad, local, [r.cid for r in results]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _stop(proc: subprocess.Popen) -> None:
    with contextlib.suppress(ProcessLookupError):
        os.killpg(proc.pid, signal.SIGTERM)
    try:
        proc.wait(10)
    except subprocess.TimeoutExpired:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(10)


@pytest.fixture(scope="module")
def scheduler(tmp_path_factory):
    """``dask scheduler`` and two ``dask worker`` processes (one thread each, no GPU: ingest needs none)
    on 127.0.0.1; the workers hold their chunk tasks after HOLD_AFTER chunks while ``hold`` exists."""
    from distributed import Client

    logs = tmp_path_factory.mktemp("dask")
    hold = logs / "hold"
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "ARCHIVE_TEST_HOLD_AFTER_CHUNKS": f"{HOLD_AFTER}:{hold}"}
    port = _free_port()
    address = f"tcp://127.0.0.1:{port}"
    procs = []

    def start(args, name):
        with open(logs / f"{name}.log", "w") as log:
            procs.append(subprocess.Popen([PY, "-m", *args], stdout=log, stderr=subprocess.STDOUT, env=env, cwd=logs,
                                          start_new_session=True))

    try:
        start(["distributed.cli.dask_scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"],
              "scheduler")
        for i in range(2):
            start(["distributed.cli.dask_worker", address, "--name", f"w{i}", "--nthreads", "1", "--memory-limit",
                   "1GB", "--no-dashboard", "--local-directory", str(logs / f"w{i}")], f"worker{i}")
        with Client(address, timeout="60s") as client:
            client.wait_for_workers(2, timeout=60)
        yield address, hold
    finally:
        for proc in reversed(procs):
            _stop(proc)


def _ingest(*args: str, wait: bool = True, report: Path | None = None):
    cmd = [PY, "-m", "archive", "ingest", *args, "--fov", str(FOV), "--ground-height", "80", "--quiet",
           *(["--report", str(report)] if report else [])]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    if not wait:
        return proc
    out, err = proc.communicate(timeout=300)
    return proc.returncode, out, err


def _same_collection(archive: Path, local: Path, cid: str) -> None:
    store = f"collections/{cid}.zarr"
    assert snapshot(archive / store) == snapshot(local / store), f"{cid}: the stores differ"
    assert item(archive, cid) == item(local, cid)


def test_sigkill_of_the_command_then_rerun_resumes(flights, scheduler, tmp_path):
    """SIGKILL of ``archive ingest --scheduler`` (its session) while its workers hold mid-store; the same
    command again resumes the partial store, keeps the chunks written, and gives the local ingest's bytes."""
    dirs, _, local, ids = flights
    address, hold = scheduler
    archive = tmp_path / "archive"
    hold.touch()
    proc = _ingest(str(dirs[0]), "--archive", str(archive), "--scheduler", address, wait=False)
    partial = archive / "collections" / f"{ids[0]}.zarr.partial"
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and proc.poll() is None and not Path(f"{hold}.reached").exists():
            time.sleep(0.05)
        assert proc.poll() is None, f"the ingest ended before the kill: {proc.communicate()}"
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(30)
    finally:
        hold.unlink()
    kept = {p: p.read_bytes() for p in (partial / "dn" / "c").rglob("0") if p.is_file()}
    assert len(kept) >= HOLD_AFTER and not (archive / "collections" / f"{ids[0]}.zarr").exists()
    from distributed import Client

    with Client(address, timeout="30s") as client:   # the held tasks let go, finish, and leave the scheduler
        deadline = time.monotonic() + 60
        while client.run_on_scheduler(lambda dask_scheduler: len(dask_scheduler.tasks)) and time.monotonic() < deadline:
            time.sleep(0.1)
    code, out, err = _ingest(str(dirs[0]), "--archive", str(archive), "--scheduler", address)
    assert code == 0, err
    assert f"resumed {dirs[0]}: {ids[0]}" in out, out
    _same_collection(archive, local, ids[0])
    store = archive / "collections" / f"{ids[0]}.zarr"
    assert all((store / p.relative_to(partial)).read_bytes() == v for p, v in kept.items())


def test_scheduler_ingest_equals_local_and_a_bad_flight_fails_alone(flights, scheduler, tmp_path):
    dirs, bad, local, ids = flights
    address, _ = scheduler
    archive, report = tmp_path / "archive", tmp_path / "report.json"
    code, out, err = _ingest(str(dirs[0]), str(bad), str(dirs[1]), str(dirs[2]), str(dirs[0]), "--archive",
                             str(archive), "--scheduler", address, report=report)
    assert code == 1, err
    lines = [line for line in out.splitlines() if line.startswith("archive ingest: ")]
    failed = [line for line in lines if line.startswith(f"archive ingest: failed {bad}: ")]
    assert len(failed) == 1 and "sim_Pika_L_2.bil" in failed[0] and "truncated" in failed[0], out
    for d, cid in zip(dirs, ids, strict=True):
        assert any(line.startswith(f"archive ingest: ingested {d}: {cid} (") for line in lines), out
    assert lines[-1] == "archive ingest: 4 flights: 3 ingested, 0 resumed, 0 already ingested, 1 failed", out
    doc = json.loads(report.read_text())
    assert doc["complete"] and (doc["total"], doc["ingested"], doc["failed"], doc["pending"]) == (4, 3, 1, 0)
    entries = {e["directory"]: e for e in doc["flights"]}
    assert entries[str(bad)]["status"] == "failed" and "truncated" in entries[str(bad)]["error"]
    assert [entries[str(d)]["id"] for d in dirs] == ids
    # every collection equal to the local ingest's, byte for byte, and its Item
    for cid in ids:
        _same_collection(archive, local, cid)
        assert verify_store(archive / "collections" / f"{cid}.zarr") == []
    assert sorted(p.name for p in (archive / "collections").iterdir() if p.suffix == ".zarr") == \
        sorted(f"{cid}.zarr" for cid in ids)
    # the DN is the raw cubes' (the truth of DN: what the camera wrote)
    cubes = discover_flight(dirs[1]).cubes
    dn = CheckedDn(archive / "collections" / f"{ids[1]}.zarr")
    for c, cube in enumerate(cubes):
        raw = EnviCube(cube.data).read()
        for b in (0, 5):
            assert np.array_equal(dn.read(b, 100 * c, 100 * (c + 1)), raw[b])
    # the same command again: nothing to do but the bad flight
    code, out, _ = _ingest(*map(str, dirs), "--archive", str(archive), "--scheduler", address)
    assert code == 0 and out.splitlines()[-1].endswith("0 ingested, 0 resumed, 3 already ingested, 0 failed"), out


def test_two_ingests_into_one_archive_at_once_through_one_scheduler(flights, scheduler, tmp_path):
    """Two commands at once, sharing a flight, through one scheduler: each flight written once (its lock:
    the second finds it ingested, or waits for it), both exit 0, the catalog holds the three, every store
    equal to the local ingest's."""
    dirs, _, local, ids = flights
    address, _ = scheduler
    archive = tmp_path / "archive"
    a = _ingest(str(dirs[0]), str(dirs[1]), "--archive", str(archive), "--scheduler", address, wait=False)
    b = _ingest(str(dirs[1]), str(dirs[2]), "--archive", str(archive), "--scheduler", address, wait=False)
    (out_a, err_a), (out_b, err_b) = a.communicate(timeout=300), b.communicate(timeout=300)
    assert (a.returncode, b.returncode) == (0, 0), err_a + err_b
    said = [line for line in (out_a + out_b).splitlines() if f": {ids[1]} (" in line]
    assert sorted(line.split()[2] for line in said) == ["already", "ingested"], said
    from archive.catalog.index import search

    assert sorted(r.id for r in search(archive / "catalog" / "index.sqlite")) == sorted(ids)
    for cid in ids:
        _same_collection(archive, local, cid)


def test_sigkill_of_a_worker_mid_flight(flights, scheduler, tmp_path):
    """A worker process killed (SIGKILL) while it holds a chunk task: the scheduler runs its tasks again on
    the other (and on the worker its nanny restarts), the command completes, the store is the local one."""
    import psutil
    from distributed import Client

    dirs, _, local, ids = flights
    address, hold = scheduler
    archive = tmp_path / "archive"
    hold.touch()
    proc = _ingest(str(dirs[2]), "--archive", str(archive), "--scheduler", address, wait=False)
    try:
        with Client(address, timeout="30s") as client:
            deadline = time.monotonic() + 120
            while time.monotonic() < deadline and proc.poll() is None:
                busy = [w for w, keys in client.processing().items() if any("ingest-dn-" in str(k) for k in keys)]
                if busy and Path(f"{hold}.reached").exists():
                    break
                time.sleep(0.05)
            assert proc.poll() is None and busy, "no worker held a chunk task"
            pid = client.run(os.getpid, workers=[busy[0]])[busy[0]]
            psutil.Process(pid).kill()
            hold.unlink()
            out, err = proc.communicate(timeout=300)
            assert proc.returncode == 0, err
            assert f"ingested {dirs[2]}: {ids[2]}" in out, out
            _same_collection(archive, local, ids[2])
            client.wait_for_workers(2, timeout=60)   # the nanny's new worker, for the tests after this one
    finally:
        hold.unlink(missing_ok=True)
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)


def test_a_store_of_format_1_reads_verifies_and_is_found_ingested(flights, tmp_path):
    """A collection as ingest wrote it before issue 45 (sha256 chunk digests in ``dn_sha256``, sha256 of
    the raw files, no recorded algorithm, format 1): read and checked chunk by chunk, verified, a
    corrupt chunk named, and a rerun of its ingest is a no-op."""
    dirs, _, _, ids = flights
    archive = tmp_path / "archive"
    (r,) = ingest([str(dirs[2])], archive, FOV, ground_height=80.0, checksum="sha256", compression="small",
                  progress=False)
    store = r.store
    meta = json.loads((store / "zarr.json").read_text())
    attrs = meta["attributes"]
    assert attrs.pop("archive:dn_checksum") == "sha256"
    attrs["archive:format_version"] = 1
    assert all("sha256" in s and "blake3" not in s for s in attrs["sources"])
    (store / "zarr.json").write_text(json.dumps(meta))
    assert "dn_sha256" in zarr.open_group(store, mode="r") and verify_store(store) == []
    raw = EnviCube(discover_flight(dirs[2]).cubes[1].data).read()
    assert np.array_equal(CheckedDn(store).read(4, 100, 200), raw[4])
    assert [x.status for x in ingest([str(dirs[2])], archive, FOV, ground_height=80.0, progress=False)] == \
        ["already ingested"]
    path = chunk_path(store, 3, 1)
    import numcodecs

    codec = numcodecs.Blosc(cname="zstd", clevel=3, shuffle=numcodecs.Blosc.BITSHUFFLE)
    values = np.frombuffer(codec.decode(path.read_bytes()), "<u2").copy()
    values[7] ^= 1
    path.write_bytes(codec.encode(values))
    assert verify_store(store) == ["dn chunk (band 3, lines 100-199): checksum mismatch"]
    with pytest.raises(Exception, match=f"collection {ids[2]}: array dn, band 3, lines 100-199: chunk does not "
                                        "match its recorded sha256"):
        CheckedDn(store).read(3, 0, 200)


def test_option_names_and_refusals(flights, tmp_path, capsys):
    from archive.cli import main
    from archive.collection import CHECKSUMS, DN_COMPRESSIONS
    from archive.ingest.arguments import CHECKSUM_NAMES, COMPRESSION_NAMES

    assert set(COMPRESSION_NAMES) == set(DN_COMPRESSIONS) and set(CHECKSUM_NAMES) == set(CHECKSUMS)
    dirs = flights[0]
    for extra, words in ((["--job-cores", "4"], "--job-cores: sizes the worker jobs of --cluster slurm"),
                         (["--cluster", "slurm", "--scheduler", "tcp://127.0.0.1:1"], "--cluster and --scheduler"),
                         (["--report", str(tmp_path / "r.json")], "--report: reports the flights of an ingest on a "
                                                                  "cluster")):
        assert main(["ingest", str(dirs[0]), "--archive", str(tmp_path / "a"), "--fov", str(FOV), "--quiet",
                     *extra]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and words in err[0], err
    assert not (tmp_path / "a").exists()


@pytest.fixture()
def s3_bucket():
    """A bucket on moto's S3 server on 127.0.0.1 (this process's AWS environment set for the test, so that the
    local cluster's worker processes, spawned from it, reach the same server)."""
    pytest.importorskip("moto")
    import logging
    import uuid

    import boto3
    from moto.server import ThreadedMotoServer

    saved = dict(os.environ)
    logging.getLogger("werkzeug").setLevel(logging.ERROR)
    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    host, port = server.get_host_and_port()
    os.environ.update(AWS_ENDPOINT_URL=f"http://{host}:{port}", AWS_ACCESS_KEY_ID="AKIATESTING",
                      AWS_SECRET_ACCESS_KEY="testing-secret", AWS_DEFAULT_REGION="us-east-1")
    os.environ.pop("AWS_PROFILE", None)
    bucket = f"ingest-cluster-{uuid.uuid4().hex[:10]}"
    boto3.client("s3").create_bucket(Bucket=bucket)
    try:
        yield bucket
    finally:
        os.environ.clear()
        os.environ.update(saved)
        server.stop()


def test_an_s3_archive_through_a_local_cluster(flights, s3_bucket, tmp_path):
    """Two flights into an s3:// archive on a local cluster of two worker processes (the chunks PUT by the
    workers): complete, verified, its DN the raw cubes', equal chunk for chunk to the local ingest's."""
    import boto3

    from archive.catalog.root import open_root

    dirs, _, local, ids = flights
    url = f"s3://{s3_bucket}/arch"
    os.environ["XDG_CACHE_HOME"] = str(tmp_path / "cache")
    results = ingest([str(d) for d in dirs[:2]], url, FOV, ground_height=80.0, workers=2, threads=1, progress=False)
    assert [(r.cid, r.status) for r in results] == [(ids[0], "ingested"), (ids[1], "ingested")]
    root = open_root(url)
    s3 = boto3.client("s3")
    for cid in ids[:2]:
        assert verify_store(root.store(cid)) == []
        prefix = f"arch/collections/{cid}.zarr/"
        keys = [o["Key"] for page in s3.get_paginator("list_objects_v2").paginate(Bucket=s3_bucket, Prefix=prefix)
                for o in page.get("Contents", [])]
        chunks = [k for k in keys if "/dn/c/" in k]
        assert len(chunks) == 6 * 2
        for k in chunks:
            body = s3.get_object(Bucket=s3_bucket, Key=k)["Body"].read()
            assert body == (local / "collections" / k.removeprefix("arch/collections/")).read_bytes(), k
    raw = EnviCube(discover_flight(dirs[0]).cubes[0].data).read()
    assert np.array_equal(CheckedDn(root.store(ids[0])).read(3, 0, 100), raw[3])
