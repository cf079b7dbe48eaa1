"""The ``archive simulate`` command line (its parser; the work is :func:`archive.simulator.command.run`)."""

from __future__ import annotations

import argparse

__all__ = ["add_simulate", "positive_int"]


def positive_int(text: str) -> int:
    """An argparse type: a positive integer."""
    value = int(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text}")
    return value


def add_simulate(sub) -> None:
    """The ``archive simulate`` subcommand's parser (``sub``: what ``add_subparsers`` returned)."""
    p = sub.add_parser("simulate", help="write a simulated Resonon flight with its ground truth", description=(
        "Write a simulated airborne pushbroom flight in the Resonon layout (<base>.bil, .bil.hdr, "
        ".lcf, .bil.times per cube, plus calibration.icp) and its ground truth (truth/: scene, "
        "true per-line poses, footprint). Lawn-mower passes at ~10 m/s, ~40 m above flat ground, "
        "near Memphis (35.12 N, 89.94 W), 249 lines/s, INS at 200 Hz. Defaults are small (test "
        "size); paper scale is --samples 900 --lines 1000 --bands 300 --cubes 40."))
    p.add_argument("directory", metavar="DIR", help="output directory (created; must be empty unless --overwrite)")
    p.add_argument("--cubes", type=positive_int, default=4, help="number of cubes (default 4)")
    p.add_argument("--bands", type=positive_int, default=8, help="spectral bands per cube (default 8)")
    p.add_argument("--samples", type=positive_int, default=128, help="samples per line (default 128)")
    p.add_argument("--lines", type=positive_int, default=250, help="lines per cube (default 250)")
    p.add_argument("--cubes-per-pass", type=positive_int, default=2,
                   help="cubes recorded back to back on each straight pass (default 2)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--scene-seed", type=int, metavar="K",
                   help="seed of the ground (scene and targets) and of the camera's radiometry (default: --seed): "
                        "flights of one --scene-seed fly over the same field, each with its own wobble, noise and "
                        "start (e.g. --seed 1 --scene-seed 0 --start 2024-06-19T16:00:00Z flies seed 0's field a "
                        "week later)")
    p.add_argument("--start", metavar="ISO8601",
                   help="UTC start of the flight (the first line follows 0.5 s later), e.g. 2024-06-12T16:00:00Z (default: 2024-06-12T16:00:00Z "
                        "plus --seed minutes, so flights of different seeds get different ids)")
    p.add_argument("--clouds", action="store_true",
                   help="the sky's brightness drifts 30 %% within cubes; writes the kit's downwelling spectra "
                        "(<set>_downwelling_<k>_pre.spec per cube, downwelling.dcp) and the truth (truth/clouds.json)")
    p.add_argument("--lat", type=float, default=35.12, help="latitude of the site, degrees (default 35.12)")
    p.add_argument("--lon", type=float, default=-89.94, help="longitude of the site, degrees (default -89.94)")
    p.add_argument("--fov", type=float, default=47.5, help="across-track field of view, degrees (default 47.5)")

    def numbers(count: int | None):
        def parse(text: str) -> tuple[float, ...]:
            try:
                values = tuple(float(v) for v in text.replace(" ", "").split(","))
            except ValueError:
                values = ()
            if not values or (count is not None and len(values) != count) \
                    or not all(abs(v) < float("inf") for v in values):
                what = f"{count} comma-separated numbers" if count else "comma-separated numbers"
                raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}")
            return values
        return parse

    r = p.add_argument_group("recorder realism (each off by default: an ideal recorder)")
    r.add_argument("--dropped-frames", type=int, default=0, choices=range(11), metavar="N",
                   help="frames dropped at each cube switch within a pass: the next cube starts N+1 frame "
                        "intervals after the previous one's last line (default 0)")
    shutter = r.add_mutually_exclusive_group()
    shutter.add_argument("--shutters", type=numbers(None), metavar="MS,MS,...",
                         help="shutter (ms) of each cube, cycled over cubes, gain 0 dB unless --gains "
                              "(default: shutter and gain cycle over 3/0, 2.5/3, 3.9/0, 2.6/6 ms/dB)")
    shutter.add_argument("--shutter-steps", action="store_true",
                         help="shutters 3, 1.5, 3.9, 2.2 ms cycled over cubes at gain 0 dB")
    r.add_argument("--gains", type=numbers(None), metavar="DB,DB,...", help="gain (dB) of each cube, cycled over cubes")
    r.add_argument("--sync-offset", type=float, default=0.0, metavar="S",
                   help="true camera-to-navigation offset, seconds: each .lcf starts S before its cube's first "
                        "line, so 'archive render --sync-offset S' recovers the truth (default 0)")
    r.add_argument("--bank-deg", type=float, metavar="D",
                   help="coordinated turns between passes with a sustained bank of D degrees, 10..70 "
                        "(default: flat half-circle turns)")
    r.add_argument("--record-turns", action="store_true",
                   help="keep recording into the turn after each pass (to the end of the sustained bank "
                        "with --bank-deg): lines with huge view angles")
    r.add_argument("--pause", type=float, default=0.0, metavar="S",
                   help="the recorder stops S seconds before the middle line of one cube and continues in "
                        "the same file (default 0: no pause)")
    r.add_argument("--pause-cube", type=int, default=0, metavar="K", help="0-based cube of --pause (default 0)")
    r.add_argument("--boresight", type=numbers(3), metavar="ROLL,PITCH,YAW",
                   help="true camera mounting angles, degrees, aerospace signs (default 0,0,0)")
    r.add_argument("--lever-arm", type=numbers(3), metavar="X,Y,Z",
                   help="true camera position from the INS in the body frame, metres (default 0,0,0)")
    r.add_argument("--gnss-bias", type=numbers(3), metavar="DE,DN,DU",
                   help="the .lcf records every position this far off the truth, metres (grid east, north, up): "
                        "the GNSS bias of a kit without RTK (default 0,0,0)")
    p.add_argument("--scene-from", metavar="FLIGHT_DIR",
                   help="fly over exactly the ground of an earlier simulated flight (its truth's scene), whatever "
                        "this flight's heading or shape")
    p.add_argument("--ground-changes", type=float, default=0.0, metavar="F", help="paint this fraction (0..0.9) of "
                   "the ground with new material patches (default 0)")
    p.add_argument("--heading", type=float, metavar="DEG", help="grid heading of the even passes, degrees clockwise "
                   "from grid north (default 20)")
    p.add_argument("--terrain", choices=["hills", "ridge"],
                   help="terrain instead of flat ground: 'hills' (>= 10 m relief) or 'ridge' (with ground hidden "
                        "from some lines); writes dem.tif (ellipsoidal heights) beside the flight")
    p.add_argument("--overwrite", action="store_true", help="replace DIR if it exists")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
