"""``archive verify``: every collection (or one) checked against its recorded digests, the catalog too."""

from __future__ import annotations

import argparse
from pathlib import Path

from archive.catalog.root import open_root
from archive.collection import verify_store
from archive.drawing.preview_layout import verify_previews

__all__ = ["run_verify"]


def run_verify(args: argparse.Namespace) -> int:
    """CLI handler of ``archive verify``: exit 0 when every checked collection is intact, 1 if not."""
    root = open_root(args.archive)
    ids = [args.id] if args.id else root.collection_ids()
    incomplete = [cid for cid in root.incomplete_ids() if not args.id or cid == args.id]
    for cid in incomplete:   # named, never passed over: its readers call it "not found"
        print(f"{cid}: INCOMPLETE: {root.store(cid)} has no completion marker (an update of it was interrupted "
              f"by an older version); re-ingest it from its raw files: archive ingest RAW_DIR --archive {root.path} "
              "--overwrite")
    if args.id and incomplete:
        return 1
    if args.id:
        root.require_collection(args.id)
    from archive.catalog.health import catalog_problems

    bad = len(incomplete)
    for where, problem in catalog_problems(root):   # the catalog too: a damaged Item or index
        if args.id and args.id not in Path(where).name and Path(where).name != "index.sqlite":
            continue
        if any(Path(where).name == f"{cid}.zarr" for cid in incomplete):
            continue   # named above
        bad += 1
        print(f"{where}: DAMAGED: {problem}")
    if not ids:
        print(f"{root.path}: no collections")
        return 1 if bad else 0
    for cid in ids:
        problems = verify_store(root.store(cid), progress=not args.quiet) + \
            ([] if root.is_url else verify_previews(root.store(cid)))   # previews: local archives only (yet)
        if problems:
            bad += 1
            print(f"{cid}: CORRUPT ({len(problems)} problems)")
            for p in problems[:20]:
                print(f"  {p}")
            if len(problems) > 20:
                print(f"  ... {len(problems) - 20} more")
        else:
            print(f"{cid}: OK")
    return 1 if bad else 0
