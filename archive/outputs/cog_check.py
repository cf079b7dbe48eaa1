"""Checks of a Cloud-Optimized GeoTIFF's layout, read from the file's own structure.

:func:`file_layout` reads the header, the ghost structural metadata and every IFD's tile offsets;
:func:`check_cog` runs the checks of GDAL's ``validate_cloud_optimized_geotiff.py --full-check``
on every band. Used by the tests and the benchmarks on what :mod:`archive.outputs.tiff` writes.
"""

from __future__ import annotations

import mmap
import os
import struct
from itertools import pairwise

import numpy as np

from archive.outputs.tiff import TYPES

__all__ = ["check_cog", "file_layout"]

_ASCII_TYPE = 2   # TIFF field type ASCII


def file_layout(path: str | os.PathLike) -> dict:
    """What a COG check needs, read from the file's own structure (memory-mapped: ``data``): ``bigtiff``, ``ghost`` (the
    structural metadata text), ``ifds`` (offsets, in chain order) and per IFD ``width``,
    ``height``, ``subfile``, ``offsets`` and ``counts`` (tile offsets / byte counts, in TIFF order),
    ``planar``, ``compression``, ``predictor``."""
    with open(path, "rb") as f:
        data = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
    if data[:2] != b"II":
        raise ValueError(f"{path}: not a little-endian TIFF")
    version = struct.unpack_from("<H", data, 2)[0]
    bigtiff = version == 43
    first = struct.unpack_from("<Q", data, 8)[0] if bigtiff else struct.unpack_from("<I", data, 4)[0]
    ghost = ""
    start = 16 if bigtiff else 8
    if data[start:start + 30] == b"GDAL_STRUCTURAL_METADATA_SIZE=":
        size = int(data[start + 30:start + 36])
        line = data.find(b"\n", start) + 1
        ghost = data[line:line + size].decode("latin1")
    ifds, out = [], []
    offset = first
    sizes = {t: s for t, (_, s) in TYPES.items()}
    codes = {t: c for t, (c, _) in TYPES.items()}
    while offset:
        ifds.append(offset)
        if bigtiff:
            n = struct.unpack_from("<Q", data, offset)[0]
            pos, entry, inline = offset + 8, 20, 8
        else:
            n = struct.unpack_from("<H", data, offset)[0]
            pos, entry, inline = offset + 2, 12, 4
        tags = {}
        for k in range(n):
            p = pos + k * entry
            tag, kind = struct.unpack_from("<HH", data, p)
            count = struct.unpack_from("<Q" if bigtiff else "<I", data, p + 4)[0]
            nbytes = sizes.get(kind, 1) * count
            vp = p + (12 if bigtiff else 8)
            if nbytes > inline:
                vp = struct.unpack_from("<Q" if bigtiff else "<I", data, vp)[0]
            if kind in codes and kind != _ASCII_TYPE:
                tags[tag] = np.frombuffer(data, f"<{codes[kind]}", count, vp)
            else:
                tags[tag] = data[vp:vp + nbytes]
        offset = struct.unpack_from("<Q" if bigtiff else "<I", data, pos + n * entry)[0]
        out.append({"width": int(tags[256][0]), "height": int(tags[257][0]),
                    "subfile": int(tags.get(254, [0])[0]), "offsets": np.asarray(tags.get(324, []), np.int64),
                    "counts": np.asarray(tags.get(325, []), np.int64), "planar": int(tags.get(284, [1])[0]),
                    "compression": int(tags[259][0]), "predictor": int(tags.get(317, [1])[0]),
                    "samples": int(tags.get(277, [1])[0]), "tile": (int(tags[323][0]), int(tags[322][0]))})
    return {"bigtiff": bigtiff, "ghost": ghost, "ifds": ifds, "images": out, "size": len(data), "data": data}


def check_cog(path: str | os.PathLike) -> list[str]:
    """Errors of the COG layout of ``path`` (empty when valid): the checks of GDAL's
    ``validate_cloud_optimized_geotiff.py`` with ``--full-check``, done on every band: ghost
    metadata right after the header, the main IFD right after it, IFDs before any tile data and in
    order of decreasing size, tile data from the smallest overview to the full resolution, tiles
    row-major (band after band), each tile's size leader and repeated trailer."""
    layout = file_layout(path)
    errors: list[str] = []
    raw = layout["data"]
    ghost = layout["ghost"]
    if "LAYOUT=IFDS_BEFORE_DATA" not in ghost:
        errors.append("no GDAL structural metadata with LAYOUT=IFDS_BEFORE_DATA after the header")
    start = 16 if layout["bigtiff"] else 8
    expected = start + len(f"GDAL_STRUCTURAL_METADATA_SIZE={0:06d} bytes\n") + len(ghost)
    expected += expected % 2
    if layout["ifds"][0] != expected:
        errors.append(f"main IFD at {layout['ifds'][0]}, expected {expected}")
    images = layout["images"]
    if any(b < a for a, b in pairwise(layout["ifds"])):
        errors.append("IFDs are not in increasing offset order")
    for a, b in pairwise(images):
        if b["width"] > a["width"] or b["height"] > a["height"] or b["subfile"] != 1:
            errors.append("overviews are not reduced-resolution images of decreasing size")
    first_data = min(int(im["offsets"].min()) for im in images)
    if first_data < max(layout["ifds"]):
        errors.append("tile data before the last IFD")
    firsts = [int(im["offsets"][0]) for im in images]
    if any(firsts[i] < firsts[i + 1] for i in range(len(firsts) - 1)):
        errors.append("tile data not ordered from the smallest overview to the full resolution")
    lasts = [int((im["offsets"] + im["counts"]).max()) for im in images]
    if any(lasts[i + 1] > firsts[i] for i in range(len(images) - 1)):
        errors.append("levels' tile data overlap")
    for li, im in enumerate(images):
        offs, cnts = im["offsets"], im["counts"]
        if "BLOCK_ORDER=ROW_MAJOR" in ghost and np.any(np.diff(offs) < 0):
            errors.append(f"image {li}: tiles not in row-major (band after band) order")
        for o, n in zip(offs.tolist(), cnts.tolist()):
            if struct.unpack_from("<I", raw, o - 4)[0] != n:
                errors.append(f"image {li}: tile at {o}: wrong size leader")
                break
            if n >= 4 and raw[o + n - 4:o + n] != raw[o + n:o + n + 4]:
                errors.append(f"image {li}: tile at {o}: wrong trailer")
                break
    return errors

