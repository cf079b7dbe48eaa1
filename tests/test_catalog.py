"""Catalog: STAC Items of ingested flights, the SQLite index, and `archive catalog` queries.
Three simulated flights at different places, times and wavelengths; real files and databases."""

from __future__ import annotations

import dataclasses
import json
import re
import sqlite3
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pystac
import pytest
from pyproj import Transformer

from archive.catalog.footprint import points_in_polygon
from archive.catalog.index import SCHEMA, parse_bbox, parse_datetime_range, search
from archive.catalog.stac import item_summary
from archive.cli import main
from archive.errors import InputError
from archive.ingest.command import ingest
from archive.formats.flight import discover_flight
from archive.formats.lcf import read_lcf, write_lcf
from archive.simulator.command import simulate_flight
from helpers import FOV

REPO = Path(__file__).resolve().parents[1]
DAY = 86400.0


def _shift_times(d: Path, seconds: float) -> None:
    for c in discover_flight(d).cubes:
        lcf = read_lcf(c.lcf)
        write_lcf(c.lcf, dataclasses.replace(lcf, time=lcf.time + seconds))


def _rewrite_headers(d: Path, wavelengths: np.ndarray | None = None, sensor: str | None = None) -> None:
    for c in discover_flight(d).cubes:
        text = c.header.read_text()
        if wavelengths is not None:
            wl = ", ".join(f"{w:.3f}" for w in wavelengths)
            text = re.sub(r"wavelength = \{[^}]*\}", f"wavelength = {{{wl}}}", text)
        if sensor is not None:
            text = re.sub(r"imager serial number = .*", f"imager serial number = {sensor}", text)
        c.header.write_text(text)


FLIGHTS = {
    # name: (simulate kwargs, time shift s, new wavelengths, new sensor)
    "memphis": (dict(lat=35.12, lon=-89.94, bands=4, cubes_per_pass=2), 0.0, None, None),
    "dakota": (dict(lat=45.5, lon=-100.3, bands=5, cubes_per_pass=1), 30 * DAY, None, None),
    "sydney": (dict(lat=-33.9, lon=151.2, bands=6, cubes_per_pass=1), 400 * DAY,
               np.linspace(950.0, 1700.0, 6), "Pika IR-99"),
}


@pytest.fixture(scope="module")
def catalog(tmp_path_factory):
    base = tmp_path_factory.mktemp("catalog")
    archive_dir = base / "archive"
    flights, truths = {}, {}
    for name, (kw, shift, wl, sensor) in FLIGHTS.items():
        d = base / name
        truths[name] = simulate_flight(d, cubes=2, samples=48, lines=250, seed=len(name),
                                       start="2024-06-12T16:00:00Z", **kw)
        if shift:
            _shift_times(d, shift)
        if wl is not None or sensor is not None:
            _rewrite_headers(d, wl, sensor)
            (d / "calibration.icp").unlink()  # it no longer matches the bands
        flights[name] = d
    ids = {}
    for name, d in flights.items():
        (r,) = ingest([str(d)], archive_dir, FOV, ground_height=truths[name].ground_height, progress=False)
        ids[name] = r.cid
    return archive_dir, ids, truths


def _item(archive_dir: Path, cid: str) -> dict:
    return json.loads((archive_dir / "catalog" / "items" / f"{cid}.json").read_text())


def _search(archive_dir: Path, capsys, *args: str) -> set[str]:
    capsys.readouterr()
    assert main(["catalog", "search", "--archive", str(archive_dir), *args, "--json"]) == 0
    collection = pystac.ItemCollection.from_dict(json.loads(capsys.readouterr().out))
    return {item.id for item in collection}


def test_ids(catalog):
    _, ids, _ = catalog
    assert ids == {"memphis": "Pika-L-SIM_20240612T160000", "dakota": "Pika-L-SIM_20240712T160000",
                   "sydney": "Pika-IR-99_20250717T160000"}


def test_items_parse_with_pystac(catalog):
    archive_dir, ids, truths = catalog
    for name, cid in ids.items():
        d = _item(archive_dir, cid)
        item = pystac.Item.from_dict(d)
        assert item.id == cid
        assert item.to_dict(include_self_link=False, transform_hrefs=False)["properties"] == d["properties"]
        asset = item.assets["data"]
        assert asset.media_type == "application/vnd+zarr"
        store = (archive_dir / "catalog" / "items" / asset.href).resolve()
        assert store == (archive_dir / "collections" / f"{cid}.zarr").resolve() and store.is_dir()
        props = item.properties
        assert props["archive:bands"] == FLIGHTS[name][0]["bands"]
        assert len(props["eo:bands"]) == props["archive:bands"]
        assert props["instruments"] == [FLIGHTS[name][3] or "Pika L-SIM"]
        assert item.common_metadata.start_datetime < item.common_metadata.end_datetime
    # nominal across-track GSD: 2 h tan(fov/2) / samples with h ~ 40 m above the ground
    memphis = _item(archive_dir, ids["memphis"])["properties"]
    assert memphis["gsd"] == pytest.approx(2 * 40 * np.tan(np.radians(47.5 / 2)) / 48, rel=0.05)
    assert memphis["start_datetime"].startswith("2024-06-12T16:00:00")


def test_footprints_contain_the_truth(catalog):
    archive_dir, ids, truths = catalog
    for name, cid in ids.items():
        item = _item(archive_dir, cid)
        geom = item["geometry"]
        polys = [geom["coordinates"]] if geom["type"] == "Polygon" else geom["coordinates"]
        rings = [np.asarray(p[0], float) for p in polys]
        truth = truths[name]
        assert len(rings) == len(truth.footprint())  # one ring per strip
        to_lonlat = Transformer.from_crs(truth.epsg, 4326, always_xy=True)
        pts = []
        for strip in truth.footprint():
            lon, lat = to_lonlat.transform(strip[:, 0], strip[:, 1])
            pts.append(np.stack([lon, lat], axis=-1))
        pts = np.vstack(pts)
        inside = np.zeros(len(pts), bool)
        for ring in rings:
            inside |= points_in_polygon(pts, ring)
        assert inside.all(), f"{name}: {np.count_nonzero(~inside)} true footprint vertices outside"
        # ... and not much larger: the bbox grows by less than 3 m on every side
        w, s, e, n = item["bbox"]
        m_lat = 1 / 111_000.0
        m_lon = m_lat / np.cos(np.radians(pts[:, 1].mean()))
        assert 0 <= pts[:, 0].min() - w < 3 * m_lon and 0 <= e - pts[:, 0].max() < 3 * m_lon
        assert 0 <= pts[:, 1].min() - s < 3 * m_lat and 0 <= n - pts[:, 1].max() < 3 * m_lat


def test_search_by_bbox(catalog, capsys):
    archive_dir, ids, _ = catalog
    everything = set(ids.values())
    assert _search(archive_dir, capsys, "--bbox", "-180,-90,180,90") == everything
    assert _search(archive_dir, capsys) == everything
    for name, cid in ids.items():
        w, s, e, n = _item(archive_dir, cid)["bbox"]
        cx, cy = (w + e) / 2, (s + n) / 2
        assert _search(archive_dir, capsys, "--bbox", f"{cx - 0.01},{cy - 0.01},{cx + 0.01},{cy + 0.01}") == {cid}
        # touching the east edge exactly still intersects; 1e-6 deg further does not
        assert search(archive_dir / "catalog" / "index.sqlite", bbox=(e, s, e + 1, n)) != []
        assert [r.id for r in search(archive_dir / "catalog" / "index.sqlite", bbox=(e + 1e-6, s, e + 1, n))] == []
    assert _search(archive_dir, capsys, "--bbox", "-100,30,-80,40") == {ids["memphis"]}
    assert _search(archive_dir, capsys, "--bbox", "-120,30,-80,50") == {ids["memphis"], ids["dakota"]}
    assert _search(archive_dir, capsys, "--bbox", "0,0,10,10") == set()


def test_search_by_time(catalog, capsys):
    archive_dir, ids, _ = catalog
    m, d, s = ids["memphis"], ids["dakota"], ids["sydney"]
    assert _search(archive_dir, capsys, "--datetime", "2024-06-12") == {m}
    assert _search(archive_dir, capsys, "--datetime", "2024-06-12T16:00:01Z") == {m}
    assert _search(archive_dir, capsys, "--datetime", "2024-06-12T17:00:00Z") == set()
    assert _search(archive_dir, capsys, "--datetime", "2024-07-01/..") == {d, s}
    assert _search(archive_dir, capsys, "--datetime", "../2024-07-12T00:00:00Z") == {m}
    assert _search(archive_dir, capsys, "--datetime", "2024-06-12T12:00:00-04:00/2024-07-12") == {m, d}
    assert _search(archive_dir, capsys, "--datetime", "2025-01-01/2026-01-01") == {s}


def test_search_by_wavelength_and_combined(catalog, capsys):
    archive_dir, ids, _ = catalog
    m, d, s = ids["memphis"], ids["dakota"], ids["sydney"]
    assert _search(archive_dir, capsys, "--wavelength", "500") == {m, d}
    assert _search(archive_dir, capsys, "--wavelength", "1200") == {s}
    assert _search(archive_dir, capsys, "--wavelength", "1000") == {m, d, s}
    assert _search(archive_dir, capsys, "--wavelength", "300") == set()
    assert _search(archive_dir, capsys, "--bbox", "-180,-90,180,90", "--datetime", "2024-06-01/2024-12-31",
                   "--wavelength", "960") == {m, d}
    assert _search(archive_dir, capsys, "--bbox", "-120,30,-80,50", "--wavelength", "1200") == set()


def test_table_list_and_rebuild(catalog, capsys):
    archive_dir, ids, _ = catalog
    capsys.readouterr()
    assert main(["catalog", "list", "--archive", str(archive_dir)]) == 0
    out = capsys.readouterr().out
    lines = out.strip().splitlines()
    assert lines[0].split()[:5] == ["id", "start", "end", "bands", "wavelengths"]
    assert lines[-1] == "3 flights"
    assert [line.split()[0] for line in lines[1:4]] == [ids["memphis"], ids["dakota"], ids["sydney"]]
    assert "950.0-1700.0 nm" in lines[3]
    # a half-written collection is never listed
    (archive_dir / "collections" / "Pika-L-SIM_20990101T000000.zarr.partial").mkdir()
    # lost index, damaged index: rebuilt from the Items on demand (it is a cache of them)
    index = archive_dir / "catalog" / "index.sqlite"
    index.unlink()
    assert _search(archive_dir, capsys, "--wavelength", "1200") == {ids["sydney"]}
    index.write_bytes(b"not a database at all" * 100)
    assert main(["catalog", "list", "--archive", str(archive_dir)]) == 0
    assert capsys.readouterr().out.strip().splitlines()[-1] == "3 flights"
    assert index.read_bytes().startswith(b"SQLite format 3")
    assert main(["catalog", "rebuild", "--archive", str(archive_dir)]) == 0
    assert "3 items indexed" in capsys.readouterr().out
    assert _search(archive_dir, capsys) == set(ids.values())
    with sqlite3.connect(index) as con:
        assert con.execute("SELECT count(*) FROM items_bbox").fetchone()[0] == 3
        plan = " ".join(str(r) for r in con.execute(
            "EXPLAIN QUERY PLAN SELECT id FROM items WHERE start_time <= ? AND end_time >= ?", (1.0, 0.0)))
        assert "items_start" in plan or "items_end" in plan


def test_schema_and_example_item_in_sync():
    assert (REPO / "catalogs" / "schema.sql").read_text() == SCHEMA
    example = json.loads((REPO / "catalogs" / "example-item.json").read_text())
    item = pystac.Item.from_dict(example)
    summary = item_summary(example)
    assert summary["bands"] == len(item.properties["eo:bands"])
    assert example["assets"]["data"]["type"] == "application/vnd+zarr"


@pytest.mark.parametrize("args, message", [
    (["--bbox", "1,2,3"], "expected 4 comma-separated numbers"),
    (["--bbox", "a,b,c,d"], "expected numbers"),
    (["--bbox", "10,0,5,1"], "west 10.0 is east of east 5.0"),
    (["--bbox", "0,95,1,96"], "out of range"),
    (["--bbox", "0,5,1,2"], "south 5.0 is north of north 2.0"),
    (["--datetime", "2024-13-01"], "is not a date or date-time"),
    (["--datetime", "../.."], "both ends"),
    (["--datetime", "2025-01-01/2024-01-01"], "is after end"),
    (["--datetime", "a/b/c"], "expected START/END"),
    (["--wavelength", "-5"], "not a positive wavelength"),
])
def test_malformed_queries(catalog, capsys, args, message):
    archive_dir, _, _ = catalog
    capsys.readouterr()
    assert main(["catalog", "search", "--archive", str(archive_dir), *args]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1


def test_not_an_archive(tmp_path, capsys):
    assert main(["catalog", "list", "--archive", str(tmp_path)]) == 2
    assert "not an archive (no archive.json)" in capsys.readouterr().err
    assert main(["catalog", "search", "--archive", str(tmp_path / "missing")]) == 2
    assert "archive directory not found" in capsys.readouterr().err


def test_parsers():
    assert parse_bbox(" -90.5, 35 ,-89,36") == (-90.5, 35.0, -89.0, 36.0)
    start, end = parse_datetime_range("2024-06-12")
    assert start == datetime(2024, 6, 12, tzinfo=UTC).timestamp()
    assert end == pytest.approx(datetime(2024, 6, 13, tzinfo=UTC).timestamp(), abs=1e-5)
    assert parse_datetime_range("2024-06-12T10:00:00Z/..") == (datetime(2024, 6, 12, 10, tzinfo=UTC).timestamp(), None)
    with pytest.raises(InputError):
        parse_bbox("1,2,3,inf")


def test_datetime_months_and_years():
    from datetime import UTC, datetime

    start, end = parse_datetime_range("2024-06/2024-07")
    assert datetime.fromtimestamp(start, UTC) == datetime(2024, 6, 1, tzinfo=UTC)
    assert datetime.fromtimestamp(end, UTC) == datetime(2024, 7, 31, 23, 59, 59, 999999, tzinfo=UTC)
    start, end = parse_datetime_range("2023")
    assert datetime.fromtimestamp(end, UTC).date().isoformat() == "2023-12-31"
    with pytest.raises(InputError, match="not a date"):
        parse_datetime_range("2024-13")
