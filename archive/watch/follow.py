"""The cubes of recorder folders over time: one state machine, driven by :meth:`Follower.scan`.

Every scan lists each folder's data files (``*.bil``, ``*.bip``, ``*.bsq``) and their files' sizes and
modification times (:func:`archive.watch.cubes.signature`), and turns what changed into events:

- a cube whose files have held still for ``settle`` seconds and are whole (:func:`check_cube`) is
  :class:`Complete`; a partly written cube is never one (its header comes last, its sizes must agree);
- a cube that is not whole and has not changed for ``stall`` seconds is :class:`Skipped`, once (a
  truncated ``.bil`` of a recorder that died); should it move again and become whole, it completes;
- a complete cube whose files change or vanish (a recorder that restarted and wrote over it) is
  :class:`Changed` (it is no longer complete until it holds still again and is whole);
- a folder that disappears (USB unplugged) is :class:`FolderGone`, once; :class:`FolderBack` when it
  returns (its cubes are looked at afresh).

Cubes belong to flights by folder and image set (:func:`archive.watch.cubes.image_set`): a new image
set name starts a new flight. Times are ``time.time()`` seconds. No threads, no I/O but ``stat`` and
the small files :func:`check_cube` reads.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

from archive.watch.cubes import DATA_SUFFIXES, CubeCheck, Signature, check_cube, image_set, signature

__all__ = ["Changed", "Complete", "CubeState", "FlightKey", "FolderBack", "FolderGone", "Follower", "Skipped",
           "flight_name"]

#: A flight: (its recorder folder, its image set name).
FlightKey = tuple


def flight_name(key: FlightKey) -> str:
    """How a flight is named in lines and in ``/api/live``: ``<folder name>/<image set>``."""
    return f"{Path(key[0]).name}/{key[1]}"


@dataclass
class CubeState:
    """One cube as followed: ``state`` is 'growing' (being written, or not looked at yet), 'complete'
    or 'skipped' (reported incomplete once); ``changed``: when its signature last changed (s)."""

    data: Path
    base: str
    flight: FlightKey
    seen: float
    changed: float
    sig: Signature
    state: str = "growing"
    check: CubeCheck | None = None
    closed: float | None = None   #: when it was found complete (s)
    reported: bool = False


@dataclass(frozen=True)
class Complete:
    cube: CubeState


@dataclass(frozen=True)
class Skipped:
    cube: CubeState
    why: str


@dataclass(frozen=True)
class Changed:
    cube: CubeState
    why: str


@dataclass(frozen=True)
class FolderGone:
    folder: Path
    cubes: tuple[CubeState, ...]   #: its complete cubes, no longer served


@dataclass(frozen=True)
class FolderBack:
    folder: Path


@dataclass
class Follower:
    """The cubes of ``folders``; ``settle``: seconds a whole cube's files must hold still before it is
    complete; ``stall``: seconds without change after which an incomplete cube is skipped."""

    folders: list[Path]
    settle: float = 0.5
    stall: float = 15.0
    cubes: dict[Path, CubeState] = field(default_factory=dict)
    gone: set[Path] = field(default_factory=set)

    def scan(self, now: float) -> list:
        """Look at every folder once; the events of what changed since the last scan, in order."""
        events: list = []
        for folder in self.folders:
            events += self._scan_folder(folder, now)
        return events

    def growing(self) -> bool:
        """Whether a cube is being written (or waits to be looked at): then scans should come often."""
        return any(c.state == "growing" for c in self.cubes.values())

    def flights(self) -> dict[FlightKey, list[CubeState]]:
        """Every flight seen and its cubes (all states), each in the order the cubes appeared."""
        found: dict[FlightKey, list[CubeState]] = {}
        for cube in sorted(self.cubes.values(), key=lambda c: (c.seen, c.base)):
            found.setdefault(cube.flight, []).append(cube)
        return found

    def _scan_folder(self, folder: Path, now: float) -> list:
        events: list = []
        try:
            names = [e.name for e in os.scandir(folder) if e.is_file()]
        except OSError:   # gone (unplugged, unmounted) or unreadable
            if folder not in self.gone:
                self.gone.add(folder)
                mine = [c for c in self.cubes.values() if c.data.parent == folder]
                for c in mine:
                    del self.cubes[c.data]
                events.append(FolderGone(folder, tuple(c for c in mine if c.state == "complete")))
            return events
        if folder in self.gone:
            self.gone.discard(folder)
            events.append(FolderBack(folder))
        present = set()
        for name in sorted(names):
            data = folder / name
            suffix = data.suffix.lower()
            if suffix not in DATA_SUFFIXES:
                continue
            present.add(data)
            sig = signature(data)
            cube = self.cubes.get(data)
            if cube is None:
                base = name[: -len(suffix)]
                cube = CubeState(data, base, (folder, image_set(base)), now, now, sig)
                self.cubes[data] = cube
            elif sig != cube.sig:
                cube.sig, cube.changed = sig, now
                if cube.state == "complete":
                    cube.state, cube.closed = "growing", None
                    events.append(Changed(cube, "its files changed after it was complete (a recorder that restarted "
                                                "and wrote over it?): looked at again"))
                elif cube.state == "skipped":
                    cube.state = "growing"
            if cube.state != "growing" or now - cube.changed < self.settle:
                continue
            cube.check = check_cube(data)
            if cube.check.whole and signature(data) == cube.sig:
                cube.state, cube.closed = "complete", now
                events.append(Complete(cube))
            elif not cube.check.whole and now - cube.changed >= self.stall:
                cube.state = "skipped"
                if not cube.reported:
                    cube.reported = True
                    events.append(Skipped(cube, f"incomplete for {now - cube.changed:.0f} s ({cube.check.why})"))
        for data in [d for d, c in self.cubes.items() if c.data.parent == folder and d not in present]:
            cube = self.cubes.pop(data)
            if cube.state == "complete":
                events.append(Changed(cube, "its data file is gone"))
        return events
