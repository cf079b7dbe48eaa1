"""Describe a completed collection store as a STAC Item, and keep the catalog in step with it."""

from __future__ import annotations

from datetime import datetime

import numpy as np

from archive.catalog.footprint import flight_footprint, recorded_footprint
from archive.catalog.index import SCHEMA_VERSION, add_rows, ensure_index, row_from_item, schema_version
from archive.catalog.root import ArchiveRoot
from archive.catalog.stac import make_item, write_item
from archive.catalog.tree import COLLECTION_ID, item_links, write_catalog
from archive.collection import read_info, read_poses
from archive.errors import FormatError


def item_for_collection(root: ArchiveRoot, cid: str) -> dict:
    """The STAC Item of collection ``cid``: footprint from the stored per-line poses (with the
    ingest's navigation parameters) at the stored ground height, or as traced on the DEM at ingest
    (``archive ingest --dem``), times, wavelengths and FWHM, sensor, nominal GSD, DN data type,
    the software version that ingested it, and its place in the archive's STAC tree."""
    store = root.require_collection(cid)
    info = read_info(store, navigation=False)
    attrs = info.attrs
    if info.ground_height is None:
        raise FormatError(store, "no ground height recorded: cannot compute the footprint",
                          "re-ingest with --ground-height M")
    frame = info.frame
    rec = read_poses(store)
    bands, lines, samples = rec.shape
    terrain = attrs.get("terrain") or {}
    if terrain.get("footprint_lonlat"):   # traced on the DEM at ingest (the DEM may be gone since)
        fp = recorded_footprint(terrain["footprint_lonlat"], frame.epsg, float(terrain["gsd"]))
    else:
        fp = flight_footprint(rec.time, rec.position, rec.attitude, frame, info.fov_deg, info.ground_height,
                              samples, where=str(store))
    wavelengths = rec.wavelengths
    extra = {
        "archive:fov_deg": info.fov_deg,
        "archive:ground_height": info.ground_height,
        "archive:epsg": int(frame.epsg),
        "archive:cubes": len(info.cubes),
        "archive:lines": lines,
        "archive:samples": samples,
        "archive:strips": len(fp.strips_utm),
        "archive:software": attrs.get("archive:software"),
    }
    from archive.params import coregistration_properties   # co-registered to a reference (calibrate --reference)
    extra.update(coregistration_properties(attrs))
    if terrain:
        extra["archive:dem"] = terrain.get("dem")
        extra["archive:dem_datum"] = terrain.get("datum")
    software = str(attrs.get("archive:software") or "")
    return make_item(
        cid, fp.geometry(), fp.bbox(), datetime.fromisoformat(attrs["start_datetime"]),
        datetime.fromisoformat(attrs["end_datetime"]), wavelengths, bands,
        attrs.get("sensor"), fp.gsd, f"../../collections/{cid}.zarr", extra,
        fwhm=getattr(rec, "fwhm", None), data_type=np.dtype(attrs["dtype"]).name if attrs.get("dtype") else None,
        collection=COLLECTION_ID, links=item_links(),
        software=software.removeprefix("archive ").strip() or None)


def catalog_collection(root: ArchiveRoot, cid: str) -> dict:
    """Write (or rewrite) the Item of ``cid``, upsert its index row and rewrite the archive's root
    Catalog and Collection (:func:`archive.catalog.tree.write_catalog`). Returns the Item."""
    from archive.catalog.index import read_item_file
    from archive.catalog.register import carry_outputs

    from archive.catalog.tree import locked
    from archive.errors import FormatError as _FormatError

    item = item_for_collection(root, cid)
    with locked(root):  # the Item, its index row and the tree change together
        previous = root.item_path(cid)
        if previous.is_file():  # registered outputs (archive catalog add) stay linked
            try:
                item = carry_outputs(read_item_file(previous), item)
            except _FormatError:  # a damaged Item is replaced
                pass
        path = write_item(root.item_path(cid), item)
        rel = path.relative_to(root.path).as_posix()
        if schema_version(root.index_path) == SCHEMA_VERSION:
            add_rows(root.index_path, [row_from_item(item, rel)])
        else:  # a lost, damaged or older index: rebuild it from every Item (this one included)
            ensure_index(root)
        write_catalog(root)
    return item
