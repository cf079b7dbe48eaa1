"""``open_source``: the one place that turns what a user names (a raw flight directory, or a
collection id of an archive) into a flight source."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from archive.catalog.root import open_root  # resolves collection ids: only here among sources
from archive.errors import InputError, MissingInputError
from archive.params import NavigationParams
from archive.sources.base import FlightSource
from archive.sources.collection import CollectionSource
from archive.sources.raw import RawFlightSource

__all__ = ["collection_fov", "open_source"]


def open_source(path_or_id: str | os.PathLike, params: NavigationParams,
                calibration: str | os.PathLike | None = None,
                white_reference: np.ndarray | None = None,
                archive: str | os.PathLike | None = None,
                irradiance_calibration: str | os.PathLike | None = None,
                navigation: str | os.PathLike | None = None, navigation_columns: dict | None = None) -> FlightSource:
    """A flight source: a raw flight directory, or a collection id in ``archive``.

    A directory wins over a collection of the same name. A collection carries its own calibration,
    so ``calibration`` must be None for one; likewise its downwelling spectra
    (``irradiance_calibration``: a raw flight's ``.dcp`` kept elsewhere). ``navigation``: a raw flight's
    post-processed trajectory (SBET or CSV, :mod:`archive.formats.trajectory`; ``navigation_columns`` for a
    CSV export's names) georectifies it instead of its ``.lcf``.
    """
    path = Path(path_or_id)
    if path.is_dir():
        return RawFlightSource(path.absolute(), params, calibration=calibration, white_reference=white_reference,
                               irradiance_calibration=irradiance_calibration,
                               navigation=None if str(navigation) == "lcf" else navigation,
                               navigation_columns=navigation_columns)
    if archive is not None and not path.exists():
        if calibration is not None:
            raise InputError("--calibration", f"collection {path_or_id} carries the calibration it was "
                             "ingested with", "leave out --calibration, or re-ingest with another .icp")
        if navigation is not None and Path(navigation).is_file():
            raise InputError("--navigation", f"collection {path_or_id} is georectified from the navigation sources it "
                             "was ingested with", "pass --navigation lcf or a track's name, or ingest the flight "
                             "again with --navigation FILE")
        if irradiance_calibration is not None:
            raise InputError("--irradiance-calibration", f"collection {path_or_id} carries the downwelling "
                             "irradiance it was ingested with", "leave it out, or re-ingest the flight")
        store = open_root(archive).require_collection(str(path_or_id))
        return CollectionSource(store, str(path_or_id), params, white_reference=white_reference,
                                navigation=None if navigation is None else str(navigation))
    if path.exists():
        raise InputError(path, "is not a directory", "give a raw flight directory or a collection id with --archive")
    raise MissingInputError(path, "flight directory",
                            "give a raw flight directory, or a collection id together with --archive ARCHIVE")


def collection_fov(archive: str | os.PathLike, ids) -> float:
    """The field of view (deg) the collections ``ids`` of ``archive`` were ingested with (they must
    agree, else InputError asking for --fov); reads their root attributes only."""
    from archive.collection import read_attrs

    root = open_root(archive)
    fovs = {float(read_attrs(root.require_collection(str(i)))["fov_deg"]) for i in ids}
    if len(fovs) != 1:
        raise InputError("--fov", f"the collections were ingested with different fields of view {sorted(fovs)}",
                         "pass --fov DEG")
    return fovs.pop()
