"""One `archive render` with its task stream and CPU-seconds per stage (issue 20).

    python bench/stage_profile.py OUT.json [--workers N] [--threads N] [--stream FILE] -- FLIGHT --out X.hdr --gsd ... (render args)

Starts the local cluster exactly as the command does (:func:`archive.run.cluster.start_cluster`: the
same worker processes, threads, GPU resources, LP_NUM_THREADS and malloc settings), installs stage
timers in the workers, runs ``archive.cli.main(render args + --scheduler ADDRESS)`` in this process
under ``distributed.get_task_stream``, and writes OUT.json:

- ``wall_s``: the command (open, plan, graph, publish; cluster start-up before it not included:
  ``start_s``); ``graph_s``: first task start to last task end (task stream);
- ``cpu``: CPU-seconds (user + system) of this process (client, scheduler, planning, COG layout)
  and of each worker process, read before the cluster closes;
- ``threads``: worker CPU-seconds by thread kind (``llvmpipe`` = Mesa's rasteriser threads,
  ``archive-gl`` = the GL thread: uploads, interleaving, read-back; ``python`` = the others: task
  threads, Dask's event loop); ``all_threads_in_gl_tasks_s``: seconds of the graph during which every
  worker thread held a lookup or render task (waiting for the one GL thread: no writer could run);
- ``tasks``: per key prefix (lookup, render, write, blank, overview, saturated, gate, ...) count and
  summed task seconds from the task stream;
- ``stages``: CPU-seconds (thread CPU time; for GL calls plus the llvmpipe threads' CPU while the
  call ran: one GL call at a time per process) and calls of the wrapped functions (a wrapped call
  made inside another counts in the outer one's stage only, e.g. the COG layout's ``os.pwrite``): GL lookup, GL
  band passes, GL compute gather, CPU band gather, DN reads, mosaic, NaN checks, compression, overview downsampling,
  writes (``os.pwrite``, Zarr chunk files, COG spool files).

``--stream FILE`` also writes the task stream itself, one line per task run: key prefix, worker
thread id, start and stop (seconds from the first start), tab-separated.

The wrappers are installed only in this benchmark's workers (``Client.run``), never in the package.
"""

from __future__ import annotations

import json
import os
import resource
import sys
import time


def _gl_thread_id() -> int | None:
    """Native id of this process's GL thread, as the GL stage timers recorded it (asking the GL
    thread from the worker's event loop hung the worker)."""
    return getattr(sys, "_archive_gl_tid", None)


def _thread_cpu_by_kind() -> dict:
    """CPU-seconds of this process's threads by kind, from /proc/self/task: llvmpipe (Mesa's
    rasteriser threads, named by Mesa), archive-gl (the GL thread), python (the others: Dask's task
    threads, its event loop)."""
    gl = _gl_thread_id()
    tick = os.sysconf("SC_CLK_TCK")
    out: dict[str, float] = {}
    for tid in os.listdir("/proc/self/task"):
        try:
            with open(f"/proc/self/task/{tid}/stat") as fh:
                stat = fh.read()
        except OSError:
            continue
        name = stat[stat.index("(") + 1:stat.rindex(")")]
        fields = stat[stat.rindex(")") + 2:].split()
        cpu = (int(fields[11]) + int(fields[12])) / tick
        kind = ("llvmpipe" if name.startswith("llvmpipe") else "archive-gl" if int(tid) == gl else "python")
        out[kind] = out.get(kind, 0.0) + cpu
    return out


def _llvmpipe_cpu() -> float:
    return _thread_cpu_by_kind().get("llvmpipe", 0.0)


def install_stage_timers() -> list:
    """Wrap the functions each stage runs in, in this (worker) process; returns what was wrapped."""
    import functools
    import importlib
    import threading

    # kept on the sys module: these functions are pickled by value, each call is a new function
    if getattr(sys, "_archive_stage_stats", None) is not None:
        return ["already"]
    stats: dict[str, list] = {}
    lock = threading.Lock()
    sys._archive_stage_stats = stats

    inside = threading.local()   # a timed call in progress in this thread: nested ones count in it

    def wrap(owner, attr: str, stage: str, gl: bool = False) -> bool:
        fn = getattr(owner, attr, None)
        if fn is None:
            return False

        @functools.wraps(fn)
        def timed(*args, **kwargs):
            if getattr(inside, "stage", None) is not None:   # e.g. os.pwrite inside the COG layout
                return fn(*args, **kwargs)
            inside.stage = stage
            try:
                return timed_call(*args, **kwargs)
            finally:
                inside.stage = None

        def timed_call(*args, **kwargs):
            if gl:
                sys._archive_gl_tid = threading.get_native_id()
            lp = _llvmpipe_cpu() if gl else 0.0
            t = time.thread_time()
            try:
                return fn(*args, **kwargs)
            finally:
                spent = time.thread_time() - t + ((_llvmpipe_cpu() - lp) if gl else 0.0)
                with lock:
                    entry = stats.setdefault(stage, [0.0, 0])
                    entry[0] += spent
                    entry[1] += 1

        setattr(owner, attr, timed)
        return True

    done = []
    targets = [
        ("archive.render.renderer", None, "rasterize_lookup", "GL lookup", True),
        ("archive.render.renderer", None, "render_lookup", "GL band passes", True),
        ("archive.render.gather", None, "gather_lookup", "CPU band gather", False),
        ("archive.render.compute", None, "compute_lookup", "GL compute gather", True),
        ("archive.sources.raw", "RawFlightSource", "read_bands", "read DN", False),
        ("archive.sources.collection", "CollectionSource", "read_bands", "read DN", False),
        ("archive.sources.raw", "RawFlightSource", "radiometry", "radiometry terms", False),
        ("archive.graph.tasks", "PackedLookup", "unpack", "lookup unpack", False),
        ("archive.graph.tasks", "PackedLookup", "gather_index", "lookup decode", False),
        ("archive.overlap", None, "last_values", "mosaic (last)", False),     # the rules' chunk writers
        ("archive.overlap", None, "nadir_values", "mosaic (nadir)", False),
        ("archive.graph.tasks", None, "last_values", "mosaic (last)", False),  # trees before archive.overlap
        ("archive.graph.tasks", None, "nadir_values", "mosaic (nadir)", False),
        ("archive.outputs.cog", None, "all_nan", "NaN checks", False),
        ("archive.outputs.tiff", None, "encode_tile", "compression (COG)", False),
        ("archive.outputs.tiff", None, "write_spool", "writes (COG spool)", False),
        ("archive.outputs.tiff", None, "write_level_part", "COG layout in the graph", False),
        ("archive.outputs.tiff", None, "downsample2", "overviews (2x2 mean)", False),
        ("archive.outputs.zarr", None, "write_atomic", "writes (Zarr chunk files)", False),
        ("os", None, "pwrite", "writes (pwrite)", False),
    ]
    for module, cls, attr, stage, gl in targets:
        try:
            owner = importlib.import_module(module)
        except ImportError:
            continue
        if cls is not None:
            owner = getattr(owner, cls, None)
            if owner is None:   # an older tree (compare with a baseline)
                continue
        if wrap(owner, attr, stage, gl):
            done.append(f"{module}.{attr}")
    # Zarr compression: the codec's encode inside ChunkWriter.write (the chunk's NaN check and the
    # file write are timed apart: 'writes (Zarr chunk files)').
    try:
        zarr_out = importlib.import_module("archive.outputs.zarr")
        original = zarr_out._direct_codec

        def direct_codec(*args, **kwargs):
            codec = original(*args, **kwargs)
            if codec is not None and not getattr(codec, "_stage_timed", False):
                class Timed:
                    _stage_timed = True

                    def __init__(self, inner):
                        self.inner = inner

                    def encode(self, buf):
                        t = time.thread_time()
                        try:
                            return self.inner.encode(buf)
                        finally:
                            with lock:
                                entry = stats.setdefault("compression (Zarr Blosc)", [0.0, 0])
                                entry[0] += time.thread_time() - t
                                entry[1] += 1

                    def __getattr__(self, name):
                        return getattr(self.inner, name)
                return Timed(codec)
            return codec

        zarr_out._direct_codec = direct_codec
        done.append("archive.outputs.zarr._direct_codec")
    except (ImportError, AttributeError):
        pass
    return done


def collect_stage_timers() -> dict:
    import psutil

    cpu = psutil.Process().cpu_times()
    return {"stages": {k: {"cpu_s": v[0], "calls": v[1]} for k, v in (getattr(sys, "_archive_stage_stats", None) or {}).items()},
            "threads": _thread_cpu_by_kind(), "cpu_s": cpu.user + cpu.system,
            "rss": psutil.Process().memory_info().rss}


def main(argv=None) -> int:
    import argparse

    argv = list(sys.argv[1:] if argv is None else argv)
    split = argv.index("--")
    ap = argparse.ArgumentParser()
    ap.add_argument("json")
    ap.add_argument("--workers", type=int)
    ap.add_argument("--threads", type=int)
    ap.add_argument("--stream", help="also write each task's prefix, thread, start and stop (s) here")
    args = ap.parse_args(argv[:split])
    render = argv[split + 1:]

    from distributed import get_task_stream

    from archive.cli import main as cli_main
    from archive.run.cluster import start_cluster

    t0 = time.perf_counter()
    client, cluster = start_cluster(None, args.workers, lambda *a, **k: None, args.threads)
    try:
        client.run(install_stage_timers)
        before = client.run(collect_stage_timers)   # start-up and imports: not the render's
        start_s = time.perf_counter() - t0
        own0 = resource.getrusage(resource.RUSAGE_SELF)
        t = time.perf_counter()
        with get_task_stream(client) as ts:
            code = cli_main(["render", *render, "--scheduler", cluster.scheduler_address, "--quiet"])
        wall = time.perf_counter() - t
        own1 = resource.getrusage(resource.RUSAGE_SELF)
        workers = client.run(collect_stage_timers)
        nthreads = sum(client.nthreads().values())
    finally:
        client.close()
        cluster.close()
    tasks: dict[str, dict] = {}
    starts, stops = [], []
    for task in ts.data:
        prefix = str(task["key"]).split("-")[0] if isinstance(task["key"], str) else str(task["key"][0]).split("-")[0]
        for ss in task["startstops"]:
            if ss["action"] != "compute":
                continue
            entry = tasks.setdefault(prefix, {"count": 0, "task_s": 0.0})
            entry["count"] += 1
            entry["task_s"] += ss["stop"] - ss["start"]
            starts.append(ss["start"])
            stops.append(ss["stop"])
    graph_s = (max(stops) - min(starts)) if starts else 0.0
    # Seconds during which every worker thread held a GL task (lookup or render): no writer could
    # run then, whatever the GL thread was doing (one GL thread per process, llvmpipe's threads).
    events = []
    for task in ts.data:
        key = task["key"] if isinstance(task["key"], str) else str(task["key"][0])
        if key.startswith(("lookup-", "render-")):
            for ss in task["startstops"]:
                if ss["action"] == "compute":
                    events += [(ss["start"], 1), (ss["stop"], -1)]
    events.sort()
    gl_bound = 0.0
    level, since = 0, None
    for t, d in events:
        if level >= nthreads and since is not None:
            gl_bound += t - since
        level += d
        since = t
    stages: dict[str, dict] = {}
    threads: dict[str, float] = {}
    for addr, w in workers.items():
        w["cpu_s"] -= before[addr]["cpu_s"]
        for k, v in before[addr]["threads"].items():
            w["threads"][k] -= v
    for w in workers.values():
        for k, v in w["stages"].items():
            s = stages.setdefault(k, {"cpu_s": 0.0, "calls": 0})
            s["cpu_s"] += v["cpu_s"]
            s["calls"] += v["calls"]
        for k, v in w["threads"].items():
            threads[k] = threads.get(k, 0.0) + v
    own = (own1.ru_utime - own0.ru_utime) + (own1.ru_stime - own0.ru_stime)
    out = {"code": code, "render": render, "start_s": start_s, "wall_s": wall, "graph_s": graph_s,
           "all_threads_in_gl_tasks_s": gl_bound,
           "nthreads": nthreads, "cores": os.cpu_count(),
           "cpu": {"client": own, "workers": {k: w["cpu_s"] for k, w in workers.items()}},
           "threads": threads, "tasks": tasks, "stages": stages, "load": os.getloadavg()}
    with open(args.json, "w") as fh:
        json.dump(out, fh, indent=1)
    if args.stream:
        t0 = min(starts, default=0.0)
        with open(args.stream, "w") as fh:
            for task in ts.data:
                key = task["key"] if isinstance(task["key"], str) else str(task["key"][0])
                for ss in task["startstops"]:
                    if ss["action"] == "compute":
                        fh.write(f"{key.split('-')[0]}\t{task.get('thread')}\t{ss['start'] - t0:.4f}\t"
                                 f"{ss['stop'] - t0:.4f}\n")
    return code


if __name__ == "__main__":
    raise SystemExit(main())
