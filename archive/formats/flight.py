"""Discover the cubes of a raw Resonon flight directory.

A cube ``<base>`` is the data file ``<base>.bil`` (or ``.bip``/``.bsq``) with its header
``<base>.bil.hdr``, navigation ``<base>.lcf`` and line times ``<base>.bil.times``. Cubes are
ordered by capture: the first ``.times`` value, ties broken by natural sort of the base name.
"""

from __future__ import annotations

import hashlib
import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from archive.errors import FormatError, InputError, MissingInputError
from archive.formats.times import first_time, read_times

__all__ = ["CubeFiles", "Flight", "discover_flight", "natural_key"]

_DATA_SUFFIXES = (".bil", ".bip", ".bsq")


@dataclass(frozen=True)
class CubeFiles:
    """The four files of one cube."""

    base: str     #: e.g. "flight_Pika_L_3"
    data: Path    #: <base>.bil (or .bip/.bsq)
    header: Path  #: <base>.bil.hdr
    lcf: Path     #: <base>.lcf
    times: Path   #: <base>.bil.times


@dataclass(frozen=True)
class Flight:
    """A flight directory: its complete cubes in capture order and its calibration, if any."""

    directory: Path
    cubes: tuple[CubeFiles, ...]
    calibration: Path | None


def natural_key(name: str) -> tuple:
    """Sort key treating digit runs as numbers: ``x_2`` < ``x_10``."""
    return tuple((0, int(part), "") if part.isdigit() else (1, 0, part.lower())
                 for part in re.split(r"(\d+)", name) if part)


_KINDS = {"header": "ENVI header", "lcf": "navigation (.lcf)", "times": "line times (.times)"}


def _cube_files(data: Path) -> tuple[CubeFiles | None, list[tuple[str, Path]]]:
    """The cube of data file ``data``, or None and the missing ``(kind, path)`` pairs."""
    base = data.name[: -len(data.suffix)]
    header = data.with_name(data.name + ".hdr")
    if not header.is_file() and data.with_suffix(".hdr").is_file():
        header = data.with_suffix(".hdr")
    files = {"header": header, "lcf": data.with_name(base + ".lcf"),
             "times": data.with_name(data.name + ".times")}
    missing = [(_KINDS[kind], p) for kind, p in files.items() if not p.is_file()]
    if missing:
        return None, missing
    return CubeFiles(base, data, header, files["lcf"], files["times"]), []


def _check_distinct(cubes: list[CubeFiles]) -> None:
    """InputError naming both cubes when two cubes hold the same capture (the same ``.times``
    values: the same lines recorded twice, e.g. a cube copied under another name)."""
    seen: dict[tuple[int, bytes], CubeFiles] = {}
    for cube in cubes:
        times = read_times(cube.times)  # parsed values: a reformatted copy is still the same capture
        key = (len(times), hashlib.sha256(np.ascontiguousarray(times, "<f8").tobytes()).digest())
        if key in seen:
            other = seen[key]
            raise InputError(cube.data.parent, f"cubes {other.base} and {cube.base} hold the same capture "
                             f"(identical line times in {other.times.name} and {cube.times.name})",
                             "remove the duplicated cube (a copy under another name) from the directory")
        seen[key] = cube


def discover_flight(directory: str | os.PathLike) -> Flight:
    """Find every cube of ``directory`` and the single ``*.icp`` calibration (None if absent).

    Raises :class:`MissingInputError` for a missing directory or a cube missing one of its files
    (the message names the cube and the file), :class:`FormatError` for a header without data file
    or two data files with the same base, and :class:`InputError` when there are no cubes or more
    than one ``.icp``.
    """
    directory = Path(directory)
    if not directory.exists():
        raise MissingInputError(directory, "flight directory")
    if not directory.is_dir():
        raise InputError(directory, "is not a directory", "pass the folder holding the .bil cubes")
    entries = sorted((p for p in directory.iterdir() if p.is_file()), key=lambda p: p.name)
    data_files = [p for p in entries if p.suffix.lower() in _DATA_SUFFIXES]
    seen: dict[str, Path] = {}
    for data in data_files:
        base = data.name[: -len(data.suffix)]
        if base in seen:
            raise FormatError(directory, f"cube {base} has two data files: {seen[base].name} and "
                              f"{data.name}", "keep one of them")
        seen[base] = data
    for hdr in entries:
        name = hdr.name.lower()
        if name.endswith(".hdr") and Path(name[:-4]).suffix in _DATA_SUFFIXES \
                and not hdr.with_suffix("").is_file():
            raise FormatError(hdr, f"header without its data file {hdr.with_suffix('').name}",
                              "copy the data file or remove the header")
    cubes: list[CubeFiles] = []
    incomplete: list[tuple[str, list[tuple[str, Path]]]] = []
    for data in data_files:
        cube, missing = _cube_files(data)
        if cube is None:
            incomplete.append((data.name[: -len(data.suffix)], missing))
        else:
            cubes.append(cube)
    if incomplete:
        base, missing = incomplete[0]
        kind, path = missing[0]
        also = [p.name for _, p in missing[1:]]
        fix = "every cube needs <base>.bil, <base>.bil.hdr, <base>.lcf and <base>.bil.times"
        if also:
            fix += f"; {base} also lacks {', '.join(also)}"
        if len(incomplete) > 1:
            fix += "; other incomplete cubes: " + ", ".join(b for b, _ in incomplete[1:6])
            fix += " ..." if len(incomplete) > 6 else ""
        raise MissingInputError(path, f"{kind} of cube {base}", fix)
    if not cubes:
        raise InputError(directory, "no cubes found (no *.bil, *.bip or *.bsq data files)",
                         "pass a raw flight directory")
    cubes.sort(key=lambda c: (first_time(c.times), natural_key(c.base)))
    _check_distinct(cubes)
    icps = [p for p in entries if p.suffix.lower() == ".icp"]
    if len(icps) > 1:
        raise InputError(directory, f"{len(icps)} calibration files: "
                         f"{', '.join(p.name for p in icps)}", "pass --calibration to choose one")
    return Flight(directory, tuple(cubes), icps[0] if icps else None)
