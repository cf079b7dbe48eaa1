"""Each complete cube's DN chunks encoded as it closes, ahead of its flight's ingest (issue 47).

The watcher hands every cube it lists to an :class:`Encoder`: one thread, one cube at a time, in the
order they closed, writes the cube's line chunk of the future collection into
``ARCHIVE/.watch/ahead/<flight>/`` (:func:`archive.ingest.ahead.write_cube_ahead`: the store's codec
and checksum, the cube's files checksummed). When the flight goes idle its ingest is the plain
``archive ingest`` with ``--prewritten`` that folder: what is left to do then is the small arrays,
the cubes the guess did not fit, the checksum table, the rename and the catalog, so the collection
follows the landing by seconds instead of by the flight's whole encoding.

Where a cube goes is guessed from the cubes closed so far (:func:`place`): the line chunk is the most
common cube length (as the ingest will choose, :func:`archive.collection.layout.chunk_lines_for`) and
the cube's chunk its line offset in the flight (cubes in name order, as recorders number them); a cube
that does not fit one chunk is left to the ingest. A wrong guess costs time, never correctness: the
ingest moves in only what is exactly its own (:func:`archive.ingest.ahead.adopt`).
"""

from __future__ import annotations

import shutil
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

from archive.collection.layout import chunk_lines_for, chunk_path
from archive.formats.flight import natural_key
from archive.ingest.ahead import current, read_records, record_cube, write_cube_ahead
from archive.watch.cubes import cube_files
from archive.watch.stage import safe_name

__all__ = ["Encoder", "place"]


def place(cubes: list[tuple[str, int]], base: str) -> tuple[int, int] | None:
    """(chunk, chunk lines) of cube ``base`` among a flight's complete ``cubes`` ((base, lines), any
    order; ``base`` among them), or None when it cannot be one line chunk of the guessed layout."""
    ordered = sorted(cubes, key=lambda c: natural_key(c[0]))
    chunk_lines = chunk_lines_for([n for _, n in ordered])
    offset = 0
    for name, lines in ordered:
        if name == base:
            if lines > chunk_lines or offset % chunk_lines:
                return None
            return offset // chunk_lines, chunk_lines
        offset += lines
    return None


@dataclass
class _Job:
    flight: str
    base: str
    future: Future
    queued: float


@dataclass
class Encoder:
    """Encodes cubes ahead of their ingest into ``work``/ahead/<flight>/ (see the module docstring),
    with the store's ``codec`` and ``checksum``; one cube at a time in one thread."""

    work: Path
    codec: dict
    checksum: str
    jobs: list[_Job] = field(default_factory=list)
    seconds: dict[str, list[float]] = field(default_factory=dict)   #: flight -> encoding seconds of each cube
    waits: dict[str, list[float]] = field(default_factory=dict)     #: flight -> queued-to-done seconds of each cube

    def __post_init__(self):
        self.pool = ThreadPoolExecutor(1, thread_name_prefix="archive-watch-encode")

    def folder(self, flight: str) -> Path:
        """Where flight ``flight``'s chunks are written ahead."""
        return self.work / "ahead" / safe_name(flight)

    def submit(self, flight: str, data: Path, base: str, where: tuple[int, int]) -> bool:
        """Queue cube ``base`` (data file ``data``) of ``flight`` as line chunk ``where`` = (chunk, chunk
        lines); False when it is encoded there already (a restarted watch) and nothing is queued."""
        chunk, chunk_lines = where
        done = read_records(self.folder(flight)).get(base)
        if done is not None and (done.get("chunk"), done.get("chunk_lines")) == (chunk, chunk_lines):
            if current(done):
                return False
        future = self.pool.submit(write_cube_ahead, self.folder(flight), cube_files(data), chunk, chunk_lines,
                                  self.codec, self.checksum)
        self.jobs.append(_Job(flight, base, future, time.monotonic()))
        return True

    def poll(self) -> list[tuple[str, str, dict | None, BaseException | None]]:
        """The cubes encoded since the last call: (flight, base, record, None) each, recorded in the
        flight's folder, or (flight, base, None, error) for one that failed (left to the ingest)."""
        done, self.jobs = [j for j in self.jobs if j.future.done()], [j for j in self.jobs if not j.future.done()]
        out = []
        for job in done:
            try:
                record = job.future.result()
            except BaseException as exc:   # noqa: BLE001 - a cube that could not be encoded: the ingest writes it
                record_cube(self.folder(job.flight), job.base, None)
                out.append((job.flight, job.base, None, exc))
                continue
            record_cube(self.folder(job.flight), job.base, record)
            self.seconds.setdefault(job.flight, []).append(record["seconds"])
            self.waits.setdefault(job.flight, []).append(time.monotonic() - job.queued)
            out.append((job.flight, job.base, record, None))
        return out

    def busy(self, flight: str) -> bool:
        """Whether a cube of ``flight`` is queued or being encoded."""
        return any(j.flight == flight for j in self.jobs)

    def waiting(self) -> int:
        """Cubes queued or being encoded (all flights)."""
        return len(self.jobs)

    def moved(self, flight: str) -> tuple[int, int]:
        """(cubes whose chunks an ingest moved in, cubes encoded) of ``flight``'s folder."""
        records = read_records(self.folder(flight))
        gone = sum(1 for r in records.values() if not chunk_path(self.folder(flight), 0, r["chunk"]).exists())
        return gone, len(records)

    def discard(self, flight: str) -> None:
        """Forget ``flight``'s chunks written ahead (its ingest moved in what it used)."""
        self.seconds.pop(flight, None)
        self.waits.pop(flight, None)
        shutil.rmtree(self.folder(flight), ignore_errors=True)

    def stop(self) -> None:
        """Drop the cubes queued and finish the one in hand (its record kept: a restart reuses it)."""
        self.pool.shutdown(wait=True, cancel_futures=True)
        self.poll()
