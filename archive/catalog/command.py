"""``archive catalog search|list|rebuild``."""

from __future__ import annotations

import argparse
import json

from archive.catalog.index import (IndexRow, ensure_index, parse_bbox, parse_datetime_range, read_item_file,
                                   rebuild_index, search)
from archive.catalog.root import ArchiveRoot, open_archive
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
    root = open_archive(args.archive)
    if args.catalog_command == "rebuild":
        if getattr(args, "items", False):
            from archive.catalog.describe import item_for_collection
            from archive.catalog.stac import write_item

            for cid in root.collection_ids():
                write_item(root.item_path(cid), item_for_collection(root, cid))
        n = rebuild_index(root)
        print(f"{root.index_path}: {n} item{'s' if n != 1 else ''} indexed")
        return 0
    index = ensure_index(root)
    if args.catalog_command == "list":
        _print(root, search(index), args.json)
        return 0
    rows = search(index, bbox=bbox, start=start, end=end, wavelength=wavelength)
    _print(root, rows, args.json)
    return 0
