"""``archive catalog search|list|rebuild|validate|add``."""

from __future__ import annotations

import argparse
import json
import sys

from archive.catalog.index import (IndexRow, damaged_flights, ensure_index, parse_bbox, parse_datetime_range,
                                   read_item_file, search)
from archive.catalog.root import ArchiveRoot, open_root
from archive.catalog.stac import item_collection, item_summary
from archive.errors import ArchiveError, FormatError


def _wavelengths(row: IndexRow) -> str:
    if row.min_wavelength is None:
        return "-"
    return f"{row.min_wavelength:.1f}-{row.max_wavelength:.1f} nm"


def format_table(rows: list[IndexRow]) -> str:
    """A plain-text table: id, start, end, bands, wavelength range, bbox (W,S,E,N degrees)."""
    head = ("id", "start", "end", "bands", "wavelengths", "bbox (W,S,E,N)")
    body = [(r.id, r.start_iso, r.end_iso, str(r.bands), _wavelengths(r),
             ",".join(f"{v:.6f}" for v in r.bbox)) for r in rows]
    widths = [max(len(x) for x in col) for col in zip(head, *body, strict=True)]
    lines = ["  ".join(x.ljust(w) for x, w in zip(line, widths, strict=True)).rstrip() for line in (head, *body)]
    lines.append(f"{len(rows)} flight{'s' if len(rows) != 1 else ''}")
    return "\n".join(lines)


def _print(root: ArchiveRoot, rows: list[IndexRow], as_json: bool) -> None:
    """Print ``rows`` (a table, or with ``as_json`` their Items as a FeatureCollection). Each row's Item is
    read again first (every Item in JSON, the local Items for the table: a file read each, no request to a
    bucket): one damaged since the index was built is left out with a warning line, never listed as sound."""
    items, kept = [], []
    for r in rows:
        if not as_json and root.is_url:
            kept.append(r)
            continue
        path = root.path / r.item_path
        try:
            item = read_item_file(path)
            item_summary(item, where=str(path))  # a flight's Item, not any JSON object
        except FormatError as exc:  # damaged since the index was built: costs only this flight
            print(f"archive catalog: warning: damaged flight {r.id} left out: {exc} (run 'archive catalog "
                  "rebuild')", file=sys.stderr)
            continue
        items.append(item)
        kept.append(r)
    print(json.dumps(item_collection(items), indent=1) if as_json else format_table(kept))


def _warn_damaged(root: ArchiveRoot, index) -> None:
    """One stderr line per flight the catalog cannot describe (not listed, not searchable)."""
    for d in damaged_flights(root, index):
        print(f"archive catalog: warning: damaged flight {d}", file=sys.stderr)


def _recreate_items(root: ArchiveRoot, everything: bool) -> int:
    """Write the Item of every collection store that has none, or a damaged one (``everything``:
    of every store) from the store's own metadata; returns how many stores could not be described."""
    from archive.catalog.describe import item_for_collection
    from archive.catalog.index import row_from_item
    from archive.catalog.register import carry_outputs
    from archive.catalog.stac import write_item

    failed = 0
    for cid in root.collection_ids():
        path = root.item_path(cid)
        old, why = None, None
        if not path.is_file():
            why = "had no Item"
        else:
            try:
                old = read_item_file(path)
                row_from_item(old, path.relative_to(root.path).as_posix())
            except (ArchiveError, KeyError, TypeError, ValueError) as exc:
                old, why = None, f"had a damaged Item ({' '.join(str(exc).split())[:200]})"
        if why is None and not everything:
            continue
        try:
            write_item(path, carry_outputs(old, item_for_collection(root, cid)))
        except ArchiveError as exc:
            failed += 1
            print(f"{cid}: cannot describe its collection: {exc}")
            continue
        if why is not None:
            print(f"{cid}: {why}: Item recreated from collections/{cid}.zarr")
    return failed


def _rebuild(root: ArchiveRoot, everything: bool) -> int:
    """``archive catalog rebuild``: Items recreated from their collections where missing or
    damaged, then the index and the STAC tree rebuilt from the Items. A read-only archive is
    refused in one line (its readers need no rebuild)."""
    from archive.catalog.index import cache_index_path, unwritable
    from archive.catalog.tree import locked, write_catalog
    from archive.errors import InputError

    try:
        with locked(root):
            failed = _recreate_items(root, everything)
            catalog = write_catalog(root, rescan=True)  # links the Items, rebuilds the index from them
    except OSError as exc:
        if not unwritable(exc):
            raise
        raise InputError(root.path / "catalog", f"cannot be written ({exc.strerror or exc}): a read-only archive "
                                                "is not rebuilt",
                         f"nothing to do for reading it: searches, batch renders and 'archive view' keep an index "
                         f"in {cache_index_path(root).parent}; rebuild where the archive is writable") from None
    n = len(search(root.index_path))
    print(f"{root.index_path}: {n} item{'s' if n != 1 else ''} indexed")
    print(f"{catalog}: STAC catalog of {n} item{'s' if n != 1 else ''}")
    damaged = damaged_flights(root, root.index_path)
    for d in damaged:
        print(f"DAMAGED {d}")
    return 1 if failed or damaged else 0


def _validate(args: argparse.Namespace) -> int:
    """``archive catalog validate``: every STAC file of the archive (root Catalog, Collection,
    Items) and the files given, against the vendored schemas; exit 1 when any fails."""
    from pathlib import Path

    from archive.catalog.validate import validation_errors
    from archive.errors import ArchiveError, InputError

    files = [Path(f) for f in args.files]
    if args.archive is not None:
        root = open_root(args.archive)
        files = [root.catalog_path, root.collection_path, *sorted(root.items.glob("*.json")), *files]
    if not files:
        raise InputError(None, "nothing to validate", "give --archive ARCHIVE and/or STAC JSON files")
    bad = 0
    for path in files:
        try:
            errors = validation_errors(path)
        except ArchiveError as exc:  # missing or unreadable
            errors = [f"{exc} (run 'archive catalog rebuild')" if args.archive is not None else str(exc)]
        bad += bool(errors)
        print(f"{path}: {'INVALID' if errors else 'valid'}")
        for e in errors[:20]:
            print(f"  {e}")
    checked = len(files)
    if args.archive is not None:
        from archive.catalog.health import catalog_problems

        for where, problem in catalog_problems(root, items=False):
            checked += 1
            bad += 1
            print(f"{where}: INVALID")
            print(f"  {problem}")
    print(f"{checked - bad} of {checked} valid")
    return 1 if bad else 0


def run(args: argparse.Namespace) -> int:
    """CLI handler of ``archive catalog``."""
    # Parse the filters before touching the archive, so that a malformed query fails the same way
    # whatever the archive holds.
    if args.catalog_command == "search":
        bbox = parse_bbox(args.bbox) if args.bbox is not None else None
        start, end = parse_datetime_range(args.datetime) if args.datetime is not None else (None, None)
        wavelength = args.wavelength
        if wavelength is not None and not (wavelength == wavelength and 0 < wavelength < 1e6):
            from archive.errors import InputError

            raise InputError("--wavelength", f"{wavelength} is not a positive wavelength in nm")
    if args.catalog_command == "validate":
        return _validate(args)
    root = open_root(args.archive)
    if args.catalog_command == "rebuild":
        return _rebuild(root, bool(getattr(args, "items", False)))
    if args.catalog_command == "add":
        from archive.catalog.register import register_output

        for out in args.items_json:
            ids = register_output(root, out)
            print(f"{out}: linked from {', '.join(ids)}")
        return 0
    index = ensure_index(root)
    if args.catalog_command == "list":
        _print(root, search(index), args.json)
        _warn_damaged(root, index)
        return 0
    rows = search(index, bbox=bbox, start=start, end=end, wavelength=wavelength)
    _print(root, rows, args.json)
    _warn_damaged(root, index)
    return 0
