"""Making a collection's overview previews (issue 36; the layout is :mod:`archive.drawing.preview_layout`'s): drawn
with the viewer's drawing engine (:class:`archive.drawing.flight.ViewedFlight`) from the flight opened as ``archive
view`` opens it, after the ingest published and cataloged it (:func:`add_previews`, ``archive ingest``'s hook).
Nothing of :mod:`archive.view` is imported."""

from __future__ import annotations

import math
import os
import sys
from collections.abc import Callable, Iterable

import numpy as np

from archive.overlap import LAST
from archive.drawing.preview_layout import FORMAT_VERSION, PERCENTILES, halve, is_current, plan_levels, rendered, write_previews

__all__ = ["add_previews", "make_previews"]


def make_previews(archive_path: str | os.PathLike, cid: str) -> tuple[dict, dict[str, np.ndarray]]:
    """(the ``archive:previews`` attribute, {level name: (bands, height, width) float32}) of the
    collection ``cid`` of the archive at ``archive_path``, drawn with the viewer's renderer (OpenGL: pass 1) from a
    flight opened as ``archive view`` opens it."""
    from concurrent.futures import ThreadPoolExecutor

    from archive.catalog.index import read_item_file
    from archive.catalog.root import open_root
    from archive.catalog.stac import item_summary
    from archive.collection import array_digest, content_version
    from archive.drawing.cache import ByteLRU
    from archive.drawing.flight import ViewedFlight, overview_level
    from archive.sources import open_source

    root = open_root(archive_path)
    flight_gsd = float(item_summary(read_item_file(root.item_path(cid)))["gsd"])   # the catalog's nominal GSD

    def opener(params, navigation):   # the flight as 'archive view' opens it (its default navigation source)
        return open_source(cid, params, archive=root.path, navigation=navigation)

    workers = ThreadPoolExecutor(max_workers=2, thread_name_prefix="archive-previews-bands")
    try:
        flight = ViewedFlight(cid, opener, None, ByteLRU(256 << 20), ByteLRU(64 << 20), workers)
        geometry = flight.geometry(None, None)
        cubes = range(len(flight.cubes))
        bounds = geometry.union(cubes)
        if bounds is None:
            raise ValueError(f"{cid}: no cube has a drawable mesh")
        bands = flight.default_bands()
        mode = "radiance" if flight.has_calibration else "raw"
        arrays: dict[str, np.ndarray] = {}
        records = []
        above = None
        for level in plan_levels(bounds, flight_gsd):
            if above is None or rendered(level, flight_gsd):
                grid = level.grid()
                values, _ = flight.render_keyed(grid, bands, mode, cubes, geometry, overlap=LAST,
                                                level=overview_level(grid.gsd, flight_gsd))
                made = "rendered"
            else:
                values = halve(arrays[above[0].name], above[0], level)
                made = f"mean of 2 x 2 pixels of z{above[0].zoom}"
            values = np.ascontiguousarray(values, np.float32)
            arrays[level.name] = values
            records.append({"zoom": level.zoom, "column": level.column, "row": level.row, "width": level.width,
                            "height": level.height, "made": made, "sha256": array_digest(values)})
            above = (level,)
        stats = flight.stats(None, bands, mode, cubes, None, PERCENTILES)
    finally:
        workers.shutdown(wait=True, cancel_futures=True)
    version = content_version(root.store(cid))
    attrs = {"format_version": FORMAT_VERSION, "version": version["version"],
             "mode": mode, "bands": [int(b) for b in bands], "wavelength": flight.wavelengths_of(bands),
             "flight_gsd": flight_gsd, "levels": records, "stats": stats}
    return attrs, arrays



def add_previews(root, cids: Iterable[str], warn: Callable[[str], None] | None = None) -> list[str]:
    """Give the collections ``cids`` of the archive ``root`` (an :class:`~archive.catalog.root.ArchiveRoot`)
    current previews (``archive ingest``'s hook): those that have them are left alone (nothing is
    written); the others get them under their collection's lock. A flight whose previews cannot be
    made (no OpenGL here, a full disk) is told to ``warn`` (default: a line on stderr) and stays as
    it is: complete, viewed from its DN. Returns the ids given previews."""
    from archive.collection import store_lock

    def say(line: str) -> None:
        (warn or (lambda text: print(text, file=sys.stderr)))(line)

    made = []
    cids = list(dict.fromkeys(cids))
    if cids and getattr(root, "is_url", False):
        say(f"archive ingest: no overview previews for collections in object storage yet ({root.path}); "
            "'archive view' draws them from their DN")
        return made
    for cid in cids:
        store = root.store(cid)
        if is_current(store):
            continue
        lock = store_lock(store, f"overview previews of {cid}")
        try:
            lock.acquire(wait=math.inf)
        except OSError as exc:
            say(f"archive ingest: {cid}: no overview previews (cannot lock the collection: {exc.strerror or exc})")
            continue
        try:
            if is_current(store):
                continue
            attrs, arrays = make_previews(root.path, cid)
            write_previews(store, attrs, arrays)
            made.append(cid)
        except Exception as exc:  # noqa: BLE001 - the collection is complete without them: say why, go on
            reason = " ".join(str(exc).split())[:200]
            say(f"archive ingest: {cid}: no overview previews ({type(exc).__name__}: {reason}); 'archive view' "
                "draws it from its DN; ingest it again to add them")
        finally:
            lock.release()
    return made
