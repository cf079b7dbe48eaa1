"""Benchmark of ``archive calibrate`` (issue 23): seconds per calibration of a 4-pass paper-shape
flight, and how the error shrinks with the overlap between passes.

    python bench/bench_calibrate.py [--samples 900] [--lines 1000] [--cubes 8] [--bands 8]
                                    [--fovs 40,44,47.5,55,62] [--lengths 400,800,1500]
                                    [--workdir DIR] [--results FILE]

1. Paper shape: ``archive simulate`` with --cubes 8 --cubes-per-pass 2 (4 passes of 2 x 1000 lines,
   80 m each) x 900 samples, few bands (the geometry is what calibration measures), planted boresight
   (-0.8, 0.6, 0.9) deg, sync offset +0.4 s, started with the ground 5 m too high. Timed: the
   calibration in this process (``archive.calibrate.calibrate``: reading the pass images, every
   measurement and fit), not the simulation.
2. Overlap: the same planted errors on 4-pass flights of 128 samples x 1500 lines whose field of
   view sets the overlap of neighbouring passes (25 m apart at 40 m height: overlap width =
   80 tan(fov / 2) - 25 m); error of every parameter against the truth, its 1-sigma, windows used.
3. Overlap length: the same at a 47.5 deg field of view with --lengths lines per pass.

Flights are simulated once into --workdir (kept while their truth exists). Prints a Markdown section
(machine, command, load, tables) and appends it to --results if given.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_render as br  # noqa: E402  (machine)

BORESIGHT = (-0.8, 0.6, 0.9)
SYNC = 0.4
GROUND_ERROR = 5.0
NAMES = ("roll", "pitch", "yaw", "sync", "ground")


def _flight(path: Path, **kw):
    from archive.simulator.command import simulate_flight
    from archive.simulator.truth import load_truth

    if (path / "truth" / "truth.json").exists():
        return load_truth(path), 0.0
    t0 = time.perf_counter()
    truth = simulate_flight(path, boresight_deg=BORESIGHT, sync_offset=SYNC, overwrite=True, **kw)
    return truth, time.perf_counter() - t0


def _calibrate(path: Path, truth) -> tuple[object, float]:
    from archive.calibrate import calibrate
    from archive.params import NavigationParams
    from archive.sources import RawFlightSource

    t0 = time.perf_counter()
    source = RawFlightSource(path, NavigationParams())
    result = calibrate([source], truth.fov_deg, truth.ground_height + GROUND_ERROR)
    return result, time.perf_counter() - t0


def _errors(result, truth) -> dict:
    want = np.array([*truth.boresight_deg, truth.sync_offset, truth.ground_height])
    return dict(zip(NAMES, result.params.vector() - want))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=900)
    ap.add_argument("--lines", type=int, default=1000)
    ap.add_argument("--cubes", type=int, default=8)
    ap.add_argument("--bands", type=int, default=8)
    ap.add_argument("--fovs", default="40,44,47.5,55,62")
    ap.add_argument("--lengths", default="400,800,1500")
    ap.add_argument("--workdir", default="bench_calibrate_work")
    ap.add_argument("--results", default=None)
    args = ap.parse_args(argv)
    work = Path(args.workdir)
    work.mkdir(parents=True, exist_ok=True)
    load_start = br.load() if hasattr(br, "load") else " ".join(f"{v:.2f}" for v in os.getloadavg())

    paper = work / f"paper_{args.samples}x{args.lines}x{args.cubes}"
    truth, sim_s = _flight(paper, cubes=args.cubes, cubes_per_pass=2, bands=args.bands, samples=args.samples,
                           lines=args.lines, seed=11)
    result, cal_s = _calibrate(paper, truth)
    err = _errors(result, truth)
    rows = [f"| paper shape ({args.samples} samples, {args.cubes} cubes x {args.lines} lines, 4 passes, "
            f"{args.bands} bands) | {cal_s:.1f} | " + " | ".join(_cell(err[n], result.sigma.get(n), n) for n in NAMES)
            + f" | {result.residual_before['median']:.2f} / {result.residual_after['median']:.3f} | "
              f"{result.residual_after['windows']} |"]
    def sweep_row(path: Path, first_cells: str, **flight) -> str:
        """One row of a sweep: calibrate a 4-cube, one-cube-per-pass flight of 128 x ``lines`` x 4 bands."""
        t, _ = _flight(path, cubes=4, cubes_per_pass=1, bands=4, samples=128, seed=11, **flight)
        try:
            r, s = _calibrate(path, t)
        except Exception as exc:  # noqa: BLE001 - a refusal is a result too
            return f"| {first_cells} | refused: {exc} |||||||"
        e = _errors(r, t)
        return (f"| {first_cells} | {r.residual_after['windows']} | {s:.1f} | "
                + " | ".join(_cell(e[n], r.sigma.get(n), n) for n in NAMES) + f" | {r.residual_after['median']:.3f} |")

    overlap_rows = [sweep_row(work / f"overlap_fov{fov:g}", f"{fov:g} | {2 * 40.0 * math.tan(math.radians(fov) / 2) - 25.0:.1f}",
                              lines=1500, fov_deg=fov)
                    for fov in (float(v) for v in args.fovs.split(","))]
    length_rows = [sweep_row(work / f"length_{lines}", f"{lines} | {lines / 24.9:.0f}", lines=lines)
                   for lines in (int(v) for v in args.lengths.split(","))]
    machine = br.machine()
    text = "\n".join([
        "## Self-calibration (issue 23): archive calibrate",
        "",
        f"Command: `.venv/bin/python bench/bench_calibrate.py --samples {args.samples} --lines {args.lines} "
        f"--cubes {args.cubes} --bands {args.bands} --fovs {args.fovs} --lengths {args.lengths}`; machine: {machine['cpu']}, "
        f"{machine['cores']} cores, {machine['ram_gb']} GB, Python {machine['python']}; load average at start "
        f"{load_start}, at end {' '.join(f'{v:.2f}' for v in os.getloadavg())} (other jobs share the VM: "
        "seconds are upper bounds). Planted: boresight "
        f"{BORESIGHT} deg, sync offset {SYNC:+g} s, start ground {GROUND_ERROR:g} m too high. "
        "Errors are estimate - truth (1-sigma reported by calibrate in brackets).",
        "",
        "| flight | seconds | roll deg | pitch deg | yaw deg | sync s | ground m | misregistration median before / after px | windows |",
        "|---|---|---|---|---|---|---|---|---|",
        *rows,
        "",
        "Error against overlap width (4 passes, 128 samples x 1500 lines, 4 bands; the field of view sets the overlap):",
        "",
        "| fov deg | overlap m | windows | seconds | roll deg | pitch deg | yaw deg | sync s | ground m | after median px |",
        "|---|---|---|---|---|---|---|---|---|---|",
        *overlap_rows,
        "",
        "Error against overlap length (4 passes, 128 samples, field of view 47.5 deg: 10 m wide overlaps; "
        "lines per pass at 249 lines/s and 10 m/s):",
        "",
        "| lines per pass | overlap length m | windows | seconds | roll deg | pitch deg | yaw deg | sync s | ground m | after median px |",
        "|---|---|---|---|---|---|---|---|---|---|",
        *length_rows,
        "",
    ])
    print(text)
    if args.results:
        with open(args.results, "a", encoding="utf-8") as f:
            f.write("\n" + text)
    return 0


def _cell(error: float, sigma, name: str) -> str:
    digits = {"roll": 4, "pitch": 4, "yaw": 4, "sync": 5, "ground": 3}[name]
    s = "held" if sigma is None else f"{sigma:.{digits}f}"
    return f"{error:+.{digits}f} ({s})"


if __name__ == "__main__":
    raise SystemExit(main())
