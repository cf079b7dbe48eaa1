"""A point spectrum of a viewed flight: the pixel of ``archive render``'s grid holding a clicked
point, rendered alone by the same two passes, under the overlap rule of ``archive render --overlap``."""

from __future__ import annotations

import math

import numpy as np

from archive.grid import Grid
from archive.overlap import OverlapRule, overlap_rule
from archive.drawing.placement import slice_radiometry
from archive.drawing.query import ViewQuery

__all__ = ["POINT_BAND_GROUP", "overlap_pick", "point_spectrum"]

#: Bands read per group for a point spectrum (bounds the memory of a many-band click).
POINT_BAND_GROUP = 16


def point_spectrum(flight, lon: float, lat: float, gsd: float, query: ViewQuery) -> dict:
    """The full spectrum of the output pixel at (lon, lat): the pixel of ``archive render``'s
    grid at ``gsd`` (UTM, corners on multiples of ``gsd``) holding the point, rendered alone
    by the same two passes (bit-identical values), with the cube, line and sample it shows."""
    from archive.formats.lcf import gps_seconds_to_datetime
    from archive.geometry.navigation import project, to_lonlat
    from archive.render.renderer import Lookup, rasterize_lookup, render_lookup

    geometry = flight.view_geometry(query, gsd)
    cubes = flight.cube_range(query.cubes)
    mode = flight.mode(query)
    x, y = (float(v) for v in project(lon, lat, geometry.epsg))
    col, row = math.floor(x / gsd), math.floor(y / gsd)
    grid = Grid(geometry.epsg, gsd, col * gsd, (row + 1) * gsd, 1, 1)
    cx, cy = col * gsd + gsd / 2, row * gsd + gsd / 2
    clon, clat = (float(v) for v in to_lonlat(cx, cy, geometry.epsg))
    nbands = flight.cubes[0].bands
    rule = overlap_rule(query.overlap, "overlap")
    # every cube covering the pixel: (cube, line, sample, values, saturated, the rule's key there)
    candidates = []
    for c in cubes:
        mesh = geometry.utm[c]
        if mesh.rows < 2:
            continue
        w, s, e, n = mesh.bounds_utm()
        if not (w <= cx <= e and s <= cy <= n):
            continue
        found = rasterize_lookup(mesh, grid, flight.cubes[c].samples)
        line, sample = int(found.line[0, 0]), int(found.sample[0, 0])
        if line < 0:
            continue
        one = Lookup(grid, np.zeros((1, 1), np.int32), np.zeros((1, 1), np.int32), 1, 1)
        source = flight.source(None)
        v = np.full(nbands, np.nan, np.float32)
        flagged = False
        for b0 in range(0, nbands, POINT_BAND_GROUP):
            group = list(range(b0, min(b0 + POINT_BAND_GROUP, nbands)))
            dn = source.read_bands(c, group)[:, line:line + 1, sample:sample + 1]
            rad = slice_radiometry(flight.planes.radiometry(c, group, mode), slice(line, line + 1),
                                    slice(sample, sample + 1))
            result = render_lookup(one, dn, rad)
            v[b0:b0 + len(group)] = result.values[:, 0, 0]
            flagged = flagged or bool(result.saturated[0, 0])
        key = None if rule.key is None else float(flight.rule_key_plane(geometry, c, found, rule.key)[0, 0])
        candidates.append((c, line, sample, v, flagged, key))
    values, saturated, hit = overlap_pick(candidates, nbands, rule)
    answer = {
        "id": flight.id, "lon": lon, "lat": lat, "mode": mode, "gsd": gsd, "epsg": geometry.epsg,
        "pixel": {"x": cx, "y": cy, "lon": clon, "lat": clat},
        "ground_height": geometry.ground_height, "sync_offset": float(geometry.source.params.sync_offset),
        "navigation": geometry.pose[1], "boresight_deg": [float(v) for v in geometry.source.params.boresight_deg],
        "wavelength": flight.wavelengths_of(range(nbands)),
        "values": [float(v) if np.isfinite(v) else None for v in values],
        "covered": hit is not None, "cube": None, "line": None, "sample": None, "time": None,
        "utc": None, "saturated": saturated,
    }
    if hit is not None:
        c, line, sample = hit
        t = float(geometry.source.line_times(c)[line])
        answer.update(cube=c, base=flight.cubes[c].base, line=line, sample=sample, time=t,
                      utc=gps_seconds_to_datetime(t).isoformat().replace("+00:00", "Z"))
    return answer

def overlap_pick(candidates, nbands: int, rule: OverlapRule):
    """(values (nbands,) float32, saturated, (cube, line, sample) shown or None) of one output
    pixel from the cubes covering it, in capture order, by the rule ``archive render --overlap``
    applies (:mod:`archive.overlap`; e.g. 'last', per band the latest finite value; 'nadir',
    every band of the cube seen closest to nadir, the later one on a tie).

    candidates: (cube, line, sample, values (nbands,), saturated, key) of each covering cube, the
    key being the rule's compared layer at the pixel (None for a rule without one)."""
    if not candidates:
        return np.full(nbands, np.nan, np.float32), False, None
    mosaic = rule.mosaic(nbands, 1, 1)
    whole = (slice(0, 1), slice(0, 1))
    for _, _, _, v, flagged, key in candidates:
        plane = None if key is None else np.full((1, 1), key, np.float32)
        mosaic.feed(v.reshape(nbands, 1, 1), np.full((1, 1), flagged), *whole, key=plane)
    values, saturated = mosaic.result()
    shown = rule.shown([key for *_, key in candidates])
    if shown is None:
        return values[:, 0, 0], bool(saturated[0, 0]), None
    c, line, sample = candidates[shown][:3]
    return values[:, 0, 0], bool(saturated[0, 0]), (c, line, sample)
