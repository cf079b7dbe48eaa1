"""Peak memory of `archive render` against flight length (issue 20 item 4), several runs per row.

    python bench/bench_memory.py [--flights 8x4,40x5] [--bands 32] [--formats hdr,zarr,tif] [--runs 2]
                                 [--shape heldout|sidelap|tilted] [--workdir DIR] [--worker-env KEY=VALUE,...] [--render-args ARGS] [--json FILE]

The flights of ``bench_outputs.py --scaling`` (``N``x``P``: N paper-size cubes, 900 samples x 1000
lines, over P lawn-mower passes of ``bench_outputs.py``'s ``--shape``, ``--bands`` bands; simulated
once into --workdir and reused), each
rendered to every format ``--runs`` times through ``bench_outputs.render_cli`` (``archive render``
via ``bench/stage_profile.py``: the command's own code on a local cluster started as the command
starts it), rounds interleaved (every flight and format once, then again) so the machine's load
falls on all rows alike. Per run: peak RSS of the process tree and its anonymous part (RSS minus
file-backed pages, polled every 0.1 s), CPU-seconds per cube (the command's process and the
workers), wall, load average before and after. Only this part of ``bench_outputs.py`` is run: no
300-band flight, no I/O floor, no GDAL.

``--worker-env`` adds variables to the workers' pre-spawn environment (Dask's
``distributed.nanny.pre-spawn-environ``, where :func:`archive.run.cluster.start_cluster` puts
``MALLOC_MMAP_THRESHOLD_``), e.g. ``--worker-env MALLOC_ARENA_MAX=2`` to try glibc settings without
changing the package. ``PYTHONPATH=<another checkout>`` runs that checkout's code (its own
``bench/`` is not needed: the flights and this driver are the same).
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_outputs as bo  # noqa: E402
import bench_render as br  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--flights", default="8x4,40x5")
    ap.add_argument("--bands", type=int, default=32)
    ap.add_argument("--formats", default="hdr,zarr,tif")
    ap.add_argument("--runs", type=int, default=2)
    ap.add_argument("--gsd", type=float, default=0.04)
    ap.add_argument("--shape", choices=sorted(bo.SHAPES), default="heldout",
                    help="the passes' heading and spacing (bench_outputs.py's shapes; tilted: issue 20's flights)")
    ap.add_argument("--workdir", default="/tmp/archive-bench-memory")
    ap.add_argument("--worker-env", default="", help="KEY=VALUE,... added to the workers' pre-spawn environment")
    ap.add_argument("--render-args", default="", help="more `archive render` arguments, e.g. '--bands 0,1,2' "
                    "(after the bench's '--bands all': the last one counts)")
    ap.add_argument("--json", metavar="FILE")
    args = ap.parse_args(argv)
    work = Path(args.workdir)
    work.mkdir(parents=True, exist_ok=True)
    extra = dict(kv.split("=", 1) for kv in args.worker_env.split(",") if kv)
    if extra:   # Dask merges this with its default pre-spawn variables (MALLOC_TRIM_THRESHOLD_, ...)
        os.environ["DASK_DISTRIBUTED__NANNY__PRE_SPAWN_ENVIRON"] = repr(extra)
    from archive.simulator.command import GROUND_HEIGHT

    import archive
    R: dict = {"machine": br.machine(), "args": vars(args), "code": str(Path(archive.__file__).parent),
               "worker_env": extra, "runs": []}
    flights = []
    for spec in [v for v in args.flights.split(",") if v]:
        n, p = (int(x) for x in spec.split("x"))
        d = bo.scaling_flight(work, n, p, args.bands, 900, 1000, *bo.SHAPES[args.shape])
        flights.append((spec, n, d))
    print(f"code {R['code']}, worker env {extra or '-'}   [load {br.load()}]", flush=True)
    for run in range(args.runs):
        for spec, n, d in flights:
            br.warm(d)
            for fmt in [f for f in args.formats.split(",") if f]:
                out = work / f"mem_{spec}.{fmt}"
                r = bo.render_cli(d, out, args.gsd, GROUND_HEIGHT, extra=shlex.split(args.render_args), work=work)
                bo._remove(out)
                row = {"run": run, "flight": spec, "format": fmt, "peak_rss_gb": r["peak_tree_rss"] / 1e9,
                       "peak_anon_gb": r["peak_tree_anon"] / 1e9, "cpu_s_per_cube": r["cpu_s"] / n,
                       "read_dn_s_per_cube": r["profile"]["stages"].get("read DN", {}).get("cpu_s", 0.0) / n,
                       "gather_s_per_cube": r["profile"]["stages"].get("CPU band gather", {}).get("cpu_s", 0.0) / n,
                       "wall_s": r["wall_s"], "out_mb": r["out_mb"], "load": r["load"], "cmd": r["cmd"]}
                R["runs"].append(row)
                print(f"run {run} {spec} .{fmt}: peak {row['peak_rss_gb']:.2f} GB (anon {row['peak_anon_gb']:.2f}), "
                      f"{row['cpu_s_per_cube']:.2f} CPU-s per cube (read DN {row['read_dn_s_per_cube']:.3f}, "
                      f"gather {row['gather_s_per_cube']:.2f}), {row['wall_s']:.1f} s, {row['out_mb']:.0f} MB out, "
                      f"load {r['load'][0]} -> {r['load'][1]}", flush=True)
    print("\n| flight | format | peak RSS GB (runs) | anon GB (runs) | CPU-s per cube (runs) | read DN CPU-s per cube "
          "| gather CPU-s per cube |")
    print("|---|---|---|---|---|---|---|")
    for spec, _, _ in flights:
        for fmt in [f for f in args.formats.split(",") if f]:
            rows = [x for x in R["runs"] if x["flight"] == spec and x["format"] == fmt]
            col = lambda k: ", ".join(f"{x[k]:.2f}" for x in rows)  # noqa: E731
            med = lambda k: statistics.median(x[k] for x in rows)  # noqa: E731
            print(f"| {spec} | .{fmt} | {col('peak_rss_gb')} (median {med('peak_rss_gb'):.2f}) | "
                  f"{col('peak_anon_gb')} | "
                  f"{col('cpu_s_per_cube')} | {col('read_dn_s_per_cube')} | {col('gather_s_per_cube')} |")
    if args.json:
        Path(args.json).write_text(json.dumps(R, indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
