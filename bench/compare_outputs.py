"""Outputs unchanged by a restructuring: render the same simulated flights with two source trees and
compare every output bit for bit.

    .venv/bin/python bench/compare_outputs.py --baseline /tmp/baseline [--current .] [--work DIR]

``--baseline`` is a checkout of the commit before the change (``git worktree add /tmp/baseline REV``);
``--current`` the tree under test (default: this checkout). Each tree renders, through its own
``archive render`` command (``archive.cli.main`` with ``PYTHONPATH`` set to the tree, on one local
Dask cluster per tree), the same requests:

- a flat flight: Zarr, COG and ENVI; the same with ``--overlap nadir --provenance`` and with
  ``--overlap mean``; COG and ENVI with ``--provenance`` alone;
- a terrain flight (``archive simulate --terrain hills``) with ``--dem``: Zarr, COG and ENVI, and
  Zarr with ``--provenance``.

Compared: every array of every Zarr store (values, dtype, shape, attributes), every ENVI data file
byte for byte and its header, every COG's tiles (each band and overview level, bit patterns, NaN
included) and its band descriptions and tags. The STAC Items are compared too, less the keys that
name the output's own path or time of writing. Exit code 0 when everything matches, 1 otherwise.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
FOV = 47.5
GSD = 0.03   # 2100 x 1250 px: several output tiles (1024 px), COG tiles (512 px) and overview levels

#: (name, flight, extra options, formats)
CASES = [
    ("flat", "flat", [], ["zarr", "tif", "hdr"]),
    ("flat-nadir-prov", "flat", ["--overlap", "nadir", "--provenance"], ["zarr", "tif", "hdr"]),
    ("flat-prov", "flat", ["--provenance"], ["tif", "hdr"]),
    ("flat-mean", "flat", ["--overlap", "mean"], ["zarr", "tif", "hdr"]),
    ("terrain", "terrain", ["--dem", "{dem}"], ["zarr", "tif", "hdr"]),
    ("terrain-prov", "terrain", ["--dem", "{dem}", "--provenance"], ["zarr"]),
]

RUNNER = r"""
import json, logging, sys
from distributed import LocalCluster
from archive.cli import main
jobs = json.loads(sys.argv[1])
with LocalCluster(n_workers=1, threads_per_worker=2, processes=True, resources={"GPU": 2},
                  dashboard_address=":0", silence_logs=logging.CRITICAL) as cluster:
    for argv in jobs:
        code = main(argv + ["--scheduler", cluster.scheduler_address, "--quiet"])
        if code:
            sys.exit(f"render failed ({code}): {argv}")
"""


def _run(tree: Path, argv: list[str]) -> None:
    env = dict(os.environ, PYTHONPATH=str(tree))
    subprocess.run([sys.executable, *argv], cwd=tree, env=env, check=True)


def simulate(work: Path) -> dict[str, Path]:
    """The two flights, simulated once with the current tree (inputs, not outputs)."""
    flights = {"flat": work / "flat", "terrain": work / "terrain"}
    if not (flights["flat"] / "truth").exists():
        _run(ROOT, ["-m", "archive.cli", "simulate", str(flights["flat"]), "--quiet", "--overwrite"])
    if not (flights["terrain"] / "dem.tif").exists():
        _run(ROOT, ["-m", "archive.cli", "simulate", str(flights["terrain"]), "--terrain", "hills", "--quiet",
                    "--overwrite"])
    return flights


def render_all(tree: Path, flights: dict[str, Path], out: Path) -> list[Path]:
    out.mkdir(parents=True, exist_ok=True)
    jobs, outputs = [], []
    for name, flight, extra, formats in CASES:
        options = [o.replace("{dem}", str(flights[flight] / "dem.tif")) for o in extra]
        for fmt in formats:
            path = out / f"{name}-{fmt}" / f"{name}.{fmt}"   # one folder per output: it and its siblings
            outputs.append(path)
            jobs.append(["render", str(flights[flight]), "--fov", str(FOV), "--gsd", str(GSD), "--out", str(path),
                         "--overwrite", *options])
    _run(tree, ["-c", RUNNER, json.dumps(jobs)])
    return outputs


def _bits(a: np.ndarray) -> np.ndarray:
    a = np.ascontiguousarray(a)
    return a.view(f"u{a.dtype.itemsize}") if a.dtype.kind == "f" else a


def _same_array(a: np.ndarray, b: np.ndarray) -> bool:
    return a.shape == b.shape and a.dtype == b.dtype and np.array_equal(_bits(a), _bits(b))


def compare_zarr(a: Path, b: Path) -> list[str]:
    import zarr

    ga, gb = zarr.open_group(str(a), mode="r"), zarr.open_group(str(b), mode="r")
    problems = []
    if dict(ga.attrs) != dict(gb.attrs):
        problems.append("root attributes differ")
    names_a, names_b = sorted(ga.array_keys()), sorted(gb.array_keys())
    if names_a != names_b:
        return problems + [f"arrays differ: {names_a} vs {names_b}"]
    for name in names_a:
        x, y = ga[name], gb[name]
        if dict(x.attrs) != dict(y.attrs):
            problems.append(f"{name}: attributes differ")
        if not _same_array(np.asarray(x[...]), np.asarray(y[...])):
            problems.append(f"{name}: values differ")
    return problems


def compare_cog(a: Path, b: Path) -> list[str]:
    import rasterio

    problems = []
    with rasterio.open(a) as x, rasterio.open(b) as y:
        if (x.count, x.width, x.height, x.crs, x.transform) != (y.count, y.width, y.height, y.crs, y.transform):
            return [f"{a.name}: shape, CRS or transform differ"]
        if x.descriptions != y.descriptions or x.tags() != y.tags():
            problems.append(f"{a.name}: descriptions or tags differ")
        if x.overviews(1) != y.overviews(1):
            return problems + [f"{a.name}: overview levels differ"]
        for band in range(1, x.count + 1):
            if x.tags(band) != y.tags(band) or x.tags(band, ns="IMAGERY") != y.tags(band, ns="IMAGERY"):
                problems.append(f"{a.name}: band {band} tags differ")
            if x.block_shapes[band - 1] != y.block_shapes[band - 1]:
                problems.append(f"{a.name}: band {band} tiling differs")
            if not _same_array(x.read(band), y.read(band)):
                problems.append(f"{a.name}: band {band} values differ")
    # overview levels: opened one by one (GDAL's OVERVIEW_LEVEL)
    with rasterio.open(a) as x:
        levels = len(x.overviews(1))
    for level in range(levels):
        with rasterio.open(a, OVERVIEW_LEVEL=level) as x, rasterio.open(b, OVERVIEW_LEVEL=level) as y:
            if not _same_array(x.read(), y.read()):
                problems.append(f"{a.name}: overview level {level + 1} differs")
    return problems


def compare_envi(a: Path, b: Path) -> list[str]:
    problems = []
    data_a, data_b = a.with_name(a.name[:-4]), b.with_name(b.name[:-4])
    if data_a.read_bytes() != data_b.read_bytes():
        problems.append(f"{data_a.name}: data bytes differ")
    if a.read_text() != b.read_text():
        problems.append(f"{a.name}: header differs")
    return problems


#: STAC keys that name the output's own location or the time of writing.
VOLATILE = {"href", "created", "updated", "processing:datetime", "command", "archive:seconds",
            "worker"}   # the Dask worker that rendered (its address changes from run to run)


def _strip(value):
    if isinstance(value, dict):
        return {k: _strip(v) for k, v in value.items() if k not in VOLATILE}
    if isinstance(value, list):
        return [_strip(v) for v in value]
    return value


def compare_item(a: Path, b: Path) -> list[str]:
    x, y = json.loads(a.read_text()), json.loads(b.read_text())
    x["id"] = y["id"] = None
    return [] if _strip(x) == _strip(y) else [f"{a.name}: STAC Item differs"]


def compare(a: Path, b: Path) -> list[str]:
    """Everything a render wrote beside ``a`` (its folder) against the same names beside ``b``."""
    problems = []
    names_a = {p.name for p in a.parent.iterdir()}
    names_b = {p.name for p in b.parent.iterdir()}
    problems += [f"{n}: only in the baseline" for n in sorted(names_a - names_b)]
    problems += [f"{n}: only in the current tree" for n in sorted(names_b - names_a)]
    for name in sorted(names_a & names_b):
        path_a, path_b = a.parent / name, b.parent / name
        if path_a.suffix == ".zarr":
            problems += [f"{name}: {p}" for p in compare_zarr(path_a, path_b)]
        elif path_a.suffix == ".tif":
            problems += compare_cog(path_a, path_b)
        elif path_a.suffix == ".hdr":
            problems += compare_envi(path_a, path_b)
        elif path_a.suffix == ".json":
            problems += compare_item(path_a, path_b)
    return problems


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--baseline", required=True, type=Path, help="checkout of the commit before the change")
    parser.add_argument("--current", type=Path, default=ROOT, help="tree under test (default: this checkout)")
    parser.add_argument("--work", type=Path, help="working directory (default: a temporary one)")
    parser.add_argument("--reuse-baseline", action="store_true",
                        help="keep the baseline outputs a previous run left in --work (the baseline does not change)")
    args = parser.parse_args(argv)
    work = args.work or Path(tempfile.mkdtemp(prefix="compare-outputs-"))
    work.mkdir(parents=True, exist_ok=True)
    flights = simulate(work / "flights")
    done = work / "baseline" / ".complete"
    if args.reuse_baseline and done.exists():
        before = [Path(p) for p in json.loads(done.read_text())]
    else:
        before = render_all(args.baseline.resolve(), flights, work / "baseline")
        done.write_text(json.dumps([str(p) for p in before]))
    after = render_all(args.current.resolve(), flights, work / "current")
    failed = 0
    for a, b in zip(before, after):
        problems = compare(a, b)
        print(f"{a.name}: {'identical' if not problems else 'DIFFERENT'}")
        for p in problems:
            print(f"    {p}")
        failed += bool(problems)
    print(f"{len(before) - failed} of {len(before)} outputs identical (work: {work})")
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
