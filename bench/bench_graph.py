"""What building a render's Dask graph costs the command process (issue 20): time and memory.

    python bench/bench_graph.py FLIGHT [FLIGHT ...] [--band-group N ...] [--format tif] [--gsd 0.04]

Per flight and band-group size: plans the render (``archive.api.plan``, as ``archive render``
does), builds its graph (``archive.run.pipeline.build_output``: the output's sink, made under its
temporary name and removed after) and materialises it as ``client.compute`` would
(``dask.base.collections_to_expr(writes).optimize()``: the task dict and the per-key
annotations sent to the scheduler). Prints the tasks, the writes, the seconds and the process's RSS
growth of each step (after ``gc.collect``) and the process's peak RSS. Nothing is rendered and no
cluster is started. Smaller ``--band-group`` sizes give the task counts of more bands (300 bands
of a 40-cube flight: ~50 groups). ``PYTHONPATH=<another checkout>`` measures that checkout's code.
"""

from __future__ import annotations

import argparse
import gc
import resource
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_render as br  # noqa: E402


def measure(flight: Path, group: int | None, suffix: str, gsd: float, work: Path) -> str:
    import psutil
    from dask.base import collections_to_expr

    from archive.api import plan
    from archive.outputs.publish import Output
    from archive.run.pipeline import build_output
    from archive.simulator.command import GROUND_HEIGHT

    proc = psutil.Process()
    request = plan([flight], gsd=gsd, fov=br.FOV, ground_height=GROUND_HEIGHT, band_group=group)
    gc.collect()
    rss0 = proc.memory_info().rss
    target = Output(work / f"bench-graph.{suffix}", overwrite=True)
    t0 = time.perf_counter()
    try:
        _, graph = build_output(request, target)
        t1 = time.perf_counter()
        gc.collect()
        rss1 = proc.memory_info().rss
        expr = collections_to_expr(list(graph.writes)).optimize()
        tasks = dict(expr.__dask_graph__())
        expr.__dask_annotations__()
        t2 = time.perf_counter()
        gc.collect()
        rss2 = proc.memory_info().rss
    finally:
        target.cleanup()
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3
    return (f"{flight.name} band group {group or 'auto'} .{suffix}: {len(tasks)} tasks, {len(graph.writes)} writes; "
            f"build {t1 - t0:.2f} s +{(rss1 - rss0) / 1e6:.0f} MB; materialise {t2 - t1:.2f} s "
            f"+{(rss2 - rss1) / 1e6:.0f} MB; peak RSS {peak:.0f} MB")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("flights", nargs="+", type=Path, help="simulated flight directories (archive simulate)")
    ap.add_argument("--band-group", type=int, nargs="*", default=[0], help="bands per group (0: the planner's)")
    ap.add_argument("--format", default="tif", choices=["tif", "zarr", "hdr"])
    ap.add_argument("--gsd", type=float, default=0.04)
    ap.add_argument("--workdir", type=Path, default=Path("/tmp"))
    args = ap.parse_args(argv)
    for flight in args.flights:
        for group in args.band_group:
            print(measure(flight, group or None, args.format, args.gsd, args.workdir), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
