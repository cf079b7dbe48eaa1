"""Dn chunks written ahead, one cube at a time, for an ingest that comes later (``archive watch``).

While a recorder is still writing a flight, each cube that closes can already be encoded: if the
flight's cubes are all as long as this one (the usual case: the recorder closes a cube every N lines),
the collection's line chunk of that cube will be exactly the cube, band by band. :func:`write_cube_ahead`
writes those chunks, with the store's codec and checksum, into a folder laid out as a store's ``dn``
array (``AHEAD/dn/c/<band>/<chunk>/0``), and the checksums of the cube's four files, and returns the
record of what it wrote (:func:`record_cube` keeps it in ``AHEAD/cubes.json``).

When the flight is over, a plain ingest is run with ``prewritten=AHEAD`` (:func:`adopt`): the flight
is read and checked as always (its :class:`~archive.collection.StorePlan` is what a plain ingest
makes), and a chunk written ahead is *moved* into the partial store instead of being written again
only when it is what the plan would write there: the plan's line chunk ``k`` is exactly that cube's
lines (same data file, same size and modification time as when it was encoded, same chunk length,
codec and checksum), for every band. Anything else (a cube longer than the others, cubes out of
order, a file touched since) is written by the ingest as usual; so the collection is a plain ingest's,
byte for byte, whatever was written ahead. A raw file's checksum is reused the same way (same file,
size and time).
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import replace
from pathlib import Path

from archive.collection import StorePlan, chunk_groups, write_chunks
from archive.collection.layout import chunk_path, file_digest
from archive.files import write_atomic
from archive.formats.envi import EnviCube

__all__ = ["adopt", "current", "read_records", "record_cube", "write_cube_ahead"]

RECORDS = "cubes.json"


def _stamp(path: str | os.PathLike) -> tuple[str, int, int]:
    """(real path, size, modification time ns) of a file (a link followed)."""
    real = os.path.realpath(path)
    st = os.stat(real)
    return real, int(st.st_size), int(st.st_mtime_ns)


def write_cube_ahead(ahead: str | os.PathLike, files: tuple, chunk: int, chunk_lines: int, codec: dict,
                     checksum: str) -> dict:
    """Encode the cube whose files are ``files`` = (data, header, times, navigation) as line chunk
    ``chunk`` of a store of ``chunk_lines``-line chunks (the cube's lines <= ``chunk_lines``: a shorter
    cube is an edge chunk, padded as Zarr pads it), every band, into ``ahead``; checksum its files.
    Returns the record (JSON-able): the data file's stamp, the chunk, its lines and length, codec and
    checksum, every band's chunk digest (hex, by band), every file's digest, and the seconds it took. Memory: one group of bands of the cube (:data:`archive.collection.write.GROUP_BYTES`)."""
    started = time.monotonic()
    data = str(files[0])
    stamp = _stamp(data)
    h = EnviCube(data).header   # the sizes checked against the data file's
    lines = h.lines
    if not 0 < lines <= chunk_lines:
        raise ValueError(f"a cube of {lines} lines is not one chunk of {chunk_lines} lines")
    digests: dict[int, str] = {}
    for group in chunk_groups([data], [lines], h.bands, chunk_lines, h.samples, h.dtype.itemsize):
        for band, _, digest in write_chunks(str(ahead), replace(group, chunk=chunk), chunk_lines, False, codec,
                                            checksum):
            digests[band] = digest
    if _stamp(data) != stamp:
        raise OSError(f"{data} changed while it was encoded")
    hashed = {}
    for path in files:
        real, size, mtime = _stamp(path)
        hashed[real] = [size, mtime, file_digest(real, checksum)]
    return {"data": stamp[0], "size": stamp[1], "mtime_ns": stamp[2], "chunk": int(chunk), "lines": int(lines),
            "chunk_lines": int(chunk_lines), "codec": dict(codec), "checksum": checksum,
            "digests": [digests[b] for b in range(h.bands)], "files": hashed,
            "seconds": round(time.monotonic() - started, 3)}


def read_records(ahead: str | os.PathLike) -> dict[str, dict]:
    """The records of the cubes written ahead into ``ahead``, by base name ({} when none or unreadable:
    the ingest then writes everything)."""
    try:
        return json.loads((Path(ahead) / RECORDS).read_text())
    except (OSError, ValueError):
        return {}


def record_cube(ahead: str | os.PathLike, base: str, record: dict | None) -> None:
    """Keep (or, with None, forget) cube ``base``'s record in ``ahead``'s list (rewritten whole, atomically)."""
    records = read_records(ahead)
    if record is None:
        records.pop(base, None)
    else:
        records[base] = record
    Path(ahead).mkdir(parents=True, exist_ok=True)
    write_atomic(Path(ahead) / RECORDS, json.dumps(records))


def current(record: dict) -> bool:
    """Whether the data file a record was encoded from is still as it was (path, size, time)."""
    try:
        return _stamp(record["data"]) == (record["data"], record["size"], record["mtime_ns"])
    except OSError:
        return False


def adopt(ahead: str | os.PathLike, plan: StorePlan, partial: str | os.PathLike) -> tuple[dict, dict]:
    """Move into the local ``partial`` store the chunks written ahead that are exactly what ``plan``
    writes (see the module docstring); returns (chunk digests by (band, chunk), file digests by the
    plan's source path) of what needs no writing or hashing any more."""
    ahead, partial = Path(ahead), Path(partial)
    chunks: dict[tuple[int, int], str] = {}
    files: dict[str, str] = {}
    records = [r for r in read_records(ahead).values() if isinstance(r, dict) and current(r)]
    if not records:
        return chunks, files
    by_data = {r["data"]: r for r in records}
    layout = {g.chunk: g.pieces for g in chunk_groups(plan.data_files, plan.cube_lines, 1, plan.chunk_lines,
                                                      plan.samples, plan.dtype.itemsize)}
    for k, pieces in layout.items():
        if len(pieces) != 1:
            continue
        path, a, b = pieces[0]
        r = by_data.get(os.path.realpath(path))
        # one piece: the whole cube, a full chunk or (shorter) the last one
        if (r is None or r["chunk"] != k or r["chunk_lines"] != plan.chunk_lines or (a, b) != (0, r["lines"])
                or r["codec"] != dict(plan.dn_codec) or r["checksum"] != plan.checksum
                or len(r["digests"]) != plan.bands):
            continue
        sources = [chunk_path(ahead, band, k) for band in range(plan.bands)]
        if not all(p.is_file() for p in sources):
            continue
        for band, source in enumerate(sources):
            target = chunk_path(partial, band, k)
            target.parent.mkdir(parents=True, exist_ok=True)
            os.replace(source, target)
            chunks[(band, k)] = r["digests"][band]
    known = {real: entry for r in records for real, entry in r["files"].items()}
    for path, size in plan.sources:
        try:
            real, now_size, mtime = _stamp(path)
        except OSError:
            continue
        entry = known.get(real)
        if entry is not None and entry[0] == now_size == size and entry[1] == mtime:
            files[path] = entry[2]
    return chunks, files
