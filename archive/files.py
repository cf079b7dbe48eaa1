"""Writing files and folders whole or not at all: to a temporary name beside the target, then renamed
into place.

The lowest layer of the package (imports nothing from it): raw formats, the collection store, the
output writers, the COG spool and the catalog all write through :func:`write_atomic` or
:func:`atomic_path`; outputs are moved into place (a folder replacing a folder included) by
:func:`replace_path`.
"""

from __future__ import annotations

import os
import shutil
import uuid
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path

__all__ = ["atomic_path", "path_exists", "remove_path", "replace_path", "write_atomic"]


def _temporary(path: str) -> str:
    """A temporary name beside ``path``, unique per call (concurrent writers of one path never share it)."""
    return f"{path}.{uuid.uuid4().hex}.partial"


def remove_path(path: str | os.PathLike) -> None:
    """Delete a file, link or directory tree; silent when absent."""
    path = Path(path)
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        try:
            path.unlink()
        except FileNotFoundError:
            pass


def path_exists(path: str | os.PathLike) -> bool:
    """True when ``path`` exists (a dangling link counts)."""
    path = Path(path)
    return path.exists() or path.is_symlink()


@contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """A temporary path beside ``path`` to write (a file, by any writer: zip, numpy, text); renamed
    over ``path`` when the block completes. On any error the temporary is removed and ``path`` is
    left as it was. Nested blocks rename innermost first (write a data file inside its header's
    block: the header lands last)."""
    path = os.fspath(path)
    tmp = _temporary(path)
    try:
        yield Path(tmp)
        os.replace(tmp, path)
    except BaseException:
        remove_path(tmp)
        raise


def write_atomic(path: str | os.PathLike, parts: Iterable[bytes | memoryview] | bytes | str) -> None:
    """Write ``parts`` (bytes-like objects, or one; a str is written as UTF-8) to ``path`` through
    :func:`atomic_path`."""
    if isinstance(parts, str):
        parts = parts.encode("utf-8")
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        if isinstance(parts, (bytes, bytearray, memoryview)):
            f.write(parts)
        else:
            f.writelines(parts)


def replace_path(tmp: str | os.PathLike, final: str | os.PathLike) -> None:
    """Rename ``tmp`` (a file or a folder) to ``final``; an existing ``final`` (a folder too) is moved
    aside first and deleted only once ``tmp`` is in place (put back if the rename fails)."""
    tmp, final = Path(tmp), Path(final)
    old = None
    if path_exists(final):
        old = final.with_name(f".{final.name}.old-{os.getpid()}")
        remove_path(old)
        os.replace(final, old)
    try:
        os.replace(tmp, final)
    except BaseException:
        if old is not None:
            os.replace(old, final)
        raise
    if old is not None:
        remove_path(old)
