"""``--ground-height auto``: the flat-ground height a source records, checked for plausibility.

- A collection records the height it was ingested with (``source.ground_height``): that one is
  used, whatever its headers say.
- A raw flight: every cube header's ``ground elevation`` (metres, the ``.lcf`` altitude datum). A
  missing key or exactly ``0`` is unset: Resonon's acquisition software writes ``ground elevation =
  0.000`` when nobody entered one (the real 2023 sample flies at 91.8 m above the ellipsoid). The
  cubes must agree.

Plausible means: the camera is at least :data:`MIN_CLEARANCE` metres above the ground over every
line, and at most :data:`MAX_CLEARANCE` metres above it on the median line (airborne pushbroom
imagers fly drones and light aircraft at tens of metres to a few kilometres above the ground).
Anything else is refused with an error that asks for ``--ground-height`` or ``--dem``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from archive.errors import InputError

__all__ = ["GROUND_KEY", "MAX_CLEARANCE", "MIN_CLEARANCE", "auto_ground_height", "check_ground_height",
           "dem_record", "header_ground_height", "recorded_dem", "sources_dem"]

GROUND_KEY = "ground elevation"
#: Least height of the camera above the ground, metres.
MIN_CLEARANCE = 1.0
#: Largest median height of the camera above the ground, metres.
MAX_CLEARANCE = 5000.0
_FIX = "pass --ground-height M (metres above the ellipsoid, the .lcf altitude datum) or --dem FILE"


def header_ground_height(metadata: dict) -> float | None:
    """A header's ``ground elevation`` (m), or None when absent, not a number, or the unset 0."""
    value = metadata.get(GROUND_KEY)
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        return None
    return None if float(value) == 0.0 else float(value)


def camera_altitudes(source) -> np.ndarray:
    """Camera heights above the ellipsoid (m) at the INS samples of every cube of ``source``."""
    alts = [source.frame.origin_alt - np.asarray(source.track(i).position)[:, 2] for i in range(len(source.cubes))]
    return np.concatenate(alts)


def check_ground_height(height: float, altitudes: np.ndarray, where: str, what: str) -> float:
    """``height`` if the camera (``altitudes``, m above the ellipsoid) flies plausibly above it,
    else InputError naming ``where`` and the height's origin ``what``."""
    lowest, median = float(np.min(altitudes)), float(np.median(altitudes))
    if lowest - height < MIN_CLEARANCE:
        raise InputError(where, f"{what} {height:g} m is not below the camera (lowest camera altitude "
                         f"{lowest:.1f} m above the ellipsoid)", _FIX)
    if median - height > MAX_CLEARANCE:
        raise InputError(where, f"{what} {height:g} m is implausibly far below the camera (median "
                         f"altitude {median:.1f} m, more than {MAX_CLEARANCE:g} m above the ground)", _FIX)
    return height


def auto_ground_height(sources: Sequence) -> float:
    """The ground height of ``--ground-height auto`` for a job over ``sources`` (see the module
    docstring); they must agree."""
    found: dict[float, str] = {}
    for source in sources:
        if source.ground_height is not None:
            h = float(source.ground_height)
            found.setdefault(check_ground_height(h, camera_altitudes(source), source.label,
                                                 "the ingested ground height"), source.id)
            continue
        for i, info in enumerate(source.cubes):
            h = header_ground_height(source.header(i).metadata)
            if h is None:
                raise InputError(source.label, f"cube {info.base} has no '{GROUND_KEY}' in its header (or the "
                                 "unset default 0) for --ground-height auto", _FIX)
            if h not in found:
                check_ground_height(h, camera_altitudes(source), source.label, f"cube {info.base}'s '{GROUND_KEY}'")
            found.setdefault(h, info.base)
    if len(found) > 1:
        listing = ", ".join(f"{h:g} m ({name})" for h, name in found.items())
        raise InputError("--ground-height", f"the flights disagree on the ground height: {listing}",
                         "pass --ground-height M")
    return next(iter(found))


# ---------------------------------------------------------------------------------------------
# A collection's DEM (ingested with --dem): what it records, and the checks on reading it back
# ---------------------------------------------------------------------------------------------
_CHECKED: dict[tuple, str] = {}   #: sha256 of DEM files already checked, by (path, size, mtime)


def dem_record(dem) -> dict:
    """What a collection records of the DEM it was ingested with (its ``terrain`` attribute): the
    file name, absolute path, vertical datum, whether the file declares it, and the sha256 of the
    file (so that a DEM that changed since is refused, not silently drawn)."""
    from archive.collection import sha256_file

    return {"dem": dem.path.name, "dem_path": str(Path(dem.path).absolute()), "datum": dem.datum,
            "declared": bool(dem.declared), "sha256": sha256_file(dem.path)}




def recorded_dem(terrain: dict | None, where: str):
    """The :class:`DemSpec` of a collection's recorded DEM (``terrain``: its ``terrain`` attribute,
    :func:`dem_record`), None for a collection ingested without one. The file must still be where it
    was and, when a checksum was recorded, hold the same bytes: else InputError naming the DEM and
    ``where`` (the collection) and saying how to go on. The DEM is opened with the datum recorded
    ('ellipsoid', 'egm96', ... or the declared datum's name)."""
    if not terrain or not terrain.get("dem_path"):
        return None
    path = Path(str(terrain["dem_path"]))
    fix = ("put the DEM back, pass --dem FILE to render over another DEM, or --ground-height M to "
           "render flat")
    if not path.is_file():
        raise InputError(where, f"was ingested with the DEM {path}, which is no longer there", fix)
    from archive.terrain.dem import DemSpec

    spec = DemSpec.create(path, None if terrain.get("declared") else terrain.get("datum"))
    digest = terrain.get("sha256")
    if digest:
        key = (spec.path, spec.size, spec.mtime_ns)
        if key not in _CHECKED:
            from archive.collection import sha256_file

            _CHECKED[key] = sha256_file(path)
        if _CHECKED[key] != digest:
            raise InputError(where, f"the DEM {path} changed since the collection was ingested (sha256 "
                             f"{_CHECKED[key][:12]}... instead of {str(digest)[:12]}...)", fix)
    return spec


def sources_dem(sources, where: str = "--dem"):
    """The DEM the collections among ``sources`` were ingested with, when none of them was ingested
    flat: one :class:`DemSpec` (they must agree, else InputError naming both), None when any source
    has no recorded DEM (raw flights, collections ingested flat)."""
    specs = []
    for s in sources:
        terrain = getattr(getattr(s, "info", None), "attrs", {}).get("terrain")
        spec = recorded_dem(terrain, str(getattr(s, "id", None) or s.label))
        if spec is None:
            return None
        specs.append((s, spec))
    if not specs:
        return None
    first_source, first = specs[0]
    for s, spec in specs[1:]:
        if (spec.path, spec.datum) != (first.path, first.datum):
            raise InputError(where, f"{first_source.label} was ingested with the DEM {first.path}, {s.label} with "
                             f"{spec.path}", "pass --dem FILE (or --ground-height M) for all of them, or render "
                             "them separately")
    return first
