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
#: 2: the dn chunks' checksum algorithm is recorded (:data:`CHECKSUM_ATTR`; BLAKE3 by default). Stores of
#: version 1 (sha256, ``dn_sha256``) are read and verified as they are.
FORMAT_VERSION = 2
COMPLETE = "archive:complete"
NAV_COLUMNS = ("time", "roll", "pitch", "yaw", "lon", "lat", "alt")
#: ``archive ingest --compression NAME``: the dn chunks' Blosc codec. Measured on paper-shape DN (12 bits
#: in uint16, 1000 x 900 per chunk, one thread; bench/RESULTS.md "Ingest at the disk's speed"):
#: lz4 9 + bit-shuffle ~2.2 ms a chunk, ratio 1.80 (fast, the default: ingest then waits for the disk, not
#: the CPU); zstd 3 + bit-shuffle ~7 ms, ratio 1.96 (small: 8 % fewer bytes for 3x the CPU; the codec
#: of every store before issue 45).
DN_COMPRESSIONS = {
    "fast": {"cname": "lz4", "clevel": 9, "shuffle": "bitshuffle"},
    "small": {"cname": "zstd", "clevel": 3, "shuffle": "bitshuffle"},
}
DEFAULT_DN_COMPRESSION = "fast"
DN_CODEC = DN_COMPRESSIONS[DEFAULT_DN_COMPRESSION]
SMALL_CODEC = {"cname": "zstd", "clevel": 5, "shuffle": "shuffle"}
#: Per-chunk checksums of dn a store may record (``archive ingest --checksum``): BLAKE3 (the default, ~3.5x
#: faster than sha256 here and as collision-proof) or sha256 (where a policy asks for it; every store of
#: format 1). The group attribute :data:`CHECKSUM_ATTR` names it and the table is ``dn_<algorithm>``.
CHECKSUMS = ("blake3", "sha256")
DEFAULT_CHECKSUM = "blake3"
CHECKSUM_ATTR = "archive:dn_checksum"


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


def _hasher(algorithm: str):
    """A new hash object of ``algorithm`` (one of :data:`CHECKSUMS`); ValueError for another name."""
    if algorithm == "sha256":
        return hashlib.sha256()
    if algorithm == "blake3":
        import blake3

        return blake3.blake3()   # one thread: ingest's tasks already keep every core busy
    raise ValueError(f"unknown checksum algorithm {algorithm!r} (known: {', '.join(CHECKSUMS)})")


def file_digest(path: str | os.PathLike, algorithm: str = "sha256", block: int = 1 << 22) -> str:
    """Hex digest (``algorithm``: one of :data:`CHECKSUMS`) of a file, read in 4 MiB blocks into one buffer."""
    h = _hasher(algorithm)
    buffer = bytearray(block)
    view = memoryview(buffer)
    with open(path, "rb", buffering=0) as f:
        while n := f.readinto(buffer):
            h.update(view[:n])
    return h.hexdigest()


def sha256_file(path: str | os.PathLike, block: int = 1 << 22) -> str:
    """Hex sha256 of a file, read in 4 MiB blocks."""
    return file_digest(path, "sha256", block)


def chunk_digest(data: np.ndarray, algorithm: str = "sha256") -> bytes:
    """32-byte digest (``algorithm``: one of :data:`CHECKSUMS`) of an array's bytes in C order, little
    endian (the recorded chunk checksum)."""
    a = np.ascontiguousarray(data)
    a = np.ascontiguousarray(a.astype(a.dtype.newbyteorder("<"), copy=False))
    h = _hasher(algorithm)
    h.update(a.reshape(-1).view(np.uint8))   # no copy of the bytes
    return h.digest()


def dn_checksum(attrs: dict) -> str:
    """The dn chunks' checksum algorithm a store's attributes record (none recorded: sha256, format 1)."""
    return str(attrs.get(CHECKSUM_ATTR) or "sha256")


def digest_table(algorithm: str) -> str:
    """Name of the array of a store's per-chunk dn digests for ``algorithm`` ([band, chunk, 32] uint8)."""
    return f"dn_{algorithm}"


def array_digest(data: np.ndarray) -> str:
    return chunk_digest(np.asarray(data)).hex() + f":{np.asarray(data).dtype.str}:{list(np.shape(data))}"


def chunk_lines_for(cube_lines: Sequence[int]) -> int:
    """Line chunk length: the most common cube length, ties broken by the longest."""
    counts = Counter(int(n) for n in cube_lines)
    return max(counts, key=lambda n: (counts[n], n))



def chunk_path(store: Path, band: int, chunk: int) -> Path:
    """File (or object, for a URL) of dn chunk (band, chunk) in a Zarr v3 store (default '/' chunk key encoding)."""
    return location(store) / "dn" / "c" / str(band) / str(chunk) / "0"

