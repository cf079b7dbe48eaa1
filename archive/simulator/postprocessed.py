"""A simulated flight's post-processed trajectory: the TRUE INS path (no GNSS bias, whatever the ``.lcf``
records) written as an Applanix SBET or an Inertial Explorer CSV export (:mod:`archive.formats.trajectory`
reads both), for tests and demos of ``render --navigation``."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from archive.simulator.trajectory import convergence, to_lonlat
from archive.simulator.truth import Truth

__all__ = ["write_trajectory"]

WEEK_S = 604800.0


def write_trajectory(truth: Truth, path: str | os.PathLike, *, rate: float = 200.0, margin: float = 1.0,
                     full_seconds: bool = False) -> Path:
    """Write the true INS trajectory of ``truth`` from ``margin`` s before its first line to ``margin`` s
    after its last, at ``rate`` Hz: an SBET for a ``.out``/``.sbet`` ``path`` (GPS seconds of week), else
    a CSV with Inertial Explorer's column names (degrees; ``full_seconds``: full GPS seconds instead of
    seconds of week). Returns the path."""
    path = Path(path)
    first = min(float(c.line_time[0]) for c in truth.cubes)
    last = max(float(c.line_time[-1]) for c in truth.cubes)
    t = np.arange(first - margin, last + margin, 1.0 / rate)
    pos, att = truth.ins_trajectory(t)
    lon, lat = to_lonlat(pos[:, 0], pos[:, 1], truth.epsg)
    yaw, pitch, roll = att.as_euler("ZYX").T   # aerospace: yaw about down, grid north
    heading = np.mod(yaw - convergence(lon, lat, truth.epsg), 2 * np.pi)   # true north
    sow = np.mod(t, WEEK_S)
    if path.suffix.lower() in (".out", ".sbet"):
        rec = np.zeros((t.size, 17), "<f8")
        wander = np.full(t.size, 0.25)   # a wander-azimuth mechanisation: the platform heading carries it
        rec[:, 0], rec[:, 1], rec[:, 2], rec[:, 3] = sow, np.radians(lat), np.radians(lon), pos[:, 2]
        rec[:, 7], rec[:, 8], rec[:, 9], rec[:, 10] = roll, pitch, heading + wander, wander
        rec.tofile(path)
        return path
    rows = np.column_stack([t if full_seconds else sow, lat, lon, pos[:, 2], np.degrees(roll), np.degrees(pitch),
                            np.degrees(heading)])
    with open(path, "w") as f:
        f.write("GPSTime,Latitude,Longitude,H-Ell,Roll,Pitch,Heading\n")
        for r in rows:
            f.write(f"{r[0]:.5f},{r[1]:.10f},{r[2]:.10f},{r[3]:.4f},{r[4]:.6f},{r[5]:.6f},{r[6]:.6f}\n")
    return path
