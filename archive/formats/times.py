"""Resonon ``.times`` files: one exposure time per image line, seconds of the camera clock.

The clock is relative (not GPS); only differences matter (see DESIGN section 2). The final newline
is optional.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from archive.errors import FormatError, InputError, MissingInputError
from archive.files import write_atomic

__all__ = ["first_time", "read_times", "write_times"]


def _lines(path: Path) -> list[str]:
    if not path.is_file():
        raise MissingInputError(path, "line times file (.times)")
    return path.read_bytes().decode("utf-8-sig", errors="replace").splitlines()


def _parse(path: Path, number: int, line: str) -> float:
    text = line.strip()
    if not text:
        raise FormatError(path, f"line {number}: empty line", "one time value per image line")
    value = _number(text)
    if value is None:
        raise FormatError(path, f"line {number}: {text!r} is not a number")
    if not math.isfinite(value):
        raise FormatError(path, f"line {number}: value {text!r} is not finite")
    return value


def _number(text: str) -> float | None:
    """``text`` as a float, None when it is not a number."""
    try:
        return float(text)
    except ValueError:
        return None


def read_times(path: str | os.PathLike, expected_lines: int | None = None) -> np.ndarray:
    """Read a ``.times`` file as ``(lines,)`` float64 seconds of the camera clock.

    Raises :class:`FormatError` naming the file and line for an empty file, a non-numeric or
    non-finite value, a value that does not increase, or (with ``expected_lines``) a count that
    differs from the cube's line count, in either direction ("N times for M lines").
    """
    path = Path(path)
    lines = _lines(path)
    while lines and not lines[-1].strip():
        lines.pop()
    if not lines:
        raise FormatError(path, "no line times (empty file)")
    values = np.empty(len(lines), dtype=np.float64)
    for i, line in enumerate(lines):
        values[i] = _parse(path, i + 1, line)
        if i and values[i] <= values[i - 1]:
            raise FormatError(path, f"line {i + 1}: time {line.strip()} does not increase "
                              f"(previous {lines[i - 1].strip()})")
    if expected_lines is not None and len(values) != expected_lines:
        raise FormatError(path, f"{len(values)} times for {expected_lines} lines",
                          "the .times file needs exactly one value per image line of the cube")
    return values


def first_time(path: str | os.PathLike) -> float:
    """The first value of a ``.times`` file (s), reading only until the first non-blank line."""
    path = Path(path)
    if not path.is_file():
        raise MissingInputError(path, "line times file (.times)")
    with open(path, encoding="utf-8-sig", errors="replace") as f:
        for number, line in enumerate(f, start=1):
            if line.strip():
                return _parse(path, number, line)
    raise FormatError(path, "no line times (empty file)")


def write_times(path: str | os.PathLike, times: np.ndarray) -> None:
    """Write ``times`` ``(lines,)`` s, one per line with 9 decimals (sub-microsecond round trip),
    final newline included. Written to a temporary name, then renamed."""
    path = Path(path)
    values = np.asarray(times, dtype=np.float64)
    if values.ndim != 1 or values.size == 0:
        raise InputError(path, f"times must be a non-empty 1-D array, got shape {values.shape}")
    if not np.all(np.isfinite(values)):
        raise InputError(path, "times contain NaN or inf")
    write_atomic(path, "".join(f"{v:.9f}\n" for v in values).encode("ascii"))
