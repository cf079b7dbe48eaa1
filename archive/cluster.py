"""Where a render graph runs: a local cluster or a scheduler, how it is executed, how its errors read.

- :func:`start_cluster`: ``--scheduler ADDRESS`` (checked for GPU workers) or a local cluster of
  spawned, GPU-resourced worker processes (:data:`GL_SLOTS`, glibc's :data:`MALLOC_MMAP_THRESHOLD`);
- :func:`execute`: computes the graph's writer tasks with a progress bar, maps a task's failure or a
  dead worker to a :class:`~archive.errors.RenderError` (on a shared cluster, cancelling what is
  left and waiting for running writers first);
- :func:`task_budget`: bytes of values one render task may hold on these workers;
- :func:`active_client`: the default distributed Client, if any (for lazy mosaics).
"""

from __future__ import annotations

import os
import sys
import time

import numpy as np

from archive.errors import ArchiveError, InputError, RenderError

__all__ = ["GL_SLOTS", "MALLOC_MMAP_THRESHOLD", "active_client", "check_gpu_workers", "execute", "flight_slots",
           "start_cluster", "task_budget", "wait_for_writers"]


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


def positive(value, option: str, what: str) -> int | None:
    if value is not None and (isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value <= 0):
        raise InputError(option, f"expected a positive number of {what}, got {value!r}")
    return None if value is None else int(value)


def start_cluster(scheduler: str | None, workers: int | None, say, threads: int | None = None):
    """(client, cluster or None): ``scheduler`` or a local cluster of GPU-resourced workers.

    Local cluster: ``workers`` processes (default 1) of ``threads`` threads each (default: the
    machine's cores divided among the workers, at least 2). Render tasks need the 'GPU' resource
    (GL_SLOTS per worker: one draws on the worker's GL thread while another reads); writer tasks
    need none, so the other threads mosaic, encode and write meanwhile.
    """
    import logging

    from distributed import Client, LocalCluster

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
    with dask.config.set({"distributed.nanny.pre-spawn-environ": environ}):
        cluster = LocalCluster(n_workers=workers, threads_per_worker=threads or max(2, cores), processes=True,
                               resources={"GPU": GL_SLOTS}, env={"LP_NUM_THREADS": str(cores)},
                               dashboard_address=":0", silence_logs=logging.CRITICAL)  # errors come back here
    return Client(cluster), cluster


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

    futures = client.compute(list(graph.writes))
    done = as_completed(futures)
    del futures  # only as_completed holds them: results are released as soon as they are counted
    try:
        with tqdm(total=len(graph), desc="render", unit="task", disable=quiet, file=sys.stderr) as bar:
            for future in done:
                if future.status == "error":
                    future.result()  # raises the task's exception here
                future.release()
                bar.update(1)
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
    """Flights a batch keeps in the scheduler at once (its waves, :mod:`archive.batch`): the render
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
