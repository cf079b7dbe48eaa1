"""Describe a completed collection store as a STAC Item, and keep the catalog in step with it."""

from __future__ import annotations

from datetime import datetime

import numpy as np
import zarr
from scipy.spatial.transform import Rotation

from archive.catalog.footprint import flight_footprint
from archive.catalog.index import add_rows, rebuild_index, row_from_item
from archive.catalog.root import ArchiveRoot
from archive.catalog.stac import make_item, write_item
from archive.collection import read_info
from archive.errors import FormatError


def item_for_collection(root: ArchiveRoot, cid: str) -> dict:
    """The STAC Item of collection ``cid``: footprint from the stored per-line poses (sync offset 0,
    no boresight) at the stored ground height, times, wavelengths, sensor, nominal GSD."""
    store = root.require_collection(cid)
    info = read_info(store, navigation=False)
    attrs = info.attrs
    if info.ground_height is None:
        raise FormatError(store, "no ground height recorded: cannot compute the footprint",
                          "re-ingest with --ground-height M")
    frame = info.frame
    group = zarr.open_group(store, mode="r")
    time = group["time"][...]
    position = group["position"][...]
    attitude = Rotation.from_quat(group["attitude"][...])
    samples = int(group["dn"].shape[2])
    fp = flight_footprint(time, position, attitude, frame, float(attrs["fov_deg"]), float(attrs["ground_height"]),
                          samples, where=str(store))
    wl = group["wavelength"][...]
    wavelengths = None if np.all(np.isnan(wl)) else [float(w) for w in wl]
    extra = {
        "archive:fov_deg": float(attrs["fov_deg"]),
        "archive:ground_height": float(attrs["ground_height"]),
        "archive:epsg": int(frame.epsg),
        "archive:cubes": len(attrs["cubes"]),
        "archive:lines": int(group["dn"].shape[1]),
        "archive:samples": samples,
        "archive:strips": len(fp.strips_utm),
        "archive:software": attrs.get("archive:software"),
    }
    return make_item(
        cid, fp.geometry(), fp.bbox(), datetime.fromisoformat(attrs["start_datetime"]),
        datetime.fromisoformat(attrs["end_datetime"]), wavelengths, int(group["dn"].shape[0]),
        attrs.get("sensor"), fp.gsd, f"../../collections/{cid}.zarr", extra)


def catalog_collection(root: ArchiveRoot, cid: str) -> dict:
    """Write (or rewrite) the Item of ``cid`` and upsert its index row. Returns the Item."""
    item = item_for_collection(root, cid)
    path = write_item(root.item_path(cid), item)
    rel = path.relative_to(root.path).as_posix()
    if root.index_path.exists():
        add_rows(root.index_path, [row_from_item(item, rel)])
    else:  # a lost index: rebuild it from every Item (this one included)
        rebuild_index(root)
    return item
