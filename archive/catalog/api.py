"""A STAC API over an archive's catalog, answered from its SQLite index (``archive view`` serves it
at ``/stac``).

Endpoints (JSON; Items and ItemCollections ``application/geo+json``):

- ``GET /stac`` landing page; ``GET /stac/conformance``; ``GET /stac/queryables`` (and per collection);
- ``GET /stac/collections`` the archive's one Collection (``flights``); ``GET /stac/collections/flights``;
- ``GET /stac/collections/flights/items`` (``bbox``, ``datetime``, ``limit``, ``filter``...);
  ``GET /stac/collections/flights/items/{id}``;
- ``GET|POST /stac/search``: ``bbox``, ``intersects``, ``datetime``, ``ids``, ``collections``,
  ``limit`` (1..10000, larger values are clamped; default 10), ``sortby``, ``filter`` (+
  ``filter-lang`` cql2-text | cql2-json, :mod:`archive.catalog.cql`) and ``token`` (from a ``next`` link).

Selection, order and paging are SQL on the index (:mod:`archive.catalog.index`); only the page's
Items are read from their files, links made absolute (self, parent, collection, root), asset hrefs
absolute paths here. ``bbox``, ``intersects``, ``S_INTERSECTS`` test footprints exactly; ``datetime``
selects flights whose [start, end] meets it. ``token``: an offset into the sorted result. Errors are
``{"code", "description"}`` with a 4xx status; a client that disconnects mid-body is not logged.

Untrusted input is bounded before it is parsed: a POST body (at most MAX_BODY_BYTES, JSON nested at
most :data:`archive.catalog.cql.MAX_NESTING` deep), a filter (length, nesting, operator count:
:func:`archive.catalog.cql.check_text`; the ``cql2`` parser is native code, whose stack overflow
would end the process), numbers (finite, integers within 64 bits; ``limit`` a positive integer;
``token`` offsets at most MAX_OFFSET). Every parse or translate failure is a 400 with a message.
The index is checked and rebuilt when it does not answer for the Items (in the user's cache for a
read-only archive: :func:`archive.catalog.index.ensure_index`); an Item damaged since is left out
of its page and listed under ``archive:damaged``.
"""

from __future__ import annotations

import json
import math
import os
import posixpath
import re
import sqlite3
import threading
import time
from pathlib import Path
from typing import Any
from urllib.parse import urlencode

from archive.catalog.cql import (MAX_NESTING, check_json_text, check_tree, parse, parse_bbox_values,
                                 queryables_schema, split_antimeridian, to_sql)
from archive.catalog.index import (connect_readonly, ensure_index, geometry_wkb, read_item_file, spatial_clause,
                                   time_clause)
from archive.catalog.root import ArchiveRoot
from archive.catalog.stac import STAC_VERSION, ZARR_EXTENSION, ZARR_MEDIA_TYPE, item_summary, store_asset_fields
from archive.catalog.tree import COLLECTION_ID, GEOJSON_TYPE, JSON_TYPE, collection_dict
from archive.errors import InputError, MissingInputError

API_VERSION = "v1.0.0"
_STAC_API = f"https://api.stacspec.org/{API_VERSION}"
CONFORMANCE = [
    *(f"{_STAC_API}/{c}" for c in ("core", "collections", "ogcapi-features", "item-search", "item-search#sort",
                                   "item-search#filter", "ogcapi-features#filter")),
    "http://www.opengis.net/spec/ogcapi-features-1/1.0/conf/core",
    "http://www.opengis.net/spec/ogcapi-features-1/1.0/conf/geojson",
    "http://www.opengis.net/spec/ogcapi-features-3/1.0/conf/filter",
    "http://www.opengis.net/spec/ogcapi-features-3/1.0/conf/features-filter",
    "http://www.opengis.net/spec/cql2/1.0/conf/cql2-text",
    "http://www.opengis.net/spec/cql2/1.0/conf/cql2-json",
    "http://www.opengis.net/spec/cql2/1.0/conf/basic-cql2",
    "http://www.opengis.net/spec/cql2/1.0/conf/advanced-comparison-operators",
    "http://www.opengis.net/spec/cql2/1.0/conf/basic-spatial-functions",
    "http://www.opengis.net/spec/cql2/1.0/conf/basic-spatial-functions-plus",
    "http://www.opengis.net/spec/cql2/1.0/conf/temporal-functions",
]
DEFAULT_LIMIT = 10
MAX_LIMIT = 10_000
#: Largest POST body read (bytes) and largest paging offset a token may carry.
MAX_BODY_BYTES = 1 << 20
MAX_OFFSET = 10 ** 9
#: Seconds an index found to answer for the Items is trusted before it is checked again.
INDEX_CHECK_S = 2.0
QUERYABLES_REL = "http://www.opengis.net/def/rel/ogc/1.0/queryables"
SCHEMA_JSON = "application/schema+json"
OPENAPI_TYPE = "application/vnd.oai.openapi+json;version=3.0"
#: Sortable properties -> index column (ties are broken by id).
SORTABLE = {"id": "i.id", "datetime": "i.start_time", "start_datetime": "i.start_time",
            "end_datetime": "i.end_time", "hsi:wavelength_min": "i.min_wavelength",
            "hsi:wavelength_max": "i.max_wavelength", "gsd": "i.gsd", "archive:bands": "i.bands"}
_SEARCH_KEYS = {"bbox", "intersects", "datetime", "ids", "collections", "limit", "sortby", "filter", "filter-lang",
                "filter-crs", "token", "fields", "query", "conf"}
_CRS84 = ("http://www.opengis.net/def/crs/OGC/1.3/CRS84", "https://www.opengis.net/def/crs/OGC/1.3/CRS84")


class StacApi:
    """The STAC API of one archive. Methods take the API's base URL (``http://host:port/stac``) and
    return JSON-able dicts; problems are InputError (400) or MissingInputError (404)."""

    def __init__(self, root: ArchiveRoot):
        self.root = root
        self._local = threading.local()
        self._lock = threading.Lock()
        self._checked: tuple[float, Path, tuple] | None = None

    # ---- the index ---------------------------------------------------------------------------
    def _index(self) -> tuple[Path, tuple]:
        """(path, identity) of an index that answers for the Items now: checked (and rebuilt, in
        the archive or in the user's cache folder: :func:`ensure_index`) at most every
        INDEX_CHECK_S seconds."""
        with self._lock:
            now = time.monotonic()
            if self._checked is None or now - self._checked[0] > INDEX_CHECK_S:
                path = ensure_index(self.root)
                st = os.stat(path)
                self._checked = (now, path, (str(path), st.st_ino, st.st_dev))
            return self._checked[1], self._checked[2]

    def _con(self) -> sqlite3.Connection:
        """This thread's read-only connection to the index (reopened when the file was replaced by a
        rebuild, or another file answers)."""
        path, stamp = self._index()
        held = getattr(self._local, "con", None)
        if held is None or held[0] != stamp:
            if held is not None:
                held[1].close()
            self._local.con = held = (stamp, connect_readonly(path))
        return held[1]

    # ---- documents ---------------------------------------------------------------------------
    def landing(self, base: str) -> dict:
        return {
            "type": "Catalog", "stac_version": STAC_VERSION, "id": "archive",
            "title": "Hyperspectral flight archive",
            "description": "STAC API over the archive's flights (one Item per ingested flight), answered from "
                           "the catalog index.",
            "conformsTo": list(CONFORMANCE),
            "links": [
                {"rel": "self", "href": base, "type": JSON_TYPE},
                {"rel": "root", "href": base, "type": JSON_TYPE},
                {"rel": "conformance", "href": f"{base}/conformance", "type": JSON_TYPE},
                {"rel": "service-desc", "href": f"{base}/api", "type": OPENAPI_TYPE, "title": "OpenAPI description"},
                {"rel": "data", "href": f"{base}/collections", "type": JSON_TYPE},
                {"rel": "child", "href": f"{base}/collections/{COLLECTION_ID}", "type": JSON_TYPE,
                 "title": "Ingested flights"},
                {"rel": "search", "href": f"{base}/search", "type": GEOJSON_TYPE, "method": "GET"},
                {"rel": "search", "href": f"{base}/search", "type": GEOJSON_TYPE, "method": "POST"},
                {"rel": QUERYABLES_REL, "href": f"{base}/queryables", "type": SCHEMA_JSON},
            ],
        }

    def openapi(self, base: str) -> dict:
        """A short OpenAPI 3.0 description of the endpoints (the service-desc)."""
        def op(summary: str, media: str = JSON_TYPE, params: tuple = ()) -> dict:
            return {"summary": summary, "parameters": [{"name": n, "in": w, "required": w == "path",
                                                         "schema": {"type": "string"}} for n, w in params],
                    "responses": {"200": {"description": "OK", "content": {media: {}}},
                                  "400": {"description": "bad parameter"}, "404": {"description": "not found"}}}
        search_params = tuple((n, "query") for n in ("bbox", "intersects", "datetime", "ids", "collections", "limit",
                                                      "sortby", "filter", "filter-lang", "token"))
        cid, iid = ("collectionId", "path"), ("itemId", "path")
        return {
            "openapi": "3.0.3",
            "info": {"title": "archive STAC API", "version": API_VERSION},
            "servers": [{"url": base}],
            "paths": {
                "/": {"get": op("landing page")},
                "/api": {"get": op("this document", OPENAPI_TYPE)},
                "/conformance": {"get": op("conformance classes")},
                "/queryables": {"get": op("queryables of the filter", SCHEMA_JSON)},
                "/collections": {"get": op("the collections")},
                "/collections/{collectionId}": {"get": op("a collection", JSON_TYPE, (cid,))},
                "/collections/{collectionId}/queryables": {"get": op("queryables", SCHEMA_JSON, (cid,))},
                "/collections/{collectionId}/items": {"get": op("its Items", GEOJSON_TYPE, (cid, *search_params))},
                "/collections/{collectionId}/items/{itemId}": {"get": op("an Item", GEOJSON_TYPE, (cid, iid))},
                "/search": {"get": op("search", GEOJSON_TYPE, search_params),
                            "post": {**op("search", GEOJSON_TYPE),
                                     "requestBody": {"content": {JSON_TYPE: {"schema": {"type": "object"}}}}}},
            },
        }

    def conformance(self) -> dict:
        return {"conformsTo": list(CONFORMANCE)}

    def queryables(self, base: str, cid: str | None = None) -> dict:
        if cid is not None:
            self._check_collection(cid)
            return queryables_schema(f"{base}/collections/{cid}/queryables")
        return queryables_schema(f"{base}/queryables")

    def collection(self, base: str, cid: str = COLLECTION_ID) -> dict:
        """The Collection, its extent and summaries computed by SQL on the index (no Item links:
        its Items are at ``/items``)."""
        self._check_collection(cid)
        con = self._con()
        w, s, e, n, count, gsd0, gsd1, wl0, wl1 = con.execute(
            "SELECT min(west), min(south), max(east), max(north), count(*), min(gsd), max(gsd), "
            "min(min_wavelength), max(max_wavelength) FROM items").fetchone()
        doc = collection_dict([])
        if count:
            first = con.execute("SELECT start_iso FROM items ORDER BY start_time LIMIT 1").fetchone()[0]
            last = con.execute("SELECT end_iso FROM items ORDER BY end_time DESC LIMIT 1").fetchone()[0]
            doc["extent"] = {"spatial": {"bbox": [[w, s, e, n]]}, "temporal": {"interval": [[first, last]]}}
            sensors = [r[0] for r in con.execute("SELECT DISTINCT sensor FROM items WHERE sensor IS NOT NULL "
                                                 "ORDER BY sensor LIMIT 100")]
            summaries: dict[str, Any] = {}
            if sensors:
                summaries["instruments"] = sensors
            if gsd0 is not None:
                summaries["gsd"] = {"minimum": gsd0, "maximum": gsd1}
            if wl0 is not None:
                summaries["hsi:wavelength_min"] = {"minimum": wl0, "maximum": wl1}
            doc["summaries"] = summaries
        coll = f"{base}/collections/{cid}"
        doc["links"] = [
            {"rel": "self", "href": coll, "type": JSON_TYPE},
            {"rel": "root", "href": base, "type": JSON_TYPE},
            {"rel": "parent", "href": base, "type": JSON_TYPE},
            {"rel": "items", "href": f"{coll}/items", "type": GEOJSON_TYPE},
            {"rel": QUERYABLES_REL, "href": f"{coll}/queryables", "type": SCHEMA_JSON},
        ]
        return doc

    def collections(self, base: str) -> dict:
        return {"collections": [self.collection(base)],
                "links": [{"rel": "self", "href": f"{base}/collections", "type": JSON_TYPE},
                          {"rel": "root", "href": base, "type": JSON_TYPE},
                          {"rel": "parent", "href": base, "type": JSON_TYPE}]}

    def item(self, base: str, cid: str, item_id: str) -> dict:
        self._check_collection(cid)
        found = self._con().execute("SELECT item_path, min_wavelength, max_wavelength FROM items WHERE id = ?",
                                    (item_id,)).fetchone()
        if found is None:
            raise MissingInputError(item_id, f"Item in collection {cid!r}", "list them at /stac/search")
        return self._render(base, item_id, *found)

    # ---- search ------------------------------------------------------------------------------
    def search(self, base: str, params: dict, *, method: str = "GET", url: str | None = None,
               collection: str | None = None) -> dict:
        """An ItemCollection page. params: the GET query (strings) or the POST body (JSON);
        url: the endpoint (default ``base/search``); collection: the ``/collections/{id}/items``
        form (searches that collection only)."""
        if collection is not None:
            self._check_collection(collection)
        where, args, order, limit, offset = self._query(params, method, collection)
        con = self._con()
        sql = (f"SELECT i.id, i.item_path, i.min_wavelength, i.max_wavelength FROM items AS i WHERE {where} "
               f"ORDER BY {order} LIMIT ? OFFSET ?")
        try:
            rows = con.execute(sql, [*args, limit + 1, offset]).fetchall()
            # OGC API Features' count (pystac-client's search.matched()): the same WHERE, no page
            matched = con.execute(f"SELECT COUNT(*) FROM items AS i WHERE {where}", args).fetchone()[0]
        except sqlite3.OperationalError as exc:  # e.g. an over-long expression
            raise InputError("filter", f"the query cannot be run: {exc}") from None
        more = len(rows) > limit
        features, damaged = [], []
        for r in rows[:limit]:
            try:
                features.append(self._render(base, *r))
            except MissingInputError as exc:  # an Item damaged since the index was built: only it is missing
                damaged.append({"id": r[0], "reason": str(exc)})
        url = url or f"{base}/search"
        links = [{"rel": "root", "href": base, "type": JSON_TYPE}]
        if method == "GET":
            query = urlencode(list(params.items()))
            links.append({"rel": "self", "href": f"{url}?{query}" if query else url, "type": GEOJSON_TYPE})
        else:
            links.append({"rel": "self", "href": url, "type": GEOJSON_TYPE})
        if more:
            token = f"o{offset + limit}"
            if method == "POST":
                body = {k: v for k, v in params.items() if k != "token"}
                links.append({"rel": "next", "href": url, "type": GEOJSON_TYPE, "method": "POST",
                              "body": {**body, "token": token}, "merge": False})
            else:
                query = [(k, v) for k, v in params.items() if k != "token"] + [("token", token)]
                links.append({"rel": "next", "href": f"{url}?{urlencode(query)}", "type": GEOJSON_TYPE,
                              "method": "GET"})
        page = {"type": "FeatureCollection", "features": features, "links": links,
                "numberMatched": matched, "numberReturned": len(features)}
        if damaged:
            page["archive:damaged"] = damaged
        return page

    def _query(self, params: dict, method: str, collection: str | None):
        """(where SQL, parameters, order SQL, limit, offset) of a search request."""
        get = method == "GET"
        where: list[str] = []
        args: list[Any] = []
        con = self._con()
        bbox, intersects = params.get("bbox"), params.get("intersects")
        if bbox not in (None, "", []) and intersects not in (None, ""):
            raise InputError("bbox", "bbox and intersects are exclusive", "give one of them")
        if bbox not in (None, "", []):
            if isinstance(bbox, str):
                if not get:
                    raise InputError("bbox", "a POST search gives bbox as a JSON array of numbers")
                bbox = bbox.split(",")
            parts = []
            for box in split_antimeridian(parse_bbox_values(bbox)):
                clause, more = spatial_clause(box)
                parts.append(clause)
                args += more
            where.append("(" + " OR ".join(parts) + ")")
        if intersects not in (None, ""):
            if isinstance(intersects, str):
                check_json_text(intersects, "intersects")
                try:
                    intersects = json.loads(intersects)
                except (ValueError, RecursionError):
                    raise InputError("intersects", "not a GeoJSON geometry (not JSON)") from None
            check_tree(intersects, "intersects")
            if not isinstance(intersects, dict) or intersects.get("type") not in (
                    "Point", "MultiPoint", "LineString", "MultiLineString", "Polygon", "MultiPolygon",
                    "GeometryCollection"):
                raise InputError("intersects", "not a GeoJSON geometry")
            import shapely

            wkb = geometry_wkb(intersects)
            bounds = shapely.from_wkb(wkb).bounds
            if not all(-1e3 <= v <= 1e3 for v in bounds):
                raise InputError("intersects", f"coordinates {bounds} are not longitudes and latitudes in degrees")
            clause, more = spatial_clause(bounds, wkb)
            where.append(clause)
            args += more
        when = params.get("datetime")
        if when not in (None, ""):
            start, end = parse_rfc3339_interval(when)
            clause, more = time_clause(con, start, end)
            where.append(clause)
            args += more
        ids = _list(params.get("ids"), "ids")
        if ids is not None:
            where.append(f"i.id IN ({', '.join('?' for _ in ids)})" if ids else "0")
            args += ids
        collections = _list(params.get("collections"), "collections")
        if collection is not None:   # /collections/{id}/items: pystac-client also sends collections=id
            collections = [collection] if collections is None else [c for c in collections if c == collection]
        if collections is not None and COLLECTION_ID not in collections:
            where.append("0")
        filt = params.get("filter")
        if filt not in (None, ""):
            crs = params.get("filter-crs")
            if crs not in (None, "", *_CRS84):
                raise InputError("filter-crs", f"{crs!r} is not supported", f"use {_CRS84[0]}")
            lang = params.get("filter-lang") or ("cql2-text" if get else "cql2-json")
            clause, more = to_sql(parse(filt, lang))
            where.append(clause)
            args += more
        limit = parse_limit(params.get("limit"))
        token = params.get("token")
        offset = 0
        if token not in (None, ""):
            if not isinstance(token, str) or not re.fullmatch(r"o[0-9]{1,10}", token) \
                    or int(token[1:]) > MAX_OFFSET:
                raise InputError("token", f"{str(token)[:40]!r} is not a token of this API", "follow the next link")
            offset = int(token[1:])
        return " AND ".join(where) or "1", args, _order(params.get("sortby")), limit, offset

    # ---- one Item ----------------------------------------------------------------------------
    def _render(self, base: str, item_id: str, item_path: str, wl0, wl1) -> dict:
        path = (self.root.path / item_path).absolute()
        try:
            item = read_item_file(path)
            item_summary(item, where=str(path))  # a flight Item (id, times, bands...), not any JSON object
        except Exception as exc:  # the index is older than the files: say which and how to fix
            raise MissingInputError(path, f"Item file of {item_id} ({' '.join(str(exc).split())[:300]})",
                                    "run 'archive catalog rebuild'") from None
        item_dir = path.parent
        coll = f"{base}/collections/{COLLECTION_ID}"
        keep = [ln for ln in item.get("links") or []
                if ln.get("rel") not in ("self", "root", "parent", "collection") and "://" in str(ln.get("href"))]
        item["links"] = [
            {"rel": "self", "href": f"{coll}/items/{item_id}", "type": GEOJSON_TYPE},
            {"rel": "parent", "href": coll, "type": JSON_TYPE},
            {"rel": "collection", "href": coll, "type": JSON_TYPE},
            {"rel": "root", "href": base, "type": JSON_TYPE},
            *keep,
        ]
        item["collection"] = COLLECTION_ID
        props = item.setdefault("properties", {})
        if wl0 is not None:
            props.setdefault("hsi:wavelength_min", wl0)
            props.setdefault("hsi:wavelength_max", wl1)
        for key, asset in (item.get("assets") or {}).items():
            href = str(asset.get("href", ""))
            if "://" not in href and not href.startswith("/"):
                if self.root.is_url:   # an absolute s3:// URL, '..' resolved
                    scheme, rest = str(item_dir).split("://", 1)
                    asset["href"] = f"{scheme}://{posixpath.normpath(f'{rest}/{href}')}"
                else:
                    asset["href"] = os.path.normpath(item_dir / href)
            if key == "data" and asset.get("type") == ZARR_MEDIA_TYPE and "xarray:open_kwargs" not in asset \
                    and href.rstrip("/").endswith(".zarr") and "collections/" in href:
                asset.update(store_asset_fields())  # an Item written before the store said how to open it
                exts = item.setdefault("stac_extensions", [])
                if ZARR_EXTENSION not in exts:
                    exts.append(ZARR_EXTENSION)
        return item

    def _check_collection(self, cid: str) -> None:
        if cid != COLLECTION_ID:
            raise MissingInputError(cid, "collection", f"this archive has one collection, {COLLECTION_ID!r}")


_RFC3339 = re.compile(r"^\d{4}-\d{2}-\d{2}[Tt]\d{2}:\d{2}:\d{2}(\.\d+)?([Zz]|[+-]\d{2}:\d{2})$")


def _instant(text: str) -> float:
    from datetime import datetime

    if not _RFC3339.match(text):
        raise InputError("datetime", f"{text[:40]!r} is not an RFC 3339 date-time",
                         "e.g. 2024-06-12T16:00:00Z, or an interval A/B with '..' for an open end")
    try:
        return datetime.fromisoformat(text.upper().replace("Z", "+00:00")).timestamp()
    except ValueError:
        raise InputError("datetime", f"{text[:40]!r} is not a valid date-time") from None


def parse_rfc3339_interval(text: Any) -> tuple[float | None, float | None]:
    """The ``datetime`` parameter of STAC API searches (an RFC 3339 date-time, or an interval
    ``A/B`` with ``..`` or nothing for an open end) -> (start, end) epoch s, None = open."""
    if not isinstance(text, str) or len(text) > 100:
        raise InputError("datetime", "expected an RFC 3339 date-time or interval A/B")
    parts = text.split("/")
    if len(parts) == 1:
        moment = _instant(text)
        return moment, moment
    if len(parts) != 2:
        raise InputError("datetime", f"{text[:60]!r}: an interval has two ends, A/B")
    a, b = (None if p in ("", "..") else _instant(p) for p in parts)
    if a is None and b is None:
        raise InputError("datetime", "both ends of the interval are open")
    if a is not None and b is not None and a > b:
        raise InputError("datetime", f"{text!r}: the start is after the end")
    return a, b


def parse_limit(value: Any) -> int:
    """The ``limit`` of a search (a query string or a JSON number): a positive integer, clamped to
    MAX_LIMIT; InputError for anything else (a fraction, a boolean, 1e999, a 400-digit number)."""
    if value is None or value == "":
        return DEFAULT_LIMIT
    if isinstance(value, str):
        text = value.strip()
        if not re.fullmatch(r"[+-]?[0-9]{1,18}", text):
            raise InputError("limit", f"expected a positive integer, got {value[:40]!r}")
        number = int(text)
    elif isinstance(value, bool) or not isinstance(value, int | float):
        raise InputError("limit", f"expected a positive integer, got {str(value)[:40]!r}")
    elif isinstance(value, float):
        if not math.isfinite(value) or value != int(value):
            raise InputError("limit", f"expected a positive integer, got {value!r}")
        number = int(value)
    else:
        number = value
    if number < 1:
        raise InputError("limit", f"{number} is not a positive number of Items")
    return min(number, MAX_LIMIT)


def _list(value: Any, name: str) -> list[str] | None:
    if value is None or value == "":
        return None
    if isinstance(value, str):
        value = [v.strip() for v in value.split(",") if v.strip()]
    if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
        raise InputError(name, "expected a list of strings")
    if len(value) > MAX_LIMIT:
        raise InputError(name, f"{len(value)} values, at most {MAX_LIMIT}")
    return value


def _order(sortby: Any) -> str:
    """ORDER BY of a ``sortby`` ("+a,-b" or [{"field", "direction"}]); default start time, then id."""
    if sortby in (None, "", []):
        return "i.start_time, i.id"
    if isinstance(sortby, str):
        fields = []
        for part in sortby.split(","):
            part = part.strip()
            if not part:
                continue
            direction = "desc" if part.startswith("-") else "asc"
            fields.append({"field": part.lstrip("+- "), "direction": direction})
        sortby = fields
    if not isinstance(sortby, list):
        raise InputError("sortby", "expected a list of {field, direction}")
    terms = []
    for entry in sortby:
        if not isinstance(entry, dict) or not isinstance(entry.get("field"), str):
            raise InputError("sortby", f"expected {{field, direction}}, got {str(entry)[:60]!r}")
        field = entry["field"].removeprefix("properties.")
        direction = str(entry.get("direction", "asc")).lower()
        if field not in SORTABLE:
            raise InputError("sortby", f"cannot sort by {field!r}", f"sortable: {', '.join(SORTABLE)}")
        if direction not in ("asc", "desc"):
            raise InputError("sortby", f"direction {direction!r} is not asc or desc")
        terms.append(f"{SORTABLE[field]} {direction.upper()}")
    return ", ".join([*terms, "i.id"]) if terms else "i.start_time, i.id"


# ---- HTTP (Starlette) --------------------------------------------------------------------------
def parse_body(raw: bytes) -> dict:
    """The JSON object of a POST body, bounded before it is parsed (size, nesting, count of
    values: :func:`archive.catalog.cql.check_json_text`); InputError naming ``body`` otherwise."""
    if len(raw) > MAX_BODY_BYTES:
        raise InputError("body", f"{len(raw)} bytes is too large (at most {MAX_BODY_BYTES})")
    try:
        text = raw.decode("utf-8") if raw.strip() else "{}"
    except UnicodeDecodeError:
        raise InputError("body", "not UTF-8 text", "send a JSON object") from None
    check_json_text(text, "body", max_chars=MAX_BODY_BYTES)
    try:
        body = json.loads(text)
    except (ValueError, RecursionError) as exc:
        raise InputError("body", f"not JSON: {str(exc)[:200]}", "send a JSON object") from None
    if not isinstance(body, dict):
        raise InputError("body", "expected a JSON object")
    check_tree(body, "body", MAX_NESTING)
    return body


def stac_routes(archive: ArchiveRoot | None, prefix: str = "/stac") -> list:
    """Starlette routes of the STAC API of ``archive`` under ``prefix`` (None: every route
    answers 404, the viewer serves raw directories only)."""
    from starlette.concurrency import run_in_threadpool
    from starlette.requests import ClientDisconnect
    from starlette.responses import JSONResponse
    from starlette.routing import Route

    from archive.errors import ArchiveError

    api = StacApi(archive) if archive is not None else None

    def answer(status: int, doc: dict, media_type: str = JSON_TYPE) -> JSONResponse:
        return JSONResponse(doc, status_code=status, media_type=media_type)

    def handler(fn, media_type: str = JSON_TYPE):
        async def endpoint(request):
            base = str(request.base_url).rstrip("/") + prefix
            try:
                if api is None:
                    raise MissingInputError("archive", "STAC API", "start archive view with --archive ARCHIVE")
                body = None
                if request.method == "POST":
                    body = parse_body(await _read_body(request))
                doc = await run_in_threadpool(fn, api, request, base, body)
            except ClientDisconnect:   # the client left mid-body: nobody to answer, nothing to log
                return answer(400, {"code": "ClientDisconnect", "description": "the client disconnected"})
            except MissingInputError as exc:
                return answer(404, {"code": "NotFound", "description": str(exc)})
            except ArchiveError as exc:
                return answer(400, {"code": "InvalidParameterValue", "description": str(exc)})
            except (RecursionError, OverflowError) as exc:  # a last line of defence: inputs are bounded first
                return answer(400, {"code": "InvalidParameterValue",
                                    "description": f"the request is too deeply nested or a number is out of range "
                                                   f"({type(exc).__name__})"})
            return answer(200, doc, media_type)
        return endpoint

    def query(request) -> dict:
        return dict(request.query_params)

    async def _read_body(request) -> bytes:
        size = request.headers.get("content-length")
        if size is not None and size.isdigit() and int(size) > MAX_BODY_BYTES:
            raise InputError("body", f"{size} bytes is too large (at most {MAX_BODY_BYTES})")
        chunks, total = [], 0
        async for chunk in request.stream():
            total += len(chunk)
            if total > MAX_BODY_BYTES:
                raise InputError("body", f"more than {MAX_BODY_BYTES} bytes (too large)")
            chunks.append(chunk)
        return b"".join(chunks)

    def search(api, request, base, body):
        if body is not None:
            return api.search(base, body, method="POST")
        return api.search(base, query(request))

    def items(api, request, base, body):
        cid = request.path_params["cid"]
        return api.search(base, query(request), url=f"{base}/collections/{cid}/items", collection=cid)

    return [
        Route(prefix, handler(lambda api, r, base, b: api.landing(base))),
        Route(prefix + "/", handler(lambda api, r, base, b: api.landing(base))),
        Route(prefix + "/api", handler(lambda api, r, base, b: api.openapi(base), OPENAPI_TYPE)),
        Route(prefix + "/conformance", handler(lambda api, r, base, b: api.conformance())),
        Route(prefix + "/queryables", handler(lambda api, r, base, b: api.queryables(base), SCHEMA_JSON)),
        Route(prefix + "/collections", handler(lambda api, r, base, b: api.collections(base))),
        Route(prefix + "/collections/{cid}",
              handler(lambda api, r, base, b: api.collection(base, r.path_params["cid"]))),
        Route(prefix + "/collections/{cid}/queryables",
              handler(lambda api, r, base, b: api.queryables(base, r.path_params["cid"]), SCHEMA_JSON)),
        Route(prefix + "/collections/{cid}/items", handler(items, GEOJSON_TYPE)),
        Route(prefix + "/collections/{cid}/items/{item_id}",
              handler(lambda api, r, base, b: api.item(base, r.path_params["cid"], r.path_params["item_id"]),
                      GEOJSON_TYPE)),
        Route(prefix + "/search", handler(search, GEOJSON_TYPE), methods=["GET", "POST"]),
    ]

