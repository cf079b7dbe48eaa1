"""A test helper that writes a finished (simulated) flight into a folder as a Resonon recorder does
(DESIGN 12): cube after cube, the ``.bil`` growing block by block at the camera's line rate, the
``.bil.times`` and ``.lcf`` growing with it (the ``.lcf`` rows up to the time of the last line
written), and the header ``.bil.hdr`` written last, when the cube closes. The folder's other files
(the calibration ``.icp``) are there from the start, as a recorder's setup leaves them.

Faults a real recorder has: ``stop_after`` (the recorder dies in that cube, leaving a truncated
``.bil`` without header that never completes) and ``image_set`` (the cubes written under another
image set name: a recorder restarted mid-flight names a new set).
"""

from __future__ import annotations

import shutil
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from archive.formats.envi import read_header
from archive.formats.flight import discover_flight
from archive.formats.times import read_times


@dataclass(frozen=True)
class Closed:
    """A cube the replay closed: its base name, lines, and when its header was complete (time.time())."""

    base: str
    lines: int
    closed: float


def _rows(path: Path) -> list[str]:
    return [line for line in path.read_text().splitlines() if line.strip()]


def replay(source: Path, folder: Path, *, rate: float | None = None, speed: float = 1.0, block_lines: int = 25,
           cubes: slice = slice(None), stop_after: tuple[int, float] | None = None, image_set: str | None = None,
           extras: bool = True, gap_s: float = 0.0) -> list[Closed]:
    """Write the cubes ``cubes`` (capture order) of flight ``source`` into ``folder`` as a recorder
    would, at ``rate`` lines a second (default: the header's framerate) sped up ``speed`` times, in
    blocks of ``block_lines`` lines; ``gap_s`` seconds between two cubes (a recorder's cube switch).
    ``stop_after=(k, fraction)``: the recorder dies after writing that fraction of the k-th cube
    written (no header; nothing after it). ``image_set``: the cubes' names with this image set instead
    (``sim_Pika_L_3`` -> ``<image_set>_3``). Returns the cubes closed, in order."""
    folder.mkdir(parents=True, exist_ok=True)
    flight = discover_flight(source)
    if extras:
        for p in sorted(source.iterdir()):
            if p.is_file() and p.suffix.lower() in (".icp", ".dcp"):
                shutil.copyfile(p, folder / p.name)
    closed = []
    for k, cube in enumerate(flight.cubes[cubes]):
        base = cube.base if image_set is None else f"{image_set}_{cube.base.rsplit('_', 1)[-1]}"
        header = read_header(cube.header)
        line_bytes = header.samples * header.bands * header.dtype.itemsize
        lines = header.lines
        times = read_times(cube.times)
        times_rows = _rows(cube.times)
        lcf_rows = _rows(cube.lcf)
        lcf_t = np.array([float(r.split()[0]) for r in lcf_rows])
        per_line = 1.0 / (rate or header.framerate or 249.0) / speed
        last = lines if stop_after is None or stop_after[0] != k else max(1, int(lines * stop_after[1]))
        start = time.monotonic()
        written_nav = 0
        with open(cube.data, "rb") as src, open(folder / f"{base}.bil", "wb") as bil, \
                open(folder / f"{base}.bil.times", "w") as tf, open(folder / f"{base}.lcf", "w") as lf:
            for first in range(0, last, block_lines):
                stop = min(last, first + block_lines)
                bil.write(src.read((stop - first) * line_bytes))
                tf.write("".join(r + "\n" for r in times_rows[first:stop]))
                upto = lcf_t[0] + (times[stop - 1] - times[0])
                nav_stop = len(lcf_rows) if stop == lines else int(np.searchsorted(lcf_t, upto, side="right"))
                lf.write("".join(r + "\n" for r in lcf_rows[written_nav:nav_stop]))
                written_nav = max(written_nav, nav_stop)
                for f in (bil, tf, lf):
                    f.flush()
                delay = start + stop * per_line - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
        if last < lines:   # the recorder died in this cube: no header, ever
            return closed
        text = cube.header.read_text()
        hdr = folder / f"{base}.bil.hdr"
        with open(hdr, "w") as f:   # the header last, in two writes as a recorder may (never renamed into place)
            f.write(text[: len(text) // 2])
            f.flush()
            f.write(text[len(text) // 2:])
        closed.append(Closed(base, lines, time.time()))
        if gap_s:
            time.sleep(gap_s / speed)
    return closed
