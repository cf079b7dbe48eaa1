"""New navigation for a complete collection (``archive calibrate --apply``), switched in for its
readers all at once.

The store is never without its completion marker and never left half rewritten:

1. Under the collection's lock (:func:`~archive.collection.write.store_lock`), the new arrays
   (``time``, ``position``, ``attitude``) and the new root ``zarr.json`` (their digests, the new
   parameters, the marker) are written beside the store, in the hidden folder
   ``.<id>.zarr.apply/`` (copies of the arrays' folders, rewritten by zarr with the same codecs),
   every file synced to disk. A kill here leaves the store as it was; the folder is removed by the
   next writer or reader.
2. The journal ``<id>.zarr.apply.json`` (the list of files to move) is written atomically: from
   here on the update has happened, whatever comes next.
3. Every file is renamed into the store (the root ``zarr.json`` last), then the journal and the
   folder are removed. A kill here is finished ("rolled forward") by the next opening of the
   collection (:func:`settle`: every reader, ``verify``, ``catalog``, the next apply), which moves
   the files still in the folder: the renames are idempotent.

Tests SIGKILL an update at ``apply-staged``, ``apply-journal`` and ``apply-moved``
(:func:`archive.files.test_kill`).

While the renames run (milliseconds) a reader may meet new arrays beside old digests; every small
array is checked against its digest when read, so it is refused, never used. Collections in object
storage are refused before anything is written (S3 has no rename to switch with).
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import zarr

from archive import storage
from archive.collection.layout import COMPLETE, array_digest, location, zarr_target
from archive.collection.write import store_lock
from archive.errors import FormatError, InputError
from archive.files import remove_path, test_kill, write_atomic

__all__ = ["check_updatable", "journal_path", "record_navigation", "settle"]

#: The arrays an update may replace.
REPLACEABLE = ("time", "position", "attitude")
def journal_path(store: Path) -> Path:
    """The journal of an update of ``store`` in flight: ``<id>.zarr.apply.json`` beside it."""
    return store.with_name(store.name + ".apply.json")


def _staging(store: Path) -> Path:
    return store.with_name(f".{store.name}.apply")


def _roll_forward(store: Path) -> None:
    """Finish an update whose journal exists (the caller holds the lock); remove the staging folder of
    one killed before its journal."""
    journal, staging = journal_path(store), _staging(store)
    if not journal.exists():
        remove_path(staging)   # staged, never committed (or nothing): the store is as it was
        return
    try:
        files = json.loads(journal.read_text())["files"]
    except (OSError, ValueError, KeyError, TypeError):
        files = None
    if files is None:   # written atomically, so only a foreign file: refuse to guess
        raise FormatError(journal, "is not a readable navigation-update journal",
                          "move it away, then check the collection with 'archive verify'")
    for rel in files:   # the root zarr.json is last in the list
        src = staging / rel
        if src.exists():
            os.replace(src, store / rel)
            test_kill("apply-moved")
    journal.unlink()
    remove_path(staging)


def settle(store: str | os.PathLike, wait: float = 60.0) -> None:
    """Finish (or clear) an update of the local collection ``store`` that a killed ``calibrate --apply``
    left; nothing when there is none (one ``stat``). Waits up to ``wait`` s for a live updater.
    FormatError naming the collection when it cannot be finished here (a read-only archive)."""
    if storage.is_url(store):
        return
    store = Path(store)
    if not (journal_path(store).exists() or _staging(store).exists()):
        return
    cid = store.name.removesuffix(".zarr")
    lock = store_lock(store, f"finishing an interrupted navigation update of {cid}")
    try:
        lock.acquire(wait=wait)   # a live updater's LockHeldError goes up as it is
        try:
            _roll_forward(store)
        finally:
            lock.release()
    except OSError as exc:   # a read-only archive: the lock or the renames refused
        raise FormatError(store, f"collection {cid}: a navigation update (calibrate --apply) was interrupted and "
                          f"cannot be finished here ({exc.strerror or exc})",
                          "open the archive once where it is writable (e.g. 'archive verify') to finish it") from None


def check_updatable(where) -> None:
    """InputError unless ``where`` (a collection store, or the archive holding it) is on a file system: a
    collection in object storage cannot be given new navigation (no rename to switch it with)."""
    if storage.is_url(str(where)):
        raise InputError(where, "calibrate --apply cannot update a collection in object storage (no rename to "
                         "switch its navigation with)", "leave --apply out and pass the estimates to render "
                         "(--sync-offset, --boresight), or apply to a copy of the archive on a file system")


def record_navigation(store: str | os.PathLike, navigation_params: dict, arrays: dict[str, np.ndarray],
                      ground_height: float | None = None, note: dict | None = None) -> bool:
    """Give a complete collection new navigation parameters (``archive calibrate --apply``):
    ``navigation_params`` ('sync_offset', 'boresight_deg', 'lever_arm_m'), the per-line arrays they
    give ('time', 'position', 'attitude': same shapes as stored), optionally a new flat
    ``ground_height`` (m) and a ``note`` kept as the 'navigation_calibration' attribute; switched in
    at once (module docstring). Holds the collection's lock (waits for an ingest of it to finish).
    Returns False, writing nothing, when the collection records exactly these already (an apply
    that landed, run again)."""
    store = location(store)
    check_updatable(store)
    lock = store_lock(store, f"navigation update of {store.name.removesuffix('.zarr')}")
    lock.acquire(wait=float("inf"))
    try:
        _roll_forward(store)   # a killed update first: it has happened
        return _record(store, navigation_params, arrays, ground_height, note)
    finally:
        lock.release()


def _record(store: Path, navigation_params: dict, arrays: dict[str, np.ndarray], ground_height: float | None,
            note: dict | None) -> bool:
    group = zarr.open_group(zarr_target(store), mode="r")
    attrs = dict(group.attrs)
    if attrs.get(COMPLETE) is not True:
        raise InputError(store, "is not a complete collection", "re-ingest it")
    values = {}
    for name, v in arrays.items():
        if name not in REPLACEABLE or tuple(group[name].shape) != np.shape(v):
            raise InputError(store, f"array {name} cannot be replaced by shape {np.shape(v)}")
        values[name] = np.asarray(v, group[name].dtype)
    new = dict(attrs)
    new["array_sha256"] = {**attrs.get("array_sha256", {}), **{n: array_digest(v) for n, v in values.items()}}
    new["navigation_params"] = {"sync_offset": float(navigation_params["sync_offset"]),
                                "boresight_deg": [float(v) for v in navigation_params["boresight_deg"]],
                                "lever_arm_m": [float(v) for v in navigation_params["lever_arm_m"]]}
    if ground_height is not None:
        new["ground_height"] = float(ground_height)
        new["ground_height_source"] = "archive calibrate"
    same = {k: v for k, v in new.items() if k != "navigation_calibration"} == \
        {k: v for k, v in attrs.items() if k != "navigation_calibration"}
    if same:
        return False   # landed already (same arrays, parameters and ground): nothing to switch
    if note is not None:
        new["navigation_calibration"] = note
    staging = _staging(store)
    remove_path(staging)
    staging.mkdir()
    files = []
    for name, v in values.items():
        shutil.copytree(store / name, staging / name)
        zarr.open_array(zarr_target(staging / name, read_only=False), mode="r+")[...] = v
        files += sorted(p.relative_to(staging).as_posix() for p in (staging / name).rglob("*") if p.is_file())
    root = json.loads((store / "zarr.json").read_text())
    root["attributes"] = new
    (staging / "zarr.json").write_text(json.dumps(root, indent=2, allow_nan=True))
    files.append("zarr.json")   # last: the marker and the digests of the new arrays
    for rel in files:
        with open(staging / rel, "rb") as f:
            os.fsync(f.fileno())
    test_kill("apply-staged")
    write_atomic(journal_path(store), json.dumps({"files": files}) + "\n")   # the update has happened
    test_kill("apply-journal")
    _roll_forward(store)
    return True

