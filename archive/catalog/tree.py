"""The archive's STAC tree, which STAC tools (pystac, stac-browser, odc-stac...) can walk::

    <ARCHIVE>/catalog.json               Catalog 'archive'    --child-->  catalog/collection.json
    <ARCHIVE>/catalog/collection.json    Collection 'flights' --item-->   items/<id>.json, one link per Item
    <ARCHIVE>/catalog/items/<id>.json    Item (collection 'flights'; links root, parent, collection)

Every href is relative (a self-contained catalog: the archive directory may be moved or copied),
there are no ``self`` links. The Collection's extent is the union of the Items' bboxes and time
ranges, its summaries the instruments and the range of nominal GSDs. Both files are rewritten from
the index (:mod:`archive.catalog.index`) each time an ingest catalogs a collection, under a lock,
each written to a temporary name and renamed, the Collection before the Catalog that points to it.
:func:`write_catalog` with ``rescan=True`` rebuilds everything from the Item files.
"""

from __future__ import annotations

import os
import posixpath
from pathlib import Path

from archive.catalog.index import IndexRow, collection_summary, ensure_index, read_item_file, rebuild_index
from archive.catalog.root import ArchiveRoot, locked, open_root  # locked: the catalog lock (re-exported)
from archive.catalog.stac import STAC_VERSION, write_item
from archive.errors import FormatError

CATALOG_ID = "archive"
COLLECTION_ID = "flights"
JSON_TYPE = "application/json"
GEOJSON_TYPE = "application/geo+json"
#: Licence of the archive's data: STAC's value for one that is not an SPDX licence.
LICENSE = "other"


def item_links() -> list[dict]:
    """The links of a collection Item, relative to ``catalog/items/<id>.json``."""
    return [
        {"rel": "root", "href": "../../catalog.json", "type": JSON_TYPE, "title": "Archive"},
        {"rel": "parent", "href": "../collection.json", "type": JSON_TYPE, "title": "Ingested flights"},
        {"rel": "collection", "href": "../collection.json", "type": JSON_TYPE, "title": "Ingested flights"},
    ]


def catalog_dict() -> dict:
    """The root Catalog (``<ARCHIVE>/catalog.json``)."""
    return {
        "type": "Catalog",
        "stac_version": STAC_VERSION,
        "stac_extensions": [],
        "id": CATALOG_ID,
        "title": "Hyperspectral flight archive",
        "description": "Airborne pushbroom hyperspectral flights ingested by archive: raw DN with navigation and "
                       "calibration, one Zarr store per flight, described by one STAC Item each.",
        "links": [
            {"rel": "root", "href": "./catalog.json", "type": JSON_TYPE, "title": "Archive"},
            {"rel": "child", "href": "./catalog/collection.json", "type": JSON_TYPE, "title": "Ingested flights"},
        ],
    }


def collection_dict(rows: list[IndexRow]) -> dict:
    """The Collection of the archive (``<ARCHIVE>/catalog/collection.json``) for its index rows:
    extent = union of the bboxes (degrees) and of the time ranges (UTC); an empty archive has the
    whole world and an open interval (:func:`summary_collection` of the same summary)."""
    ordered = sorted(rows, key=lambda r: (r.start_time, r.id))
    gsds = [float(r.gsd) for r in rows if r.gsd is not None]
    return summary_collection({
        "bbox": None if not rows else (min(r.bbox[0] for r in rows), min(r.bbox[1] for r in rows),
                                       max(r.bbox[2] for r in rows), max(r.bbox[3] for r in rows)),
        "start_iso": ordered[0].start_iso if rows else None,
        "end_iso": max(ordered, key=lambda r: r.end_time).end_iso if rows else None,
        "sensors": sorted({r.sensor for r in rows if r.sensor}),
        "gsd": (min(gsds), max(gsds)) if gsds else None,
        "links": [(r.id, r.item_path) for r in ordered]})


def summary_collection(summary: dict) -> dict:
    """The archive's Collection from a summary of its Items
    (:func:`archive.catalog.index.collection_summary`'s keys)."""
    if summary["bbox"] is not None:
        bbox, interval = [float(v) for v in summary["bbox"]], [summary["start_iso"], summary["end_iso"]]
    else:
        bbox, interval = [-180.0, -90.0, 180.0, 90.0], [None, None]
    summaries: dict = {}
    if summary["sensors"]:
        summaries["instruments"] = list(summary["sensors"])
    if summary["gsd"] is not None:
        summaries["gsd"] = {"minimum": summary["gsd"][0], "maximum": summary["gsd"][1]}
    links = [
        {"rel": "root", "href": "../catalog.json", "type": JSON_TYPE, "title": "Archive"},
        {"rel": "parent", "href": "../catalog.json", "type": JSON_TYPE, "title": "Archive"},
    ]
    for cid, path in summary["links"]:
        # relative to the archive: catalog/items/<id>.json, always so since it was written
        rel = path[len("catalog/"):] if path.startswith("catalog/") else posixpath.relpath(path, "catalog")
        links.append({"rel": "item", "href": "./" + rel, "type": GEOJSON_TYPE, "title": cid})
    return {
        "type": "Collection",
        "stac_version": STAC_VERSION,
        "stac_extensions": [],
        "id": COLLECTION_ID,
        "title": "Ingested flights",
        "description": "One Item per ingested flight: footprint, time range, bands (eo:bands) and the Zarr store "
                       "of its raw DN, navigation and calibration.",
        "keywords": ["hyperspectral", "airborne", "pushbroom", "raw"],
        "license": LICENSE,
        "extent": {"spatial": {"bbox": [bbox]}, "temporal": {"interval": [interval]}},
        "summaries": summaries,
        "links": links,
    }


def _link_items(root: ArchiveRoot) -> int:
    """Give every Item file the ``collection`` field and the links of this tree (Items written by
    older versions); returns how many were rewritten."""
    changed = 0
    if not root.items.is_dir():
        return 0
    links = item_links()
    for path in sorted(root.items.glob("*.json")):
        try:
            item = read_item_file(path)
        except FormatError:  # a damaged Item: recorded as such by the index (rebuild recreates it first)
            continue
        others = [ln for ln in item.get("links") or [] if ln.get("rel") not in ("root", "parent", "collection")]
        if item.get("collection") != COLLECTION_ID or (item.get("links") or []) != [*links, *others]:
            item["collection"] = COLLECTION_ID
            item["links"] = [*links, *others]
            write_item(path, item)
            changed += 1
    return changed


def write_catalog(root: ArchiveRoot | str | os.PathLike, *, rescan: bool = False) -> Path:
    """Write ``<ARCHIVE>/catalog.json`` and ``<ARCHIVE>/catalog/collection.json`` for the Items the
    index lists (the index is rebuilt from the Items first when missing). ``rescan``: first give
    every Item file its collection field and links and rebuild the index from the Item files.
    Returns the path of the root Catalog."""
    root = root if isinstance(root, ArchiveRoot) else open_root(root)
    with locked(root):
        if rescan:
            _link_items(root)
            rebuild_index(root)
        # asked of the index in SQL and written on one line through json's C encoder: O(Items) per ingest
        # still, 4x less of it (bench/RESULTS.md, issue 45)
        write_item(root.collection_path, summary_collection(collection_summary(ensure_index(root))), indent=None)
        write_item(root.catalog_path, catalog_dict())
    return root.catalog_path

