"""STAC Items describing collections: one JSON file per completed collection.

An Item (STAC 1.1.0, plain dicts, no pystac needed to write them) carries: the footprint polygon in
lon/lat (one ring per strip), its bbox, ``start_datetime``/``end_datetime`` (and ``datetime`` =
start), ``instruments`` (the sensor), ``gsd`` (nominal, m), ``eo:bands`` (centre wavelengths and,
where the headers give ``fwhm``, full widths at half maximum, both in micrometres as the eo
extension wants) and ``archive:wavelengths`` (nm), the processing extension's level ('L0': raw DN
as recorded, with navigation and calibration) and software, the ``collection`` it belongs to with
``root``/``parent``/``collection`` links (relative, see :mod:`archive.catalog.tree`), and one asset
``data`` pointing at the Zarr store by a relative href, with its ``eo:bands`` and ``raster:bands``
(the stored DN data type). The raw store is in sensor geometry (band, line, sample), not on a map
grid, so these Items claim no projection (``proj:*``) fields; rendered products do
(:mod:`archive.catalog.product`).

``hsi:wavelength_min`` / ``hsi:wavelength_max`` (nm) give the flight's wavelength range as two
numbers, so that "flights whose wavelengths span 650 nm" is one comparison of each (the index and
the STAC API's CQL2 filter use them). The store asset says how to open it
(:func:`store_asset_fields`): media type, the zarr extension's ``zarr:*`` fields and
``xarray:open_kwargs`` (the xarray-assets extension's field: ``xr.open_zarr(href, **open_kwargs)``).
"""

from __future__ import annotations

import json
import os
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from archive import storage
from archive.errors import FormatError
from archive.files import write_atomic

STAC_VERSION = "1.1.0"
EO_EXTENSION = "https://stac-extensions.github.io/eo/v1.1.0/schema.json"
RASTER_EXTENSION = "https://stac-extensions.github.io/raster/v1.1.0/schema.json"
PROJECTION_EXTENSION = "https://stac-extensions.github.io/projection/v2.0.0/schema.json"
PROCESSING_EXTENSION = "https://stac-extensions.github.io/processing/v1.2.0/schema.json"
ZARR_EXTENSION = "https://stac-extensions.github.io/zarr/v1.0.0/schema.json"
ZARR_MEDIA_TYPE = "application/vnd+zarr"
#: Keyword arguments of ``xr.open_zarr`` (or ``xr.open_dataset(..., engine="zarr")``) for a
#: collection store: its raw navigation table names its rows 'sample' like the DN's pixel columns,
#: so xarray would refuse the two sizes; it is left out (read it with zarr: ``group["navigation"]``).
STORE_OPEN_KWARGS = {"consolidated": False, "drop_variables": ["navigation"]}
#: processing:level of a collection (raw DN as recorded, sensor geometry, with navigation).
RAW_LEVEL = "L0"


def software_version() -> str:
    """This software's version: the installed distribution's, as ``archive.__version__`` reads it
    (taken from the distribution's metadata, so that the catalog imports nothing of the package root)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("archive")
    except PackageNotFoundError:  # running from a source tree without install
        return "0.0.0+unknown"


def eo_bands(wavelengths, fwhm=None, names=None) -> list[dict]:
    """eo:bands entries: ``name`` (default ``b<i>``), ``center_wavelength`` and, where ``fwhm`` has
    a finite positive value, ``full_width_half_max``, both converted from nm to micrometres.
    wavelengths, fwhm: (bands,) nm; names: (bands,) strings."""
    out = []
    for i, w in enumerate(wavelengths):
        band: dict[str, Any] = {"name": names[i] if names is not None else f"b{i}",
                                "center_wavelength": round(float(w) / 1000.0, 6)}
        if fwhm is not None and fwhm[i] is not None and float(fwhm[i]) > 0:  # NaN > 0 is False
            band["full_width_half_max"] = round(float(fwhm[i]) / 1000.0, 6)
        out.append(band)
    return out


def store_asset_fields() -> dict[str, Any]:
    """How to open a collection store (Zarr v3 group, no consolidated metadata): the fields its
    asset carries besides href, title and roles."""
    return {"type": ZARR_MEDIA_TYPE, "zarr:zarr_format": 3, "zarr:node_type": "group", "zarr:consolidated": False,
            "xarray:open_kwargs": json.loads(json.dumps(STORE_OPEN_KWARGS))}


def wavelength_range(wavelengths) -> dict[str, float]:
    """``hsi:wavelength_min`` / ``hsi:wavelength_max`` (nm) of band centres; empty without any."""
    if wavelengths is None or len(wavelengths) == 0:
        return {}
    return {"hsi:wavelength_min": float(min(wavelengths)), "hsi:wavelength_max": float(max(wavelengths))}


def rfc3339(moment: datetime) -> str:
    """UTC, 'Z' suffix, microseconds only when non-zero."""
    moment = moment.astimezone(UTC)
    text = moment.strftime("%Y-%m-%dT%H:%M:%S")
    if moment.microsecond:
        text += f".{moment.microsecond:06d}"
    return text + "Z"


def make_item(cid: str, geometry: dict, bbox: list[float], start: datetime, end: datetime,
              wavelengths: list[float] | None, bands: int, sensor: str | None, gsd: float,
              store_href: str, extra: dict[str, Any] | None = None, *, fwhm: list[float] | None = None,
              data_type: str | None = None, collection: str | None = None, links: list[dict] | None = None,
              software: str | None = None) -> dict:
    """A STAC Item dict. geometry: GeoJSON (lon/lat); bbox [west, south, east, north] degrees;
    start/end: UTC datetimes of the first and last line; wavelengths nm (bands,) or None; fwhm nm
    (bands,) or None (NaN for a band without); store_href: the Zarr store relative to the Item
    file; extra: more ``archive:*`` properties; data_type: numpy name of the stored DN type
    ('uint16'...), for ``raster:bands``; collection: id of the STAC Collection it belongs to, with
    its ``links`` (relative hrefs); software: the version of archive that ingested it (default this
    one)."""
    props: dict[str, Any] = {
        "datetime": rfc3339(start),
        "start_datetime": rfc3339(start),
        "end_datetime": rfc3339(end),
        "instruments": [sensor] if sensor else [],
        "gsd": round(float(gsd), 4),
        "archive:bands": int(bands),
        "processing:level": RAW_LEVEL,
        "processing:lineage": "raw DN as recorded (band, line, sample), with the navigation, line times and "
                              "calibration of the flight; ingested by archive",
        "processing:software": {"archive": software or software_version()},
    }
    asset: dict[str, Any] = {
        "href": store_href,
        "title": "Raw DN, navigation and calibration (Zarr v3 collection)",
        "roles": ["data"],
        **store_asset_fields(),
    }
    extensions = []
    if wavelengths is not None:
        props["archive:wavelengths"] = [float(w) for w in wavelengths]
        props.update(wavelength_range(wavelengths))
        props["eo:bands"] = eo_bands(wavelengths, fwhm)
        asset["eo:bands"] = [dict(b) for b in props["eo:bands"]]
        extensions.append(EO_EXTENSION)
    if data_type is not None:
        asset["raster:bands"] = [{"data_type": str(data_type), "unit": "DN"} for _ in range(int(bands))]
        extensions.append(RASTER_EXTENSION)
    extensions += [PROCESSING_EXTENSION, ZARR_EXTENSION]
    if extra:
        props.update(extra)
    item = {
        "type": "Feature",
        "stac_version": STAC_VERSION,
        "stac_extensions": extensions,
        "id": cid,
        "geometry": geometry,
        "bbox": [float(v) for v in bbox],
        "properties": props,
        "links": list(links or []),
        "assets": {"data": asset},
    }
    if collection is not None:
        item["collection"] = collection
    return item


def write_item(path: str | os.PathLike, item: dict, indent: int | None = 1) -> Path:
    """Write an Item (or any STAC document) as JSON (temporary name, then rename); ``indent`` None:
    on one line, through json's C encoder (the archive's Collection, one link per Item)."""
    if storage.is_url(path):   # one PUT (atomic); no folders in object storage
        path = storage.location(path)
    else:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(path, (json.dumps(item, indent=indent) + "\n").encode())
    return path


def _time(props: dict, key: str, where: str) -> datetime:
    value = props.get(key) or props.get("datetime")
    if not isinstance(value, str):
        raise FormatError(where, f"Item has no {key}", "re-ingest the flight or rewrite the Item")
    try:
        moment = datetime.fromisoformat(value.replace("Z", "+00:00"))
    except ValueError:
        raise FormatError(where, f"{key} {value!r} is not RFC 3339") from None
    return moment if moment.tzinfo else moment.replace(tzinfo=UTC)


def item_summary(item: dict, where: str = "") -> dict:
    """The queryable fields of an Item: id, start/end (epoch s and ISO), bands, min/max wavelength
    (nm or None), bbox, sensor, gsd. FormatError naming ``where`` when a field is missing."""
    try:
        cid = item["id"]
        props = item["properties"]
        bbox = [float(v) for v in item["bbox"]]
    except (KeyError, TypeError, ValueError) as exc:
        raise FormatError(where, f"not a STAC Item (missing or bad {exc})") from None
    if len(bbox) != 4:
        raise FormatError(where, f"bbox must have 4 numbers, has {len(bbox)}")
    start = _time(props, "start_datetime", where)
    end = _time(props, "end_datetime", where)
    wl = props.get("archive:wavelengths")
    if wl is None and props.get("eo:bands"):
        wl = [b["center_wavelength"] * 1000.0 for b in props["eo:bands"] if "center_wavelength" in b]
    bands = props.get("archive:bands", len(wl) if wl else 0)
    instruments = props.get("instruments") or [None]
    return {
        "id": str(cid),
        "start_time": start.timestamp(),
        "end_time": end.timestamp(),
        "start_iso": rfc3339(start),
        "end_iso": rfc3339(end),
        "bands": int(bands),
        "min_wavelength": float(min(wl)) if wl else None,
        "max_wavelength": float(max(wl)) if wl else None,
        "bbox": bbox,
        "sensor": instruments[0],
        "gsd": props.get("gsd"),
    }


def item_collection(items: list[dict]) -> dict:
    """A STAC ItemCollection (GeoJSON FeatureCollection) of Items."""
    return {"type": "FeatureCollection", "features": items}
