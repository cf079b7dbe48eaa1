"""Verifying a collection: every dn chunk and every small array against its recorded sha256."""

from __future__ import annotations

import os

import zarr

from archive import storage
from archive.collection.update import settle
from archive.collection.layout import (array_digest, chunk_digest, chunk_path, digest_table, dn_checksum, is_complete,
                                       location, zarr_target)

def verify_store(store: str | os.PathLike, progress: bool = False) -> list[str]:
    """Recompute the digest of every dn chunk (by the algorithm the store records: BLAKE3, or sha256 in
    stores of format 1) and the sha256 of every small array and compare with the recorded ones. Returns
    the problems found (empty: OK)."""
    from tqdm import tqdm

    store = location(store)
    settle(store)   # an update (calibrate --apply) a kill interrupted is finished first
    if not is_complete(store):
        return [f"{store}: incomplete collection (no completion marker)"]
    group = zarr.open_group(zarr_target(store), mode="r")
    attrs = dict(group.attrs)
    problems = []
    for name, expected in sorted(attrs.get("array_sha256", {}).items()):
        try:
            found = array_digest(group[name][...])
        except Exception as exc:  # noqa: BLE001 - report any unreadable array
            problems.append(f"array {name}: unreadable ({type(exc).__name__}: {exc})")
            continue
        if found != expected:
            problems.append(f"array {name}: checksum mismatch")
    dn = group["dn"]
    checksum = dn_checksum(attrs)
    if digest_table(checksum) not in group:
        return problems + [f"dn: no chunk checksums ({digest_table(checksum)})"]
    table = group[digest_table(checksum)][...]
    chunk = dn.chunks[1]
    bands, total = dn.shape[0], dn.shape[1]
    nchunks = table.shape[1]
    with tqdm(total=bands * nchunks, desc=f"verify {store.name}", unit="chunk", disable=not progress) as bar:
        for b in range(bands):
            for k in range(nchunks):
                where = f"dn chunk (band {b}, lines {k * chunk}-{min((k + 1) * chunk, total) - 1})"
                if not storage.exists(chunk_path(store, b, k)):
                    problems.append(f"{where}: missing")
                else:
                    try:
                        if chunk_digest(dn[b, k * chunk:(k + 1) * chunk], checksum) != table[b, k].tobytes():
                            problems.append(f"{where}: checksum mismatch")
                    except Exception as exc:  # noqa: BLE001 - undecodable chunk
                        problems.append(f"{where}: cannot be decoded ({type(exc).__name__})")
                bar.update(1)
    return problems
