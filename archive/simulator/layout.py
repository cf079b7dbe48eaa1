"""Where the targets go: one or more target tiles along each pass, inside its swath.

A tile is ~15 m along track x ~23 m across, centred on the pass centre line. Offsets are given in
the pass frame (da along the first pass's heading, dc to its right, m); every shape is then
axis-aligned in UTM (north-up), its centre snapped to 0.1 m (checkerboard corners to whole metres).

Tile content (dc, da):
- six homogeneous 3.6 m x 3.6 m patches (dc = -8.5 and +5, da = -5, 0, +5), materials rotated
  between tiles; their central 3 m x 3 m is uniform and safe for radiometry tests;
- a 4 m x 4 m checkerboard of 1 m squares (white / asphalt) at (-2, -4);
- a bar target at (-2, +3.5): white 4.0 x 3.2 m panel, asphalt bars 0.3 / 0.15 / 0.08 m wide
  (vertical, upper half) and 0.2 / 0.1 m (horizontal, lower half);
- 5 cm wide asphalt line targets, one N-S and one E-W, 6 m long, at dc = +1;
- a rotated 3 m triangle (red or blue) at (+10, +2);
- a 0.4 m glint square (saturates the sensor) at (+10, -4).
"""

from __future__ import annotations

import math

import numpy as np

from archive.simulator.scene import MATERIALS
from archive.simulator.trajectory import Trajectory

__all__ = ["TILE_ALONG", "layout"]

TILE_ALONG = 15.0   #: m between tile centres along track
PATCH = 3.6         #: m, homogeneous patch side
_M = {name: k for k, name in enumerate(MATERIALS)}
_PATCH_MATERIALS = ("concrete", "grass", "red", "blue", "white", "asphalt", "soil")


def _rect(name: str, material: str, ce: float, cn: float, we: float, hn: float, **extra) -> dict:
    return {"kind": "rect", "name": name, "material": _M[material],
            "bounds": [ce - we / 2, cn - hn / 2, ce + we / 2, cn + hn / 2], **extra}


def _snap(v: float, step: float = 0.1) -> float:
    return round(round(v / step) * step, 6)


def _tile(traj: Trajectory, a0: float, c0: float, index: int, rng: np.random.Generator) -> list[dict]:
    def at(da: float, dc: float) -> tuple[float, float]:
        e, n = traj.pass_frame_to_utm(a0 + da, c0 + dc)
        return _snap(float(e)), _snap(float(n))

    tag = f"t{index}"
    shapes: list[dict] = []
    names = [_PATCH_MATERIALS[(index + k) % len(_PATCH_MATERIALS)] for k in range(6)]
    for k, (dc, da) in enumerate([(dc, da) for dc in (-8.5, 5.0) for da in (-5.0, 0.0, 5.0)]):
        ce, cn = at(da, dc)
        shapes.append(_rect(f"{tag}_patch{k}_{names[k]}", names[k], ce, cn, PATCH, PATCH,
                            homogeneous=True))
    # checkerboard, corners on whole metres
    ce, cn = at(-4.0, -2.0)
    w, s = math.floor(ce) - 2.0, math.floor(cn) - 2.0
    shapes.append({"kind": "checker", "name": f"{tag}_checker", "bounds": [w, s, w + 4.0, s + 4.0],
                   "square": 1.0, "materials": [_M["white"], _M["asphalt"]]})
    # bar target
    ce, cn = at(3.5, -2.0)
    shapes.append(_rect(f"{tag}_bars_panel", "white", ce, cn, 4.0, 3.2))
    w, s = ce - 2.0, cn - 1.6
    x = w + 0.15
    for width in (0.3, 0.15, 0.08):                     # vertical bars, upper half
        for b in range(3):
            shapes.append(_rect(f"{tag}_vbar{width:g}_{b}", "asphalt", x + width / 2, s + 2.4,
                                width, 1.4))
            x += 2 * width
        x += 0.15
    for g, width in enumerate((0.2, 0.1)):              # horizontal bars, lower half
        x0 = w + 0.2 + g * 2.0
        for b in range(3):
            shapes.append(_rect(f"{tag}_hbar{width:g}_{b}", "asphalt", x0 + 0.8, s + 0.2 + width * (2 * b + 0.5),
                                1.6, width))
    # line targets
    ce, cn = at(0.0, 1.0)
    shapes.append(_rect(f"{tag}_line_ns", "asphalt", ce, cn, 0.05, 6.0))
    shapes.append(_rect(f"{tag}_line_ew", "asphalt", ce, cn + 1.0, 6.0, 0.05))
    # rotated triangle
    ce, cn = at(2.0, 10.0)
    theta = rng.uniform(0.0, 2.0 * np.pi) + np.array([0.0, 2.0, 4.0]) * np.pi / 3.0
    radius = 3.0 / math.sqrt(3.0)
    vertices = np.stack([ce + radius * np.sin(theta), cn + radius * np.cos(theta)], axis=1)
    shapes.append({"kind": "polygon", "name": f"{tag}_triangle", "material": _M["red" if index % 2 else "blue"],
                   "vertices": vertices.round(6).tolist()})
    # glint: a tiny over-bright square
    ce, cn = at(-4.0, 10.0)
    shapes.append(_rect(f"{tag}_glint", "glint", ce, cn, 0.4, 0.4))
    return shapes


def layout(traj: Trajectory, pass_spans: list[tuple[float, float]], rng: np.random.Generator) -> list[dict]:
    """Shapes for every pass: ``pass_spans[k]`` is (first, last) line time (GPS s) of pass k."""
    shapes: list[dict] = []
    tile = 0
    for k, (t0, t1) in enumerate(pass_spans):
        a = np.sort(traj.nominal_a(np.array([t0, t1])))
        length = float(a[1] - a[0])
        count = max(1, int((length - 2.0) // TILE_ALONG))
        c0 = float(traj.pass_c(k))
        for i in range(count):
            shapes += _tile(traj, float(a[0] + length * (i + 0.5) / count), c0, tile, rng)
            tile += 1
    return shapes
