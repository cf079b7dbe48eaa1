"""The collection format's names and primitives: attribute names, codecs, the completion marker,
chunk paths and digests (see :mod:`archive.collection` for the layout)."""

from __future__ import annotations

import hashlib
import json
import os
from collections import Counter
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from zarr.codecs import BloscCodec

from archive import storage

FORMAT = "archive-collection"
FORMAT_VERSION = 1
COMPLETE = "archive:complete"
NAV_COLUMNS = ("time", "roll", "pitch", "yaw", "lon", "lat", "alt")
# Chosen from bench/RESULTS.md "Ingest codec": best ratio on 12-bit DN among fast decoders.
DN_CODEC = {"cname": "zstd", "clevel": 3, "shuffle": "bitshuffle"}
SMALL_CODEC = {"cname": "zstd", "clevel": 5, "shuffle": "shuffle"}


def blosc(spec: dict) -> BloscCodec:
    """The zarr Blosc codec of a codec spec (:data:`DN_CODEC`, :data:`SMALL_CODEC`)."""
    return BloscCodec(cname=spec["cname"], clevel=spec["clevel"], shuffle=spec["shuffle"])


def location(store: str | os.PathLike):
    """A store location as a path object: :class:`pathlib.Path`, or a UPath for an ``s3://`` URL."""
    return storage.location(store) if storage.is_url(store) else Path(store)


def zarr_target(store, read_only: bool = True):
    """What zarr opens for the store ``store`` (the path itself, or an obstore ObjectStore for a URL)."""
    return storage.zarr_store(store, read_only=read_only) if storage.is_url(store) else store


def root_json(store) -> dict:
    """The parsed root ``zarr.json`` of a store (OSError / ValueError when absent or unreadable)."""
    return json.loads(storage.read_bytes(location(store) / "zarr.json"))


def is_complete(store: str | os.PathLike) -> bool:
    """Whether ``store`` is a collection whose completion marker was written (reads only zarr.json)."""
    try:
        meta = root_json(store)
    except (OSError, ValueError):
        return False
    return isinstance(meta, dict) and (meta.get("attributes") or {}).get(COMPLETE) is True


def sha256_file(path: str | os.PathLike, block: int = 1 << 22) -> str:
    """Hex sha256 of a file, read in 4 MiB blocks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(block):
            h.update(chunk)
    return h.hexdigest()


def chunk_digest(data: np.ndarray) -> bytes:
    """sha256 of an array's bytes in C order, little endian (the recorded chunk checksum)."""
    a = np.ascontiguousarray(data)
    a = np.ascontiguousarray(a.astype(a.dtype.newbyteorder("<"), copy=False))
    return hashlib.sha256(a.reshape(-1).view(np.uint8).data).digest()   # no copy of the bytes


def array_digest(data: np.ndarray) -> str:
    return chunk_digest(np.asarray(data)).hex() + f":{np.asarray(data).dtype.str}:{list(np.shape(data))}"


def chunk_lines_for(cube_lines: Sequence[int]) -> int:
    """Line chunk length: the most common cube length, ties broken by the longest."""
    counts = Counter(int(n) for n in cube_lines)
    return max(counts, key=lambda n: (counts[n], n))



def chunk_path(store: Path, band: int, chunk: int) -> Path:
    """File (or object, for a URL) of dn chunk (band, chunk) in a Zarr v3 store (default '/' chunk key encoding)."""
    return location(store) / "dn" / "c" / str(band) / str(chunk) / "0"

