"""Batch reprocessing at archive scale (issue 19), through the real CLI on real files: every DN chunk
read from a collection is checked against its recorded sha256 (render, archive.mosaic, the viewer);
one output per flight, each flight failing alone (report.json, exit 1); --resume after SIGKILL.

Archives of small simulated flights (2 cubes x 100 lines x 64 samples x 4 bands), one per seed
(each seed starts a minute later: distinct ids).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numcodecs
import numpy as np
import pytest

from archive.cli import main
from archive.collection import CheckedDn, CorruptChunkError, chunk_path

FOV = 47.5
GSD = "0.1"
SHAPE = dict(cubes=2, bands=4, samples=64, lines=100, cubes_per_pass=2)


@pytest.fixture(scope="module")
def flights(tmp_path_factory):
    """(raw directories, archive, ids) of three small flights ingested into one archive."""
    from archive.ingest.command import ingest
    from archive.simulator.command import simulate_flight

    root = tmp_path_factory.mktemp("batch")
    dirs, ids = [], []
    for seed in range(3):
        d = root / f"flight{seed}"
        simulate_flight(d, seed=seed, **SHAPE)
        (r,) = ingest([str(d)], root / "archive", FOV, progress=False)
        dirs.append(d)
        ids.append(r.cid)
    return dirs, root / "archive", ids


def copy_archive(archive: Path, to: Path) -> Path:
    shutil.copytree(archive, to)
    return to


def store_of(archive: Path, cid: str) -> Path:
    return archive / "collections" / f"{cid}.zarr"


def _codec():
    return numcodecs.Blosc(cname="zstd", clevel=3, shuffle=numcodecs.Blosc.BITSHUFFLE)


def flip_value(store: Path, band: int, chunk: int) -> None:
    """Silent corruption: one DN of chunk (band, chunk) changed, re-encoded (the codec still decodes it)."""
    path = chunk_path(store, band, chunk)
    values = np.frombuffer(_codec().decode(path.read_bytes()), "<u2").copy()
    values[values.size // 2] ^= 0x10
    path.write_bytes(_codec().encode(values))


def truncate(store: Path, band: int, chunk: int) -> None:
    path = chunk_path(store, band, chunk)
    path.write_bytes(path.read_bytes()[:40])


# ---------------------------------------------------------------------------------------------
# Integrity on every read
# ---------------------------------------------------------------------------------------------
def test_checked_reads_name_collection_band_and_lines(flights, tmp_path):
    _, archive, ids = flights
    archive = copy_archive(archive, tmp_path / "archive")
    store = store_of(archive, ids[1])
    intact = CheckedDn(store).read(2, 50, 150)
    assert np.array_equal(intact, CheckedDn(store).array[2, 50:150])
    flip_value(store, 2, 1)
    truncate(store, 3, 0)
    dn = CheckedDn(store)
    assert np.array_equal(dn.read(2, 0, 100), dn.array[2, 0:100])  # the other chunks read fine
    with pytest.raises(CorruptChunkError, match=rf"collection {ids[1]}: array dn, band 2, lines 100-199: chunk "
                                                r"does not match its recorded sha256.*archive verify"):
        dn.read(2, 50, 150)
    with pytest.raises(CorruptChunkError, match=r"band 3, lines 0-99: chunk cannot be decoded.*re-ingest"):
        dn.read(3, 0, 10)
    chunk_path(store, 1, 0).unlink()
    with pytest.raises(CorruptChunkError, match=r"band 1, lines 0-99: chunk file is missing"):
        dn.read(1, 0, 100)


def test_render_mosaic_and_viewer_refuse_a_corrupt_chunk(flights, tmp_path, capsys):
    import archive as api

    _, archive, ids = flights
    archive = copy_archive(archive, tmp_path / "archive")
    cid = ids[0]
    for k in (0, 1):
        flip_value(store_of(archive, cid), 0, k)
    expected = rf"collection {cid}: array dn, band 0, lines \d+-\d+: chunk does not match its recorded sha256"
    out = tmp_path / "one.tif"
    import re

    assert main(["render", cid, "--archive", str(archive), "--gsd", GSD, "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "archive verify" in err
    assert re.search(expected, err), err
    assert not out.exists() and not list(tmp_path.glob(".one.tif*"))

    ds = api.mosaic(cid, archive=archive, gsd=float(GSD), bands=[0])
    with pytest.raises(CorruptChunkError, match=expected):
        ds.radiance.compute(scheduler="threads")

    from archive.view.flights import FlightRegistry
    from archive.view.server import create_app
    from starlette.testclient import TestClient

    item = json.loads((archive / "catalog" / "items" / f"{cid}.json").read_text())
    lon = (item["bbox"][0] + item["bbox"][2]) / 2
    lat = (item["bbox"][1] + item["bbox"][3]) / 2
    with TestClient(create_app(FlightRegistry(archive))) as client:
        got = client.get(f"/api/collections/{cid}/point", params={"lon": repr(lon), "lat": repr(lat)})
    assert got.status_code == 400, got.text
    assert re.search(expected, got.json()["error"]) and "archive verify" in got.json()["error"]
