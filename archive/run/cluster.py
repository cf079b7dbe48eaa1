"""Where a render graph runs: a local cluster or a scheduler, how it is executed, how its errors read.

- :func:`start_cluster`: ``--scheduler ADDRESS`` (checked for GPU workers), Dask workers as Slurm
  jobs (:class:`SlurmJobs`, ``--cluster slurm``: dask-jobqueue's SLURMCluster) or a local cluster of
  spawned, GPU-resourced worker processes (:data:`GL_SLOTS`, glibc's :data:`MALLOC_MMAP_THRESHOLD`);
- :func:`execute`: computes the graph's writer tasks with a progress bar, maps a task's failure or a dead
  worker to a :class:`~archive.errors.RenderError` (a shared cluster: the rest cancelled, writers awaited);
- :func:`task_budget`: bytes of values one render task may hold on these workers; :func:`active_client`:
  the default distributed Client, if any (lazy mosaics); :func:`phase`: a command's phases as they
  pass, for ``bench/timeline.py`` (``ARCHIVE_TIMELINE``).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from archive.errors import ArchiveError, InputError, RenderError

if TYPE_CHECKING:
    from distributed import Client, SpecCluster

__all__ = ["ClusterClose", "ClusterStart", "GL_SLOTS", "MALLOC_MMAP_THRESHOLD", "MALLOC_TRIM_THRESHOLD",
           "SlurmJobs", "active_client", "check_gpu_workers", "close_client", "closed_or_warned", "execute",
           "flight_slots", "phase", "start_cluster", "start_slurm", "task_budget", "wait_for_writers", "warm_up"]


#: ``ARCHIVE_TIMELINE=PATH``: every :func:`phase` a command passes is appended to PATH as a line ``NAME
#: SECONDS`` (wall clock): what ``bench/timeline.py`` lays over its CPU samples (unset: one env lookup).
TIMELINE = "ARCHIVE_TIMELINE"


def phase(name: str) -> None:
    """Record that the command reached ``name`` (one word, e.g. 'cluster-up') now, in the file of
    ``$ARCHIVE_TIMELINE``; nothing when it is unset. Never raises (an unwritable file is skipped:
    a record, not a condition of the run)."""
    path = os.environ.get(TIMELINE)
    if path:
        try:
            with open(path, "a") as f:
                f.write(f"{name} {time.time():.6f}\n")
        except OSError:
            pass


def check_gpu_workers(client, where: str) -> None:
    """InputError unless some worker of ``client`` offers the 'GPU' resource the GL tasks need."""
    workers = client.scheduler_info().get("workers", {})
    if not any((w.get("resources") or {}).get("GPU", 0) >= 1 for w in workers.values()):
        raise InputError(
            where, "no worker offers the 'GPU' resource the render tasks need",
            "start workers with `dask worker ADDRESS --resources GPU=2` (docs/deploy.md)",
        )


#: Render tasks a local worker admits at once (its 'GPU' resource): one draws on the worker's GL
#: thread while the next reads its bands.
GL_SLOTS = 2


#: glibc's M_MMAP_THRESHOLD for local workers (bytes; 32 MiB, its largest): allocations up to this
#: size come from the heap and are reused, instead of fresh memory-mapped pages for every large
#: temporary (each page faulted and zeroed by the kernel: COG writers spent more CPU in the kernel
#: than in Python; a 300-band COG render went from 38 s to 23-25 s, bench/RESULTS.md).
MALLOC_MMAP_THRESHOLD = 32 * 1024**2

#: glibc's M_TRIM_THRESHOLD for local workers (bytes): free memory kept at the top of a heap before
#: it is given back to the system. Dask's default (:data:`DASK_MALLOC_TRIM_THRESHOLD`, 64 KiB) gave
#: back, after every COG tile, the ~1 MB output buffer of its Zstandard encoding, faulted in again
#: for the next tile (issue 37); at the mmap threshold a heap keeps what one temporary needs. Up to
#: this much more resident memory per malloc arena of a worker.
MALLOC_TRIM_THRESHOLD = MALLOC_MMAP_THRESHOLD
DASK_MALLOC_TRIM_THRESHOLD = 65536


def positive(value, option: str, what: str) -> int | None:
    if value is not None and (isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value <= 0):
        raise InputError(option, f"expected a positive number of {what}, got {value!r}")
    return None if value is None else int(value)


#: Longest a command waits (s) for its cluster start's import of distributed before its own imports.
IMPORT_WAIT_S = 5.0

#: Tries to start a local cluster: a worker process that dies while the cluster starts (killed, out
#: of memory) costs one more try, then a one-line error.
START_ATTEMPTS = 2


class ClusterStart:
    """A cluster being started in a thread while the command goes on (imports, opening and planning
    its inputs: serial phases otherwise, issue 37): :func:`start_cluster` of the same arguments.
    Pass it as ``scheduler`` to :func:`start_cluster` (hence to :func:`archive.georectify`), which
    then waits for it; :meth:`close` closes a cluster that was started but never taken (the command
    failed before it needed one) and is a no-op otherwise."""

    def __init__(self, scheduler, workers: int | None, say, threads: int | None = None):
        import threading

        self._result: tuple | None = None
        self._error: BaseException | None = None
        self._taken = False
        self._imported = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(scheduler, workers, say, threads),
                                        name="archive-cluster-start", daemon=True)
        self._thread.start()
        # The command's imports wait for distributed's: imported side by side they share the one
        # interpreter lock, and the worker processes were spawned only once both were done
        # (measured: ~0.6 s after the command started instead of ~0.3 s).
        self._imported.wait(IMPORT_WAIT_S)

    def _run(self, scheduler, workers, say, threads) -> None:
        try:
            try:
                import distributed  # noqa: F401  (the start's longest import, before the command's own)
            finally:
                self._imported.set()
            self._result = start_cluster(scheduler, workers, say, threads)
            phase("cluster-up")
        except BaseException as exc:   # raised again where the cluster is taken
            self._error = exc

    def result(self) -> tuple:
        """(client, cluster or None) once started; raises what starting raised."""
        phase("cluster-wanted")
        self._thread.join()
        self._taken = True
        if self._error is not None:
            raise self._error
        return self._result

    def close(self) -> None:
        """Close the cluster unless it was taken (waits for its start to end)."""
        if self._taken:
            return
        self._taken = True
        self._thread.join()
        if self._result is not None:
            client, cluster = self._result
            client.close()
            if cluster is not None:
                cluster.close()


class ClusterClose:
    """Closes a client and its cluster (None: a shared scheduler, only the client) in a thread, so
    that the command publishes its output meanwhile instead of waiting for the worker processes to
    stop first (issue 37); :meth:`join` waits and raises what closing raised. Only once the graph's
    tasks have all ended: closing stops the worker processes."""

    def __init__(self, client, cluster):
        import threading

        self._error: BaseException | None = None
        phase("cluster-close")
        self._thread = threading.Thread(target=self._run, args=(client, cluster), name="archive-cluster-close",
                                        daemon=True)
        self._thread.start()

    def _run(self, client, cluster) -> None:
        try:
            close_client(client, cluster)
            phase("cluster-closed")
        except BaseException as exc:   # raised again by join
            self._error = exc

    def join(self) -> None:
        self._thread.join()
        if self._error is not None:
            raise self._error


def close_client(client: Client, cluster: SpecCluster | None) -> None:
    """Close ``client``, then ``cluster`` (None: a shared scheduler's client, nothing more); the
    cluster even when the client's close failed, so that its worker processes stop. Raises the first
    error."""
    error: BaseException | None = None
    try:
        client.close()
    except BaseException as exc:
        error = exc
    if cluster is not None:
        try:
            cluster.close()  # stops the worker processes (cancels Slurm worker jobs), with any task still writing
        except BaseException as exc:
            error = error or exc
    if error is not None:
        raise error


def closed_or_warned(close: Callable[[], None], command: str, what: str) -> None:
    """Call ``close`` (:func:`close_client`, or :meth:`ClusterClose.join`), made only once nothing
    more is expected of the cluster: every task ended, or the run failed. An Exception it raises (a
    worker process still alive after Dask's timeouts on a loaded machine: Dask's TimeoutError) is
    one warning line on stderr, ``{command}: warning: {what}: ...``, never the command's error: the
    outputs were published, or the run's own error is the one to report, and the outputs'
    temporaries are removed after this either way."""
    try:
        close()
    except Exception as exc:   # not KeyboardInterrupt and the like
        why = " ".join(f"{type(exc).__name__}: {exc}".split()).rstrip(": ")
        print(f"{command}: warning: {what}: the Dask cluster did not close cleanly ({why})", file=sys.stderr)


def start_cluster(scheduler, workers: int | None, say, threads: int | None = None):
    """(client, cluster or None) of :func:`_start_cluster`; a local cluster whose start fails (a
    worker process died while starting) is started again, up to :data:`START_ATTEMPTS` times, then
    a one-line :class:`~archive.errors.RenderError` says why (never Dask's traceback).
    ``scheduler`` a :class:`ClusterStart`: its result (started already, or being started)."""
    if isinstance(scheduler, ClusterStart):
        return scheduler.result()
    attempts = 1 if scheduler else START_ATTEMPTS
    for attempt in range(1, attempts + 1):
        try:
            return _start_cluster(scheduler, workers, say, threads)
        except ArchiveError:
            raise
        except (RuntimeError, OSError, TimeoutError) as exc:
            cause = exc
            while cause.__cause__ is not None:   # Dask's "Nanny failed to start." wraps why
                cause = cause.__cause__
            why = " ".join(f"{type(cause).__name__}: {cause}".split())
            if attempt < attempts:
                say(f"archive render: the local Dask cluster did not start ({why}); starting it again")
                continue
            raise RenderError(f"the local Dask cluster did not start, {attempts} times: a worker process died "
                              f"while starting ({why}); check the memory left (dmesg), the DASK_* variables "
                              "(preloads) and run 'archive doctor'") from None
    raise AssertionError("unreachable")


def _start_cluster(scheduler, workers: int | None, say, threads: int | None = None):
    """(client, cluster or None): ``scheduler`` (an address, or a :class:`SlurmJobs`: workers as Slurm
    jobs) or a local cluster of GPU-resourced workers.

    Local cluster: ``workers`` processes (default 1) of ``threads`` threads each (default: the
    machine's cores divided among the workers, at least 2). Render tasks need the 'GPU' resource
    (GL_SLOTS per worker: one draws on the worker's GL thread while another reads); writer tasks
    need none, so the other threads mosaic, encode and write meanwhile.
    """
    import logging

    from distributed import Client, LocalCluster

    if isinstance(scheduler, SlurmJobs):
        if workers is not None or threads is not None:
            raise InputError("--workers/--threads", "size a local cluster, not Slurm worker jobs",
                             "give --jobs and --job-cores instead")
        return start_slurm(scheduler, say)
    if scheduler:
        try:
            client = Client(scheduler, timeout="20s")
        except OSError as exc:
            raise InputError("--scheduler", f"cannot connect to {scheduler}: {exc}",
                             "start one with `dask scheduler` and workers with `--resources GPU=2`") from None
        say(f"archive render: Dask dashboard at {client.dashboard_link}")
        try:
            check_gpu_workers(client, f"--scheduler {scheduler}")
        except InputError:
            client.close()
            raise
        return client, None
    workers = positive(workers, "--workers", "worker processes") or 1
    threads = positive(threads, "--threads", "threads per worker")
    cores = max(1, (os.cpu_count() or 1) // workers)
    # Spawned worker processes (never forked after GL). GL calls run on each worker's GL thread
    # (archive.graph.tasks.gl_call); llvmpipe draws with the worker's cores (LP_NUM_THREADS). glibc
    # reads MALLOC_* when a process starts: Dask sets its 'pre-spawn' variables before spawning.
    import dask

    environ = dict(dask.config.get("distributed.nanny.pre-spawn-environ", None) or {})
    environ.setdefault("MALLOC_MMAP_THRESHOLD_", str(MALLOC_MMAP_THRESHOLD))
    # Dask's nanny takes a variable from this process's environment before its configuration, and
    # leaves its pre-spawn values there when it spawns: a 64 KiB trim threshold found in either is
    # Dask's default (from its configuration, or an earlier cluster of this process), replaced by ours.
    trim = os.environ.get("MALLOC_TRIM_THRESHOLD_", str(environ.get("MALLOC_TRIM_THRESHOLD_", "")))
    if trim in ("", str(DASK_MALLOC_TRIM_THRESHOLD)):
        environ["MALLOC_TRIM_THRESHOLD_"] = os.environ["MALLOC_TRIM_THRESHOLD_"] = str(MALLOC_TRIM_THRESHOLD)
    # Workers spread over the node's GPUs (archive.render.device.spread_environments): each worker's
    # own CUDA_VISIBLE_DEVICES entry or EGL device; nothing to spread on one GPU or none.
    from archive.render.device import egl_devices, spread_environments

    spread = spread_environments(egl_devices(), workers)
    spreading = any(spread)
    # Each worker warms itself up while it starts (dask_setup below, a worker preload after any the
    # configuration names): the command is still importing and planning on one core meanwhile.
    configured = dask.config.get("distributed.worker.preload", None) or []
    preload = [*([configured] if isinstance(configured, str) else configured), __name__]
    with dask.config.set({"distributed.nanny.pre-spawn-environ": environ}):
        cluster = LocalCluster(n_workers=0 if spreading else workers,
                               threads_per_worker=threads or max(2, cores), processes=True,
                               resources={"GPU": GL_SLOTS}, env={"LP_NUM_THREADS": str(cores)},
                               dashboard_address=":0", silence_logs=logging.CRITICAL,  # errors come back here
                               preload=preload)
        if spreading:   # one worker spec each, with its own device variables, then started together
            for extra in spread:
                ((name, spec),) = cluster.new_worker_spec().items()
                options = dict(spec["options"])
                options["env"] = {**(options.get("env") or {}), **extra}
                cluster.worker_spec[name] = {**spec, "options": options}
            cluster.scale(workers)
    client = Client(cluster)
    if spreading:
        client.wait_for_workers(workers, timeout=120)
    return client, cluster


def warm_up() -> None:
    """What a render task's first run on a fresh worker process does besides its work, done ahead:
    import the modules the graph's tasks are unpickled with (sources, renderers, output writers:
    ~0.45 CPU-s) and make the process's GL context on its GL thread, deciding its band pass
    (:func:`archive.graph.tasks.band_pass_choice`, the same decision a render task makes). Never
    raises: a failure here is the first render task's to report, as it would have been."""
    import importlib

    try:
        for name in ("archive.outputs.registry", "archive.render.gather", "archive.sources"):
            importlib.import_module(name)   # writers, renderers, sources
        from archive.graph.tasks import band_pass_choice

        band_pass_choice()
    except BaseException:   # noqa: BLE001  (reported by the task that needs it)
        pass


def dask_setup(worker) -> None:
    """Dask worker preload hook (local clusters of :func:`_start_cluster` name this module), in the
    worker process (issue 37):

    - starts :func:`warm_up` in a daemon thread once the worker runs (has joined the cluster) and
      returns at once: the worker warms up while the command imports and plans (the first render
      task no longer pays ~0.5 s of imports and GL start-up after the graph is submitted);
    - makes the process end, once the worker has closed, as :func:`archive.cli.exit_now` ends the
      command: the ``atexit`` handlers run, the streams flushed, then ``os._exit`` (exit code 0 when
      the worker closed, else 1), without the interpreter's finalization (module teardown with a GL
      context open: 0.2-1 s that the command's :class:`ClusterClose` waited for). Every task has
      ended and closed its files before a local cluster is closed."""
    import threading

    def once_running() -> None:   # the worker registers first: the warm-up must not delay the cluster's start
        deadline = time.monotonic() + 60
        while getattr(getattr(worker, "status", None), "name", "running") != "running" and time.monotonic() < deadline:
            time.sleep(0.01)
        warm_up()

    threading.Thread(target=once_running, name="archive-warm-up", daemon=True).start()
    import atexit

    run_exitfuncs = getattr(atexit, "_run_exitfuncs", None)   # CPython's; elsewhere the worker ends as usual
    if run_exitfuncs is None:
        return

    def exit_now() -> None:   # the worker process's last atexit handler to be registered runs first
        atexit.unregister(exit_now)
        run_exitfuncs()   # the handlers registered before this one, as the interpreter would
        closed = getattr(getattr(worker, "status", None), "name", "") == "closed"
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError):
                pass
        os._exit(0 if closed else 1)

    atexit.register(exit_now)


@dataclass(frozen=True)
class SlurmJobs:
    """Dask workers as Slurm batch jobs (``--cluster slurm``: dask-jobqueue's SLURMCluster), one
    worker process per job, started with the 'GPU' resource like the workers of docs/deploy.md.
    A field left ``None`` comes from dask-jobqueue's own configuration (``jobqueue: slurm:`` in
    ~/.config/dask/jobqueue.yaml, /etc/dask/ or $DASK_CONFIG), which also holds what has no field
    here (account, interface, log-directory, local-directory, job-extra-directives, ...).

    jobs: worker jobs kept running (one that ends early, cancelled or out of walltime, is submitted
    again); queue: the partition; cores: CPUs per job (the worker's threads and LP_NUM_THREADS);
    memory: per job, e.g. '16GB' (the worker's memory limit); walltime: 'HH:MM:SS'; gpus: GPUs per
    job, 0 or 1 (``--gres=gpu:1``; a worker process draws on one GPU: more GPUs, more jobs).
    """

    jobs: int = 1
    queue: str | None = None
    cores: int | None = None
    memory: str | None = None
    walltime: str | None = None
    gpus: int | None = None


#: Seconds between two checks that every Slurm worker job is there (a lost one is submitted again,
#: once Dask's ``distributed.deploy.lost-worker-timeout`` has passed).
KEEP_JOBS_SECONDS = 10.0


def start_slurm(spec: SlurmJobs, say):
    """(client, cluster): ``spec.jobs`` Slurm jobs of one GPU-resourced worker each, submitted by
    dask-jobqueue's SLURMCluster (its scheduler runs in this process, reachable on jobqueue's
    ``interface``); returns once the first worker has connected. InputError when dask-jobqueue or
    Slurm's commands are missing, cores or memory are given nowhere, sbatch refuses the job
    (``sbatch --test-only``, before any job is queued) or every job ends before its worker connects."""
    import dask
    from distributed import Client
    from tornado.ioloop import PeriodicCallback

    try:
        from dask_jobqueue import SLURMCluster   # also loads jobqueue's configuration defaults
    except ImportError:
        raise InputError("--cluster slurm", "needs the dask-jobqueue package", "pip install dask-jobqueue") from None
    for tool in ("sbatch", "squeue", "scancel"):
        if shutil.which(tool) is None:
            raise InputError("--cluster slurm", f"Slurm's {tool} is not on PATH: this machine cannot submit jobs",
                             "run archive render on a Slurm login node (docs/deploy.md)")
    jobs = positive(spec.jobs, "--jobs", "Slurm worker jobs") or 1
    config = dask.config.get("jobqueue.slurm", default={}) or {}
    cores = positive(spec.cores, "--job-cores", "cores per job") or config.get("cores")
    memory = spec.memory or config.get("memory")
    if not cores or not memory:
        raise InputError("--job-cores/--job-memory", "a Slurm worker job needs its cores and memory",
                         "pass --job-cores N --job-memory 16GB, or set cores and memory under 'jobqueue: slurm:' "
                         "in ~/.config/dask/jobqueue.yaml (docs/deploy.md)")
    if spec.gpus is not None and (isinstance(spec.gpus, bool) or spec.gpus not in (0, 1)):
        raise InputError("--job-gpus", f"expected 0 or 1 GPUs per job, got {spec.gpus!r}",
                         "a worker process draws on one GPU: ask for more --jobs to use more GPUs")
    directives = list(config.get("job-extra-directives") or [])
    if spec.gpus:
        directives.append(f"--gres=gpu:{spec.gpus}")
    worker_args = list(config.get("worker-extra-args") or [])
    if "--resources" not in worker_args:
        worker_args += ["--resources", f"GPU={GL_SLOTS}"]
    # The configuration's own prologue comes last, so that a site's settings win.
    # A job given a GPU must render on it (archive.render.device: a software renderer is then an error).
    prologue = [f"export LP_NUM_THREADS={int(cores)}", f"export MALLOC_MMAP_THRESHOLD_={MALLOC_MMAP_THRESHOLD}",
                *(["export ARCHIVE_REQUIRE_GPU=1"] if spec.gpus else []),
                *(config.get("job-script-prologue") or [])]
    # A free dashboard port unless the configuration names one (a login node is shared; the link is printed).
    scheduler_options = {"dashboard_address": ":0", **(config.get("scheduler-options") or {})}
    try:
        cluster = SLURMCluster(cores=int(cores), processes=1, memory=memory, queue=spec.queue,
                               walltime=spec.walltime, job_extra_directives=directives,
                               worker_extra_args=worker_args, job_script_prologue=prologue,
                               scheduler_options=scheduler_options)
    except ValueError as exc:
        raise InputError("--cluster slurm", f"dask-jobqueue refuses the worker job: {exc}") from None
    client = None
    try:
        _test_submit(cluster.job_script())
        cluster.scale(jobs=jobs)
        keep = PeriodicCallback(lambda: cluster.scale(jobs=jobs), KEEP_JOBS_SECONDS * 1000)
        cluster.periodic_callbacks["archive-keep-jobs"] = keep   # stopped when the cluster closes
        cluster.loop.add_callback(keep.start)
        client = Client(cluster)
        say(f"archive render: {jobs} Slurm worker job{'s' if jobs != 1 else ''} submitted; Dask dashboard at "
            f"{client.dashboard_link}")
        _wait_for_first_worker(client, cluster, say)
        check_gpu_workers(client, "--cluster slurm")
    except BaseException:
        if client is not None:
            client.close()
        cluster.close()   # cancels the jobs (scancel)
        raise
    return client, cluster


def _test_submit(script: str) -> None:
    """InputError when ``sbatch --test-only`` refuses the worker job script (nothing is queued)."""
    try:
        done = subprocess.run(["sbatch", "--test-only"], input=script, capture_output=True, text=True, timeout=60)
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise InputError("--cluster slurm", f"sbatch --test-only did not answer: {exc}",
                         "check that Slurm's controller runs (sinfo)") from None
    if done.returncode:
        why = " ".join((done.stderr or done.stdout).split()) or f"exit code {done.returncode}"
        raise InputError("--cluster slurm", f"sbatch refuses the worker job: {why}",
                         "check --job-queue, --job-cores, --job-memory, --job-walltime, --job-gpus and the "
                         "'jobqueue: slurm:' configuration (docs/deploy.md)")


def _wait_for_first_worker(client, cluster, say, submit_timeout: float = 120.0) -> None:
    """Wait (as long as a job is queued or running) until a worker has connected; InputError when
    every worker job ended first, or when no job was submitted within ``submit_timeout`` s."""
    started, told = time.monotonic(), False
    while True:
        try:
            client.wait_for_workers(1, timeout=5)
            return
        except TimeoutError:
            pass
        ids = sorted(str(j.job_id) for j in list(cluster.workers.values()) if getattr(j, "job_id", None))
        if not ids:
            if time.monotonic() - started > submit_timeout:
                raise InputError("--cluster slurm", f"no worker job was submitted in {submit_timeout:.0f} s",
                                 "check that sbatch works on this machine (docs/deploy.md)")
            continue
        if not told:
            say(f"archive render: waiting for Slurm job{'s' if len(ids) != 1 else ''} {', '.join(ids)} to start "
                "(squeue shows why they wait)")
            told = True
        done = subprocess.run(["squeue", "-h", "-o", "%i", "-t", "PD,CF,R", "-u", str(os.getuid())],
                              capture_output=True, text=True, timeout=60)
        if done.returncode == 0 and not set(ids) & set(done.stdout.split()):
            try:
                client.wait_for_workers(1, timeout=5)   # connected just before its job ended?
                return
            except TimeoutError:
                pass
            raise InputError("--cluster slurm", f"the Slurm worker job{'s' if len(ids) != 1 else ''} "
                             f"{', '.join(ids)} ended before a worker connected to {client.scheduler.address}",
                             "read the jobs' output files (jobqueue's log-directory, else the current directory); "
                             "workers must reach this machine: set 'interface' under 'jobqueue: slurm:' "
                             "(docs/deploy.md)")


def wait_for_writers(client, timeout: float = 60.0) -> None:
    """Wait until no worker is still running one of our writer tasks (best effort)."""
    deadline = time.monotonic() + timeout
    try:
        while time.monotonic() < deadline:
            running = [k for stack in client.call_stack().values() for k in stack]
            if not any(str(k).startswith(("write-", "saturated-", "blank-", "overview-")) for k in running):
                return
            time.sleep(0.2)
    except Exception:  # the scheduler may be gone already
        pass


def execute(client, graph, quiet: bool, shared: bool) -> None:
    """Compute the writer tasks with a progress bar; re-raise the first task error as an ArchiveError.

    shared: the cluster outlives this command (``--scheduler``): on failure, cancel our tasks and
    wait for running writers, so that no chunk lands in the store after it is deleted.
    """
    from distributed import KilledWorker, as_completed
    from tqdm import tqdm

    phase("graph-submit")
    futures = client.compute(list(graph.writes))
    done = as_completed(futures, loop=client.loop)   # not the default client's loop (archive.run.batch)
    del futures  # only as_completed holds them: results are released as soon as they are counted
    try:
        with tqdm(total=len(graph), desc="render", unit="task", disable=quiet, file=sys.stderr) as bar:
            for n, future in enumerate(done):
                if future.status == "error":
                    future.result()  # raises the task's exception here
                future.release()
                bar.update(1)
                if not n:
                    phase("first-write")
        phase("last-write")
    except BaseException as exc:
        if shared:
            client.cancel(list(done.futures), force=True)
            wait_for_writers(client)
        if isinstance(exc, (ArchiveError, KeyboardInterrupt)) or not isinstance(exc, Exception):
            raise
        if isinstance(exc, KilledWorker):
            raise RenderError(f"a Dask worker died while rendering ({exc}); it may have run out of memory "
                              "or crashed in OpenGL: try a larger --gsd or fewer --wavelengths") from exc
        raise RenderError(f"a render task failed: {type(exc).__name__}: {exc}") from exc


def task_budget(client) -> int:
    """Bytes of rendered values one render task may hold: TASK_VALUES_BYTES, or a tenth of the
    smallest worker memory limit when that is less (small workers get smaller band groups)."""
    from archive.graph.build import TASK_VALUES_BYTES

    limits = [int(w.get("memory_limit") or 0) for w in client.scheduler_info().get("workers", {}).values()]
    limits = [m for m in limits if m > 0]
    return min([TASK_VALUES_BYTES] + [m // 10 for m in limits])


def flight_slots(client, budget: int) -> int:
    """Flights a batch keeps in the scheduler at once (its waves, :mod:`archive.run.batch`): the render
    slots of the workers (their 'GPU' resources), at least 2 so that one flight is planned and
    published while another renders, and at most what the workers' memory holds (a flight holds
    about ``RENDERS_AHEAD`` + 2 renders of ``budget`` bytes at a time)."""
    from archive.graph.build import RENDERS_AHEAD

    workers = client.scheduler_info().get("workers", {}).values()
    slots = sum(int((w.get("resources") or {}).get("GPU", 0)) for w in workers)
    memory = sum(int(w.get("memory_limit") or 0) for w in workers)
    by_memory = memory // ((RENDERS_AHEAD + 2) * max(int(budget), 1)) if memory else slots
    return max(2, min(slots, by_memory))


def active_client():
    """The default distributed Client, if one is active (distributed is never imported here)."""
    distributed = sys.modules.get("distributed")
    if distributed is None:
        return None
    try:
        return distributed.default_client()
    except ValueError:
        return None
