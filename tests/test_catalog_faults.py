"""A damaged catalog heals instead of hiding the archive, and a read-only archive can be searched,
batch-rendered and viewed (issue 30, findings 4 and 5).

Two small simulated flights ingested into an archive; each test damages a copy of it: a 0-byte,
truncated or foreign ``index.sqlite``; a deleted or truncated Item; the whole archive on a
read-only bind mount (``unshare -m`` + ``mount --bind -o ro``: tests run as root, for whom
``chmod a-w`` stops nothing; skipped with the reason where mounts are impossible). Through the CLI
(``main``, or its own process for the read-only mount) and the HTTP API of ``archive view``."""

from __future__ import annotations

import json
import os
import shutil
import sqlite3
import subprocess
import sys
from pathlib import Path

import pytest

from archive.catalog.health import catalog_problems
from archive.catalog.root import open_root
from archive.cli import main
from archive.ingest.command import ingest
from archive.simulator.command import simulate_flight
from archive.view.registry import FlightRegistry
from archive.view.server import LOOPBACK_NAMES, create_app
from helpers import FOV

STARTS = ("2024-06-12T16:00:00Z", "2024-07-01T10:00:00Z")


@pytest.fixture(scope="module")
def pristine(tmp_path_factory) -> tuple[Path, list[str]]:
    """(archive of two small flights, their ids); tests damage copies of it."""
    base = tmp_path_factory.mktemp("catalog_faults")
    ids = []
    for k, start in enumerate(STARTS):
        d = base / f"flight{k}"
        truth = simulate_flight(d, cubes=1, samples=32, lines=120, seed=k + 1, start=start)
        (r,) = ingest([str(d)], base / "archive", FOV, ground_height=truth.ground_height, progress=False)
        ids.append(r.cid)
    return base / "archive", ids


@pytest.fixture
def archive(pristine, tmp_path) -> tuple[Path, list[str]]:
    src, ids = pristine
    return Path(shutil.copytree(src, tmp_path / "archive")), ids


def cli(capsys, *args: str) -> tuple[int, str, str]:
    capsys.readouterr()
    code = main(list(args))
    out = capsys.readouterr()
    return code, out.out, out.err


def searched(capsys, archive: Path, *args: str) -> list[str]:
    code, out, err = cli(capsys, "catalog", "search", "--archive", str(archive), *args, "--json")
    assert code == 0, err
    return [f["id"] for f in json.loads(out)["features"]]


def _truncate(path: Path, keep: float = 0.5) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * keep)])


def _foreign_schema(path: Path) -> None:
    path.unlink()
    with sqlite3.connect(path) as con:
        con.execute("CREATE TABLE items (id TEXT, name TEXT)")
        con.execute("CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT)")
        con.execute("INSERT INTO meta VALUES ('schema_version', '2')")
        con.execute("INSERT INTO items VALUES ('x', 'y')")


@pytest.mark.parametrize("damage", ["empty", "truncated", "foreign schema", "rows lost"])
def test_a_damaged_index_is_detected_and_rebuilt(archive, capsys, damage):
    """Finding 4: a 0-byte index.sqlite made search, list, batch and view show "0 flights" with exit
    0 while validate said all was well."""
    archive_dir, ids = archive
    index = archive_dir / "catalog" / "index.sqlite"
    if damage == "empty":
        index.write_bytes(b"")
    elif damage == "truncated":
        _truncate(index, 0.4)
    elif damage == "foreign schema":
        _foreign_schema(index)
    else:  # a valid database that lost a flight's rows: the row count no longer matches the Items
        with sqlite3.connect(index) as con:
            rowid = con.execute("SELECT rowid FROM items WHERE id = ?", (ids[0],)).fetchone()[0]
            con.execute("DELETE FROM items WHERE rowid = ?", (rowid,))
            con.execute("DELETE FROM items_bbox WHERE id = ?", (rowid,))
    # validate reports the damaged index (before anything has healed it)
    code, out, _ = cli(capsys, "catalog", "validate", "--archive", str(archive_dir))
    assert code == 1 and f"{index}: INVALID" in out and "catalog index is" in out, out
    # search and list see every flight (the index is rebuilt from the Items), exit 0
    assert searched(capsys, archive_dir) == ids
    code, out, _ = cli(capsys, "catalog", "list", "--archive", str(archive_dir))
    assert code == 0 and out.strip().splitlines()[-1] == "2 flights"
    assert index.read_bytes().startswith(b"SQLite format 3")
    code, out, _ = cli(capsys, "catalog", "validate", "--archive", str(archive_dir))
    assert code == 0, out
    # the batch render's query and the viewer's listing see them too
    from archive.api import open_archive

    assert open_archive(archive_dir).search() == ids
    registry = FlightRegistry(archive_dir)
    try:
        assert sorted(registry.catalog_ids()) == sorted(ids)
    finally:
        registry.close()


def test_ingest_again_over_a_damaged_index(pristine, archive, capsys):
    """Re-ingesting a flight ("already ingested") over a 0-byte index: the index is rebuilt, not a
    traceback and not a flight lost."""
    archive_dir, ids = archive
    (archive_dir / "catalog" / "index.sqlite").write_bytes(b"")
    item = json.loads((archive_dir / "catalog" / "items" / f"{ids[0]}.json").read_text())
    raw = pristine[0].parent / "flight0"
    code, out, err = cli(capsys, "ingest", str(raw), "--archive", str(archive_dir), "--fov", str(FOV),
                         "--ground-height", str(item["properties"]["archive:ground_height"]), "--quiet")
    assert code == 0, err
    assert searched(capsys, archive_dir) == ids


def _client(archive_dir: Path):
    from starlette.testclient import TestClient

    registry = FlightRegistry(archive_dir)
    return TestClient(create_app(registry, allowed_hosts=LOOPBACK_NAMES), base_url="http://127.0.0.1"), registry


@pytest.mark.parametrize("damage", ["deleted", "truncated", "not an Item"])
def test_a_damaged_item_costs_only_its_flight(archive, capsys, damage):
    """Finding 4: one missing or truncated Item made /api/collections fail as a whole and
    /stac/search pages holding it 404; 'catalog rebuild' then dropped the flight."""
    archive_dir, ids = archive
    bad, good = ids
    item = archive_dir / "catalog" / "items" / f"{bad}.json"
    original = json.loads(item.read_text())
    # the index knows both flights, then the Item is damaged
    assert searched(capsys, archive_dir) == ids
    if damage == "deleted":
        item.unlink()
    elif damage == "truncated":
        _truncate(item)
    else:
        item.write_text(json.dumps({"type": "Feature", "id": bad, "properties": {}}))

    client, registry = _client(archive_dir)
    try:
        r = client.get("/api/collections")
        assert r.status_code == 200, r.text
        doc = r.json()
        assert [f["id"] for f in doc["features"]] == [good]
        assert [d["id"] for d in doc["damaged"]] == [bad] and doc["damaged"][0]["reason"]
        assert "rebuild" in doc["damaged"][0]["fix"]
        for url in ("/stac/search", "/stac/collections/flights/items", "/stac/search?limit=1",
                    "/stac/search?limit=1&token=o1"):
            r = client.get(url)
            assert r.status_code == 200, (url, r.text)
        r = client.post("/stac/search", json={"limit": 10})
        assert r.status_code == 200 and [f["id"] for f in r.json()["features"]] == [good], r.text
        assert client.get(f"/stac/collections/flights/items/{good}").status_code == 200
        assert client.get(f"/api/collections/{good}").status_code == 200
    finally:
        client.close()
        registry.close()

    # verify's and validate's view of the catalog name the flight and the fix
    problems = catalog_problems(open_root(archive_dir))
    assert len(problems) == 1 and bad in problems[0][0] and "rebuild" in problems[0][1], problems
    code, out, _ = cli(capsys, "catalog", "validate", "--archive", str(archive_dir))
    assert code == 1 and bad in out and "INVALID" in out, out
    # verify: the data of both flights is intact, the damaged Item makes it fail, naming it
    code, out, _ = cli(capsys, "verify", "--archive", str(archive_dir), "--quiet")
    damaged = [line for line in out.splitlines() if "DAMAGED" in line]
    assert code == 1 and len(damaged) == 1 and bad in damaged[0] and "rebuild" in damaged[0], out
    assert f"{bad}: OK" in out and f"{good}: OK" in out, out   # its data is intact
    code, out, _ = cli(capsys, "verify", "--archive", str(archive_dir), good, "--quiet")
    assert code == 0 and "DAMAGED" not in out, out
    # search and list: the other flight, and a warning naming the damaged one
    code, out, err = cli(capsys, "catalog", "list", "--archive", str(archive_dir), "--json")
    assert code == 0 and [f["id"] for f in json.loads(out)["features"]] == [good]
    assert bad in err and "damaged" in err

    # rebuild recreates the Item from the collection store (its metadata is there)
    code, out, err = cli(capsys, "catalog", "rebuild", "--archive", str(archive_dir))
    assert code == 0, (out, err)
    assert f"{bad}:" in out and "recreated" in out and "2 items indexed" in out
    assert searched(capsys, archive_dir) == ids
    rebuilt = json.loads(item.read_text())
    assert rebuilt["geometry"] == original["geometry"] and rebuilt["bbox"] == original["bbox"]
    assert rebuilt["properties"] == original["properties"]
    assert rebuilt["assets"]["data"]["href"] == original["assets"]["data"]["href"]
    code, out, _ = cli(capsys, "catalog", "validate", "--archive", str(archive_dir))
    assert code == 0, out
    assert catalog_problems(open_root(archive_dir)) == []
    code, out, _ = cli(capsys, "verify", "--archive", str(archive_dir), "--quiet")
    assert code == 0 and "DAMAGED" not in out, out


def test_a_lost_collection_store_is_listed_as_damaged(archive, capsys):
    """An Item whose collection store is gone: listed as damaged (not as a viewable flight) by the
    viewer, validate and rebuild, which keeps the Item and exits 1."""
    archive_dir, ids = archive
    shutil.rmtree(archive_dir / "collections" / f"{ids[0]}.zarr")
    client, registry = _client(archive_dir)
    try:
        doc = client.get("/api/collections").json()
        assert [f["id"] for f in doc["features"]] == [ids[1]]
        assert [d["id"] for d in doc["damaged"]] == [ids[0]] and "missing" in doc["damaged"][0]["reason"]
    finally:
        client.close()
        registry.close()
    code, out, _ = cli(capsys, "catalog", "validate", "--archive", str(archive_dir))
    assert code == 1 and f"collections/{ids[0]}.zarr is missing" in out, out
    code, out, _ = cli(capsys, "catalog", "rebuild", "--archive", str(archive_dir))
    assert code == 1 and f"DAMAGED {ids[0]}: collection store" in out, out
    assert (archive_dir / "catalog" / "items" / f"{ids[0]}.json").is_file()


# ---- read-only archives ---------------------------------------------------------------------------
def _readonly_prefix(target: Path) -> list[str]:
    """A command prefix that runs a command with ``target`` mounted read-only (a private mount
    namespace: nothing changes for other processes), or pytest.skip with the reason."""
    if shutil.which("unshare") is None or shutil.which("mount") is None:
        pytest.skip("unshare/mount not available: cannot make a read-only mount")
    prefix = ["unshare", "-m", "--propagation", "private", "sh", "-c",
              'mount --bind -o ro "$0" "$0" && exec "$@"', str(target)]
    probe = subprocess.run([*prefix, "sh", "-c", f'touch "{target}/.probe"'], capture_output=True, text=True)
    if (target / ".probe").exists():
        (target / ".probe").unlink()
        pytest.skip("a read-only bind mount does not stop writes here")
    if "Read-only" not in probe.stderr:
        pytest.skip(f"cannot make a read-only bind mount here (as {os.getuid()}): {probe.stderr.strip()[:200]}")
    return prefix


def _snapshot(root: Path) -> dict[str, tuple[int, int]]:
    return {str(p.relative_to(root)): (p.stat().st_size, p.stat().st_mtime_ns) for p in sorted(root.rglob("*"))}


def _run(prefix: list[str], *args: str, env: dict, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([*prefix, sys.executable, "-m", "archive", *args], capture_output=True, text=True,
                          env=env, timeout=timeout)


@pytest.mark.parametrize("index_state", ["current", "stale"])
def test_a_read_only_archive_is_searched_rendered_and_viewed(archive, tmp_path, index_state):
    """Finding 5: the index was written on every open, so a read-only archive could not be searched,
    batch-rendered or viewed; the message advised 'archive catalog rebuild', which ended in a
    traceback."""
    archive_dir, ids = archive
    prefix = _readonly_prefix(archive_dir)
    if index_state == "stale":  # e.g. published without its index, or with one of an older version
        (archive_dir / "catalog" / "index.sqlite").write_bytes(b"")
    env = {**os.environ, "XDG_CACHE_HOME": str(tmp_path / "cache")}
    before = _snapshot(archive_dir)

    r = _run(prefix, "catalog", "search", "--archive", str(archive_dir), "--json", env=env)
    assert r.returncode == 0, r.stderr
    assert [f["id"] for f in json.loads(r.stdout)["features"]] == ids
    r = _run(prefix, "catalog", "search", "--archive", str(archive_dir), "--wavelength", "600", env=env)
    assert r.returncode == 0 and r.stdout.strip().endswith("2 flights"), r.stderr
    cached = list((tmp_path / "cache").rglob("index.sqlite"))
    assert len(cached) == (1 if index_state == "stale" else 0)

    # rebuild: one line saying why and what to do, no traceback
    r = _run(prefix, "catalog", "rebuild", "--archive", str(archive_dir), env=env)
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    (line,) = r.stderr.strip().splitlines()
    assert "read-only" in line and "not rebuilt" in line

    # a batch render to a folder elsewhere
    out = tmp_path / "out"
    r = _run(prefix, "render", "--archive", str(archive_dir), "--query-bbox", "-180,-90,180,90", "--gsd", "0.2",
             "--out", str(out), "--format", "tif", "--quiet", "--workers", "1", env=env, timeout=600)
    assert r.returncode == 0, (r.stdout, r.stderr[-3000:])
    assert sorted(p.name for p in out.glob("*.tif")) == sorted(f"{cid}.tif" for cid in ids)

    # the viewer and its STAC API
    from test_stac_faults import request, start_view, stop_view

    proc, base = start_view(archive_dir, env=env, user=prefix)
    try:
        status, doc = request(f"{base}/api/collections")
        assert status == 200 and sorted(f["id"] for f in doc["features"]) == sorted(ids), doc
        status, doc = request(f"{base}/stac/search?limit=10")
        assert status == 200 and [f["id"] for f in doc["features"]] == ids, doc
        status, doc = request(f"{base}/stac/search", "POST", b'{"filter": "gsd > 0", "filter-lang": "cql2-text"}')
        assert status == 200 and len(doc["features"]) == 2, doc
        status, doc = request(f"{base}/stac/collections/flights")
        assert status == 200 and doc["extent"]["spatial"]["bbox"], doc
        status, doc = request(f"{base}/api/collections/{ids[0]}")
        assert status == 200, doc
        assert proc.poll() is None
    finally:
        stop_view(proc)
    assert _snapshot(archive_dir) == before  # nothing in the archive was written


def test_catalog_add_on_a_read_only_archive_is_one_line(archive, tmp_path):
    """Issue 50: ``catalog add`` on a read-only archive ended in a traceback (the catalog lock's OSError)."""
    archive_dir, ids = archive
    out = tmp_path / "o.tif"
    code = main(["render", ids[0], "--archive", str(archive_dir), "--gsd", "0.5", "--out", str(out), "--quiet"])
    assert code == 0
    prefix = _readonly_prefix(archive_dir)
    r = _run(prefix, "catalog", "add", "--archive", str(archive_dir), str(out) + ".json",
             env={**os.environ, "XDG_CACHE_HOME": str(tmp_path / "cache")})
    lines = r.stderr.strip().splitlines()
    assert r.returncode != 0 and len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    assert "read-only" in lines[0] and str(archive_dir.name) in lines[0], lines


def test_catalog_list_leaves_out_an_item_truncated_since_the_index(archive, capsys):
    """Issue 50: ``catalog list`` listed a truncated Item from the index as if it were sound."""
    archive_dir, ids = archive
    code, out, err = cli(capsys, "catalog", "list", "--archive", str(archive_dir))
    assert code == 0 and all(i in out for i in ids)
    _truncate(archive_dir / "catalog" / "items" / f"{ids[0]}.json")
    code, out, err = cli(capsys, "catalog", "list", "--archive", str(archive_dir))
    assert code == 0 and ids[0] not in out and ids[1] in out and out.strip().endswith("1 flight")
    assert f"damaged flight {ids[0]}" in err and "unreadable STAC Item" in err, err
