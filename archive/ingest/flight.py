"""One flight of an ingest, the steps the local ingest (:mod:`archive.ingest.command`) and the cluster's
(:mod:`archive.ingest.cluster`) share: what every flight's checks are given (:class:`PrepareArguments`),
its tasks (:func:`flight_tasks`), its store found there already (:func:`begin_flight`), cataloged once
published (:func:`finish_flight`), and its result (:class:`IngestResult`)."""

from __future__ import annotations

import os
from dataclasses import dataclass, field, replace
from pathlib import Path

from archive import storage
from archive.catalog.root import ArchiveRoot
from archive.collection import StorePlan, chunk_groups, hash_file_task, is_complete, write_chunks
from archive.collection.layout import CHECKSUMS, DEFAULT_CHECKSUM, DEFAULT_DN_COMPRESSION, DN_COMPRESSIONS
from archive.errors import InputError
from archive.ingest.checks import cataloged, check_ingested, disk_full_is_an_error

__all__ = ["IngestResult", "PrepareArguments", "begin_flight", "finish_flight", "flight_tasks", "split_results",
           "store_choices"]


def store_choices(compression: str | None, checksum: str | None) -> tuple[dict, str]:
    """(dn codec, checksum algorithm) named by ``--compression`` and ``--checksum`` (None: the defaults);
    InputError naming the option for an unknown name."""
    name = DEFAULT_DN_COMPRESSION if compression is None else str(compression).strip().lower()
    if name not in DN_COMPRESSIONS:
        raise InputError("--compression", f"unknown compression {compression!r}",
                         f"use one of {', '.join(DN_COMPRESSIONS)} (docs/ingest.md)")
    algorithm = DEFAULT_CHECKSUM if checksum is None else str(checksum).strip().lower()
    if algorithm not in CHECKSUMS:
        raise InputError("--checksum", f"unknown checksum {checksum!r}", f"use one of {', '.join(CHECKSUMS)}")
    return dict(DN_COMPRESSIONS[name]), algorithm


@dataclass(frozen=True)
class PrepareArguments:
    """What :func:`archive.ingest.prepare.prepare_flight` is given for every flight of one ingest, and the
    store's codec and checksum: one value, pickled to the workers with each check task."""

    fov_deg: float
    calibration: object = None
    ground_height: float | None = None
    sync_offset: float = 0.0
    boresight: tuple = (0.0, 0.0, 0.0)
    lever_arm: tuple = (0.0, 0.0, 0.0)
    dem: object = None
    dem_datum: str | None = None
    irradiance_calibration: object = None
    navigation: object = None
    navigation_columns: dict | None = None
    dn_codec: dict = field(default_factory=lambda: dict(DN_COMPRESSIONS[DEFAULT_DN_COMPRESSION]))
    checksum: str = DEFAULT_CHECKSUM

    def absolute(self) -> PrepareArguments:
        """These arguments with every local file path made absolute (for workers whose current folder differs)."""
        def local(path):
            return path if path is None or storage.is_url(path) else os.path.abspath(path)

        return replace(self, calibration=local(self.calibration), dem=local(self.dem),
                       irradiance_calibration=local(self.irradiance_calibration), navigation=local(self.navigation))

    def prepare(self, directory: str) -> StorePlan:
        """The checked plan of the flight in ``directory`` (raises what the checks raise)."""
        from archive.ingest.prepare import prepare_flight

        plan = prepare_flight(directory, self.fov_deg, self.calibration, self.ground_height, self.sync_offset,
                              self.boresight, self.lever_arm, self.dem, self.dem_datum, self.irradiance_calibration,
                              self.navigation, self.navigation_columns)
        return replace(plan, dn_codec=dict(self.dn_codec), checksum=self.checksum)


def flight_tasks(plan: StorePlan, partial, resumed: bool, written: frozenset = frozenset(),
                 hashed: frozenset = frozenset()) -> list[tuple[str, object, tuple]]:
    """The tasks that write ``plan``'s dn chunks into ``partial`` and checksum its raw files: (key,
    function, arguments) each, keys from the plan's token (the same flight gives the same keys). The
    chunk tasks return [(band, chunk, hex digest), ...], the file tasks (path, hex digest). Left out:
    the line chunks ``written`` (every band there already: :func:`archive.ingest.ahead.adopt`) and the
    source paths ``hashed``."""
    from dask.base import tokenize

    token = tokenize(plan.token(), resumed, str(partial))
    itemsize = plan.dtype.itemsize
    groups = chunk_groups(plan.data_files, plan.cube_lines, plan.bands, plan.chunk_lines, plan.samples, itemsize)
    tasks: list[tuple[str, object, tuple]] = [
        (f"ingest-dn-{g.chunk}-{g.band0}-{token}", write_chunks,
         (str(partial), g, plan.chunk_lines, resumed, plan.dn_codec, plan.checksum))
        for g in groups if g.chunk not in written]
    tasks += [(f"ingest-{plan.checksum}-{k}-{token}", hash_file_task, (path, plan.checksum))
              for k, (path, _) in enumerate(plan.sources) if path not in hashed]
    return tasks


def split_results(plan: StorePlan, results: list) -> tuple[dict[tuple[int, int], str], dict[str, str]]:
    """(chunk digests by (band, chunk), file digests by path) of :func:`flight_tasks`' results in order."""
    chunks: dict[tuple[int, int], str] = {}
    files: dict[str, str] = {}
    for value in results:
        if isinstance(value, list):
            chunks.update({(b, k): d for b, k, d in value})
        else:
            files[value[0]] = value[1]
    return chunks, files


@dataclass(frozen=True)
class IngestResult:
    """One flight of an ingest: its collection id (None when its checks failed before it had one), store,
    status ('ingested' | 'resumed' | 'already ingested' | 'failed': on a cluster only, where a flight
    fails alone), the raw directory, the one-line error of a failed flight and its seconds (cluster)."""

    cid: str | None
    store: Path | None
    status: str
    directory: str | None = None
    error: str | None = None
    seconds: float | None = None


def begin_flight(root: ArchiveRoot, plan: StorePlan, directory: str, overwrite: bool) -> IngestResult | None:
    """With the collection's lock held: the flight's result when its store is there already (checked to
    hold this flight as asked, cataloged when an earlier run died before that), else None (write it)."""
    from archive.catalog.describe import catalog_collection

    final = root.store(plan.cid)
    # in object storage an incomplete store under the final prefix is a killed run's: resumed by the writer
    if (is_complete(final) if root.is_url else final.exists()) and not overwrite:
        check_ingested(root, plan, directory)
        if not cataloged(root, plan.cid):
            with disk_full_is_an_error(root, plan.cid):
                catalog_collection(root, plan.cid)  # an earlier run may have died before cataloging
        return IngestResult(plan.cid, final, "already ingested", directory)
    return None


def finish_flight(root: ArchiveRoot, plan: StorePlan, directory: str, resumed: bool) -> IngestResult:
    """Catalog a flight whose store has just been published (its lock held): its result."""
    from archive.catalog.describe import catalog_collection

    with disk_full_is_an_error(root, plan.cid):
        catalog_collection(root, plan.cid)
    return IngestResult(plan.cid, root.store(plan.cid), "resumed" if resumed else "ingested", directory)


