"""The STAC API of ``archive view`` (/stac), checked by clients we did not write: stac-api-validator
(core, collections, features, item-search, sort, filter) against a live uvicorn server on loopback,
and pystac-client, whose searches must return exactly the ids of ``archive catalog search``.
Three simulated flights (test_catalog's) ingested into an archive; CQL2 filters; paging by next
links; the store asset opened with xarray as its Item says.
"""

from __future__ import annotations

import json
import urllib.request
from pathlib import Path

import pytest

from archive.cli import main
from archive.view.registry import FlightRegistry
from archive.view.server import create_app, LOOPBACK_NAMES
from test_catalog import FLIGHTS, catalog  # noqa: F401  (the module fixture: 3 flights ingested)

pystac_client = pytest.importorskip("pystac_client")


@pytest.fixture(scope="module")
def stac(catalog):  # noqa: F811
    """(base URL of the STAC API of a live server on loopback, archive, ids by flight name)."""
    from tests.conftest import serve_loopback

    archive_dir, ids, _ = catalog
    with serve_loopback(create_app(FlightRegistry(archive_dir), allowed_hosts=LOOPBACK_NAMES), 64) as url:
        yield f"{url}/stac", archive_dir, ids


def _get(url: str) -> dict:
    with urllib.request.urlopen(url, timeout=30) as r:
        return json.loads(r.read())


def _post(url: str, body: dict) -> tuple[int, dict]:
    req = urllib.request.Request(url, json.dumps(body).encode(), {"Content-Type": "application/json"})
    try:
        with urllib.request.urlopen(req, timeout=30) as r:
            return r.status, json.loads(r.read())
    except urllib.error.HTTPError as exc:
        return exc.code, json.loads(exc.read())


def _cli_ids(archive_dir: Path, capsys, *args: str) -> list[str]:
    capsys.readouterr()
    assert main(["catalog", "search", "--archive", str(archive_dir), *args, "--json"]) == 0
    return [f["id"] for f in json.loads(capsys.readouterr().out)["features"]]


def test_stac_api_validator_passes(stac, monkeypatch):
    """stac-api-validator (PyPI) against the live server. It validates every object with
    stac-validator, which downloads the STAC schemas: this machine has no web access, so schema
    URLs are answered from the copies vendored in catalogs/schemas (the same texts)."""
    stac_validator_utilities = pytest.importorskip("stac_validator.utilities")
    from stac_api_validator.validations import QueryConfig, validate_api

    from archive.catalog.validate import vendored_schemas

    original = stac_validator_utilities.fetch_and_parse_file
    schemas = vendored_schemas()

    def offline(path, headers=None):
        url = str(path).split("#")[0]
        if url in schemas:
            return json.loads(json.dumps(schemas[url]))
        assert not url.startswith("https://"), f"schema not vendored: {url}"
        return original(path, headers)

    monkeypatch.setattr(stac_validator_utilities, "fetch_and_parse_file", offline)
    base, _, ids = stac
    classes = ["core", "collections", "features", "item-search", "item-search#sort", "filter"]
    warnings, errors = validate_api(
        root_url=base, ccs_to_validate=classes, collection="flights",
        geometry=json.dumps({"type": "Point", "coordinates": [-89.94, 35.12]}), auth_bearer_token=None,
        auth_query_parameter=None, fields_nested_property=None, validate_pagination=True,
        query_config=QueryConfig(*([None] * 13)), transaction_collection=None, headers=None)
    assert not list(errors), "\n".join(str(e) for e in errors)


def test_landing_conformance_and_collection(stac):
    base, _, ids = stac
    landing = _get(base)
    rels = {ln["rel"] for ln in landing["links"]}
    assert {"self", "root", "conformance", "data", "search", "service-desc",
            "http://www.opengis.net/def/rel/ogc/1.0/queryables"} <= rels
    assert "https://api.stacspec.org/v1.0.0/item-search#filter" in _get(f"{base}/conformance")["conformsTo"]
    (coll,) = _get(f"{base}/collections")["collections"]
    assert coll["id"] == "flights" and coll["summaries"]["hsi:wavelength_min"] == {"minimum": 400.0,
                                                                                    "maximum": 1700.0}
    w, s, e, n = coll["extent"]["spatial"]["bbox"][0]
    assert w < -100 and e > 151 and s < -33 and n > 45
    queryables = _get(f"{base}/queryables")
    assert {"hsi:wavelength_min", "hsi:wavelength_max", "datetime", "geometry"} <= set(queryables["properties"])


@pytest.mark.parametrize("kind, query, cli", [
    ("bbox", dict(bbox=[-100, 30, -80, 40]), ["--bbox", "-100,30,-80,40"]),
    ("bbox", dict(bbox=[-120, 30, -80, 50]), ["--bbox", "-120,30,-80,50"]),
    ("bbox", dict(bbox=[0, 0, 10, 10]), ["--bbox", "0,0,10,10"]),
    ("datetime", dict(datetime="2024-07-01T00:00:00Z/.."), ["--datetime", "2024-07-01T00:00:00Z/.."]),
    ("datetime", dict(datetime="2024-06-12T16:00:01Z"), ["--datetime", "2024-06-12T16:00:01Z"]),
    ("datetime", dict(datetime="2024-06-12T16:00:00Z/2024-07-12T23:00:00Z"),
     ["--datetime", "2024-06-12T16:00:00Z/2024-07-12T23:00:00Z"]),
    ("wavelength", dict(filter="hsi:wavelength_min <= 500 AND hsi:wavelength_max >= 500"), ["--wavelength", "500"]),
    ("wavelength", dict(filter="hsi:wavelength_min <= 1200 AND hsi:wavelength_max >= 1200"),
     ["--wavelength", "1200"]),
    ("wavelength", dict(filter={"op": "and", "args": [
        {"op": "<=", "args": [{"property": "hsi:wavelength_min"}, 1000]},
        {"op": ">=", "args": [{"property": "hsi:wavelength_max"}, 1000]}]}, filter_lang="cql2-json"),
     ["--wavelength", "1000"]),
    ("combined", dict(bbox=[-180, -90, 180, 90], datetime="2024-06-01T00:00:00Z/2024-12-31T00:00:00Z",
                      filter="hsi:wavelength_min <= 960 AND hsi:wavelength_max >= 960"),
     ["--bbox", "-180,-90,180,90", "--datetime", "2024-06-01T00:00:00Z/2024-12-31T00:00:00Z", "--wavelength", "960"]),
])
@pytest.mark.parametrize("method", ["POST", "GET"])
def test_pystac_client_equals_catalog_search(stac, capsys, kind, query, cli, method):
    base, archive_dir, _ = stac
    client = pystac_client.Client.open(base)
    got = [item.id for item in client.search(method=method, max_items=None, limit=2, **query).items()]
    assert got == _cli_ids(archive_dir, capsys, *cli), (kind, query)


@pytest.mark.parametrize("limit", [1, 2, 10])
def test_pystac_client_collection_items_and_counts(stac, capsys, limit):
    """The first calls of many notebooks (issue 36): the collection's get_items() (pystac-client sends
    collections=flights to /collections/flights/items), get_item(id), and search(...).matched() from
    numberMatched, whatever the page size."""
    base, archive_dir, ids = stac
    client = pystac_client.Client.open(base)
    collection = client.get_collection("flights")
    everything = _cli_ids(archive_dir, capsys)
    assert sorted(item.id for item in collection.get_items()) == sorted(everything) == sorted(ids.values())
    memphis = collection.get_item(ids["memphis"])
    assert memphis is not None and memphis.id == ids["memphis"] and memphis.collection_id == "flights"
    assert collection.get_item("no-such-flight") is None
    assert client.search(collections=["flights"], limit=limit).matched() == 3
    box = client.search(bbox=[-100, 30, -80, 40], limit=limit)
    assert box.matched() == len(_cli_ids(archive_dir, capsys, "--bbox", "-100,30,-80,40")) == 1
    assert client.search(collections=["other"], limit=limit).matched() == 0
    page = _get(f"{base}/collections/flights/items?limit={limit}&collections=flights")
    assert page["numberMatched"] == 3 and page["numberReturned"] == min(limit, 3) == len(page["features"])
    assert _get(f"{base}/collections/flights/items?collections=other")["numberMatched"] == 0


def test_cql2_filters(stac):
    base, _, ids = stac
    m, d, s = ids["memphis"], ids["dakota"], ids["sydney"]

    def found(filt, lang=None):
        body = {"filter": filt, "limit": 100}
        if lang:
            body["filter-lang"] = lang
        status, doc = _post(f"{base}/search", body)
        assert status == 200, doc
        return {f["id"] for f in doc["features"]}

    # the example: flights whose wavelengths span 650 nm, in one filter
    assert found("hsi:wavelength_min <= 650 AND hsi:wavelength_max >= 650", "cql2-text") == {m, d}
    item = _get(f"{base}/collections/flights/items/{s}")
    assert item["properties"]["hsi:wavelength_min"] == 950.0 and item["properties"]["hsi:wavelength_max"] == 1700.0
    w, so, e, n = item["bbox"]
    cx, cy = (w + e) / 2, (so + n) / 2
    assert found(f"S_INTERSECTS(geometry, POINT({cx} {cy}))", "cql2-text") == {s}
    assert found({"op": "s_intersects", "args": [{"property": "geometry"}, {"bbox": [-120, 30, -80, 50]}]}) == {m, d}
    assert found(f"S_INTERSECTS(geometry, POINT({w - 0.01} {cy}))", "cql2-text") == set()
    assert found("T_INTERSECTS(datetime, INTERVAL('2024-07-01T00:00:00Z', '..'))", "cql2-text") == {d, s}
    assert found("T_BEFORE(datetime, TIMESTAMP('2024-07-01T00:00:00Z'))", "cql2-text") == {m}
    assert found("datetime >= TIMESTAMP('2025-01-01T00:00:00Z') OR id = '%s'" % m, "cql2-text") == {m, s}
    assert found(f"NOT id = '{m}' AND archive:bands > 4", "cql2-text") == {d, s}
    assert found("id LIKE 'Pika-L-%'", "cql2-text") == {m, d}
    assert found("gsd BETWEEN 0 AND 100 AND collection = 'flights'", "cql2-text") == {m, d, s}
    assert found("eo:cloud_cover < 10", "cql2-text") == set()  # not a property of these Items: null
    assert found(f"id IN ('{d}', 'nope')", "cql2-text") == {d}
    # GET with cql2-text; errors are 400 with a description
    doc = _get(f"{base}/search?" + urllib.parse.urlencode({"filter": "hsi:wavelength_max > 1500"}))
    assert [f["id"] for f in doc["features"]] == [s]
    for bad in ["hsi:wavelength_max >", "foo(1) = 2", "S_INTERSECTS(id, POINT(0 0))"]:
        status, doc = _post(f"{base}/search", {"filter": bad, "filter-lang": "cql2-text"})
        assert status == 400 and "filter" in doc["description"], (bad, doc)


def test_paging_with_next_links(stac):
    base, _, ids = stac
    everything = sorted(ids.values(), key=lambda cid: cid[-15:])  # ingest order = start time order here
    seen, url, pages = [], f"{base}/search?limit=1", 0
    while url:
        doc = _get(url)
        seen += [f["id"] for f in doc["features"]]
        url = next((ln["href"] for ln in doc["links"] if ln["rel"] == "next"), None)
        pages += 1
    assert pages == 3 and seen == everything
    # POST: the next link carries the body; sortby reverses the order
    status, doc = _post(f"{base}/search", {"limit": 2, "sortby": [{"field": "datetime", "direction": "desc"}]})
    nxt = next(ln for ln in doc["links"] if ln["rel"] == "next")
    assert nxt["method"] == "POST" and nxt["body"]["limit"] == 2
    status, rest = _post(nxt["href"], nxt["body"])
    assert [f["id"] for f in doc["features"] + rest["features"]] == everything[::-1]
    assert not any(ln["rel"] == "next" for ln in rest["links"])
    # the Features form pages the same way
    doc = _get(f"{base}/collections/flights/items?limit=2")
    assert len(doc["features"]) == 2 and any(ln["rel"] == "next" for ln in doc["links"])


def test_store_asset_opens_with_xarray_as_documented(stac):
    import pystac
    import xarray as xr

    base, archive_dir, ids = stac
    client = pystac_client.Client.open(base)
    (item,) = client.search(ids=[ids["memphis"]]).items()
    asset = item.assets["data"]
    assert asset.media_type == "application/vnd+zarr"
    assert asset.extra_fields["zarr:zarr_format"] == 3 and asset.extra_fields["zarr:node_type"] == "group"
    assert Path(asset.href) == (archive_dir / "collections" / f"{ids['memphis']}.zarr").absolute()
    ds = xr.open_zarr(asset.href, **asset.extra_fields["xarray:open_kwargs"])
    assert ds["dn"].dims == ("band", "line", "sample") and ds.sizes["band"] == FLIGHTS["memphis"][0]["bands"]
    assert ds.attrs["archive:id"] == ids["memphis"]
    assert isinstance(pystac.Item.from_dict(item.to_dict()), pystac.Item)


def test_errors_and_404s(stac):
    base, _, _ = stac
    for path, status in [("/collections/nope", 404), ("/collections/flights/items/nope", 404),
                         ("/search?limit=0", 400), ("/search?bbox=1,2,3", 400), ("/search?datetime=2024-06-12", 400),
                         ("/search?sortby=-nope", 400), ("/search?token=zzz", 400)]:
        try:
            urllib.request.urlopen(base + path, timeout=10)
            raise AssertionError(f"{path} answered 200")
        except urllib.error.HTTPError as exc:
            doc = json.loads(exc.read())
            assert exc.code == status and doc["code"] and doc["description"], (path, doc)
    status, doc = _post(f"{base}/search", {"bbox": [0, 0, 1, 1], "intersects": {"type": "Point", "coordinates": [0, 0]}})
    assert status == 400


def test_catalog_add_links_a_rendered_output(stac, tmp_path, capsys):
    """``archive catalog add OUT.json``: the output becomes an asset of its source flight's Item
    (served by the API with an absolute href), kept when the Item is rewritten; an output of raw
    directories is refused."""
    from archive.catalog.describe import catalog_collection
    from archive.catalog.root import open_root

    base, archive_dir, ids = stac
    m = ids["memphis"]
    out = tmp_path / "mosaic.tif"
    out.write_bytes(b"not really a COG")
    product = {"type": "Feature", "stac_version": "1.1.0", "id": "mosaic.tif", "geometry": None,
               "properties": {"datetime": "2024-06-12T16:00:00Z",
                              "archive:recipe": {"sources": [m, "/some/raw/flight"], "command": "archive render"}},
               "links": [], "assets": {"data": {"href": "./mosaic.tif", "roles": ["data"], "title": "radiance",
                                                "type": "image/tiff; application=geotiff; profile=cloud-optimized"}}}
    (tmp_path / "mosaic.tif.json").write_text(json.dumps(product))
    capsys.readouterr()
    assert main(["catalog", "add", str(tmp_path / "mosaic.tif.json"), "--archive", str(archive_dir)]) == 0
    assert m in capsys.readouterr().out
    asset = _get(f"{base}/collections/flights/items/{m}")["assets"]["output-mosaic.tif"]
    assert Path(asset["href"]) == out.absolute() and "archive:output" in asset["roles"]
    catalog_collection(open_root(archive_dir), m)  # as a re-ingest does
    assert "output-mosaic.tif" in _get(f"{base}/collections/flights/items/{m}")["assets"]
    product["properties"]["archive:recipe"]["sources"] = ["/some/raw/flight"]
    (tmp_path / "raw.tif.json").write_text(json.dumps(product))
    assert main(["catalog", "add", str(tmp_path / "raw.tif.json"), "--archive", str(archive_dir)]) == 2
    assert "is a collection of" in capsys.readouterr().err
