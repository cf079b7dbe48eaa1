"""Archives and outputs in S3-compatible object storage (issue 35), against a real S3 server on
loopback: moto's ``ThreadedMotoServer`` on 127.0.0.1, started here (what zarr-python, s3fs and
obstore test against). The same tests run against another endpoint when ``ARCHIVE_TEST_S3_BUCKET``
names a bucket there (endpoint and credentials from the usual AWS environment: AWS_ENDPOINT_URL,
AWS_ACCESS_KEY_ID, ...).

Checked: ingest into ``s3://``, a rerun a no-op, verify, search, renders from the s3 archive equal
bit for bit to those from a local archive of the same flight (to a local COG and to an ``s3://``
Zarr), a damaged chunk object refused by name, a killed ingest resumed, two concurrent ingests of
one flight, the lock object, the catalog's local index cache going stale when an Item changes, and
that no credential is written into any object.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import numpy as np
import pytest
from helpers import FOV

pytest.importorskip("moto")
pytest.importorskip("obstore")

SECRET = "s3cr3t-" + uuid.uuid4().hex   # must never appear in an object the archive writes


@pytest.fixture(scope="session")
def s3_bucket(tmp_path_factory):
    """A bucket on an S3 server: moto's on 127.0.0.1 (started here), or ``ARCHIVE_TEST_S3_BUCKET``
    on the endpoint of the environment. Sets the AWS environment of this process (and so of the
    subprocesses it starts) for the session; the catalog caches go to a temporary folder."""
    saved = dict(os.environ)
    server = None
    bucket = os.environ.get("ARCHIVE_TEST_S3_BUCKET")
    if bucket is None:
        from moto.server import ThreadedMotoServer

        logging.getLogger("werkzeug").setLevel(logging.ERROR)   # one log line per request otherwise
        server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
        server.start()
        host, port = server.get_host_and_port()
        os.environ.update(AWS_ENDPOINT_URL=f"http://{host}:{port}", AWS_ACCESS_KEY_ID="AKIATESTING",
                          AWS_SECRET_ACCESS_KEY=SECRET, AWS_DEFAULT_REGION="us-east-1")
        os.environ.pop("AWS_PROFILE", None)
        bucket = f"archive-test-{uuid.uuid4().hex[:12]}"
        import boto3

        boto3.client("s3").create_bucket(Bucket=bucket)
    os.environ["XDG_CACHE_HOME"] = str(tmp_path_factory.mktemp("xdg_cache"))
    try:
        yield bucket
    finally:
        os.environ.clear()
        os.environ.update(saved)
        if server is not None:
            server.stop()


def _keys(bucket: str, prefix: str) -> dict[str, int]:
    """{key: size} of every object under ``prefix``."""
    import boto3

    out = {}
    for page in boto3.client("s3").get_paginator("list_objects_v2").paginate(Bucket=bucket, Prefix=prefix):
        out.update({o["Key"]: o["Size"] for o in page.get("Contents", [])})
    return out


def _get(bucket: str, key: str) -> bytes:
    import boto3

    return boto3.client("s3").get_object(Bucket=bucket, Key=key)["Body"].read()


def _cli(*args: str, env: dict | None = None, timeout: float = 240) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "archive", *args], capture_output=True, text=True,
                          env={**os.environ, **(env or {})}, timeout=timeout)


@pytest.fixture(scope="module")
def s3_archive(s3_bucket, small_flight):
    """(archive URL, collection id, first ingest's status) of the small flight ingested into s3."""
    from archive.ingest.command import ingest

    url = f"s3://{s3_bucket}/arc-{uuid.uuid4().hex[:6]}"
    (r,) = ingest([str(small_flight)], url, FOV, progress=False)
    return url, r.cid, r.status


def test_ingest_verify_search(s3_archive, small_archive, small_flight):
    from archive.catalog.index import ensure_index, search
    from archive.catalog.root import open_root
    from archive.collection import is_complete, read_attrs, verify_store
    from archive.ingest.command import ingest

    url, cid, status = s3_archive
    assert status == "ingested" and cid == small_archive[1]
    bucket, prefix = url[5:].split("/", 1)
    keys = _keys(bucket, prefix + "/")
    store = f"{prefix}/collections/{cid}.zarr"
    # one dn chunk per band per cube (2 cubes x 4 bands), no .partial, no lock left behind
    assert len([k for k in keys if k.startswith(f"{store}/dn/c/")]) == 8
    assert not [k for k in keys if ".partial" in k or k.endswith(".lock")]
    assert f"{prefix}/catalog/items/{cid}.json" in keys and f"{prefix}/archive.json" in keys
    # the stored bytes are the local store's: same chunks, same attributes
    local_store = Path(small_archive[0]) / "collections" / f"{cid}.zarr"
    for k in (f"{store}/dn/c/0/0/0", f"{store}/dn/c/3/1/0", f"{store}/position/c/0/0"):
        assert _get(bucket, k) == (local_store / k[len(store) + 1:]).read_bytes()
    assert read_attrs(f"s3://{bucket}/{store}") == read_attrs(local_store)
    root = open_root(url)
    assert root.collection_ids() == [cid] and is_complete(root.store(cid))
    assert verify_store(root.store(cid)) == []
    # a rerun is a no-op: writes nothing
    before = {k: _get(bucket, k) for k in keys if not k.endswith("/0")}
    (again,) = ingest([str(small_flight)], url, FOV, progress=False)
    assert again.status == "already ingested"
    assert {k: _get(bucket, k) for k in before} == before and set(_keys(bucket, prefix + "/")) == set(keys)
    # the index is a local cache (SQLite needs a file), answering like the local archive's own
    index = ensure_index(root)
    assert str(index).startswith(os.environ["XDG_CACHE_HOME"])
    (row,) = search(index, ids=[cid])
    (local_row,) = search(ensure_index(open_root(small_archive[0])), ids=[cid])
    assert row.bbox == local_row.bbox and row.start_iso == local_row.start_iso and row.bands == 4
    # the CLI: verify and search, one line per flight
    v = _cli("verify", "--archive", url, "--quiet")
    assert v.returncode == 0 and f"{cid}: OK" in v.stdout, v.stderr
    s = _cli("catalog", "search", "--archive", url)
    assert s.returncode == 0 and cid in s.stdout and "1 flight" in s.stdout, s.stderr
    val = _cli("catalog", "validate", "--archive", url)
    assert val.returncode == 0 and "3 of 3 valid" in val.stdout, val.stdout + val.stderr
    # no credential in any object written
    for k in keys:
        if not k.split("/")[-1].isdigit():
            body = _get(bucket, k)
            assert SECRET.encode() not in body and b"AKIATESTING" not in body, k


def test_index_cache_goes_stale_when_an_item_changes(s3_archive):
    """The local index cache records the Items' ETags (one LIST): an Item rewritten by another
    machine makes it stale, and it is rebuilt from the Items."""
    from archive.catalog.index import ensure_index, index_problem, search
    from archive.catalog.root import open_root
    from archive import storage

    url, cid, _ = s3_archive
    root = open_root(url)
    index = ensure_index(root)
    assert index_problem(index, root) is None
    item_url = root.item_path(cid)
    original = storage.read_bytes(item_url)
    item = json.loads(original)
    item["properties"]["archive:sensor_note"] = "edited elsewhere"
    item["bbox"] = [round(v + 0.001, 9) for v in item["bbox"]]
    storage.write_bytes(item_url, json.dumps(item).encode())
    try:
        assert "changed" in index_problem(index, root)
        (row,) = search(ensure_index(root), ids=[cid])
        assert row.bbox[0] == pytest.approx(item["bbox"][0])
    finally:
        storage.write_bytes(item_url, original)
    (row,) = search(ensure_index(root), ids=[cid])
    assert row.bbox[0] == pytest.approx(json.loads(original)["bbox"][0])


def _read_tif(path) -> np.ndarray:
    import rasterio

    with rasterio.open(path) as src:
        return src.read()


def test_renders_from_s3_equal_local(s3_archive, small_archive, tmp_path):
    """Render the flight from the s3 archive to a local COG and to an s3 Zarr; both equal bit for
    bit the render of the same flight from the local archive; the s3 Zarr's Item is written."""
    import xarray as xr
    import zarr

    from archive import storage

    url, cid, _ = s3_archive
    local_arc, _ = small_archive
    common = ["--gsd", "0.5", "--fov", str(FOV), "--quiet"]
    a = _cli("render", cid, "--archive", url, "--out", str(tmp_path / "s3.tif"), *common)
    assert a.returncode == 0, a.stderr
    b = _cli("render", cid, "--archive", str(local_arc), "--out", str(tmp_path / "local.tif"), *common)
    assert b.returncode == 0, b.stderr
    from_s3, from_local = _read_tif(tmp_path / "s3.tif"), _read_tif(tmp_path / "local.tif")
    assert from_s3.shape[0] == 4 and np.isfinite(from_s3).mean() > 0.3
    np.testing.assert_array_equal(from_s3, from_local)
    out = url + "-out/mosaic.zarr"
    c = _cli("render", cid, "--archive", url, "--out", out, *common)
    assert c.returncode == 0, c.stderr
    item = json.loads(storage.read_bytes(out + ".json"))   # written last: the output is complete
    assert item["assets"]["data"]["href"] == "./mosaic.zarr"
    assert out in item["properties"]["archive:recipe"]["command"] and "staging" not in json.dumps(item)
    ds = xr.open_zarr(storage.zarr_store(out), consolidated=False, decode_coords="all")
    values = np.asarray(ds[list(ds.data_vars)[0]].values) if "radiance" not in ds else np.asarray(ds["radiance"])
    np.testing.assert_array_equal(values, from_local)
    # a second render to the same URL without --overwrite is refused, naming it
    d = _cli("render", cid, "--archive", url, "--out", out, *common)
    assert d.returncode != 0 and "mosaic.zarr" in d.stderr and "exists" in d.stderr.lower()


def test_damaged_chunk_object_is_refused_by_name(s3_bucket, small_flight):
    """A chunk object whose bytes changed (still decodable) is found by verify and refused by every
    DN read, both naming the collection, band and lines."""
    from archive import storage
    from archive.collection import CheckedDn, CorruptChunkError, verify_store
    from archive.ingest.command import ingest

    url = f"s3://{s3_bucket}/damaged-{uuid.uuid4().hex[:6]}"
    (r,) = ingest([str(small_flight)], url, FOV, progress=False)
    store = f"{url}/collections/{r.cid}.zarr"
    chunk = f"{store}/dn/c/2/1/0"
    import numcodecs

    from archive.collection import DN_CODEC
    from archive.codecs import numcodecs_blosc

    codec = numcodecs_blosc(DN_CODEC["cname"], DN_CODEC["clevel"], DN_CODEC["shuffle"])
    values = np.frombuffer(codec.decode(storage.read_bytes(chunk)), "<u2").copy()
    values[5] ^= 1
    storage.write_bytes(chunk, codec.encode(values))
    assert isinstance(codec, numcodecs.abc.Codec)
    problems = verify_store(store)
    assert problems == ["dn chunk (band 2, lines 100-199): checksum mismatch"]
    dn = CheckedDn(store)
    np.testing.assert_array_equal(dn.read(2, 0, 100).shape, (100, 64))   # the intact chunk still reads
    with pytest.raises(CorruptChunkError, match=rf"{r.cid}: array dn, band 2, lines 100-199"):
        dn.read(2, 50, 150)
    v = _cli("verify", "--archive", url, "--quiet")
    assert v.returncode == 1 and "CORRUPT" in v.stdout and "band 2, lines 100-199" in v.stdout


def test_killed_ingest_is_resumed(s3_bucket, small_flight):
    """An ingest killed after 3 chunk writes leaves an incomplete store that no reader lists; the
    rerun resumes it (keeps the chunks already there) and the result verifies."""
    from archive.catalog.root import open_root
    from archive.collection import verify_store

    url = f"s3://{s3_bucket}/killed-{uuid.uuid4().hex[:6]}"
    bucket, prefix = url[5:].split("/", 1)
    p = subprocess.Popen([sys.executable, "-m", "archive", "ingest", str(small_flight), "--archive", url,
                          "--fov", str(FOV), "--quiet", "--workers", "1"],
                         env={**os.environ, "ARCHIVE_TEST_HOLD_AFTER_CHUNKS": "3"},
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 120
    while len([k for k in _keys(bucket, prefix + "/") if "/dn/c/" in k]) < 3:
        assert p.poll() is None, p.communicate()
        assert time.monotonic() < deadline
        time.sleep(0.2)
    p.send_signal(signal.SIGKILL)
    p.wait()
    chunks_then = {k: _get(bucket, k) for k in _keys(bucket, prefix + "/") if "/dn/c/" in k}
    assert len(chunks_then) == 3
    root = open_root(url)
    assert root.collection_ids() == []            # no completion marker: invisible
    for args in (["catalog", "list", "--archive", url], ["verify", "--archive", url, "--quiet"]):
        said = _cli(*args)   # the advice is what repairs it: the same ingest, not 'catalog rebuild' (issue 50)
        text = said.stdout + said.stderr
        assert "run the same 'archive ingest' again" in text and "catalog rebuild" not in text, (args, text)
    r = _cli("ingest", str(small_flight), "--archive", url, "--fov", str(FOV), "--quiet")
    assert r.returncode == 0 and ": resumed (" in r.stdout, (r.stdout, r.stderr)
    (cid,) = root.collection_ids()
    assert verify_store(root.store(cid)) == []
    assert {k: _get(bucket, k) for k in chunks_then} == chunks_then


def test_two_concurrent_ingests_of_one_flight(s3_bucket, small_flight):
    """Two ingests of one flight into one s3 archive at once: one writes it, the other waits on
    the lock object (a conditional PUT) and finds it ingested; one complete store, verified."""
    from archive.catalog.index import ensure_index, search
    from archive.catalog.root import open_root
    from archive.collection import verify_store

    url = f"s3://{s3_bucket}/twice-{uuid.uuid4().hex[:6]}"
    args = [sys.executable, "-m", "archive", "ingest", str(small_flight), "--archive", url, "--fov", str(FOV),
            "--quiet"]
    procs = [subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for _ in range(2)]
    outs = [p.communicate(timeout=240) for p in procs]
    assert [p.returncode for p in procs] == [0, 0], outs
    statuses = sorted(o[0].split(": ", 1)[1].split(" (")[0] for o in outs)
    assert statuses == ["already ingested", "ingested"], outs
    root = open_root(url)
    (cid,) = root.collection_ids()
    assert verify_store(root.store(cid)) == []
    assert [r.id for r in search(ensure_index(root))] == [cid]
    bucket, prefix = url[5:].split("/", 1)
    assert not [k for k in _keys(bucket, prefix + "/") if k.endswith(".lock") or k.endswith(".break")]


def test_lock_object(s3_bucket):
    """The lock of a URL is an object created with If-None-Match: *: a second taker is refused
    naming the owner; a dead owner's (this host, PID gone) is taken over; release deletes it."""
    from archive import storage
    from archive.files import FileLock, LockHeldError, host_name

    url = f"s3://{s3_bucket}/locks-{uuid.uuid4().hex[:6]}/x.lock"
    first = FileLock(url, "first job")
    first.acquire()
    try:
        with pytest.raises(LockHeldError, match=rf"first job by PID {os.getpid()} on {host_name()}"):
            FileLock(url, "second job").acquire(wait=0.3)
    finally:
        first.release()
    assert storage.head(url) is None
    dead = json.dumps({"host": host_name(), "pid": 2 ** 22 + 7, "process_start": None, "since": "x",
                       "purpose": "killed job"}).encode()
    assert storage.put_if_absent(url, dead) and not storage.put_if_absent(url, dead)
    third = FileLock(url, "third job")
    third.acquire(wait=5)
    assert json.loads(storage.read_bytes(url))["purpose"] == "third job"
    third.release()
    assert storage.head(url) is None


def test_stac_api_and_viewer_over_an_s3_archive(s3_archive, small_archive):
    """``archive view --archive s3://...``'s app: the STAC API answers a search and serves the Item,
    and one map tile of the flight draws pixels, equal to the same tile from the local archive."""
    import io
    import warnings

    from PIL import Image
    from pyproj import Transformer

    from archive.view.registry import FlightRegistry
    from archive.view.server import create_app
    from archive.grid import HALF_WORLD

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        from starlette.testclient import TestClient

    url, cid, _ = s3_archive
    z = 21

    def tile(archive) -> tuple[dict, np.ndarray]:
        with TestClient(create_app(FlightRegistry(archive))) as c:
            found = c.get("/stac/search", params={"ids": cid}).json()
            assert [f["id"] for f in found["features"]] == [cid]
            item = c.get(f"/stac/collections/flights/items/{cid}").json()
            w, s, e, n = item["bbox"]
            x, y = Transformer.from_crs(4326, 3857, always_xy=True).transform((w + e) / 2, (s + n) / 2)
            side = 2 * HALF_WORLD / 2 ** z
            r = c.get(f"/api/collections/{cid}/tiles/{z}/{int((x + HALF_WORLD) // side)}/"
                      f"{int((HALF_WORLD - y) // side)}.png")
            assert r.status_code == 200 and r.headers["content-type"] == "image/png", r.text
            return item, np.asarray(Image.open(io.BytesIO(r.content)).convert("RGBA"))

    item, rgba = tile(url)
    local_item, local_rgba = tile(str(small_archive[0]))
    assert (rgba[..., 3] > 0).mean() > 0.2
    np.testing.assert_array_equal(rgba, local_rgba)
    assert item["bbox"] == local_item["bbox"]
    assert item["assets"]["data"]["href"] == f"{url}/collections/{cid}.zarr"   # workers read it from the bucket


def test_killed_batch_into_s3_is_resumed(s3_bucket, tiny_flights):
    """A batch of two flights from an s3 archive into an ``s3://`` folder, killed once the first
    output is uploaded (its Item last): the rerun with --resume skips it (same recipe, its Item
    untouched) and renders the other; the report in the bucket says so; no staging folder is left."""
    import tempfile

    from archive import storage
    from archive.ingest.command import ingest

    url = f"s3://{s3_bucket}/batch-arc-{uuid.uuid4().hex[:6]}"
    ids = sorted(r.cid for r in ingest([str(tiny_flights(1)), str(tiny_flights(2))], url, FOV, progress=False))
    assert len(ids) == 2
    out = f"{s3_bucket}/batch-out-{uuid.uuid4().hex[:6]}"
    args = ["render", "--archive", url, "--query-bbox", "-180,-90,180,90", "--gsd", "0.5", "--out", f"s3://{out}",
            "--format", "tif", "--quiet"]
    staging_before = {p.name for p in Path(tempfile.gettempdir()).glob("archive-staging-*")}
    p = subprocess.Popen([sys.executable, "-m", "archive", *args], env={**os.environ, "ARCHIVE_TEST_HOLD_AFTER": "1"},
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    report = f"s3://{out}/report.json"
    deadline = time.monotonic() + 240
    while True:
        assert p.poll() is None, p.communicate()
        assert time.monotonic() < deadline
        if storage.exists(report) and json.loads(storage.read_bytes(report))["done"] == 1:
            break
        time.sleep(0.3)
    p.send_signal(signal.SIGKILL)
    p.wait()
    doc = json.loads(storage.read_bytes(report))
    done = [o["id"] for o in doc["outputs"] if o["status"] == "done"]
    assert len(done) == 1 and not doc["complete"]
    first = f"s3://{out}/{done[0]}.tif"
    assert storage.exists(first) and storage.exists(first + ".json")
    etag = storage.head(first + ".json")["e_tag"]
    (other,) = [i for i in ids if i != done[0]]
    assert not storage.exists(f"s3://{out}/{other}.tif.json")
    r = _cli(*args, "--resume")
    assert r.returncode == 0, r.stderr
    assert f"skipped {done[0]}" in r.stdout + r.stderr and f"done {other}" in r.stdout + r.stderr
    assert storage.head(first + ".json")["e_tag"] == etag   # untouched
    for cid in ids:
        item = json.loads(storage.read_bytes(f"s3://{out}/{cid}.tif.json"))
        assert item["assets"]["data"]["href"] == f"./{cid}.tif"
    import rasterio

    with rasterio.MemoryFile(storage.read_bytes(f"s3://{out}/{other}.tif")) as mem, mem.open() as src:
        assert src.count == 2 and np.isfinite(src.read()).mean() > 0.1   # a diagonal strip
    final = json.loads(storage.read_bytes(report))
    assert final["complete"] and final["done"] == 1 and final["skipped"] == 1
    assert not storage.exists(f"s3://{out}/.archive-batch.lock")
    # the resumed run removed its own staging folders (the killed run's stays in $TMPDIR)
    left = {p.name for p in Path(tempfile.gettempdir()).glob("archive-staging-*")} - staging_before
    assert len(left) <= 2


def test_python_api_over_an_s3_archive(s3_archive, small_archive):
    """``archive.open_archive("s3://...")``: search, and a lazy mosaic computed in this process
    (threads), equal bit for bit to the same mosaic from the local archive."""
    import archive

    url, cid, _ = s3_archive
    arc = archive.open_archive(url)
    assert arc.search(bbox=(-180, -90, 180, 90)) == [cid] and arc.search(wavelength=5000) == []
    import dask

    with dask.config.set(scheduler="threads"):
        a = archive.mosaic([cid], archive=arc, gsd=0.5).compute()
        b = archive.mosaic([cid], archive=archive.open_archive(small_archive[0]), gsd=0.5).compute()
    name = list(a.data_vars)[0]
    assert np.isfinite(a[name].values).mean() > 0.3
    np.testing.assert_array_equal(a[name].values, b[name].values)


def test_bad_bucket_or_endpoint_is_one_line(s3_bucket, small_flight):
    """A missing bucket, a missing archive and an endpoint that refuses connections are each one
    line naming the URL and what to check, exit 2, no traceback, no credential in it."""
    cases = [
        (["ingest", str(small_flight), "--archive", "s3://no-such-bucket-35/arc", "--fov", str(FOV), "--quiet"], {},
         "s3://no-such-bucket-35/arc: object storage: the bucket does not exist"),
        (["catalog", "search", "--archive", f"s3://{s3_bucket}/no-archive-here"], {},
         f"s3://{s3_bucket}/no-archive-here/archive.json: archive marker not found"),
        (["catalog", "search", "--archive", f"s3://{s3_bucket}/arc"], {"AWS_ENDPOINT_URL": "http://127.0.0.1:9"},
         "cannot connect to http://127.0.0.1:9 (connection refused)"),
    ]
    for args, env, expected in cases:
        r = _cli(*args, env=env)
        lines = [line for line in r.stderr.splitlines() if line.strip()]
        assert r.returncode == 2 and len(lines) == 1 and expected in lines[0], (args, r.stderr)
        assert "AWS_ENDPOINT_URL" in lines[0] and SECRET not in r.stderr + r.stdout


def test_two_concurrent_ingests_of_two_flights(s3_bucket, tiny_flights):
    """Two ingests of different flights into one new s3 archive at once: the archive marker (a
    conditional PUT) made once, both collections complete, and the catalog (its updates take turns
    on the catalog's lock object) lists both: the index and the STAC Collection's item links."""
    from archive.catalog.index import ensure_index, search
    from archive.catalog.root import open_root
    from archive import storage

    url = f"s3://{s3_bucket}/pair-{uuid.uuid4().hex[:6]}"
    procs = [subprocess.Popen([sys.executable, "-m", "archive", "ingest", str(tiny_flights(seed)), "--archive", url,
                               "--fov", str(FOV), "--quiet"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for seed in (3, 4)]
    outs = [p.communicate(timeout=240) for p in procs]
    assert [p.returncode for p in procs] == [0, 0], outs
    root = open_root(url)
    ids = root.collection_ids()
    assert len(ids) == 2 and all(": ingested (" in o[0] for o in outs), outs
    assert sorted(r.id for r in search(ensure_index(root))) == ids
    links = json.loads(storage.read_bytes(root.collection_path))["links"]
    assert sorted(ln["href"].rsplit("/", 1)[-1][:-5] for ln in links if ln["rel"] == "item") == ids


def test_zarr_output_chunks_go_straight_to_the_bucket(s3_archive, tmp_path):
    """A Zarr output in a bucket: once rendered and before its publication, its value chunks are
    objects in the bucket (written by the tile tasks) while the local staging folder holds no chunk,
    and no Item exists (readers do not trust it yet); killed there, it never gets one, and the
    rerun with --overwrite publishes it."""
    from archive import storage

    url, cid, _ = s3_archive
    out = url + f"-direct-{uuid.uuid4().hex[:6]}/m.zarr"
    bucket, prefix = out[5:].split("/", 1)
    hold = tmp_path / "hold"
    hold.touch()
    staging = tmp_path / "tmp"
    staging.mkdir()
    args = ["render", cid, "--archive", url, "--out", out, "--gsd", "0.5", "--fov", str(FOV), "--quiet"]
    p = subprocess.Popen([sys.executable, "-m", "archive", *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         env={**os.environ, "ARCHIVE_TEST_HOLD_PUBLISH": str(hold), "TMPDIR": str(staging)})
    deadline = time.monotonic() + 240
    while not Path(f"{hold}.reached").exists():
        assert p.poll() is None, p.communicate()
        assert time.monotonic() < deadline
        time.sleep(0.2)
    chunks = [k for k in _keys(bucket, prefix + "/") if k.startswith(f"{prefix}/radiance/") and k[-1].isdigit()]
    assert len(chunks) >= 4   # 4 bands x the tiles the flight covers
    local = [q for q in staging.rglob("*") if q.is_file() and "radiance" in q.parts and q.name[-1].isdigit()]
    assert local == []
    assert not storage.exists(out + ".json")
    p.send_signal(signal.SIGKILL)
    p.wait()
    assert not storage.exists(out + ".json")
    again = _cli(*args)
    assert again.returncode != 0 and "exists" in again.stderr.lower()   # data without an Item: not replaced silently
    again = _cli(*args, "--overwrite")
    assert again.returncode == 0, again.stderr
    assert storage.exists(out + ".json")


def test_a_stack_into_a_bucket_is_refused(s3_archive):
    """Stacks are not written into object storage yet: one line, exit 2, nothing written."""
    url, cid, _ = s3_archive
    out = url + "-stack/field.zarr"
    r = _cli("render", "--archive", url, "--query-bbox", "-180,-90,180,90", "--stack", "--gsd", "0.5", "--out", out)
    lines = [line for line in r.stderr.splitlines() if line.strip()]
    assert r.returncode == 2 and len(lines) == 1 and "cannot be written into object storage" in lines[0], r.stderr
    bucket, prefix = out[5:].split("/", 1)
    assert _keys(bucket, prefix.rsplit("/", 1)[0] + "/") == {} and not Path("s3:").exists()


def test_an_archive_created_by_another_ingest_meanwhile_is_opened(s3_bucket, monkeypatch):
    """The marker of a new s3 archive PUT by another ingest between this one's check for it and its
    listing of the prefix (the race CI met once: 'holds objects but no archive.json'): the prefix is
    an archive, opened, not refused."""
    from archive import storage
    from archive.catalog import root as roots

    url = f"s3://{s3_bucket}/race-{uuid.uuid4().hex[:6]}"
    real_exists, calls = storage.exists, []

    def exists_as_before_the_other_put(loc):
        calls.append(loc)
        if len(calls) == 1:   # checked before the other ingest's PUT ...
            storage.put_if_absent(storage.location(url) / roots.MARKER, b'{"format": "archive", "version": 1}\n')
            return False
        return real_exists(loc)   # ... which has happened by the listing

    monkeypatch.setattr(storage, "exists", exists_as_before_the_other_put)
    root = roots.create_archive(url)
    assert str(root.path).rstrip("/") == url and len(calls) >= 2


def test_small_arrays_in_a_bucket_are_checked_and_apply_is_refused_before_writing(s3_bucket, small_flight, tmp_path):
    """Issue 50: a flipped value of a collection's navigation in the bucket is one line naming the array (not a
    render on a wrong grid); ``calibrate --apply`` on an s3 archive is refused before anything is written."""
    import zarr

    from archive import storage
    from archive.ingest.command import ingest

    url = f"s3://{s3_bucket}/small-{uuid.uuid4().hex[:6]}"
    (r,) = ingest([str(small_flight)], url, FOV, progress=False)
    bucket, prefix = url[5:].split("/", 1)
    before = sorted(_keys(bucket, prefix + "/"))
    c = _cli("calibrate", r.cid, "--archive", url, "--apply", "--quiet")
    err = c.stderr.strip().splitlines()
    assert c.returncode != 0 and len(err) == 1 and "object storage" in err[0] and "--apply" in err[0], c.stderr
    assert sorted(_keys(bucket, prefix + "/")) == before   # nothing written
    store = f"{url}/collections/{r.cid}.zarr"
    nav = zarr.open_array(storage.zarr_store(store, read_only=False), path="navigation", mode="r+")
    values = nav[...]
    values[3, 4] += 1e-6   # a latitude moved by a few cm: still decodable, still plausible
    nav[...] = values
    out = tmp_path / "o.tif"
    c = _cli("render", r.cid, "--archive", url, "--gsd", "0.5", "--out", str(out), "--quiet")
    err = c.stderr.strip().splitlines()
    assert c.returncode != 0 and len(err) == 1 and f"{r.cid}: array navigation does not match" in err[0], c.stderr
    assert not out.exists()


def test_object_storage_mistakes_are_one_line(s3_archive, tmp_path):
    """Issue 50: no credentials anywhere, a URL without a bucket, a batch into a bucket that does not exist:
    one line each, naming the URL; a stack renders from an archive in a bucket."""
    url, cid, _ = s3_archive
    bare = {k: v for k, v in os.environ.items() if not k.startswith("AWS_")}
    bare.update(AWS_ENDPOINT_URL=os.environ["AWS_ENDPOINT_URL"], HOME=str(tmp_path), AWS_CONFIG_FILE=str(tmp_path / "c"),
                AWS_SHARED_CREDENTIALS_FILE=str(tmp_path / "k"), AWS_EC2_METADATA_DISABLED="true")
    cases = [
        (["catalog", "search", "--archive", url], bare, "no credentials found"),
        (["catalog", "list", "--archive", "s3:///x"], None, "s3:///x: names no bucket"),
        (["render", "--archive", url, "--query-datetime", "2024-06-01/2024-07-01", "--gsd", "0.5",
          "--out", "s3://no-such-bucket-50/out"], None, "the bucket does not exist"),
    ]
    for args, env, said in cases:
        done = subprocess.run([sys.executable, "-m", "archive", *args], capture_output=True, text=True, timeout=240,
                              env=env)
        lines = done.stderr.strip().splitlines()
        assert done.returncode != 0 and len(lines) == 1 and said in lines[0] and "Traceback" not in done.stderr, \
            (args, done.stderr)
    out = tmp_path / "stack.zarr"
    done = _cli("render", "--archive", url, "--query-datetime", "2024-06-01/2024-07-01", "--stack", "--gsd", "0.5",
                "--out", str(out), "--quiet")
    assert done.returncode == 0 and "1 added" in done.stdout, done.stderr
