"""Writing a collection (ingest): the plan of a store, its layout, the dn chunk tasks, the
checksums and the completion marker (last), the writer's lock and the publish rename."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np
import zarr

from archive import storage
from archive.codecs import numcodecs_blosc
from archive.collection.layout import (CHECKSUM_ATTR, COMPLETE, DEFAULT_CHECKSUM, DN_CODEC, SMALL_CODEC, array_digest,
                                       blosc, chunk_digest, chunk_lines_for, chunk_path, digest_table, file_digest,
                                       location, root_json, zarr_target)
from archive.files import FileLock, replace_path, test_hold_calls, write_atomic
from archive.formats.envi import EnviCube

@dataclass(frozen=True)
class ChunkTask:
    """One dn chunk: band ``band``, lines [line0, line1) of the collection, assembled from
    ``pieces`` = ((data file, first cube line, end cube line), ...) in order."""

    band: int
    chunk: int
    line0: int
    line1: int
    pieces: tuple[tuple[str, int, int], ...]


def chunk_tasks(data_files: Sequence[str], cube_lines: Sequence[int], bands: int, chunk_lines: int) -> list[ChunkTask]:
    """Every (band, chunk) of a flight, band-major, and the cube line ranges that fill it."""
    offsets = np.concatenate([[0], np.cumsum(cube_lines)]).astype(int)
    total = int(offsets[-1])
    layout = []
    for k, l0 in enumerate(range(0, total, chunk_lines)):
        l1 = min(l0 + chunk_lines, total)
        pieces = []
        for c, path in enumerate(data_files):
            a, b = max(l0, offsets[c]), min(l1, offsets[c + 1])
            if a < b:
                pieces.append((str(path), int(a - offsets[c]), int(b - offsets[c])))
        layout.append((k, l0, l1, tuple(pieces)))
    return [ChunkTask(b, k, l0, l1, pieces) for b in range(bands) for k, l0, l1, pieces in layout]


@dataclass(frozen=True)
class ChunkGroup:
    """The dn chunks of bands [band0, band1) over lines [line0, line1) of the collection (line chunk
    ``chunk``), assembled from ``pieces`` = ((data file, first cube line, end cube line), ...) in order:
    one task reads those bands of those lines at once (one ``preadv`` per line: a run of bands of a BIL
    line, instead of one pass over the file per band) and writes each band's chunk."""

    band0: int
    band1: int
    chunk: int
    line0: int
    line1: int
    pieces: tuple[tuple[str, int, int], ...]


#: Bytes of raw DN one :class:`ChunkGroup` reads at most (its band run sized to it: 64 MiB, ~34 bands of a
#: 1000 x 900 uint16 cube; few enough tasks for a scheduler, little memory per task, long contiguous reads).
GROUP_BYTES = 64 << 20


def chunk_groups(data_files: Sequence[str], cube_lines: Sequence[int], bands: int, chunk_lines: int,
                 samples: int, itemsize: int, group_bytes: int = GROUP_BYTES) -> list[ChunkGroup]:
    """Every dn chunk of a flight in :class:`ChunkGroup` s, line chunk by line chunk (a cube's file read
    front to back by its groups), each of at most ``group_bytes`` of raw DN (at least one band); the
    bands split into runs of equal length (the last may be shorter)."""
    per_band = max(1, chunk_lines * samples * itemsize)
    runs = -(-bands // max(1, min(bands, group_bytes // per_band)))   # how many runs
    size = -(-bands // runs)
    groups = []
    for t in chunk_tasks(data_files, cube_lines, 1, chunk_lines):   # band 0 of each line chunk: the layout
        for b0 in range(0, bands, size):
            groups.append(ChunkGroup(b0, min(b0 + size, bands), t.chunk, t.line0, t.line1, t.pieces))
    return groups



@lru_cache(maxsize=64)
def _cube(path: str, size: int, mtime_ns: int) -> EnviCube:
    return EnviCube(path)


#: Test-only: ``ARCHIVE_TEST_HOLD_AFTER_CHUNKS=N`` makes an ingest stop (its chunk tasks wait until
#: the process is killed) once its store holds N dn chunks (kept from a resumed run or written), so
#: that a test kills it mid-store at a moment it controls (never set outside tests).
TEST_HOLD_AFTER_CHUNKS = "ARCHIVE_TEST_HOLD_AFTER_CHUNKS"


def write_chunk(store: str, task: ChunkTask, chunk_lines: int, resume: bool, codec: dict = DN_CODEC,
                checksum: str = "sha256") -> tuple[int, int, str]:
    """Dask task body: read one band of the raw cubes for ``task``, write it as one dn chunk, and
    return (band, chunk, hex digest of the chunk's values by ``checksum``); :func:`write_chunks` of one band."""
    group = ChunkGroup(task.band, task.band + 1, task.chunk, task.line0, task.line1, task.pieces)
    return write_chunks(store, group, chunk_lines, resume, codec, checksum)[0]


def write_chunks(store: str, group: ChunkGroup, chunk_lines: int, resume: bool, codec: dict = DN_CODEC,
                 checksum: str = "sha256") -> list[tuple[int, int, str]]:
    """Dask task body: read bands [band0, band1) of the raw cubes' lines of ``group`` (one ``preadv`` per
    line and piece), write each band as one dn chunk, and return [(band, chunk, hex digest of the chunk's
    values by ``checksum``), ...].

    A chunk is encoded here with the store's Blosc ``codec`` (bytes little endian + Blosc, the same bytes
    zarr writes, checked by the tests) and written under a temporary name then renamed, which runs the
    compression in this worker thread instead of zarr's event loop. An edge chunk is padded with the fill
    value 0 to ``chunk_lines`` lines, as Zarr stores it. With ``resume``, a chunk already on disk that
    decodes to the same values is kept. Memory: the group's raw DN (at most :data:`GROUP_BYTES`) and one
    chunk's encoding.
    """
    bands = list(range(group.band0, group.band1))
    parts = []
    for path, a, b in group.pieces:
        st = os.stat(path)
        parts.append(_cube(path, st.st_size, st.st_mtime_ns).bands(bands)[:, a:b])
    block = parts[0] if len(parts) == 1 else np.concatenate(parts, axis=1)
    blosc_codec = numcodecs_blosc(codec["cname"], codec["clevel"], codec["shuffle"])
    url = storage.is_url(store)
    out = []
    for i, band in enumerate(bands):
        test_hold_calls(TEST_HOLD_AFTER_CHUNKS)
        data = np.ascontiguousarray(block[i], dtype=block.dtype.newbyteorder("<"))
        out.append((band, group.chunk, _write_one(store, band, group.chunk, data, chunk_lines, resume, blosc_codec,
                                                   checksum, url)))
    return out


def _write_one(store: str, band: int, chunk: int, data: np.ndarray, chunk_lines: int, resume: bool, codec,
               checksum: str, url: bool) -> str:
    """Write one dn chunk (band, chunk) of (lines, samples) little-endian ``data``; its hex digest."""
    digest = chunk_digest(data, checksum)
    target = chunk_path(location(store), band, chunk)
    if resume and (url or target.is_file()):
        try:
            old = np.frombuffer(codec.decode(storage.read_bytes(target)), data.dtype)
            if chunk_digest(old[: data.size], checksum) == digest:
                return digest.hex()
        except Exception:  # noqa: BLE001 - a damaged chunk from a killed run is simply rewritten
            pass
    if data.shape[0] < chunk_lines:
        padded = np.zeros((chunk_lines, data.shape[1]), data.dtype)
        padded[: data.shape[0]] = data
        data = padded
    if url:   # one PUT, straight from this worker (no staging): atomic per object
        storage.write_bytes(target, codec.encode(data))
        return digest.hex()
    target.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(target, codec.encode(data))
    return digest.hex()


def hash_file_task(path: str, checksum: str = "sha256") -> tuple[str, str]:
    """Dask task body: (path, hex digest of the file by ``checksum``)."""
    return path, file_digest(path, checksum)


# ----------------------------------------------------------------------------------------------
# writing


@dataclass
class StorePlan:
    """Everything an ingest writes, prepared in memory before the archive is touched.

    arrays: small arrays by name; attrs: group attributes (without checksums and the marker);
    data_files: the cubes' data files in capture order; cube_lines, bands, samples, dtype: dn shape
    and type; sources: (path, size) of every raw file whose sha256 is recorded.
    """

    cid: str
    arrays: dict[str, np.ndarray]
    attrs: dict
    data_files: list[str]
    cube_lines: list[int]
    bands: int
    samples: int
    dtype: np.dtype
    sources: list[tuple[str, int]]
    dims: dict[str, tuple[str, ...]] = field(default_factory=dict)
    #: the dn chunks' Blosc codec ({cname, clevel, shuffle}: :data:`~archive.collection.layout.DN_COMPRESSIONS`)
    dn_codec: dict = field(default_factory=lambda: dict(DN_CODEC))
    #: the checksum of every dn chunk and raw source file (:data:`~archive.collection.layout.CHECKSUMS`)
    checksum: str = DEFAULT_CHECKSUM

    @property
    def chunk_lines(self) -> int:
        return chunk_lines_for(self.cube_lines)

    def token(self) -> str:
        """Identifies what is being written (sources, shapes, parameters, the small arrays' names: a
        partial store laid out by an older version without some array is not resumed), to resume safely."""
        text = json.dumps([self.cid, self.sources, self.cube_lines, self.bands, self.samples, self.dtype.str,
                           self.attrs.get("fov_deg"), self.attrs.get("ground_height"), self.dn_codec, self.checksum,
                           self.attrs.get("navigation_params"), sorted(self.arrays)], default=str)
        return hashlib.sha256(text.encode()).hexdigest()


def _create_arrays(store: Path, plan: StorePlan) -> None:
    # "w-", not "w": the store is new (open_partial removed any old one), and "w" makes zarr clear it,
    # which for a local store removes the folder it has just created and makes it again; a SIGKILL
    # in between left no partial store at all (seen once in CI: tests/test_collection.py's SIGKILL test)
    group = zarr.open_group(zarr_target(store, read_only=False), mode="w-", zarr_format=3)
    total = sum(plan.cube_lines)
    group.create_array(
        "dn", shape=(plan.bands, total, plan.samples), chunks=(1, plan.chunk_lines, plan.samples),
        dtype=plan.dtype, compressors=[blosc(plan.dn_codec)], fill_value=0,
        dimension_names=("band", "line", "sample"), config={"write_empty_chunks": True})
    for name, values in plan.arrays.items():
        a = group.create_array(name, shape=values.shape, chunks=values.shape or (1,), dtype=values.dtype,
                               compressors=[blosc(SMALL_CODEC)], fill_value=0,
                               dimension_names=plan.dims.get(name), config={"write_empty_chunks": True})
        a[...] = values


def _clean_stray_temporaries(store: Path) -> None:
    # zarr's LocalStore writes '<key>.<uuid>.partial' then renames; a SIGKILL can leave them.
    for p in store.rglob("*.partial"):
        if p.is_file():
            p.unlink()


def open_partial(partial: Path, plan: StorePlan) -> bool:
    """Prepare ``partial`` for writing ``plan``: reuse it when an earlier run of the same plan left
    it (returns True: resume), else create it afresh (returns False). For a URL, ``partial`` is the
    store's final prefix (S3 has no rename): its ``zarr.json`` says complete only once finished."""
    token = plan.token()
    url = storage.is_url(partial)
    if partial.exists():
        try:
            attrs = root_json(partial).get("attributes", {})
        except (OSError, ValueError):
            attrs = {}
        if attrs.get("archive:plan") == token and not (url and attrs.get(COMPLETE) is True):
            if not url:
                _clean_stray_temporaries(partial)
            return True
        if url:
            storage.delete(partial / "zarr.json")   # first: the old store stops being complete
            storage.delete_prefix(partial)
        else:
            shutil.rmtree(partial)
    if not url:
        partial.parent.mkdir(parents=True, exist_ok=True)
    _create_arrays(partial, plan)
    # Written after every array exists: a partial store carrying this token is fully laid out.
    group = zarr.open_group(zarr_target(partial, read_only=False), mode="r+")
    group.attrs.put({"archive:plan": token})
    return False


def finish_store(partial: Path, plan: StorePlan, chunk_digests: dict[tuple[int, int], str],
                 file_digests: dict[str, str]) -> None:
    """Record checksums (``chunk_digests``: (band, chunk) -> hex, ``file_digests``: path -> hex, both by
    ``plan.checksum``) and metadata, then the completion marker (last write)."""
    nchunks = -(-sum(plan.cube_lines) // plan.chunk_lines)
    table = np.zeros((plan.bands, nchunks, 32), np.uint8)
    for (b, k), hexd in chunk_digests.items():
        table[b, k] = np.frombuffer(bytes.fromhex(hexd), np.uint8)
    group = zarr.open_group(zarr_target(partial, read_only=False), mode="r+")
    a = group.create_array(digest_table(plan.checksum), shape=table.shape, chunks=table.shape, dtype=np.uint8,
                           compressors=[blosc(SMALL_CODEC)], fill_value=0, overwrite=True,
                           dimension_names=("band", "chunk", "byte"), config={"write_empty_chunks": True})
    a[...] = table
    attrs = dict(plan.attrs)
    attrs["sources"] = [{"name": attrs["source_names"][path], "size": size, plan.checksum: file_digests[path]}
                        for path, size in plan.sources]
    attrs[CHECKSUM_ATTR] = plan.checksum
    del attrs["source_names"]
    attrs["array_sha256"] = {name: array_digest(v) for name, v in sorted(plan.arrays.items())}
    attrs["archive:plan"] = plan.token()
    group.attrs.put(attrs)
    group.attrs.put({**attrs, COMPLETE: True})




def store_lock(store: str | os.PathLike, purpose: str) -> FileLock:
    """The exclusive lock of the collection ``store`` (``<id>.zarr.lock`` beside it, not yet taken):
    whoever writes the store (an ingest, its partial store included; ``calibrate --apply``) holds it,
    so that two writers of one id, in two processes or on two hosts, never share a partial store.
    ``purpose`` says what the holder does (shown to whoever waits)."""
    store = location(store)
    cid = store.name.removesuffix(".zarr")
    return FileLock(store.with_name(store.name + ".lock"), purpose, what=f"collection {cid}",
                    fix="wait for it to finish")


def publish(partial: Path, final: Path) -> None:
    """Rename the finished partial store to its final name (replacing an older store). In object
    storage the partial store IS the final one (its completion marker, written last, published it)."""
    if storage.is_url(final):
        if str(partial) != str(final):
            raise ValueError(f"{partial}: an object store's partial store must be its final prefix {final}")
        return
    replace_path(partial, final)

