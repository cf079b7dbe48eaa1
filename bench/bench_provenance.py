"""What ``--provenance`` adds to a render (issue 12: at most 15 % of the same job's render time).

    python bench/bench_provenance.py [--cubes 2] [--bands 300] [--samples 900] [--lines 1000]
                                     [--gsd 0.04] [--formats zarr,tif] [--repeats 2] [--workdir DIR]

On one simulated flight (bench_render's flights: simulated once into --workdir, reused), for each
format, ``python -m archive render`` (its own local cluster, as a user runs it) without and with
``--provenance``, alternating (without, with, with, without, ...) so that a drift of the shared
machine's load hits both alike. Reported per format: the command's own seconds (its summary line:
imports excluded, cluster start included) and wall + sync, medians, and their ratio with / without.
Also with ``--overlap nadir`` (the rule needs the view zenith layer) against 'last'.
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_outputs as bo  # noqa: E402  (render_cli: wall, sync, peak RSS of the process tree)
import bench_render as br  # noqa: E402  (flights, machine, load)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    br.add_flight_arguments(ap, bands=300, workdir="/tmp/archive-bench-outputs")
    ap.add_argument("--formats", default="zarr,tif")
    ap.add_argument("--repeats", type=int, default=2, help="pairs of runs per variant and format")
    args = ap.parse_args(argv)
    work = Path(args.workdir)
    work.mkdir(parents=True, exist_ok=True)
    from archive.simulator.command import GROUND_HEIGHT

    flight = br.flight_dir(args)
    br.warm(flight)
    print(f"machine {br.machine()}; flight {flight} ({args.cubes} cubes x {args.lines} lines x {args.samples} "
          f"samples x {args.bands} bands), --gsd {args.gsd}", flush=True)
    variants = {"plain": [], "provenance": ["--provenance"], "nadir": ["--overlap", "nadir"]}
    rows = []
    for fmt in [f for f in args.formats.split(",") if f]:
        times: dict[str, list[dict]] = {v: [] for v in variants}
        order = []
        for _ in range(args.repeats):
            order += ["plain", "provenance", "nadir", "nadir", "provenance", "plain"]
        for variant in order:
            out = work / f"prov-{variant}.{fmt}"
            r = bo.render_cli(flight, out, args.gsd, GROUND_HEIGHT, variants[variant])
            times[variant].append(r)
            print(f"  {fmt:4s} {variant:10s} command {r['command_s']:.1f} s, wall+sync {r['wall_sync_s']:.1f} s, "
                  f"peak tree RSS {r['peak_tree_rss'] / 1e9:.2f} GB   [load {br.load()}]", flush=True)
        med = {v: {k: statistics.median(x[k] for x in rs) for k in ("command_s", "wall_sync_s")}
               for v, rs in times.items()}
        for v in ("provenance", "nadir"):
            rows.append((fmt, v, med[v]["command_s"] / med["plain"]["command_s"],
                         med[v]["wall_sync_s"] / med["plain"]["wall_sync_s"], med[v], med["plain"]))
    print("\n| format | variant | command s (variant / plain) | ratio | wall+sync ratio |")
    print("|---|---|---|---|---|")
    for fmt, v, ratio, wall_ratio, m, plain in rows:
        print(f"| {fmt} | {v} | {m['command_s']:.1f} / {plain['command_s']:.1f} | {ratio:.3f} | {wall_ratio:.3f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
