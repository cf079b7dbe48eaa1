"""``archive catalog search|list|rebuild|validate|add``."""

from __future__ import annotations

import argparse
import json

from archive.catalog.index import (IndexRow, ensure_index, parse_bbox, parse_datetime_range, read_item_file,
                                   search)
from archive.catalog.root import ArchiveRoot, open_root
from archive.catalog.stac import item_collection


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
    if as_json:
        items = [read_item_file(root.path / r.item_path) for r in rows]
        print(json.dumps(item_collection(items), indent=1))
    else:
        print(format_table(rows))


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
    print(f"{len(files) - bad} of {len(files)} valid")
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
        from archive.catalog.tree import write_catalog

        if getattr(args, "items", False):
            from archive.catalog.describe import item_for_collection
            from archive.catalog.stac import write_item

            from archive.catalog.register import carry_outputs

            for cid in root.collection_ids():
                path = root.item_path(cid)
                old = read_item_file(path) if path.is_file() else None
                write_item(path, carry_outputs(old, item_for_collection(root, cid)))
        catalog = write_catalog(root, rescan=True)  # links the Items, rebuilds the index from them
        n = len(search(root.index_path))
        print(f"{root.index_path}: {n} item{'s' if n != 1 else ''} indexed")
        print(f"{catalog}: STAC catalog of {n} item{'s' if n != 1 else ''}")
        return 0
    if args.catalog_command == "add":
        from archive.catalog.register import register_output

        for out in args.items_json:
            ids = register_output(root, out)
            print(f"{out}: linked from {', '.join(ids)}")
        return 0
    index = ensure_index(root)
    if args.catalog_command == "list":
        _print(root, search(index), args.json)
        return 0
    rows = search(index, bbox=bbox, start=start, end=end, wavelength=wavelength)
    _print(root, rows, args.json)
    return 0
