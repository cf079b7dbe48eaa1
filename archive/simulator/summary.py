"""The few lines ``archive simulate`` prints about a simulated flight: shape, size, site, GSD and
what the simulator planted (recorder faults, sync offset, GNSS bias, mounting, ground changes)."""

from __future__ import annotations

import math

from archive.simulator.terrain import DEM_NAME
from archive.simulator.truth import Truth
from archive.simulator.writer import size_on_disk

__all__ = ["summary"]


def summary(truth: Truth) -> str:
    """A short human-readable summary of a simulated flight."""
    lines = sum(c.lines for c in truth.cubes)
    size = size_on_disk(truth.directory)
    lon, lat = truth.site
    return "\n".join([
        f"simulated flight: {truth.directory}",
        f"  cubes {len(truth.cubes)} ({len(truth.strips)} strips), lines {lines} "
        f"({truth.cubes[0].lines} per cube), bands {truth.wavelengths.size} "
        f"({truth.wavelengths[0]:.0f}-{truth.wavelengths[-1]:.0f} nm), samples {truth.samples}",
        f"  size on disk {size / 1e6:.1f} MB",
        f"  site {lat:.5f} N, {lon:.5f} E; EPSG:{truth.epsg}; grid convergence "
        f"{math.degrees(truth.convergence):+.3f} deg",
        f"  nominal GSD {truth.nominal_gsd * 100:.1f} cm across, "
        f"{truth.flight.speed / truth.cubes[0].framerate * 100:.1f} cm along; field of view "
        f"{truth.fov_deg:g} deg; ground {truth.ground_height:g} m (ellipsoid)",
        *_recorder_summary(truth),
        *([] if truth.terrain is None else [
            f"  terrain: {truth.terrain.kind}, {truth.terrain.relief[0]:g}-{truth.terrain.relief[1]:g} m bounds "
            f"(ellipsoid); DEM {truth.directory / DEM_NAME}"]),
        f"  truth: {truth.directory / 'truth'}",
    ])


def _recorder_summary(truth: Truth) -> list[str]:
    out = []
    if truth.dropped_frames:
        out.append(f"  dropped frames at cube switches: {truth.dropped_frames}")
    if truth.sync_offset:
        out.append(f"  sync offset (true): {truth.sync_offset:+g} s")
    if truth.bank_deg:
        out.append(f"  banked turns: {truth.bank_deg:g} deg" + (", recorded" if truth.record_turns else ""))
    elif truth.record_turns:
        out.append("  turns recorded")
    if truth.pause_cube is not None:
        out.append(f"  pause: {truth.pause_s:g} s before line {truth.pause_line} of cube "
                   f"{truth.cubes[truth.pause_cube].base}")
    if any(truth.gnss_bias_m):
        out.append("  GNSS bias (true, recorded - true): {} m (dE, dN, dU)".format(
            ",".join(f"{v:g}" for v in truth.gnss_bias_m)))
    if truth.ground_changes:
        out.append(f"  ground changed: {truth.ground_changes:.0%} painted with new patches")
    if not truth.mount.identity:
        out.append("  boresight (roll, pitch, yaw) {} deg, lever arm (x, y, z) {} m".format(
            ",".join(f"{v:g}" for v in truth.boresight_deg), ",".join(f"{v:g}" for v in truth.lever_arm_m)))
    return out
