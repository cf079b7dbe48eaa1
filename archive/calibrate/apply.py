"""``archive calibrate --apply``: record the estimates where renders find them.

- A collection: its navigation parameters (``navigation_params``, what ``ingest --sync-offset /
  --boresight`` records), the per-line times and poses stored with them, and (flat ground) its
  ground height, through :func:`archive.collection.record_navigation`; then its STAC Item is
  rewritten (the footprint follows the new poses). Renders of the collection default to them, as
  to an ingest's.
- A raw flight directory: the sidecar ``navigation_params.json``
  (:data:`archive.sources.raw.NAVIGATION_SIDECAR`), read by :class:`~archive.sources.raw.RawFlightSource`
  whenever the caller leaves a parameter unset (``render`` without ``--sync-offset``/``--boresight``,
  ``--ground-height auto``).

Parameters the calibration held (not separable) are recorded at the value it held them at (their
start value); the lever arm is kept.

A co-registration (``--reference``) also records the flight's position offset (dE, dN, dU m, DESIGN
11) and the flight it is relative to: a collection keeps them in its calibration note
(``navigation_calibration``: 'position_offset_m', 'relative_to', read back by
:func:`archive.params.recorded_navigation`) and its STAC Item says so
(:func:`archive.params.coregistration_properties`);
a raw flight in its sidecar. Every cube's navigation moves by the offset.
"""

from __future__ import annotations

import datetime as _dt
import json
from pathlib import Path

import numpy as np

from archive.params import NavigationParams

__all__ = ["apply"]


def _note(result, previous: dict | None = None) -> dict:
    note = {"by": "archive calibrate", "estimated": list(result.estimated),
            "sigma": {k: v for k, v in result.sigma.items()}, "observable": result.observable,
            "residual_px_after": result.residual_after,
            "date": _dt.datetime.now(_dt.timezone.utc).replace(microsecond=0).isoformat()}
    offset = [float(v) for v in result.params.position_offset]
    if result.reference is not None:
        note.update(position_offset_m=offset, relative_to=result.reference,
                    residual_px_between={"before": result.between_before, "after": result.between_after},
                    windows_between=result.windows)
    elif any(offset):   # a flight calibrated again on its own keeps its co-registration
        note.update(position_offset_m=offset, relative_to=(previous or {}).get("relative_to"))
    return note


def apply(sources, result, fov_deg: float, archive=None) -> list[Path]:
    """Record ``result`` (a :class:`~archive.calibrate.estimate.Calibration`, estimated with the field
    of view ``fov_deg``, degrees: a raw flight's sidecar records it) for every source; returns the
    paths written (a collection that records these estimates already is left as it is, with a line on
    stderr). InputError before anything is written when a source is a collection in object storage."""
    from archive.collection import check_updatable

    for source in sources:   # every collection refused before anything is written
        if hasattr(source, "store"):
            check_updatable(source.store)
    written = []
    for source in sources:
        params = {"sync_offset": float(result.params.sync),
                  "boresight_deg": [float(v) for v in result.params.boresight_deg],
                  "lever_arm_m": [float(v) for v in source.params.lever_arm_m],
                  "position_offset_m": [float(v) for v in result.params.position_offset]}
        ground = None if result.dem is not None else float(result.params.ground)
        if hasattr(source, "store"):
            previous = getattr(source, "info", None)
            previous = (previous.attrs.get("navigation_calibration") if previous is not None else None) or {}
            path = _apply_collection(source, params, ground, _note(result, previous), archive)
            if path is None:   # the same estimates landed already (a rerun): nothing written twice
                import sys

                print(f"archive calibrate: {source.id}: these estimates are recorded already; nothing written",
                      file=sys.stderr)
            else:
                written.append(path)
        else:
            written.append(_apply_raw(source, params, ground, result, fov_deg))
    return written


def _apply_raw(source, params: dict, ground, result, fov_deg: float) -> Path:
    from archive.files import write_atomic
    from archive.sources.raw import NAVIGATION_SIDECAR

    path = Path(source.directory) / NAVIGATION_SIDECAR
    from archive.sources.raw import read_navigation_sidecar

    previous = read_navigation_sidecar(source.directory).get("calibration") or {}
    note = _note(result, previous)
    record = {**params, "ground_height": ground, "fov_deg": float(fov_deg), "calibration": note}
    if note.get("relative_to") is not None:
        record["relative_to"] = note["relative_to"]
    if result.dem is not None:
        record["dem"] = result.dem
        record["dem_offset_m"] = float(result.params.ground)
    write_atomic(path, json.dumps(record, indent=1) + "\n")
    return path


def _apply_collection(source, params: dict, ground, note: dict, archive) -> Path | None:
    from archive.collection import record_navigation
    from archive.sources.collection import CollectionSource

    nav = NavigationParams(sync_offset=params["sync_offset"], boresight_deg=tuple(params["boresight_deg"]),
                           lever_arm_m=tuple(params["lever_arm_m"]), position_offset_m=tuple(params["position_offset_m"]))
    fresh = CollectionSource(source.store, source.id, nav)
    n = len(fresh.cubes)
    poses = [fresh.poses(i) for i in range(n)]
    arrays = {"time": np.concatenate([fresh.line_times(i) for i in range(n)]),
              "position": np.concatenate([p.position for p in poses]),
              "attitude": np.concatenate([p.attitude.as_quat() for p in poses])}
    if not record_navigation(source.store, params, arrays, ground_height=ground, note=note):
        return None
    if archive is not None:
        from archive.catalog.describe import catalog_collection
        from archive.catalog.root import open_root

        from archive.ingest.previews import add_previews

        root = open_root(archive)
        catalog_collection(root, source.id)
        add_previews(root, [source.id])   # the previews drawn under the old navigation are stale now
    return Path(source.store)
