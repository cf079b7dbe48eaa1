"""Task bodies of the render graph: plain module-level functions of explicit inputs.

They run on Dask workers but can be called directly (tests, debugging). Boxes are
``(row0, col0, height, width)`` in pixels of the output grid; rasters are ``(band, y, x)``.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from archive.errors import InputError, RenderError
from archive.graph.mosaic import make_rule
from archive.grid import Grid
from archive.outputs import MosaicStore

Box = tuple[int, int, int, int]

__all__ = ["Box", "assemble_task", "render_task", "write_saturated_task", "write_values_task"]


def render_task(source, cube: int, bands: Sequence[int], mesh, window: Grid, mode: str,
                bands_per_pass: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Render ``bands`` of ``cube`` of ``source`` on ``window`` (the cube's part of the output grid).

    Reads the bands and radiometry here, on the worker, then draws with this thread's GL context.
    Returns values (len(bands), window.height, window.width) float32 (NaN where not covered) and
    saturated (window.height, window.width) bool.
    """
    from archive.render.renderer import render_cube  # GL only on workers

    bands = list(bands)
    try:
        dn = source.read_bands(cube, bands)
        radiometry = source.radiometry(cube, bands, mode)
        result = render_cube(mesh, dn, radiometry, window, bands_per_pass=min(bands_per_pass, len(bands)))
    except (InputError, RenderError) as exc:  # say which cube: the renderer cannot know
        where = f"{getattr(source, 'directory', source.id)} cube {source.cubes[cube].base}"
        if isinstance(exc, InputError):
            raise InputError(where, str(exc)) from exc
        raise RenderError(f"{where}: {exc}") from exc
    return result.values, result.saturated


def _overlap(tile: Box, box: Box) -> tuple[tuple[slice, slice], tuple[slice, slice]] | None:
    """Slices (in the tile, in the box's array) of the pixels the two boxes share, or None."""
    r0 = max(tile[0], box[0])
    c0 = max(tile[1], box[1])
    r1 = min(tile[0] + tile[2], box[0] + box[2])
    c1 = min(tile[1] + tile[3], box[1] + box[3])
    if r1 <= r0 or c1 <= c0:
        return None
    in_tile = (slice(r0 - tile[0], r1 - tile[0]), slice(c0 - tile[1], c1 - tile[1]))
    in_box = (slice(r0 - box[0], r1 - box[0]), slice(c0 - box[1], c1 - box[1]))
    return in_tile, in_box


def assemble_task(rule: str, tile: Box, nbands: int, boxes: Sequence[Box],
                  *renders: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Mosaic cube renders onto one output tile with the overlap ``rule`` ('last' | 'mean').

    boxes[i]: where renders[i] (values (nbands, h, w), saturated (h, w)) lies in the output grid;
    renders in capture order. Returns values (nbands, tile h, tile w) float32, saturated (h, w) bool.
    """
    if len(boxes) != len(renders):
        raise ValueError(f"{len(boxes)} boxes for {len(renders)} renders")
    mosaic = make_rule(rule, nbands, tile[2], tile[3])
    for box, (values, saturated) in zip(boxes, renders):
        shared = _overlap(tile, box)
        if shared is None:
            continue
        (tr, tc), (br, bc) = shared
        mosaic.feed(values[:, br, bc], saturated[br, bc], tr, tc)
    return mosaic.result()


def write_values_task(store: MosaicStore, band0: int, tile: Box, assembled: tuple[np.ndarray, np.ndarray],
                      saturated_before: np.ndarray | None = None) -> np.ndarray:
    """Write an assembled tile's values into its own chunks.

    Returns the tile's saturation mask (h, w) bool OR ``saturated_before`` (earlier band groups).
    """
    values, saturated = assembled
    store.write_values(band0, tile[0], tile[1], values)
    return saturated if saturated_before is None else saturated | saturated_before


def write_saturated_task(store: MosaicStore, tile: Box, *masks: np.ndarray) -> int:
    """OR the saturation masks of one tile and write them; returns the saturated pixel count."""
    mask = np.zeros(tile[2:], bool)
    for m in masks:
        mask |= m
    store.write_saturated(tile[0], tile[1], mask)
    return int(mask.sum())
