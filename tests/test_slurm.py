"""``archive render --cluster slurm`` on a real one-node Slurm (issue 19, item 6).

The test starts Debian's ``munged``, ``slurmctld`` and ``slurmd`` itself, as root, on loopback (a
temporary ``slurm.conf`` and munge key; ports picked free), renders a 3-flight batch through
``--cluster slurm`` (two worker jobs submitted by dask-jobqueue's SLURMCluster, their size partly
from dask-jobqueue's own ``jobqueue: slurm:`` configuration file), cancels one worker job with
``scancel`` while flights are still rendering, and checks that the batch completes and its outputs
equal single-flight renders on a local cluster bit for bit. Every daemon, job and process it
started is stopped at the end, also when the test fails.

Skipped, with the reason, when not root, when ``slurm-wlm`` / ``munge`` / ``dask-jobqueue`` are
missing (``./dev.sh test`` installs them) or when the daemons do not come up.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from helpers import FOV, ingest_each

GSD = "0.02"
#: Flights large enough that one renders for seconds on one worker thread (the cancel lands mid-batch).
SHAPE = dict(cubes=2, bands=6, samples=96, lines=160, cubes_per_pass=2)
DAEMONS = ("munged", "slurmctld", "slurmd", "sbatch", "squeue", "scancel", "sinfo", "srun", "scontrol")


def _why_not() -> str | None:
    if not hasattr(os, "geteuid") or os.geteuid() != 0:
        return "needs root to start munged, slurmctld and slurmd (run as root, e.g. in CI's container)"
    missing = [d for d in DAEMONS if shutil.which(d) is None and not Path("/usr/sbin", d).exists()]
    if missing:
        return f"{', '.join(missing)} not installed: apt-get install slurm-wlm munge (./dev.sh test does)"
    try:
        import dask_jobqueue  # noqa: F401
    except ImportError:
        return "dask-jobqueue is not installed: pip install -e '.[test]'"
    return None


needs_slurm = pytest.mark.skipif(_why_not() is not None, reason=_why_not() or "")


def test_slurm_options_are_checked_before_anything_starts(tmp_path, capsys):
    """--job-* without --cluster slurm, --cluster with --scheduler or --workers: one line, exit 2."""
    from archive.cli import main

    base = ["render", str(tmp_path / "flight"), "--fov", str(FOV), "--gsd", "0.1", "--out", str(tmp_path / "o.tif")]
    cases = [(["--jobs", "2"], "--jobs: sizes the worker jobs of --cluster slurm"),
             (["--job-memory", "4GB"], "--job-memory: sizes the worker jobs of --cluster slurm"),
             (["--cluster", "slurm", "--scheduler", "tcp://h:8786"], "--cluster and --scheduler both say where"),
             (["--cluster", "slurm", "--workers", "2"], "size a local cluster, not Slurm worker jobs")]
    for extra, message in cases:
        capsys.readouterr()
        assert main(base + extra) == 2, extra
        err = capsys.readouterr().err
        assert message in err and len(err.strip().splitlines()) == 1, err
    assert not list(tmp_path.iterdir())


def test_slurm_jobs_come_from_options_and_jobqueue_config(monkeypatch):
    """SlurmJobs from the options; what is left out comes from dask-jobqueue's configuration; the job
    script starts a worker with the GPU resource, LP_NUM_THREADS = its cores, one GPU by --gres."""
    pytest.importorskip("dask_jobqueue")
    import argparse

    import dask
    from dask_jobqueue import SLURMCluster

    from archive.run.cluster import SlurmJobs
    from archive.run.command import JOB_OPTIONS

    assert set(JOB_OPTIONS.values()) == {f.name for f in __import__("dataclasses").fields(SlurmJobs)}
    from archive.cli import build_parser

    args = build_parser().parse_args(["render", "x", "--gsd", "1", "--out", "o.zarr", "--cluster", "slurm",
                                      "--jobs", "3", "--job-queue", "gpu", "--job-cores", "8", "--job-gpus", "1"])
    from archive.run.command import _where

    spec = _where(args)
    assert spec == SlurmJobs(jobs=3, queue="gpu", cores=8, gpus=1)
    seen = {}

    class Fake(SLURMCluster):   # records the job script instead of submitting it
        def __init__(self, **kw):
            super().__init__(**kw)
            seen["script"] = self.job_script()
            self.close()
            raise ValueError("stop here")

    monkeypatch.setattr("dask_jobqueue.SLURMCluster", Fake)
    monkeypatch.setattr("shutil.which", lambda name: f"/usr/bin/{name}")
    from archive.run.cluster import start_slurm
    from archive.errors import InputError

    with dask.config.set({"jobqueue.slurm.memory": "24GB", "jobqueue.slurm.account": "lab42",
                          "jobqueue.slurm.scheduler-options": {"dashboard_address": ":0"}}):
        with pytest.raises(InputError, match="stop here"):
            start_slurm(spec, print)
    script = seen["script"]
    for line in ("#SBATCH -p gpu", "#SBATCH -A lab42", "#SBATCH --cpus-per-task=8", "#SBATCH --gres=gpu:1",
                 "export LP_NUM_THREADS=8", "--resources GPU=2", "--nthreads 8"):
        assert line in script, (line, script)
    assert "#SBATCH --mem=" in script
    with pytest.raises(InputError, match="needs its cores and memory"):
        with dask.config.set({"jobqueue.slurm.memory": None, "jobqueue.slurm.cores": None}):
            start_slurm(SlurmJobs(jobs=1), print)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _exe(name: str) -> str:
    return shutil.which(name) or str(Path("/usr/sbin", name))


class Slurm:
    """munged + slurmctld + slurmd of one node, all under ``root`` (a temporary directory)."""

    def __init__(self, root: Path):
        self.root = root
        self.procs: dict[str, subprocess.Popen] = {}
        self.host = socket.gethostname().split(".")[0]
        self.partition = "archive"
        self.conf = root / "slurm.conf"
        self.env = {**os.environ, "SLURM_CONF": str(self.conf)}

    def log_tail(self, lines: int = 8) -> str:
        out = []
        for name in ("munged.log", "slurmctld.log", "slurmd.log"):
            p = self.root / name
            if p.exists():
                out.append(f"--- {name}\n" + "\n".join(p.read_text(errors="replace").splitlines()[-lines:]))
        return "\n".join(out)

    def _spawn(self, name: str, *args: str) -> None:
        log = open(self.root / f"{name}.out", "w")
        self.procs[name] = subprocess.Popen([_exe(name), *args], stdout=log, stderr=subprocess.STDOUT,
                                            env=self.env, start_new_session=True)

    def start(self) -> None:
        d = self.root
        d.chmod(0o755)   # munged wants its socket's directory traversable by everyone
        for sub in ("state", "spool"):
            (d / sub).mkdir()
        key = d / "munge.key"
        key.write_bytes(os.urandom(1024))
        key.chmod(0o600)
        sock = d / "munge.sock"
        self._spawn("munged", "-F", "--force", f"--socket={sock}", f"--key-file={key}", f"--pid-file={d}/munged.pid",
                    f"--log-file={d}/munged.log", f"--seed-file={d}/munged.seed")
        self._wait(lambda: sock.exists(), 10, "munged made no socket")
        self.conf.write_text("\n".join([
            "ClusterName=archivetest",
            f"SlurmctldHost={self.host}(127.0.0.1)",
            f"SlurmctldPort={_free_port()}",
            f"SlurmdPort={_free_port()}",
            "AuthType=auth/munge",
            f"AuthInfo=socket={sock}",
            "CredType=cred/munge",
            "SlurmUser=root",
            "SlurmdUser=root",
            f"StateSaveLocation={d}/state",
            f"SlurmdSpoolDir={d}/spool",
            f"SlurmctldPidFile={d}/slurmctld.pid",
            f"SlurmdPidFile={d}/slurmd.pid",
            f"SlurmctldLogFile={d}/slurmctld.log",
            f"SlurmdLogFile={d}/slurmd.log",
            "ProctrackType=proctrack/linuxproc",
            "TaskPlugin=task/none",
            "SelectType=select/cons_tres",
            "SelectTypeParameters=CR_Core",
            "SlurmdParameters=config_overrides",   # 4 CPUs declared on a 2-core machine
            "ReturnToService=2",
            "KillWait=5",
            "MpiDefault=none",
            "JobAcctGatherType=jobacct_gather/none",
            "AccountingStorageType=accounting_storage/none",
            f"NodeName={self.host} NodeAddr=127.0.0.1 CPUs=4 RealMemory=8000 State=UNKNOWN",
            f"PartitionName={self.partition} Nodes={self.host} Default=YES MaxTime=INFINITE State=UP",
        ]) + "\n")
        self._spawn("slurmctld", "-D", "-i", "-f", str(self.conf))
        self._spawn("slurmd", "-D", "-f", str(self.conf))
        self._wait(lambda: self.run("sinfo", "-h", "-o", "%T").stdout.strip() in ("idle", "mixed"), 30,
                   "the node did not come up idle")
        got = self.run("srun", "-N1", "hostname", timeout=30)
        if got.returncode:
            raise RuntimeError(f"srun hostname failed: {got.stderr.strip()}")

    def _wait(self, ready, seconds: float, what: str) -> None:
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            dead = [n for n, p in self.procs.items() if p.poll() is not None]
            if dead:
                raise RuntimeError(f"{', '.join(dead)} exited")
            try:
                if ready():
                    return
            except (OSError, subprocess.SubprocessError):
                pass
            time.sleep(0.3)
        raise RuntimeError(what)

    def run(self, *args: str, timeout: float = 30) -> subprocess.CompletedProcess:
        return subprocess.run(list(args), capture_output=True, text=True, env=self.env, timeout=timeout)

    def jobs(self, states: str = "PD,CF,R,CG") -> list[str]:
        return self.run("squeue", "-h", "-o", "%i", "-t", states).stdout.split()

    def stop(self) -> None:
        """Cancel every job, stop the daemons, then whatever the jobs started that is still alive."""
        import psutil

        try:
            self.run("scancel", "--user", "root")
            deadline = time.monotonic() + 20
            while self.jobs() and time.monotonic() < deadline:
                time.sleep(0.5)
        except (OSError, subprocess.SubprocessError):
            pass
        started = []   # slurmd's descendants: job steps and the workers they run
        if "slurmd" in self.procs:
            try:
                started = psutil.Process(self.procs["slurmd"].pid).children(recursive=True)
            except psutil.Error:
                pass
        for name in ("slurmd", "slurmctld", "munged"):
            p = self.procs.get(name)
            if p is not None and p.poll() is None:
                p.send_signal(signal.SIGTERM)
                try:
                    p.wait(10)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait(10)
        for child in started:
            try:
                child.kill()
            except psutil.Error:
                pass


@pytest.fixture(scope="module")
def slurm(tmp_path_factory):
    cluster = Slurm(tmp_path_factory.mktemp("slurm"))
    try:
        try:
            cluster.start()
        except (RuntimeError, OSError, subprocess.SubprocessError) as exc:
            pytest.skip(f"a one-node Slurm did not come up ({exc}):\n{cluster.log_tail()}")
        yield cluster
    finally:
        cluster.stop()


@pytest.fixture(scope="module")
def archive3(simulated, tmp_path_factory):
    """(archive, ids) of three small flights (seeds 0-2: distinct ids)."""
    archive = tmp_path_factory.mktemp("slurm-archive") / "archive"
    return archive, ingest_each([simulated(seed=seed, **SHAPE)[0] for seed in range(3)], archive)


def _read(path: Path) -> np.ndarray:
    import rasterio

    with rasterio.open(path) as src:
        return src.read()


@needs_slurm
def test_batch_on_slurm_survives_a_cancelled_worker_job(slurm, archive3, scheduler, tmp_path):
    archive, ids = archive3
    config = tmp_path / "dask"
    config.mkdir()
    # dask-jobqueue's own configuration gives what the command line leaves out (memory, interface...)
    (config / "jobqueue.yaml").write_text(
        "jobqueue:\n  slurm:\n    memory: 2GB\n    interface: lo\n    death-timeout: 30\n"
        "    scheduler-options: {dashboard_address: ':0'}\n"
        f"    log-directory: {tmp_path / 'logs'}\n    local-directory: {tmp_path / 'spill'}\n")
    # the batch holds after its first flight while the hold file exists (ARCHIVE_TEST_HOLD_AFTER=1:PATH):
    # the job is cancelled while flights are pending, however loaded the machine
    hold = tmp_path / "batch.hold"
    hold.touch()
    env = {**slurm.env, "DASK_CONFIG": str(config), "DASK_DISTRIBUTED__DEPLOY__LOST_WORKER_TIMEOUT": "2s",
           "ARCHIVE_TEST_HOLD_AFTER": f"1:{hold}"}
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "archive", "render", "--archive", str(archive), "--query-bbox", "-180,-90,180,90",
           "--gsd", GSD, "--out", str(out), "--format", "tif", "--cluster", "slurm", "--jobs", "2",
           "--job-queue", slurm.partition, "--job-cores", "1", "--job-walltime", "00:10:00"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=tmp_path,
                            start_new_session=True)
    lines, cancelled, at_cancel = [], None, None
    import threading

    watchdog = threading.Timer(540, lambda: os.killpg(proc.pid, signal.SIGKILL))   # never hang CI
    watchdog.start()
    try:
        for line in proc.stdout:   # one line per finished flight
            lines.append(line.rstrip())
            if cancelled is None and " done " in f" {line}":
                held = time.monotonic() + 120
                while not Path(f"{hold}.reached").exists() and time.monotonic() < held:
                    time.sleep(0.05)
                while len(running := sorted(slurm.jobs("R"), key=int)) < 2 and time.monotonic() < held:
                    time.sleep(0.2)   # the second worker job may still be starting on a loaded machine
                assert len(running) == 2, (running, slurm.log_tail())
                at_cancel = json.loads((out / "report.json").read_text())
                cancelled = running[0]
                assert slurm.run("scancel", cancelled).returncode == 0
                hold.unlink()       # the batch goes on without that worker
        stderr = proc.stderr.read()
        code = proc.wait(timeout=60)
    finally:
        watchdog.cancel()
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(30)
    assert cancelled is not None, (lines, stderr[-3000:])
    assert at_cancel["pending"] >= 1, "the worker job was cancelled after every flight had finished"
    doc = json.loads((out / "report.json").read_text())
    assert code == 0, (lines, stderr[-3000:], doc)
    assert doc["complete"] and (doc["done"], doc["failed"], doc["pending"]) == (3, 0, 0), doc
    ended = time.monotonic() + 20   # cancelled jobs complete within KillWait
    while slurm.jobs("PD,CF,R") and time.monotonic() < ended:
        time.sleep(0.5)
    assert not slurm.jobs("PD,CF,R"), "the command left Slurm worker jobs behind"
    # the cancelled job really ended before its worker's job would have
    state = slurm.run("scontrol", "show", "job", cancelled).stdout
    assert "JobState=CANCELLED" in state, state

    # the same flights, each rendered alone on a local cluster: equal bit for bit
    import archive as api

    for cid in ids:
        single = tmp_path / "single" / f"{cid}.tif"
        api.georectify([cid], single, archive=archive, gsd=float(GSD), scheduler=scheduler)
        assert np.array_equal(_read(out / f"{cid}.tif"), _read(single), equal_nan=True), cid
