"""When a cube a recorder writes is complete, and which flight (image set) it belongs to.

A Resonon recorder writes ``<base>.bil`` block by block, ``<base>.bil.times`` and ``<base>.lcf`` with
it, and the header ``<base>.bil.hdr`` (``lines = N``) when the cube closes (DESIGN 12). A cube is
*whole* here when its header parses and the data file has exactly the header's size, the ``.times``
exactly ``lines`` rows and the ``.lcf`` at least two rows; it is *complete* once whole and its files'
sizes and times have not changed for a settle interval (:mod:`archive.watch.follow` decides that).
Nothing here reads pixels.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

from archive.errors import ArchiveError
from archive.formats.envi import read_header
from archive.formats.lcf import read_lcf
from archive.formats.times import read_times

__all__ = ["DATA_SUFFIXES", "CubeCheck", "Signature", "check_cube", "cube_files", "image_set", "signature"]

DATA_SUFFIXES = (".bil", ".bip", ".bsq")

#: (size, mtime_ns) of each of a cube's files that exists, in the order of :func:`cube_files`, None
#: for a file not there (yet).
Signature = tuple


def image_set(base: str) -> str:
    """The image set (the flight) of a cube base name: the name without its trailing cube number
    (``Juvika_June2022_Pika_L_12`` -> ``Juvika_June2022_Pika_L``); a name without one is its own."""
    found = re.match(r"^(.*?)[_-]?(\d+)$", base)
    return found.group(1) if found and found.group(1) else base


def cube_files(data: Path) -> tuple[Path, Path, Path, Path]:
    """(data, header, times, lcf) paths of the cube whose data file is ``data`` (the header as
    ``<base>.bil.hdr``, else ``<base>.hdr`` when only that one exists)."""
    base = data.name[: -len(data.suffix)]
    header = data.with_name(data.name + ".hdr")
    if not header.exists() and data.with_suffix(".hdr").exists():
        header = data.with_suffix(".hdr")
    return data, header, data.with_name(data.name + ".times"), data.with_name(base + ".lcf")


def signature(data: Path) -> Signature:
    """The sizes and modification times of a cube's files (None for a missing one): a cube whose
    signature holds still for the settle interval has stopped growing."""
    found = []
    for path in cube_files(data):
        try:
            st = os.stat(path)
        except OSError:
            found.append(None)
        else:
            found.append((st.st_size, st.st_mtime_ns))
    return tuple(found)


@dataclass(frozen=True)
class CubeCheck:
    """What one look at a cube found: ``whole`` (header written, every file agrees with it), else
    ``why`` it is not (one phrase naming the file); ``lines`` (the header's, 0 without one)."""

    whole: bool
    why: str
    lines: int = 0
    samples: int = 0
    bands: int = 0


def check_cube(data: Path) -> CubeCheck:
    """Whether the cube of data file ``data`` is whole now (see the module docstring); reads the
    header, the ``.times`` and the ``.lcf`` (small files), never the pixels."""
    data, header, times, lcf = cube_files(data)
    if not header.exists():
        return CubeCheck(False, f"no header {header.name} yet (the recorder writes it when the cube closes)")
    try:
        h = read_header(header)
    except (ArchiveError, OSError, ValueError) as exc:
        return CubeCheck(False, f"header {header.name} does not parse ({_short(exc)})")
    try:
        size = os.path.getsize(data)
    except OSError:
        return CubeCheck(False, f"{data.name} is gone", h.lines, h.samples, h.bands)
    if size != h.data_size:
        return CubeCheck(False, f"{data.name} holds {size} bytes, its header says {h.data_size} "
                         f"({h.lines} lines x {h.samples} samples x {h.bands} bands)", h.lines, h.samples, h.bands)
    for path, what in ((times, "line times"), (lcf, "navigation")):
        if not path.exists():
            return CubeCheck(False, f"no {what} {path.name}", h.lines, h.samples, h.bands)
    try:
        rows = len(read_times(times))
    except (ArchiveError, OSError, ValueError) as exc:
        return CubeCheck(False, f"{times.name} does not parse ({_short(exc)})", h.lines, h.samples, h.bands)
    if rows != h.lines:
        return CubeCheck(False, f"{times.name} has {rows} rows, the header says {h.lines} lines",
                         h.lines, h.samples, h.bands)
    try:
        nav = read_lcf(lcf)
    except (ArchiveError, OSError, ValueError) as exc:
        return CubeCheck(False, f"{lcf.name} does not parse ({_short(exc)})", h.lines, h.samples, h.bands)
    if len(nav) < 2:
        return CubeCheck(False, f"{lcf.name} has {len(nav)} rows", h.lines, h.samples, h.bands)
    return CubeCheck(True, "", h.lines, h.samples, h.bands)


def _short(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return text if len(text) <= 160 else text[:157] + "..."
