"""Folders of links that hold exactly one cube, or exactly one flight's complete cubes, of a recorder
folder (which may also hold cubes being written, cubes that never completed and other image sets).

A staged cube is what the viewer serves as a raw flight while the flight records (it never changes:
a cube written over gets a new staged folder); a staged flight is what ``archive ingest`` reads when
the recorder folder itself is not exactly that flight. Each is made under a temporary name and renamed
into place (:func:`archive.files.replace_path`), so a reader never sees half of one. The links are
symbolic (the recorder folder is often another file system: a USB disk, a network mount); the files
ingest records are named by their base names, so a staged flight's collection holds what an ingest
of a folder of those files holds.
"""

from __future__ import annotations

import os
import re
import shutil
import uuid
from collections.abc import Iterable
from pathlib import Path

from archive.files import replace_path
from archive.watch.cubes import DATA_SUFFIXES, cube_files

__all__ = ["flight_extras", "safe_name", "stage_links"]


def safe_name(text: str) -> str:
    """``text`` as one file-name component ([A-Za-z0-9._-], never empty, never hidden)."""
    return re.sub(r"[^A-Za-z0-9._-]+", "_", text).strip("._") or "flight"


def flight_extras(folder: Path, cube_names: Iterable[str]) -> list[Path]:
    """The files of ``folder`` that belong to no cube (a calibration ``*.icp``, the sky
    spectrometer's ``*.dcp`` and spectra, a trajectory, the navigation sidecar): ``cube_names`` are the
    base names of every cube there, whatever its flight or state."""
    bases = set(cube_names)
    found = []
    for entry in sorted(os.scandir(folder), key=lambda e: e.name):
        if not entry.is_file() or entry.name.startswith("."):
            continue
        name = entry.name
        stem = name
        for suffix in (".hdr", ".times", ".lcf"):
            if stem.lower().endswith(suffix):
                stem = stem[: -len(suffix)]
                break
        for suffix in DATA_SUFFIXES:
            if stem.lower().endswith(suffix):
                stem = stem[: -len(suffix)]
        if stem in bases or Path(name).suffix.lower() in DATA_SUFFIXES:
            continue
        found.append(Path(entry.path))
    return found


def stage_links(target: Path, data_files: Iterable[Path], extras: Iterable[Path] = ()) -> Path:
    """Make folder ``target`` hold a symbolic link to each cube file of ``data_files`` (data, header,
    times, navigation) and to each of ``extras``, replacing what ``target`` held; returns ``target``."""
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = target.with_name(f".{target.name}.{uuid.uuid4().hex[:8]}.tmp")
    tmp.mkdir()
    try:
        for data in data_files:
            for path in cube_files(Path(data)):
                os.symlink(os.path.abspath(path), tmp / path.name)
        for path in extras:
            os.symlink(os.path.abspath(path), tmp / Path(path).name)
        replace_path(tmp, target)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return target
