"""The ``archive watch`` command line (its parser; the work is :func:`archive.watch.command.run`)."""

from __future__ import annotations

import argparse
import math

__all__ = ["INGEST_OPTIONS", "add_watch", "ingest_argv"]

#: The options passed on to ``archive ingest`` as given (destination, flag).
INGEST_OPTIONS = (("calibration", "--calibration"), ("irradiance_calibration", "--irradiance-calibration"),
                  ("ground_height", "--ground-height"), ("dem", "--dem"), ("dem_datum", "--dem-datum"),
                  ("sync_offset", "--sync-offset"), ("boresight", "--boresight"), ("lever_arm", "--lever-arm"),
                  ("navigation", "--navigation"), ("navigation_columns", "--navigation-columns"),
                  ("workers", "--workers"))


def _seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value >= 0):
        raise argparse.ArgumentTypeError(f"expected a number of seconds >= 0, got {text!r}")
    return value


def add_watch(sub) -> None:
    """The ``archive watch`` subcommand's parser (``sub``: what ``add_subparsers`` returned)."""
    p = sub.add_parser("watch", help="follow recorder folders: show each cube georectified as it closes, "
                       "ingest each flight when it stops", description=(
                           "Follow Resonon recorder folders while they are written (inotify; polling on network "
                           "mounts or with --poll). A cube is complete when its header exists (recorders write it "
                           "last) and its .bil, .bil.times and .lcf agree with it and have stopped growing; a cube "
                           "that stays incomplete is reported once and skipped. Each complete cube is listed on the "
                           "live map at once (unless --no-view); after --idle seconds without a new cube the flight "
                           "(one image set name) is ingested into ARCHIVE exactly as 'archive ingest' does. "
                           "Restarting on the same folders resumes without re-ingesting; SIGTERM or Ctrl-C stops "
                           "with the archive consistent (exit 0). See docs/watch.md."))
    p.add_argument("folders", nargs="+", metavar="DIR", help="recorder folder (mounted or synced; may appear later)")
    p.add_argument("--archive", required=True, metavar="ARCHIVE", help="local archive directory (created if absent)")
    p.add_argument("--fov", required=True, type=float, metavar="DEG",
                   help="across-track field of view of the camera, degrees (47.5 for a Pika L)")
    p.add_argument("--idle", type=_seconds, default=30.0, metavar="S",
                   help="seconds without a new cube after which a flight is complete and ingested (default 30)")
    p.add_argument("--settle", type=_seconds, default=0.5, metavar="S",
                   help="seconds a whole cube's files must stay unchanged before it is read (default 0.5)")
    p.add_argument("--stall", type=_seconds, default=15.0, metavar="S",
                   help="seconds without change after which an incomplete cube is reported and skipped (default 15)")
    p.add_argument("--poll", type=_seconds, nargs="?", const=1.0, default=None, metavar="S",
                   help="look at the folders every S seconds (default 1) instead of inotify events: for network "
                        "mounts (chosen by itself on NFS, SMB, SSHFS...)")
    p.add_argument("--no-view", action="store_true", help="serve no live map")
    p.add_argument("--host", default="127.0.0.1", help="address of the live map (default 127.0.0.1, loopback only)")
    p.add_argument("--port", type=int, default=8000, help="port of the live map (default 8000; 0 picks a free one)")
    p.add_argument("--allow-remote", action="store_true",
                   help="allow a --host that is not loopback (anyone who can reach it can read the flights)")
    p.add_argument("--cache-mb", type=int, default=512, metavar="MIB", help="the viewer's cache memory, MiB (default 512)")
    p.add_argument("--quiet", action="store_true", help="no line per cube (flights, skipped cubes and faults still)")
    g = p.add_argument_group("ingest options", "passed on to 'archive ingest' (see 'archive ingest --help')")
    g.add_argument("--calibration", metavar="FILE.icp")
    g.add_argument("--irradiance-calibration", metavar="FILE.dcp")
    g.add_argument("--ground-height", metavar="M")
    g.add_argument("--dem", metavar="FILE")
    g.add_argument("--dem-datum", choices=["ellipsoid", "egm96", "egm2008"])
    g.add_argument("--sync-offset", metavar="S")
    g.add_argument("--boresight", metavar="R,P,Y")
    g.add_argument("--lever-arm", metavar="X,Y,Z")
    g.add_argument("--navigation", metavar="FILE")
    g.add_argument("--navigation-columns", metavar="time=COL,...")
    g.add_argument("--workers", metavar="N")


def ingest_argv(args: argparse.Namespace) -> list[str]:
    """The ``archive ingest`` options of ``args`` as command-line words (what was given, as given;
    ingest checks them: a bad one is its one line)."""
    words: list[str] = []
    for dest, flag in INGEST_OPTIONS:
        value = getattr(args, dest, None)
        if value is not None:
            words += [f"{flag}={value}"]
    return words
