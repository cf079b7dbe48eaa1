"""Zonal statistics (issue 48): ``archive stats`` against rendering a stack and computing the same
table by hand with xarray. Zones x flights; wall, peak RSS (the command's process tree: the command
and its local cluster's worker, summed, sampled every 50 ms), CPU-s per flight (the children's
user + system time), and the ratio by hand / stats, from one run.

Builds (once, kept in --work) an archive of N flights of one field (``simulate_flight(seed=k,
scene_seed=0, clouds=True)``, 2 cubes x 150 lines x 96 samples x 8 bands, one hour apart) and Z
non-overlapping square zones on a lattice over the first flight's footprint (GeoJSON, lon/lat), then:

- **stats**: ``archive stats --archive A --query-datetime ... --zones Z --index NDVI --gsd G --out T.csv``;
- **by hand**: ``archive render ... --stack --wavelengths 657.143,828.571 --mode reflectance --gsd G``
  (the same two bands), then a child process opens the Zarr with xarray, computes NDVI per flight,
  rasterises the zones (``rasterio.features.rasterize``, pixel centres: no fractions) and loops zones x
  flights with numpy (count, mean, std, min, p10, median, p90, max).

The two tables' means are compared (median |difference|: fractions vs pixel centres).

    .venv/bin/python bench/bench_stats.py --flights 20 --zones 1000
"""

from __future__ import annotations

import argparse
import json
import resource
import shutil
import subprocess
import sys
import threading
import time
from datetime import UTC, datetime, timedelta
from pathlib import Path

SHAPE = dict(cubes=2, bands=8, samples=96, lines=150, cubes_per_pass=2)
START = datetime(2024, 6, 12, 16, tzinfo=UTC)
BANDS = "657.143,828.571"   # the camera bands NDVI takes (R: 620-690 nm, N: 760-900 nm)


def build(work: Path, n: int, zones: int, side: float) -> None:
    """The archive of ``n`` flights and the zones file (a lattice of ``side`` m squares, 0.25 m apart)."""
    import numpy as np
    from shapely.geometry import Polygon, box

    from archive.ingest.command import ingest
    from archive.simulator.command import simulate_flight
    from archive.simulator.truth import load_truth

    archive = work / "archive"
    have = len(list((archive / "collections").glob("*.zarr"))) if archive.is_dir() else 0
    for k in range(have, n):
        d = work / "raw" / f"flight{k:03d}"
        simulate_flight(d, seed=k, scene_seed=0, clouds=True, start=START + timedelta(hours=k), overwrite=True, **SHAPE)
        if k == 0:
            shutil.copytree(d / "truth", work / "truth0", dirs_exist_ok=True)
        ingest([str(d)], archive, 47.5, progress=False)
        shutil.rmtree(d)
    truth = load_truth(work / "truth0")
    w, s, e, n_ = Polygon(truth.footprint()[0]).bounds
    step = side + 0.25
    features = []
    for y in np.arange(s, n_ - side, step):
        for x in np.arange(w, e - side, step):
            if len(features) == zones:
                break
            ring = np.array(box(x, y, x + side, y + side).exterior.coords)
            lon, lat = truth.from_utm(ring[:, 0], ring[:, 1], crs=4326)
            features.append({"type": "Feature", "id": f"z{len(features):04d}", "properties": {},
                             "geometry": {"type": "Polygon", "coordinates": [[[float(a), float(b)]
                                                                              for a, b in zip(lon, lat)]]}})
    if len(features) < zones:
        raise SystemExit(f"only {len(features)} zones of {side} m fit on the field: pass a smaller --side")
    (work / "zones.geojson").write_text(json.dumps({"type": "FeatureCollection", "features": features}))


def tree_rss(pid: int) -> int:
    """Resident bytes of process ``pid`` and all its descendants."""
    import psutil

    try:
        root = psutil.Process(pid)
        procs = [root, *root.children(recursive=True)]
    except psutil.Error:
        return 0
    total = 0
    for p in procs:
        try:
            total += p.memory_info().rss
        except psutil.Error:
            pass
    return total


def measured(cmd: list[str]) -> dict:
    """Run ``cmd``; its wall, peak tree RSS and CPU seconds (its process tree, waited for)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    peak = {"rss": 0}
    stop = threading.Event()

    def sample() -> None:
        while not stop.is_set():
            peak["rss"] = max(peak["rss"], tree_rss(proc.pid))
            time.sleep(0.05)

    thread = threading.Thread(target=sample, daemon=True)
    thread.start()
    stdout, stderr = proc.communicate()
    stop.set()
    thread.join()
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode:
        raise SystemExit(f"{' '.join(cmd[:4])} failed: {stderr.strip()}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return {"wall_s": wall, "peak_rss": peak["rss"], "cpu_s": cpu, "stdout": stdout.strip()}


def by_hand(stack: Path, zones: Path, out: Path) -> None:
    """The table by hand from a rendered stack (run in a child process)."""
    import geopandas as gpd
    import numpy as np
    import pandas as pd
    import rasterio.features
    import rioxarray  # noqa: F401  (.rio)
    import xarray as xr
    from affine import Affine

    ds = xr.open_zarr(stack, decode_coords="all")
    values = ds["reflectance"]
    x, y = ds["x"].values, ds["y"].values
    gsd = float(x[1] - x[0])
    transform = Affine(gsd, 0, x[0] - gsd / 2, 0, -gsd, y[0] + gsd / 2)
    frame = gpd.read_file(zones).to_crs(ds.rio.crs)
    labels = rasterio.features.rasterize(((g, k + 1) for k, g in enumerate(frame.geometry)),
                                         out_shape=(ds.sizes["y"], ds.sizes["x"]), transform=transform, fill=0,
                                         dtype="int32")
    order = np.argsort(labels, axis=None, kind="stable")
    bounds = np.searchsorted(labels.ravel()[order], np.arange(len(frame) + 2))
    rows = []
    ids, flights = list(frame["id"]), [str(f) for f in ds["flight"].values]
    for t, flight in enumerate(flights):
        red, nir = values.isel(time=t).sel(wavelength=[657.143, 828.571], method="nearest").values
        ndvi = ((nir - red) / (nir + red)).ravel()[order]
        for k, zid in enumerate(ids):
            v = ndvi[bounds[k + 1]:bounds[k + 2]]
            v = v[np.isfinite(v)]
            stats = ([len(v), v.mean(), v.std(), v.min(), *np.quantile(v, [0.1, 0.5, 0.9]), v.max()] if len(v)
                     else [0, *([np.nan] * 7)])
            rows.append([zid, flight, "NDVI", *stats])
    pd.DataFrame(rows, columns=["zone", "flight", "index", "count", "mean", "std", "min", "p10", "median", "p90",
                                "max"]).to_csv(out, index=False)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--flights", type=int, default=20, help="flights (default 20)")
    parser.add_argument("--zones", type=int, default=1000, help="zones (default 1000)")
    parser.add_argument("--side", type=float, default=0.6, help="zone side, m (default 0.6)")
    parser.add_argument("--gsd", default="0.1", help="the stack's GSD, m (default 0.1)")
    parser.add_argument("--work", default="/tmp/bench_stats", help="work folder (archive and zones kept there)")
    parser.add_argument("--build-only", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--by-hand", nargs=3, metavar=("STACK", "ZONES", "OUT"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    work = Path(args.work)
    if args.by_hand:
        by_hand(*map(Path, args.by_hand))
        return
    if args.build_only:   # in a child process: the bench's own process holds no catalog handle
        build(work, args.flights, args.zones, args.side)
        return
    work.mkdir(parents=True, exist_ok=True)
    t = time.perf_counter()
    subprocess.run([sys.executable, __file__, "--work", str(work), "--flights", str(args.flights), "--zones",
                    str(args.zones), "--side", str(args.side), "--build-only"], check=True)
    print(f"archive of {args.flights} flights and {args.zones} zones ready in {time.perf_counter() - t:.0f} s",
          file=sys.stderr)
    end = START + timedelta(hours=args.flights - 1, minutes=30)
    query = ["--archive", str(work / "archive"), "--query-datetime",
             f"{START.isoformat().replace('+00:00', 'Z')}/{end.isoformat().replace('+00:00', 'Z')}"]
    zones = work / "zones.geojson"
    table, stack, hand = work / "stats.csv", work / "stack.zarr", work / "by_hand.csv"
    for p in (table, hand):
        p.unlink(missing_ok=True)
    shutil.rmtree(stack, ignore_errors=True)
    stack.with_name(stack.name + ".json").unlink(missing_ok=True)
    stats = measured([sys.executable, "-m", "archive", "stats", *query, "--zones", str(zones), "--index", "NDVI",
                      "--gsd", args.gsd, "--out", str(table), "--quiet"])
    render = measured([sys.executable, "-m", "archive", "render", *query, "--stack", "--wavelengths", BANDS,
                       "--mode", "reflectance", "--gsd", args.gsd, "--out", str(stack), "--quiet"])
    loop = measured([sys.executable, __file__, "--by-hand", str(stack), str(zones), str(hand)])
    import pandas as pd

    a = pd.read_csv(table)
    b = pd.read_csv(hand)
    both = a.merge(b, on=["zone", "flight", "index"], suffixes=("", "_hand"))
    diff = (both["mean"] - both["mean_hand"]).abs().median()
    hand_wall = render["wall_s"] + loop["wall_s"]
    result = {"zones": args.zones, "flights": args.flights, "gsd": float(args.gsd), "rows": len(a),
              "stats": {k: v for k, v in stats.items() if k != "stdout"}, "render_stack": render | {"stdout": None},
              "by_hand_loop": loop | {"stdout": None}, "median_abs_mean_difference": float(diff),
              "ratio_by_hand_over_stats": hand_wall / stats["wall_s"], "summary": stats["stdout"]}
    print(json.dumps(result, indent=1))
    n = args.flights
    print(f"\n| {args.zones} zones x {n} flights, GSD {args.gsd} m | wall | CPU-s per flight | peak RSS (tree) |")
    print("|---|---|---|---|")
    print(f"| archive stats | {stats['wall_s']:.1f} s | {stats['cpu_s'] / n:.2f} | {stats['peak_rss'] / 1e6:.0f} MB |")
    print(f"| render --stack + xarray by hand | {hand_wall:.1f} s ({render['wall_s']:.1f} + {loop['wall_s']:.1f}) "
          f"| {(render['cpu_s'] + loop['cpu_s']) / n:.2f} | {max(render['peak_rss'], loop['peak_rss']) / 1e6:.0f} MB |")
    print(f"\nratio (by hand / stats): {hand_wall / stats['wall_s']:.2f}; median |mean difference| {diff:.2g}")


if __name__ == "__main__":
    main()
