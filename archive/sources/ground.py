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

import numpy as np

from archive.errors import InputError

__all__ = ["GROUND_KEY", "MAX_CLEARANCE", "MIN_CLEARANCE", "auto_ground_height", "check_ground_height",
           "header_ground_height"]

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
