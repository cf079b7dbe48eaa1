"""Task bodies of the render graph: plain module-level functions of explicit inputs.

They run on Dask workers but can be called directly (tests, debugging). Boxes are
``(row0, col0, height, width)`` in pixels of the output grid; rasters are ``(band, y, x)``.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from archive.errors import InputError, RenderError
from archive.graph.mosaic import last_saturation, last_values, make_rule
from archive.grid import Grid
from archive.outputs import CHUNK, MosaicStore

Box = tuple[int, int, int, int]

__all__ = ["Box", "assemble_task", "assemble_write_task", "lookup_task", "render_task", "write_saturated_task",
           "write_values_task"]


def lookup_task(mesh, window: Grid, samples: int):
    """Pass 1 of the renderer for one cube: which (line, sample) each pixel centre of ``window`` sees.

    Runs once per cube (GL, on a worker); returns a picklable :class:`archive.render.renderer.Lookup`
    ((height, width) int32 line and sample, -1 where not covered) that every band group reuses.
    """
    from archive.render.renderer import rasterize_lookup  # GL only on workers

    return rasterize_lookup(mesh, window, samples)


def render_task(source, cube: int, bands: Sequence[int], lookup, mode: str,
                bands_per_pass: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Render ``bands`` of ``cube`` of ``source`` through the cube's ``lookup`` (from :func:`lookup_task`).

    Reads the bands and radiometry here, on the worker, then draws with this thread's GL context,
    ``bands_per_pass`` (1..8) bands per full-screen pass.
    Returns values (len(bands), window height, window width) float32 (NaN where not covered) and
    saturated (window height, window width) bool.
    """
    from archive.render.renderer import render_lookup  # GL only on workers

    bands = list(bands)
    try:
        dn = source.read_bands(cube, bands)
        radiometry = source.radiometry(cube, bands, mode)
        result = render_lookup(lookup, dn, radiometry, bands_per_pass=min(bands_per_pass, len(bands)))
    except (InputError, RenderError) as exc:  # say which cube: the renderer cannot know
        where = f"{source.label} cube {source.cubes[cube].base}"
        if isinstance(exc, InputError):
            # keep the kind, problem and fix; name the file too when it is more than the source
            named = exc.where if exc.where not in (None, source.label) else None
            raise type(exc)(where if named is None else f"{where} ({named})", exc.problem, exc.fix) from exc
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


def _tile_parts(tile: Box, boxes: Sequence[Box], renders) -> list:
    """(values, saturated, tile rows, tile cols) of each render's part inside ``tile``, in order."""
    parts = []
    for box, (values, saturated) in zip(boxes, renders):
        shared = _overlap(tile, box)
        if shared is not None:
            (tr, tc), (br, bc) = shared
            parts.append((values[:, br, bc], saturated[br, bc], tr, tc))
    return parts


def assemble_task(rule: str, tile: Box, nbands: int, boxes: Sequence[Box],
                  *renders: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Mosaic cube renders onto one output tile with the overlap ``rule`` ('last' | 'mean').

    boxes[i]: where renders[i] (values (nbands, h, w), saturated (h, w)) lies in the output grid;
    renders in capture order. Returns values (nbands, tile h, tile w) float32, saturated (h, w) bool.
    """
    if len(boxes) != len(renders):
        raise ValueError(f"{len(boxes)} boxes for {len(renders)} renders")
    mosaic = make_rule(rule, nbands, tile[2], tile[3])
    for values, saturated, tr, tc in _tile_parts(tile, boxes, renders):
        mosaic.feed(values, saturated, tr, tc)
    return mosaic.result()


def write_values_task(store: MosaicStore, band0: int, tile: Box, assembled: tuple[np.ndarray, np.ndarray],
                      saturated_before: np.ndarray | None = None) -> np.ndarray:
    """Write an assembled tile's values into its own chunks.

    Returns the tile's saturation mask (h, w) bool OR ``saturated_before`` (earlier band groups).
    """
    values, saturated = assembled
    store.write_values(band0, tile[0], tile[1], values)
    return saturated if saturated_before is None else saturated | saturated_before


def assemble_write_task(store: MosaicStore, rule: str, band0: int, tile: Box, nbands: int,
                        boxes: Sequence[Box], saturated_before: np.ndarray | None,
                        *renders: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """:func:`assemble_task` and :func:`write_values_task` in one: mosaic the renders of one band
    group onto one output tile (one chunk wide) and write its chunks, band by band.

    For the 'last' rule no tile is built: each band is mosaicked by
    :func:`~archive.graph.mosaic.last_values` straight into this thread's reusable chunk buffer (the
    grid's outside part, zarr's padding of edge chunks, left NaN) and encoded from there; the other
    rules assemble the tile first. The written values and the returned saturation mask (h, w) bool
    (OR ``saturated_before``) are those of :func:`assemble_task` then :func:`write_values_task`.
    """
    if rule != "last":
        return write_values_task(store, band0, tile, assemble_task(rule, tile, nbands, boxes, *renders),
                                 saturated_before)
    if len(boxes) != len(renders):
        raise ValueError(f"{len(boxes)} boxes for {len(renders)} renders")
    if tile[0] % CHUNK or tile[1] % CHUNK or tile[2] > CHUNK or tile[3] > CHUNK:
        raise ValueError(f"tile {tile} is not one {CHUNK} px chunk")
    store.check_aligned(tile[2:], tile[0], tile[1])
    parts = _tile_parts(tile, boxes, renders)
    writer = store.chunk_writer()
    buffer = writer.buffer()
    row, col = tile[0] // CHUNK, tile[1] // CHUNK
    for b in range(nbands):
        last_values(buffer, [(values[b], tr, tc) for values, _, tr, tc in parts])
        writer.write(band0 + b, row, col, buffer)
    saturated = last_saturation(tile[2], tile[3], parts)
    return saturated if saturated_before is None else saturated | saturated_before


def write_saturated_task(store: MosaicStore, tile: Box, *masks: np.ndarray) -> int:
    """OR the saturation masks of one tile and write them; returns the saturated pixel count."""
    mask = np.zeros(tile[2:], bool)
    for m in masks:
        mask |= m
    store.write_saturated(tile[0], tile[1], mask)
    return int(mask.sum())
