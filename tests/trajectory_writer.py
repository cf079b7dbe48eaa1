"""An independent writer of post-processed trajectories for the tests (numpy's structured records, the
csv module and pyproj; not :mod:`archive.simulator.postprocessed`): the simulator's error-free INS path
as an Applanix SBET and as a Qinertia-like CSV export (issue 46)."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pyproj

WEEK = 604800.0
#: An SBET record as PDAL's reader names its 17 little-endian doubles.
SBET = np.dtype([(name, "<f8") for name in (
    "GpsTime", "Y", "X", "Z", "XVelocity", "YVelocity", "ZVelocity", "Roll", "Pitch", "PlatformHeading",
    "WanderAngle", "XBodyAccel", "YBodyAccel", "ZBodyAccel", "XBodyAngRate", "YBodyAngRate", "ZBodyAngRate")])
#: A Qinertia-like export: its own column names, given with --navigation-columns.
COLUMNS = ("GPS Time (s)", "Latitude (deg)", "Longitude (deg)", "Ellipsoidal Height (m)", "Roll (deg)",
           "Pitch (deg)", "Heading (deg)")
#: --navigation-columns' keys, in COLUMNS' order.
KEYS = ("time", "lat", "lon", "height", "roll", "pitch", "heading")


def true_path(truth, rate: float = 200.0):
    """(GPS seconds, lon, lat, height, roll, pitch, true heading): the INS's true path (radians),
    from a second before the first line to a second after the last, at ``rate`` Hz."""
    first = min(float(c.line_time[0]) for c in truth.cubes) - 1.0
    last = max(float(c.line_time[-1]) for c in truth.cubes) + 1.0
    t = np.arange(first, last, 1.0 / rate)
    pos, att = truth.ins_trajectory(t)   # UTM E, N, ellipsoidal height; body -> NED about GRID north
    to_geo = pyproj.Transformer.from_crs(truth.epsg, 4326, always_xy=True)
    lon, lat = to_geo.transform(pos[:, 0], pos[:, 1])
    # the grid azimuth of true north at each point, from a step along the meridian
    to_grid = pyproj.Transformer.from_crs(4326, truth.epsg, always_xy=True)
    e1, n1 = to_grid.transform(lon, lat + 1e-4)
    north = np.arctan2(e1 - pos[:, 0], n1 - pos[:, 1])
    yaw, pitch, roll = att.as_euler("ZYX").T
    heading = np.mod(yaw - north, 2 * np.pi)
    return t, np.radians(lon), np.radians(lat), pos[:, 2], roll, pitch, heading


def write_sbet(path: Path, rows) -> Path:
    """``rows`` (:func:`true_path`'s) as an SBET at ``path``: GPS seconds of week, wander angle 0."""
    t, lon, lat, h, roll, pitch, heading = rows
    rec = np.zeros(t.size, SBET)
    rec["GpsTime"], rec["Y"], rec["X"], rec["Z"] = np.mod(t, WEEK), lat, lon, h
    rec["Roll"], rec["Pitch"], rec["PlatformHeading"] = roll, pitch, heading   # wander angle 0
    rec.tofile(path)
    return path


def write_csv(path: Path, rows) -> Path:
    """``rows`` (:func:`true_path`'s) as a CSV export with :data:`COLUMNS` (degrees, 9 decimals of lat/lon)."""
    t, lon, lat, h, roll, pitch, heading = rows
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(COLUMNS)
        for row in zip(np.mod(t, WEEK), np.degrees(lat), np.degrees(lon), h, np.degrees(roll), np.degrees(pitch),
                       np.degrees(heading)):
            writer.writerow([f"{row[0]:.4f}", f"{row[1]:.9f}", f"{row[2]:.9f}", f"{row[3]:.3f}",
                             *(f"{v:.5f}" for v in row[4:])])
    return path
