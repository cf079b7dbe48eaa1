"""Writing a file whole or not at all: to a temporary name beside it, then renamed into place.

The lowest layer of the package (imports nothing from it): raw formats, sinks, the COG spool and the
catalog all write through :func:`write_atomic`.
"""

from __future__ import annotations

import os
import uuid
from collections.abc import Iterable

__all__ = ["write_atomic"]


def write_atomic(path: str | os.PathLike, parts: Iterable[bytes | memoryview] | bytes) -> None:
    """Write ``parts`` (bytes-like objects, or one) to ``path``: into a temporary file in the same
    folder (unique per call, so concurrent writers of one path never share it), renamed over ``path``
    when complete; on any error the temporary is removed and ``path`` is left as it was."""
    path = os.fspath(path)
    tmp = f"{path}.{uuid.uuid4().hex}.partial"
    try:
        with open(tmp, "wb") as f:
            if isinstance(parts, (bytes, bytearray, memoryview)):
                f.write(parts)
            else:
                f.writelines(parts)
        os.replace(tmp, path)
    except BaseException:
        try:
            os.remove(tmp)
        except OSError:
            pass
        raise
