"""STAC that tools can walk (issue 12): the archive's root Catalog -> Collection -> Items, the
sidecar Item of a rendered output, and offline validation against the vendored schemas.

Real files throughout: simulated flights ingested into an archive, a COG rendered by the real
pipeline, read back by pystac and by a real loader (odc-stac) and compared with rasterio's reads.
"""

from __future__ import annotations

import dataclasses
import json
import shlex
import shutil
import socket
import urllib.request
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pystac
import pytest
from pyproj import Transformer

from archive.catalog.product import (COG_MEDIA_TYPE, grid_footprint, product_item, product_item_path, render_command,
                                     write_product_item)
from archive.catalog.pystac_validator import use_with_pystac
from archive.catalog.stac import (EO_EXTENSION, PROCESSING_EXTENSION, PROJECTION_EXTENSION, RASTER_EXTENSION,
                                  ZARR_EXTENSION)
from archive.catalog.tree import COLLECTION_ID, write_catalog
from archive.catalog.validate import CORE_SCHEMAS, schema_registry, validate, validation_errors, vendored_schemas
from archive.cli import build_parser, main
from archive.errors import FormatError, InputError
from archive.grid import Grid
from archive.ingest.command import ingest
from archive.outputs.registry import format_named
from archive.simulator.command import simulate_flight
from helpers import FOV

REPO = Path(__file__).resolve().parents[1]
DAY = 86400.0


@pytest.fixture(autouse=True)
def offline_pystac():
    """pystac validates with the vendored schemas in every test here (and the default afterwards)."""
    import pystac.validation

    use_with_pystac()
    yield
    pystac.validation.set_validator(pystac.validation.JsonSchemaSTACValidator())


class NetworkUsed(AssertionError):
    pass


@pytest.fixture
def no_network(monkeypatch):
    """Any attempt at a connection or a name lookup fails the test (and is recorded)."""
    attempts: list[str] = []

    def refuse(*args, **kwargs):
        attempts.append(repr(args[:2]))
        raise NetworkUsed(f"network used: {args[:2]!r}")

    monkeypatch.setattr(socket.socket, "connect", refuse)
    monkeypatch.setattr(socket, "create_connection", refuse)
    monkeypatch.setattr(socket, "getaddrinfo", refuse)
    monkeypatch.setattr(urllib.request, "urlopen", refuse)
    return attempts


# ---------------------------------------------------------------------------------------------
# The archive's STAC tree
# ---------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def stac_archive(tmp_path_factory):
    """Two small flights at different places and days, ingested into one archive."""
    from archive.formats.flight import discover_flight
    from archive.formats.lcf import read_lcf, write_lcf

    base = tmp_path_factory.mktemp("stac")
    archive_dir = base / "archive"
    ids = []
    for k, (lat, lon, shift) in enumerate([(35.12, -89.94, 0.0), (45.5, -100.3, 3 * DAY)]):
        d = base / f"flight{k}"
        truth = simulate_flight(d, cubes=2, bands=4, samples=32, lines=100, cubes_per_pass=2, seed=k, lat=lat,
                                lon=lon)
        if shift:
            for c in discover_flight(d).cubes:
                lcf = read_lcf(c.lcf)
                write_lcf(c.lcf, dataclasses.replace(lcf, time=lcf.time + shift))
        (r,) = ingest([str(d)], archive_dir, FOV, ground_height=truth.ground_height, progress=False)
        ids.append(r.cid)
    return archive_dir, ids


def _json(path: Path) -> dict:
    return json.loads(path.read_text())


def _hrefs(obj: dict) -> list[str]:
    return [ln["href"] for ln in obj.get("links", [])] + [a["href"] for a in obj.get("assets", {}).values()]


def test_pystac_walks_the_archive_and_every_object_validates(stac_archive):
    archive_dir, ids = stac_archive
    root = pystac.Catalog.from_file(str(archive_dir / "catalog.json"))
    (collection,) = list(root.get_children())
    assert isinstance(collection, pystac.Collection) and collection.id == COLLECTION_ID
    items = list(root.get_items(recursive=True))
    assert sorted(i.id for i in items) == sorted(ids)
    walked = [(c.id, sorted(i.id for i in its)) for c, _, its in root.walk()]
    assert walked == [("archive", []), (COLLECTION_ID, sorted(ids))]
    for obj in [root, collection, *items]:
        obj.validate()  # the offline validator (fixture): core + every extension schema
    root.validate_all()
    for item in items:
        assert item.collection_id == COLLECTION_ID
        assert item.get_collection().id == COLLECTION_ID and item.get_root().id == "archive"
        assert item.get_parent().id == COLLECTION_ID
        store = Path(item.assets["data"].get_absolute_href())
        assert store == (archive_dir / "collections" / f"{item.id}.zarr").resolve() and store.is_dir()
        assert set(item.stac_extensions) == {EO_EXTENSION, RASTER_EXTENSION, PROCESSING_EXTENSION, ZARR_EXTENSION}
        assert not any(k.startswith("proj:") for k in item.properties)  # the raw store has no map grid
        bands = item.assets["data"].extra_fields["eo:bands"]
        assert len(bands) == 4 and all(0.3 < b["center_wavelength"] < 2.6 for b in bands)  # micrometres
        assert all(b["full_width_half_max"] > 0 for b in bands)  # the simulated headers have fwhm
        assert item.assets["data"].extra_fields["raster:bands"][0]["data_type"] == "uint16"
        assert item.properties["processing:level"] == "L0"
    # the Collection's extent is the union of the Items' bboxes and time ranges
    (bbox,) = collection.extent.spatial.bboxes
    assert bbox == [min(i.bbox[0] for i in items), min(i.bbox[1] for i in items),
                    max(i.bbox[2] for i in items), max(i.bbox[3] for i in items)]
    (interval,) = collection.extent.temporal.intervals
    assert interval[0] == min(i.common_metadata.start_datetime for i in items)
    assert interval[1] == max(i.common_metadata.end_datetime for i in items)
    assert collection.summaries.get_list("instruments") == ["Pika L-SIM"]
    assert collection.license == "other"


def test_every_file_validates_offline_and_every_href_is_relative(stac_archive, no_network):
    archive_dir, ids = stac_archive
    files = [archive_dir / "catalog.json", archive_dir / "catalog" / "collection.json",
             *(archive_dir / "catalog" / "items" / f"{cid}.json" for cid in ids)]
    for path in files:
        urls = validate(path)
        assert urls[0] in CORE_SCHEMAS.values()
        for href in _hrefs(_json(path)):
            assert "://" not in href and not href.startswith("/"), f"{path}: absolute href {href}"
        assert not any(ln["rel"] == "self" for ln in _json(path)["links"])
    assert main(["catalog", "validate", "--archive", str(archive_dir)]) == 0
    assert no_network == []


def test_the_archive_can_move(stac_archive, tmp_path):
    archive_dir, ids = stac_archive
    moved = tmp_path / "elsewhere" / "copy"
    shutil.copytree(archive_dir, moved)
    items = list(pystac.Catalog.from_file(str(moved / "catalog.json")).get_items(recursive=True))
    assert len(items) == len(ids)
    for item in items:
        assert Path(item.assets["data"].get_absolute_href()) == (moved / "collections" / f"{item.id}.zarr").resolve()


def test_rebuild_restores_the_tree(stac_archive, tmp_path, capsys):
    archive_dir, ids = stac_archive
    copy = tmp_path / "archive"
    shutil.copytree(archive_dir, copy)
    before = {p: _json(copy / p) for p in ("catalog.json", "catalog/collection.json", f"catalog/items/{ids[0]}.json")}
    # lose the root files and the first Item's links (as an Item written by an older version)
    (copy / "catalog.json").unlink()
    (copy / "catalog" / "collection.json").unlink()
    item = _json(copy / "catalog" / "items" / f"{ids[0]}.json")
    del item["collection"]
    item["links"] = []
    (copy / "catalog" / "items" / f"{ids[0]}.json").write_text(json.dumps(item))
    assert main(["catalog", "validate", "--archive", str(copy)]) == 1
    assert "INVALID" in capsys.readouterr().out
    assert main(["catalog", "rebuild", "--archive", str(copy)]) == 0
    assert f"{copy / 'catalog.json'}: STAC catalog of 2 items" in capsys.readouterr().out
    for p, content in before.items():
        assert _json(copy / p) == content, p
    # the function itself, idempotent
    write_catalog(copy)
    assert _json(copy / "catalog" / "collection.json") == before["catalog/collection.json"]


def test_validation_reports_errors_and_never_fetches(stac_archive, no_network):
    archive_dir, ids = stac_archive
    item = _json(archive_dir / "catalog" / "items" / f"{ids[0]}.json")
    bad = json.loads(json.dumps(item))
    bad["assets"]["data"]["eo:bands"][1]["center_wavelength"] = "550 nm"
    (error,) = validation_errors(bad)
    assert error.startswith(EO_EXTENSION) and "center_wavelength" in error and "not of type 'number'" in error
    with pytest.raises(FormatError, match="not valid STAC"):
        validate(bad)
    bad = json.loads(json.dumps(item))
    bad["assets"]["data"]["raster:bands"][0]["data_type"] = "uint12"
    assert any(e.startswith(RASTER_EXTENSION) for e in validation_errors(bad))
    bad = json.loads(json.dumps(item))
    del bad["properties"]["datetime"]
    assert any(e.startswith(CORE_SCHEMAS["Feature"]) for e in validation_errors(bad))
    # a schema that is not vendored is an error, not a download
    other = "https://stac-extensions.github.io/sat/v1.0.0/schema.json"
    bad = {**item, "stac_extensions": [*item["stac_extensions"], other]}
    (error,) = validation_errors(bad)
    assert error.startswith(other) and "not vendored" in error
    with pytest.raises(pystac.errors.STACValidationError, match="not vendored"):
        pystac.Item.from_dict(bad).validate()
    # ... and so is a schema that refers to one that is not (proj:projjson -> PROJJSON v0.5)
    bad = {**item, "stac_extensions": [*item["stac_extensions"], PROJECTION_EXTENSION]}
    bad["properties"] = {**item["properties"], "proj:projjson": {"type": "ProjectedCRS"}}
    assert any("not vendored" in e for e in validation_errors(bad))
    assert "1.1.0 schemas are vendored" in validation_errors({**item, "stac_version": "1.0.0"})[0]
    assert no_network == []


def test_vendored_schemas_are_complete():
    schemas = vendored_schemas()
    from jsonschema import Draft7Validator

    for url, schema in schemas.items():
        Draft7Validator.check_schema(schema)
        assert schema["$id"].rstrip("#") in (url, url.replace(".json", "json")), url  # common.json: '...commonjson'
    # every reference resolves inside the vendored set (or to the JSON Schema meta-schema), except
    # the PROJJSON one of proj:projjson (never written by the archive)
    registry = schema_registry()
    unresolved = []

    def refs(node):
        if isinstance(node, dict):
            if isinstance(node.get("$ref"), str):
                yield node["$ref"]
            for v in node.values():
                yield from refs(v)
        elif isinstance(node, list):
            for v in node:
                yield from refs(v)

    from jsonschema_specifications import REGISTRY as META_SCHEMAS

    registry = META_SCHEMAS.combine(registry)
    for url, schema in schemas.items():
        resolver = registry.resolver(base_uri=url)
        for ref in refs(schema):
            try:
                resolver.lookup(ref)
            except Exception:
                unresolved.append(ref)
    assert set(unresolved) == {"https://proj.org/schemas/v0.5/projjson.schema.json"}
    readme = (REPO / "catalogs" / "schemas" / "README.md").read_text()
    for url in schemas:
        if "stac-extensions" in url:
            assert url in readme


def test_example_item_is_valid():
    assert validate(REPO / "catalogs" / "example-item.json")[0] == CORE_SCHEMAS["Feature"]


# ---------------------------------------------------------------------------------------------
# The Item of a rendered output
# ---------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    """A small flight rendered by the real pipeline to a COG and to ENVI, each with its sidecar
    Item written: {fmt: (out, item path)}, the output plan and the request."""
    import archive
    from archive.api import plan
    from archive.formats.lcf import gps_seconds_to_datetime
    from archive.run.options import RenderOptions

    base = tmp_path_factory.mktemp("product")
    flight = base / "flight"
    simulate_flight(flight, cubes=2, bands=5, samples=48, lines=120, cubes_per_pass=2, seed=1)
    keywords = dict(gsd=0.1, fov=FOV, wavelengths=[450.0, 550.0, 650.0])
    planned = plan([str(flight)], **keywords)
    request = RenderOptions.create([str(flight)], **keywords)
    source = planned.sources[0]
    times = np.concatenate([source.line_times(i) for i in range(len(source.cubes))])
    start, end = gps_seconds_to_datetime(float(times.min())), gps_seconds_to_datetime(float(times.max()))
    outputs = {}
    for fmt, name in (("cog", "mosaic.tif"), ("envi", "mosaic.hdr")):
        out = base / name
        archive.georectify([str(flight)], out, workers=1, threads=2, **keywords)
        item = product_item(out, fmt=format_named(fmt), grid=planned.plan.grid, band_indices=planned.plan.bands[0],
                            wavelengths=planned.wavelengths, fwhm=getattr(planned, "fwhm", None),
                            variable=planned.variable, attrs=planned.attrs, start=start, end=end,
                            sources=request.sources, command=render_command(request, out), request=request,
                            created=datetime(2025, 1, 2, 3, 4, 5, tzinfo=UTC))
        outputs[fmt] = (out, write_product_item(out, item))
    return outputs, planned, request


@pytest.fixture(scope="module")
def rendered_cog(rendered):
    """(COG path, its Item's path, the output plan, the request)."""
    outputs, planned, request = rendered
    return (*outputs["cog"], planned, request)


def test_product_item_is_valid_and_holds_its_recipe(rendered_cog, no_network):
    out, path, planned, request = rendered_cog
    assert path == out.with_name("mosaic.tif.json") == product_item_path(out)
    assert validate(path) == [CORE_SCHEMAS["Feature"], PROJECTION_EXTENSION, RASTER_EXTENSION, EO_EXTENSION,
                              PROCESSING_EXTENSION]
    item = pystac.Item.from_file(str(path))
    item.validate()
    props = item.properties
    grid = planned.plan.grid
    assert props["proj:code"] == f"EPSG:{grid.epsg}" and props["proj:shape"] == [grid.height, grid.width]
    assert props["processing:level"] == "L1B" and props["processing:datetime"] == "2025-01-02T03:04:05Z"
    assert props["archive:mode"] == "radiance" and props["archive:gsd_m"] == 0.1
    recipe = props["archive:recipe"]
    assert recipe["software"]["name"] == "archive" and recipe["software"]["version"]
    assert recipe["sources"] == list(request.sources)
    args = build_parser().parse_args(shlex.split(recipe["command"])[1:])
    assert args.command == "render" and Path(args.out) == out and args.gsd == 0.1
    assert recipe["request"]["wavelengths"] == [450.0, 550.0, 650.0]
    asset = item.assets["data"]
    assert asset.media_type == COG_MEDIA_TYPE and asset.href == "./mosaic.tif"
    eo = asset.extra_fields["eo:bands"]
    assert [round(b["center_wavelength"] * 1000, 3) for b in eo] == pytest.approx(planned.wavelengths)
    assert no_network == []


@pytest.mark.filterwarnings("ignore::PendingDeprecationWarning")  # odc-geo's use of affine's '*'
@pytest.mark.filterwarnings("ignore:The 'shapely.ops.transform:DeprecationWarning")  # odc-geo's too
def test_odc_stac_loads_the_cog_from_its_item(rendered_cog):
    """A real loader opens the product from its Item: right CRS, grid and band values."""
    import odc.stac
    import rasterio

    out, path, planned, _ = rendered_cog
    item = pystac.Item.from_file(str(path))
    with rasterio.open(out) as ds:
        values, crs, transform, shape = ds.read(), ds.crs, ds.transform, ds.shape
    names = [b["name"] for b in item.assets["data"].extra_fields["eo:bands"]]
    loaded = odc.stac.load([item])  # every band, on the asset's own grid
    gbox = loaded.odc.geobox
    assert gbox.crs.epsg == crs.to_epsg() == planned.plan.grid.epsg
    assert gbox.shape == shape and tuple(gbox.affine)[:6] == pytest.approx(tuple(transform)[:6], abs=1e-9)
    assert list(loaded.data_vars) == names  # aliased by the eo:bands names
    for b, name in enumerate(names):
        got = loaded[name].values[0]
        np.testing.assert_array_equal(got.view(np.uint32), values[b].view(np.uint32))  # NaN where not covered too
    assert np.isfinite(values).any() and np.isnan(values).any()
    # the canonical asset.band names, in any order and subset
    some = odc.stac.load([item], bands=["data.3", "data.1"])
    np.testing.assert_array_equal(some["data.3"].values[0], values[2])
    np.testing.assert_array_equal(some["data.1"].values[0], values[0])


@pytest.mark.filterwarnings("ignore::PendingDeprecationWarning")  # odc-geo's use of affine's '*'
@pytest.mark.filterwarnings("ignore:The 'shapely.ops.transform:DeprecationWarning")  # odc-geo's too
def test_odc_stac_loads_envi_from_its_item(rendered):
    """ENVI: the data file is the asset; GDAL finds its header beside it only when it may list the
    folder, which odc-stac forbids by default (GDAL_DISABLE_READDIR_ON_OPEN=EMPTY_DIR, for cloud
    reads): with that allowed, odc-stac loads it like the COG."""
    import odc.stac
    import rasterio

    outputs, planned, _ = rendered
    out, path = outputs["envi"]
    assert validate(path)[1:] == [PROJECTION_EXTENSION, RASTER_EXTENSION, EO_EXTENSION, PROCESSING_EXTENSION]
    item = pystac.Item.from_file(str(path))
    assert Path(item.assets["data"].get_absolute_href()) == out.with_suffix("")
    assert Path(item.assets["header"].get_absolute_href()) == out
    assert item.assets["data"].media_type == "image/x-envi" and item.assets["header"].media_type == "text/plain"
    with rasterio.open(out.with_suffix("")) as ds:
        values, transform = ds.read(), ds.transform
    odc.stac.configure_rio(GDAL_DISABLE_READDIR_ON_OPEN="FALSE")   # docs/ecosystem.md's recipe, as written there
    try:
        loaded = odc.stac.load([pystac.Item.from_file(str(path))])
    finally:
        odc.stac.configure_rio(GDAL_DISABLE_READDIR_ON_OPEN="EMPTY_DIR")
    assert loaded.odc.geobox.crs.epsg == planned.plan.grid.epsg
    assert tuple(loaded.odc.geobox.affine)[:6] == pytest.approx(tuple(transform)[:6], abs=1e-9)
    for b, name in enumerate(loaded.data_vars):
        np.testing.assert_array_equal(loaded[name].values[0].view(np.uint32), values[b].view(np.uint32))


def test_every_asset_has_a_media_type(rendered):
    """Loaders pick assets by media type (issue 36): no asset of an output Item goes without one."""
    outputs, _, _ = rendered
    for fmt, (_, path) in outputs.items():
        item = pystac.Item.from_file(str(path))
        assert all(a.media_type for a in item.assets.values()), (fmt, {k: a.media_type for k, a in item.assets.items()})


def test_docs_give_the_odc_stac_envi_recipe():
    """docs/ecosystem.md's recipe is the one the ENVI test above runs (configure_rio, not the
    environment; tests/test_ecosystem.py runs the page's recipes)."""
    doc = (Path(__file__).resolve().parents[1] / "docs" / "ecosystem.md").read_text()
    assert 'odc.stac.configure_rio(GDAL_DISABLE_READDIR_ON_OPEN="FALSE")' in doc
    assert "with `GDAL_DISABLE_READDIR_ON_OPEN=FALSE`, an ENVI" not in doc


def test_grid_footprint(rendered_cog):
    _, _, planned, _ = rendered_cog
    grid = planned.plan.grid
    geometry, bbox = grid_footprint(grid)
    ring = np.asarray(geometry["coordinates"][0])
    assert geometry["type"] == "Polygon" and np.array_equal(ring[0], ring[-1])
    x, y = ring[:-1, 0], ring[:-1, 1]
    assert 0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y) > 0  # counter-clockwise (RFC 7946)
    expected = Transformer.from_crs(grid.epsg, 4326, always_xy=True).transform_bounds(*grid.bounds, densify_pts=21)
    np.testing.assert_allclose(bbox, expected, atol=1e-8)


def _grid() -> Grid:
    return Grid(32616, 0.5, 232000.0, 3890400.0, 40, 30)


def _item(out: Path, fmt: str, **more) -> dict:
    kwargs = dict(fmt=format_named(fmt), grid=_grid(), band_indices=[3, 7], wavelengths=[550.0, 650.0],
                  fwhm=[5.0, float("nan")],
                  variable="reflectance", attrs={"mode": "reflectance", "gsd_m": 0.5, "sources": ["f"]},
                  start=datetime(2024, 6, 12, 16, tzinfo=UTC), end=datetime(2024, 6, 12, 16, 5, tzinfo=UTC),
                  sources=["f"], command="archive render f --out x --gsd 0.5", request={"gsd": 0.5, "bands": (3, 7)})
    kwargs.update(more)
    return product_item(out, **kwargs)


def _write_geotiff(path: Path, count: int) -> None:
    import rasterio

    grid = _grid()
    with rasterio.open(path, "w", driver="GTiff", width=grid.width, height=grid.height, count=count,
                       dtype="float32", crs=grid.crs, transform=grid.transform, nodata=float("nan")) as ds:
        ds.write(np.zeros((count, grid.height, grid.width), np.float32))
        for b in range(count):
            ds.set_band_description(b + 1, f"layer{b}")
        ds.units = ["degree"] * count


def test_product_items_of_every_format(tmp_path):
    # ENVI: the data file and the header, two assets; ENVI data has no registered media type: image/x-envi
    envi = _item(tmp_path / "m.hdr", "envi")
    assert validate(envi)[0] == CORE_SCHEMAS["Feature"]
    assert envi["id"] == "m.hdr" and envi["assets"]["data"]["href"] == "./m"
    assert envi["assets"]["data"]["type"] == "image/x-envi"
    assert envi["assets"]["header"] == {"href": "./m.hdr", "type": "text/plain", "title": "ENVI header",
                                        "roles": ["metadata"]}
    eo = envi["assets"]["data"]["eo:bands"]
    assert eo == [{"name": "b3", "center_wavelength": 0.55, "full_width_half_max": 0.005},
                  {"name": "b7", "center_wavelength": 0.65}]  # no fwhm where it is unknown
    assert envi["properties"]["processing:level"] == "L2A"
    assert envi["assets"]["data"]["raster:bands"][0] == {"data_type": "float32", "nodata": "nan", "sampling": "area",
                                                         "scale": 1.0, "offset": 0.0, "spatial_resolution": 0.5,
                                                         "unit": "1"}
    assert envi["properties"]["archive:recipe"]["request"] == {"gsd": 0.5, "bands": [3, 7]}
    # Zarr, its provenance layers inside the same store: described in the properties only
    import zarr

    store = tmp_path / "m.zarr"
    group = zarr.open_group(store, mode="w")
    for name in ("reflectance", "saturated", "x", "y", "view_zenith", "cube"):
        group.create_array(name, shape=(2,), dtype="f4")
    group["view_zenith"].attrs["units"] = "degree"
    zitem = _item(store, "zarr", provenance=store)
    assert validate(zitem)[0] == CORE_SCHEMAS["Feature"]
    assert zitem["assets"]["data"]["type"] == "application/vnd+zarr" and set(zitem["assets"]) == {"data"}
    assert zitem["properties"]["archive:provenance"] == {
        "asset": "data", "layers": [{"name": "cube"}, {"name": "view_zenith", "units": "degree"}]}
    # COG with a sibling provenance COG: an asset of its own, its bands read from the file
    _write_geotiff(tmp_path / "m_provenance.tif", 3)
    cog = _item(tmp_path / "m.tif", "cog", provenance=tmp_path / "m_provenance.tif", wavelengths=None, fwhm=None)
    assert validate(cog) == [CORE_SCHEMAS["Feature"], PROJECTION_EXTENSION, RASTER_EXTENSION, PROCESSING_EXTENSION]
    prov = cog["assets"]["provenance"]
    assert prov["href"] == "./m_provenance.tif" and prov["archive:layers"] == ["layer0", "layer1", "layer2"]
    assert prov["raster:bands"] == [{"data_type": "float32", "nodata": "nan", "unit": "degree"}] * 3
    assert prov["proj:shape"] == [30, 40]
    assert "eo:bands" not in cog["properties"]
    with pytest.raises(InputError, match="2 wavelengths for 1 bands"):
        _item(tmp_path / "m.tif", "cog", band_indices=[1])
    with pytest.raises(InputError, match="unknown output format"):
        _item(tmp_path / "m.tif", "gtiff")


# ---------------------------------------------------------------------------------------------
# The command in the recipe
# ---------------------------------------------------------------------------------------------
def _round_trip(command: str):
    """The RenderOptions that ``archive render`` would build from ``command``."""
    from archive.run.options import KEYWORDS
    from archive.run.command import render_keywords
    from archive.run.options import RenderOptions

    args = build_parser().parse_args(shlex.split(command)[1:])
    keywords = render_keywords(args)
    return RenderOptions.create(keywords["sources"], **{k: keywords[k] for k in KEYWORDS}), keywords


def test_render_command_leaves_out_defaults(tmp_path):
    from archive.run.options import RenderOptions

    flight = tmp_path / "my flight"
    flight.mkdir()
    request = RenderOptions.create([str(flight)], gsd=0.25, fov=FOV)
    command = render_command(request, tmp_path / "out.tif")
    assert command == shlex.join(["archive", "render", str(flight), "--out", str(tmp_path / "out.tif"),
                                  "--gsd", "0.25", "--fov", str(FOV)])
    again, keywords = _round_trip(command)
    assert again == request and keywords["out"] == str(tmp_path / "out.tif")


def test_render_command_round_trips_every_option(tmp_path, monkeypatch):
    from archive.run.options import RenderOptions

    monkeypatch.chdir(tmp_path)
    (tmp_path / "arc").mkdir()
    (tmp_path / "dem.tif").touch()
    (tmp_path / "white.txt").touch()
    request = RenderOptions.create(
        ["Pika-L-SIM_20240612T160000"], gsd=0.2, archive="arc", fov=30.0, ground_height=81.5,
        bands=[0, 2, 5], mode="reflectance", white_reference="white.txt", sync_offset=-0.012,
        boresight=(-0.5, 1.25, 0.0), lever_arm=(0.1, -0.2, 0.3), overlap="mean", crs="EPSG:32615",
        max_view_angle=35.0, dem="dem.tif", dem_datum="egm96")
    command = render_command(request, "out dir/m.zarr", quicklook="q.png", provenance=True, overwrite=True)
    words = shlex.split(command)
    assert words[:3] == ["archive", "render", "Pika-L-SIM_20240612T160000"]  # a collection id stays an id
    assert "--boresight=-0.5,1.25,0" in words and "--sync-offset=-0.012" in words
    assert {"--provenance", "--overwrite"} <= set(words)
    again, keywords = _round_trip(command)
    expected = dataclasses.replace(request, archive=str(tmp_path / "arc"), dem=str(tmp_path / "dem.tif"),
                                   white_reference=str(tmp_path / "white.txt"), provenance=True)  # --provenance
    assert dataclasses.replace(again, ground_height=float(again.ground_height)) == expected
    assert keywords["out"] == str(tmp_path / "out dir" / "m.zarr") and keywords["quicklook"] == str(tmp_path / "q.png")
    with pytest.raises(InputError, match="render options"):
        render_command({"gsd": 1.0}, "x.tif")


def test_the_collection_summarises_many_items_as_the_items_say(tmp_path):
    """The archive's Collection (asked of the index in SQL since issue 45) against the Item files
    themselves: 60 synthetic Items at random places and times, some sharing a start or an end time."""
    import random
    from datetime import UTC, datetime, timedelta

    from archive.catalog.index import add_rows, row_from_item
    from archive.catalog.root import create_archive
    from archive.catalog.stac import make_item, write_item
    from archive.catalog.tree import item_links, write_catalog

    rng = random.Random(4)
    root = create_archive(tmp_path / "archive")
    t0 = datetime(2020, 1, 1, tzinfo=UTC)
    rows, items = [], []
    for k in range(60):
        cid = f"sim-{k:03d}"
        lon, lat = rng.uniform(-120, -70), rng.uniform(25, 50)
        start = t0 + timedelta(hours=rng.choice([0, 5, 9, 9, 30, 48]), minutes=k % 7)
        end = start + timedelta(minutes=rng.choice([3, 10, 10]))
        ring = [[lon, lat], [lon + 0.01, lat], [lon + 0.01, lat + 0.01], [lon, lat + 0.01], [lon, lat]]
        item = make_item(cid, {"type": "Polygon", "coordinates": [ring]}, [lon, lat, lon + 0.01, lat + 0.01], start,
                         end, [500.0, 600.0], 2, rng.choice(["Pika L", "Pika XC2"]), rng.choice([0.03, 0.05, 0.04]),
                         f"../../collections/{cid}.zarr", collection=COLLECTION_ID, links=item_links())
        path = write_item(root.item_path(cid), item)
        items.append(item)
        rows.append(row_from_item(item, path.relative_to(root.path).as_posix()))
    add_rows(root.index_path, rows)
    write_catalog(root)
    doc = _json(root.collection_path)
    (bbox,) = doc["extent"]["spatial"]["bbox"]
    assert bbox == pytest.approx([min(i["bbox"][0] for i in items), min(i["bbox"][1] for i in items),
                                  max(i["bbox"][2] for i in items), max(i["bbox"][3] for i in items)])
    (interval,) = doc["extent"]["temporal"]["interval"]
    starts = [i["properties"]["start_datetime"] for i in items]
    ends = [i["properties"]["end_datetime"] for i in items]
    assert interval == [min(starts), max(ends)]
    assert doc["summaries"]["instruments"] == sorted({i["properties"]["instruments"][0] for i in items})
    gsds = [i["properties"]["gsd"] for i in items if i["properties"].get("gsd") is not None]
    assert doc["summaries"]["gsd"] == {"minimum": min(gsds), "maximum": max(gsds)}
    by_time = sorted(items, key=lambda i: (i["properties"]["start_datetime"], i["id"]))
    assert [ln["title"] for ln in doc["links"] if ln["rel"] == "item"] == [i["id"] for i in by_time]
    assert all((root.collection_path.parent / ln["href"]).is_file() for ln in doc["links"] if ln["rel"] == "item")
    pystac.Collection.from_dict(doc).validate()
