"""Benchmark of the render graph on Dask (issue 5): worker scaling and graph overhead.

    python bench/bench_cluster.py scaling  [--cubes 4] [--bands 32] [--samples 256] [--lines 500]
                                           [--gsd 0.04] [--workers 1,2] [--workdir DIR] [--json FILE]
    python bench/bench_cluster.py overhead [--cubes 40] [--bands 300] [--lines 1000] [--gsd 0.04]
                                           [--workers 2] [--workdir DIR] [--json FILE]

scaling: one simulated flight rendered (all bands, radiance) by ``archive.georectify`` (the library call
under ``archive render``) on a LocalCluster of 1, then 2, ... spawned worker processes (1 thread,
``resources={"GPU": 1}``, ``LP_NUM_THREADS`` = cores / workers). Each cluster first renders the
flight once (warm-up: imports, GL context, page cache), then the timed run renders it again into a fresh store; the seconds are the summary's
``graph_seconds`` (the graph's run, without planning and store conversion). Reports seconds, output
band-pixels/s and the ratio to one worker. The GL renderer is whatever EGL gives the workers
(Mesa llvmpipe on a CPU machine, the NVIDIA driver on a GPU machine: printed).

overhead: the graph ``archive.georectify`` builds (:func:`archive.run.pipeline.build_output` on the plan of
:func:`archive.api.plan`) for a paper-size flight description (default 40 cubes x 1000 lines, 300
bands, 4 cm): the flight's geometry is simulated with few samples and one band (the graph depends on
the footprints, the grid and the number of band groups, not on the pixels); the plan asks for 300
bands. Measures the time to build the graph, its task count, then runs a graph of exactly the same
shape (same keys, same dependencies, render tasks still annotated GPU=1) whose task bodies do
nothing, on a LocalCluster of ``--workers`` workers: tasks/s and scheduler time per task.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import shutil
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_render as br  # noqa: E402  (machine, the flight options)

FOV = 47.5


def machine() -> dict:
    import dask
    import distributed

    return {**br.machine(), "dask": dask.__version__, "distributed": distributed.__version__,
            "load_avg_1min": round(os.getloadavg()[0], 2)}


def _simulate(workdir: Path, name: str, **kw) -> tuple[Path, object]:
    from archive.simulator.command import simulate_flight
    from archive.simulator.truth import load_truth

    directory = workdir / name
    marker = workdir / f"{name}.done"
    if marker.exists():
        return directory, load_truth(directory)
    if directory.exists():
        shutil.rmtree(directory)
    truth = simulate_flight(directory, **kw)
    marker.write_text("ok")
    return directory, truth


def _plan(directory: Path, ground: float, gsd: float, nbands: int | None = None, mode: str = "radiance"):
    """The library's plan of a raw flight (:func:`archive.api.plan`: metadata and geometry only).

    nbands: plan that many output bands whatever the flight holds (the overhead bench's hollow
    graph never reads them), in band groups sized as ``archive.georectify`` sizes them.
    """
    import dataclasses

    from archive.api import plan
    from archive.graph.build import with_task_groups

    planned = plan([directory], gsd=gsd, fov=FOV, ground_height=ground, mode=mode,
                   bands=None if nbands is None else "0")
    if nbands is None:
        return planned
    wide = with_task_groups(dataclasses.replace(planned.plan, bands=(tuple(range(nbands)),)))
    return dataclasses.replace(planned, plan=wide, wavelengths=None)


def _graph(planned, store_path: Path):
    """The render graph ``archive.georectify`` builds for ``planned``, into a new store at ``store_path``
    (created under its temporary name and removed again: the overhead bench never writes it)."""
    from archive.outputs.publish import Output
    from archive.run.pipeline import build_output

    output = Output(store_path, overwrite=True)
    try:
        return build_output(planned, output)[1]
    finally:
        output.cleanup()


def _cluster(workers: int):
    from distributed import Client, LocalCluster

    cores = max(1, (os.cpu_count() or 1) // workers)
    cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, resources={"GPU": 1},
                           env={"LP_NUM_THREADS": str(cores)}, dashboard_address=":0",
                           silence_logs=logging.ERROR)
    return cluster, Client(cluster)


def _gl_renderer(client) -> str:
    def info():
        from archive.render.context import gl_info

        i = gl_info()
        return f"{i['renderer']} ({i['vendor']}, {i['version']})"

    return str(next(iter(client.run(info).values())))


def scaling(args) -> dict:
    workdir = Path(args.workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    directory, truth = _simulate(workdir, f"scaling_{args.cubes}x{args.lines}x{args.samples}x{args.bands}",
                                 cubes=args.cubes, bands=args.bands, samples=args.samples, lines=args.lines,
                                 cubes_per_pass=2, seed=1)
    import archive

    plan = _plan(directory, truth.ground_height, args.gsd).plan
    band_pixels = plan.grid.width * plan.grid.height * plan.nbands
    rows = []
    for n in [int(w) for w in args.workers.split(",")]:
        cluster, client = _cluster(n)
        try:
            for attempt in ("warm-up", "timed"):
                store = workdir / f"out-{n}-{attempt}.zarr"
                shutil.rmtree(store, ignore_errors=True)
                # what `archive render` runs; its graph_seconds time the graph alone, as before
                summary = archive.georectify([directory], store, gsd=args.gsd, fov=FOV, ground_height=truth.ground_height,
                                         scheduler=cluster.scheduler_address, overwrite=True)
                seconds = summary["graph_seconds"]
                shutil.rmtree(store, ignore_errors=True)
            renderer = _gl_renderer(client)
        finally:
            client.close()
            cluster.close()
        rows.append({"workers": n, "seconds": round(seconds, 3),
                     "tasks": summary["renders"] + 2 * summary["assemblies"],
                     "mega_band_pixels_per_s": round(band_pixels / seconds / 1e6, 2), "renderer": renderer})
        print(f"{n} worker(s): {seconds:.2f} s, {band_pixels / seconds / 1e6:.1f} M band-px/s ({renderer})",
              file=sys.stderr)
    base = rows[0]["seconds"]
    for r in rows:
        r["speedup_vs_first"] = round(base / r["seconds"], 2)
    return {"bench": "scaling", "flight": {"cubes": args.cubes, "lines": args.lines, "samples": args.samples,
                                           "bands": args.bands},
            "gsd": args.gsd, "grid": [plan.grid.width, plan.grid.height], "band_pixels": band_pixels,
            "machine": machine(), "rows": rows}


# ---------------------------------------------------------------------------------------------
# Graph overhead with trivial task bodies
# ---------------------------------------------------------------------------------------------
def _nothing(*args) -> int:
    return 0


def _hollow(graph) -> list:
    """Delayed outputs of a graph of the same shape (keys, dependencies, layer annotations such as
    ``resources={"GPU": 1}``) whose every task body is :func:`_nothing`."""
    from dask._task_spec import Task, TaskRef
    from dask.core import get_dependencies
    from dask.delayed import Delayed
    from dask.highlevelgraph import HighLevelGraph, MaterializedLayer

    merged = HighLevelGraph.merge(*[w.__dask_graph__() for w in graph.writes])
    dsk = dict(merged)
    layers = {}
    for name, layer in merged.layers.items():
        tasks = {}
        for key in layer:
            deps = sorted(get_dependencies(dsk, key), key=str)
            tasks[key] = Task(key, _nothing, *[TaskRef(d) for d in deps])
        layers[name] = MaterializedLayer(tasks, annotations=layer.annotations)
    hollow = HighLevelGraph(layers, merged.dependencies)
    return [Delayed(w.key, hollow) for w in graph.writes]


def _materialize(graph) -> dict:
    """The graph of all the writer tasks as one plain dict (key -> task)."""
    from dask.highlevelgraph import HighLevelGraph

    return dict(HighLevelGraph.merge(*[w.__dask_graph__() for w in graph.writes]))


def overhead(args) -> dict:
    workdir = Path(args.workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    directory, truth = _simulate(workdir, f"geometry_{args.cubes}x{args.lines}", cubes=args.cubes, bands=1,
                                 samples=32, lines=args.lines, cubes_per_pass=2, seed=2)
    t0 = time.perf_counter()
    planned = _plan(directory, truth.ground_height, args.gsd, nbands=args.bands, mode="raw")
    plan = planned.plan
    t_plan = time.perf_counter() - t0
    store = workdir / "overhead.zarr"
    shutil.rmtree(store, ignore_errors=True)
    t0 = time.perf_counter()
    graph = _graph(planned, store)
    t_build = time.perf_counter() - t0
    t0 = time.perf_counter()
    dsk = _materialize(graph)
    t_materialize = time.perf_counter() - t0
    shutil.rmtree(store, ignore_errors=True)
    hollow = _hollow(graph)
    cluster, client = _cluster(args.workers)
    try:
        # warm-up: a small graph, so that the timed run does not pay for connections
        client.gather(client.get({"w": (_nothing,)}, "w", sync=False))
        t0 = time.perf_counter()
        futures = client.compute(hollow, optimize_graph=False)
        client.gather(futures)
        t_run = time.perf_counter() - t0
        del futures
    finally:
        client.close()
        cluster.close()
    n = len(dsk)
    result = {
        "bench": "overhead", "flight": {"cubes": args.cubes, "lines": args.lines, "bands": args.bands},
        "gsd": args.gsd, "grid": [plan.grid.width, plan.grid.height], "tiles": len(plan.grid.tiles(1024)),
        "band_groups": len(plan.groups), "render_tasks": graph.renders, "assemble_tasks": graph.assemblies,
        "tasks": n, "plan_s": round(t_plan, 3), "build_s": round(t_build, 3),
        "materialize_s": round(t_materialize, 3), "graph_tasks_check": len(dsk),
        "hollow_run_s": round(t_run, 3), "tasks_per_s": round(n / t_run, 1),
        "ms_per_task": round(1000 * t_run / n, 3), "workers": args.workers, "machine": machine(),
    }
    print(json.dumps(result, indent=1), file=sys.stderr)
    return result


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="what", required=True)
    s = sub.add_parser("scaling")
    br.add_flight_arguments(s, bands=32, workdir="/tmp/archive-bench-cluster", cubes=4, samples=256, lines=500)
    s.add_argument("--workers", default="1,2")
    o = sub.add_parser("overhead")   # its flight has 32 samples per line
    br.add_flight_arguments(o, bands=300, workdir="/tmp/archive-bench-cluster", cubes=40, samples=None)
    o.add_argument("--workers", type=int, default=2)
    for p in (s, o):
        p.add_argument("--json", help="also write the result here")
    args = parser.parse_args(argv)
    result = scaling(args) if args.what == "scaling" else overhead(args)
    text = json.dumps(result, indent=1)
    print(text)
    if args.json:
        Path(args.json).write_text(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
