"""Ingest into Zarr collections: bit-identical read back, idempotence, resume after SIGKILL,
checksums, refusal of broken flights. Real files, real Zarr, simulated flights."""

from __future__ import annotations

import os
import pickle
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import blake3
import numcodecs
import numpy as np
import pytest
import zarr

import archive
from archive.catalog.index import search
from archive.cli import main
from archive.errors import ArchiveError, FormatError, InputError, MissingInputError
from archive.collection import chunk_lines_for, chunk_tasks
from archive.sources import open_source
from archive.ingest.command import ingest
from archive.formats.envi import EnviCube, read_header, write_envi
from archive.formats.flight import discover_flight
from archive.formats.icp import read_icp
from archive.formats.lcf import read_lcf
from archive.formats.times import read_times, write_times
from archive.params import NavigationParams
from archive.simulator.command import simulate_flight
from archive.simulator.sensor import band_fwhm
from archive.sources import MODES, RawFlightSource
from helpers import FOV

PARAMS = [NavigationParams(),
          NavigationParams(sync_offset=0.011, boresight_deg=(0.4, -0.7, 1.5), lever_arm_m=(0.1, -0.2, 0.3))]


def snapshot(path: Path) -> dict[str, bytes]:
    """Every file under ``path`` (relative name -> bytes)."""
    return {p.relative_to(path).as_posix(): p.read_bytes() for p in sorted(path.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def flight(tmp_path_factory) -> tuple[Path, object]:
    d = tmp_path_factory.mktemp("flight") / "raw"
    truth = simulate_flight(d, cubes=4, bands=6, samples=64, lines=100, cubes_per_pass=2, seed=3)
    return d, truth


@pytest.fixture(scope="module")
def ingested(flight, tmp_path_factory):
    d, truth = flight
    archive_dir = tmp_path_factory.mktemp("arch") / "archive"
    results = ingest([str(d)], archive_dir, FOV, ground_height=truth.ground_height, threads=2, progress=False)
    assert [r.status for r in results] == ["ingested"]
    return archive_dir, results[0].cid


def test_id_and_layout(flight, ingested):
    d, truth = flight
    archive_dir, cid = ingested
    assert cid == "Pika-L-SIM_20240612T160300"  # <sensor>_<UTC start>; seed 3 starts at 16:03
    store = archive_dir / "collections" / f"{cid}.zarr"
    assert (archive_dir / "archive.json").is_file()
    assert not (archive_dir / "collections" / f"{cid}.zarr.partial").exists()
    group = zarr.open_group(store, mode="r")
    dn = group["dn"]
    assert dn.shape == (6, 400, 64) and dn.chunks == (1, 100, 64) and dn.dtype == np.uint16
    blosc = dn.metadata.codecs[-1]
    assert (blosc.cname.value, blosc.clevel, blosc.shuffle.value) == ("lz4", 9, "bitshuffle")
    # one chunk file per band per cube
    assert len(list((store / "dn" / "c").rglob("0"))) >= 6 * 4
    attrs = dict(group.attrs)
    assert attrs["archive:complete"] is True
    assert list(attrs)[-1] == "archive:complete"
    assert attrs["archive:software"] == f"archive {archive.__version__}"
    assert attrs["fov_deg"] == FOV and attrs["ground_height"] == truth.ground_height
    assert attrs["sensor"] == "Pika L-SIM"
    # sources: every raw file with its size and BLAKE3 (the default --checksum, recorded with its name)
    files = sorted(p for p in d.iterdir() if p.is_file())
    recorded = {s["name"]: s for s in attrs["sources"]}
    assert sorted(recorded) == sorted(p.name for p in files)
    for p in files:
        assert recorded[p.name]["size"] == p.stat().st_size
        assert recorded[p.name]["blake3"] == blake3.blake3(p.read_bytes()).hexdigest()
    assert attrs["archive:dn_checksum"] == "blake3" and "dn_blake3" in group and "dn_sha256" not in group
    table = group["dn_blake3"][...]
    assert table.shape == (6, 4, 32)
    assert table[2, 1].tobytes() == blake3.blake3(np.ascontiguousarray(dn[2, 100:200], "<u2").tobytes()).digest()
    # header metadata kept whole
    assert attrs["cubes"][2]["header"]["imager serial number"] == "Pika L-SIM"
    assert attrs["cubes"][2]["line_offset"] == 200
    np.testing.assert_array_equal(group["wavelength"][...], truth.wavelengths)
    np.testing.assert_array_equal(group["fwhm"][...], band_fwhm(truth.wavelengths))
    np.testing.assert_array_equal(group["cube"][...], np.repeat(np.arange(4), 100))


def test_read_back_bit_identical(flight, ingested):
    d, _ = flight
    archive_dir, cid = ingested
    group = zarr.open_group(archive_dir / "collections" / f"{cid}.zarr", mode="r")
    f = discover_flight(d)
    dn = group["dn"][...]
    raw = np.concatenate([EnviCube(c.data).read() for c in f.cubes], axis=1)
    np.testing.assert_array_equal(dn, raw)
    # navigation: raw .lcf samples and .times, bit for bit
    offsets = group["navigation_offset"][...]
    nav = group["navigation"][...]
    cal = read_icp(f.calibration)
    for k, c in enumerate(f.cubes):
        lcf = read_lcf(c.lcf)
        rows = nav[offsets[k]:offsets[k + 1]]
        for j, name in enumerate(("time", "roll", "pitch", "yaw", "lon", "lat", "alt")):
            assert np.array_equal(rows[:, j], getattr(lcf, name))
        assert np.array_equal(group["camera_time"][100 * k:100 * (k + 1)], read_times(c.times))
        dark, gain = cal.for_cube(read_header(c.header))
        assert np.array_equal(group["dark"][k], dark)
        assert np.array_equal(group["gain"][int(group["gain_index"][k])], gain)
    assert group.attrs["calibration"]["shutter_cal"] == cal.shutter_cal


def test_xarray_opens_the_collection(flight, ingested):
    """A collection opens as an xarray Dataset as it is: every dimension name means one length
    (the .lcf samples have their own, not the image's 'sample')."""
    import xarray as xr

    d, _ = flight
    archive_dir, cid = ingested
    ds = xr.open_zarr(archive_dir / "collections" / f"{cid}.zarr", consolidated=False)
    assert ds["dn"].dims == ("band", "line", "sample") and ds.sizes["sample"] == 64
    rows = sum(len(read_lcf(c.lcf).time) for c in discover_flight(d).cubes)
    assert ds["navigation"].dims == ("nav_sample", "column") and ds.sizes["nav_sample"] == rows
    raw = EnviCube(discover_flight(d).cubes[1].data).read()   # [band, line, sample]; line 150 is its line 50
    np.testing.assert_array_equal(ds["dn"][2, 150].values, raw[2, 50])


@pytest.mark.parametrize("params", PARAMS, ids=["default", "offset-boresight-lever"])
def test_collection_source_equals_raw(flight, ingested, params):
    d, _ = flight
    archive_dir, cid = ingested
    raw = RawFlightSource(d, params)
    col = pickle.loads(pickle.dumps(open_source(cid, params, archive=archive_dir)))
    assert col.cubes == raw.cubes and col.frame == raw.frame and col.wavelengths == raw.wavelengths
    white = np.linspace(1.0, 2.0, 6)
    for i in range(len(raw.cubes)):
        for delay in (0.0, 0.0015):
            a, b = raw.poses(i, delay), col.poses(i, delay)
            assert np.array_equal(a.time, b.time)
            assert np.array_equal(a.position, b.position)
            assert np.array_equal(a.attitude.as_quat(), b.attitude.as_quat())
        got = col.read_bands(i, [4, 0, 2])
        assert got.dtype == np.uint16
        assert np.array_equal(got, raw.read_bands(i, [4, 0, 2]))
        for mode in MODES:
            x = raw.radiometry(i, [1, 5], mode, white_reference=white)
            y = col.radiometry(i, [1, 5], mode, white_reference=white)
            for field in ("dark", "gain", "response"):
                u, v = getattr(x, field), getattr(y, field)
                assert u.dtype == v.dtype and np.array_equal(u, v), (mode, field)
            assert x.saturation == y.saturation


def test_rerun_is_a_noop(flight, ingested, capsys):
    d, truth = flight
    archive_dir, cid = ingested
    before = snapshot(archive_dir)
    mtimes = {p: p.stat().st_mtime_ns for p in archive_dir.rglob("*")}
    code = main(["ingest", str(d), "--archive", str(archive_dir), "--fov", str(FOV),
                 "--ground-height", str(truth.ground_height), "--quiet"])
    assert code == 0
    assert "already ingested" in capsys.readouterr().out
    assert snapshot(archive_dir) == before
    assert {p: p.stat().st_mtime_ns for p in archive_dir.rglob("*")} == mtimes


def test_deterministic_store_and_overwrite(flight, ingested, tmp_path):
    d, truth = flight
    archive_dir, cid = ingested
    ingest([str(d)], tmp_path / "again", FOV, ground_height=truth.ground_height, threads=1, progress=False)
    assert snapshot(tmp_path / "again") == snapshot(archive_dir)
    (r,) = ingest([str(d)], tmp_path / "again", FOV, ground_height=truth.ground_height, overwrite=True,
                  progress=False)
    assert r.status == "ingested"
    again, first = snapshot(tmp_path / "again"), snapshot(archive_dir)
    index = "catalog/index.sqlite"  # its bytes count changes (SQLite header), not its rows
    assert again.pop(index) != b"" and first.pop(index) != b""
    assert again == first


def test_other_flight_with_the_same_id(flight, ingested, tmp_path):
    d, truth = flight
    archive_dir, cid = ingested
    other = tmp_path / "other"
    shutil.copytree(d, other, ignore=shutil.ignore_patterns("truth"))
    hdr = other / "sim_Pika_L_2.bil.hdr"
    hdr.write_text(hdr.read_text().replace("target = simulate", "target = simulatX"))  # same size
    before = snapshot(archive_dir)
    with pytest.raises(InputError, match=f"different flight than .*other under the same id {cid}"):
        ingest([str(other)], archive_dir, FOV, ground_height=truth.ground_height, progress=False)
    assert snapshot(archive_dir) == before


def test_verify_detects_corruption(flight, tmp_path, capsys):
    d, truth = flight
    archive_dir = tmp_path / "archive"
    (cid,) = [r.cid for r in ingest([str(d)], archive_dir, FOV, ground_height=truth.ground_height, progress=False)]
    assert main(["verify", "--archive", str(archive_dir), "--quiet"]) == 0
    assert f"{cid}: OK" in capsys.readouterr().out
    store = archive_dir / "collections" / f"{cid}.zarr"
    # a chunk that still decodes, but to other values
    chunk = store / "dn" / "c" / "3" / "2" / "0"
    codec = numcodecs.Blosc(cname="zstd", clevel=3, shuffle=numcodecs.Blosc.BITSHUFFLE)
    values = np.frombuffer(codec.decode(chunk.read_bytes()), np.uint16).copy()
    values[17] += 1
    chunk.write_bytes(codec.encode(values))
    (store / "dn" / "c" / "0" / "1" / "0").unlink()
    assert main(["verify", "--archive", str(archive_dir), cid, "--quiet"]) == 1
    out = capsys.readouterr().out
    assert f"{cid}: CORRUPT (2 problems)" in out
    assert "band 3, lines 200-299): checksum mismatch" in out
    assert "band 0, lines 100-199): missing" in out


def test_resume_from_damaged_partial(flight, ingested, tmp_path):
    """What a kill can leave: some chunks written, one damaged, a temporary file; the rerun repairs."""
    from archive.catalog.root import create_archive
    from archive.collection import open_partial, write_chunk
    from archive.ingest.command import prepare_flight

    d, truth = flight
    archive_dir, cid = ingested
    plan = prepare_flight(d, FOV, ground_height=truth.ground_height)
    root = create_archive(tmp_path / "archive")
    partial = root.partial(plan.cid)
    assert open_partial(partial, plan) is False
    tasks = chunk_tasks(plan.data_files, plan.cube_lines, plan.bands, plan.chunk_lines)
    for t in tasks[:9]:
        write_chunk(str(partial), t, plan.chunk_lines, False)
    damaged = partial / "dn" / "c" / str(tasks[4].band) / str(tasks[4].chunk) / "0"
    damaged.write_bytes(damaged.read_bytes()[:50])
    (damaged.parent / "0.1234.partial").write_bytes(b"junk")
    results = ingest([str(d)], root.path, FOV, ground_height=truth.ground_height, progress=False)
    assert [r.status for r in results] == ["resumed"]
    assert snapshot(root.path) == snapshot(archive_dir)


def _chunk_count(partial: Path) -> int:
    try:
        return sum(len(files) for _, _, files in os.walk(partial / "dn" / "c"))
    except OSError:
        return 0


def test_a_new_partial_store_is_never_removed_once_it_appears(tmp_path, monkeypatch):
    """Laying out a new partial store never removes its folder: zarr's mode "w" removed the folder
    its store had just made and made it again, and a SIGKILL in between (test_sigkill_and_rerun
    killing at the store's first appearance, once in CI) left no partial store."""
    d = tmp_path / "raw"
    truth = simulate_flight(d, cubes=2, bands=4, samples=32, lines=40, cubes_per_pass=2, seed=2)
    removed: list[Path] = []
    rmtree = shutil.rmtree

    def spy(path, *args, **kwargs):
        removed.append(Path(path))
        return rmtree(path, *args, **kwargs)

    monkeypatch.setattr(shutil, "rmtree", spy)
    (r,) = ingest([str(d)], tmp_path / "root", FOV, ground_height=truth.ground_height, threads=1, progress=False)
    partial = tmp_path / "root" / "collections" / f"{r.cid}.zarr.partial"
    assert (tmp_path / "root" / "collections" / f"{r.cid}.zarr").is_dir() and not partial.exists()
    assert partial not in removed, removed


def test_sigkill_and_rerun(tmp_path):
    """SIGKILL `python -m archive ingest` at several moments; each rerun completes, and the final
    store equals a clean ingest byte for byte."""
    d = tmp_path / "raw"
    truth = simulate_flight(d, cubes=4, bands=40, samples=64, lines=100, cubes_per_pass=2, seed=5)
    cmd = [sys.executable, "-m", "archive", "ingest", str(d), "--fov", str(FOV),
           "--ground-height", str(truth.ground_height), "--quiet", "--workers", "1"]
    clean = tmp_path / "clean"
    (r,) = ingest([str(d)], clean, FOV, ground_height=truth.ground_height, threads=2, progress=False)
    expected = snapshot(clean)
    cid = r.cid
    total = 40 * 4

    work = tmp_path / "work"
    partial = work / "collections" / f"{cid}.zarr.partial"
    # kill when: the partial store appears; after 1/4 of the chunks; after 3/4 of them. Each run
    # holds there (ARCHIVE_TEST_HOLD_AFTER_CHUNKS: its chunk tasks wait once the store holds that
    # many chunks), so the kill lands mid-store however loaded the machine.
    for at in (0, total // 4, 3 * total // 4):
        proc = subprocess.Popen(cmd + ["--archive", str(work)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                env={**os.environ, "ARCHIVE_TEST_HOLD_AFTER_CHUNKS": str(at)})
        deadline = time.monotonic() + 300
        while proc.poll() is None and time.monotonic() < deadline:
            if partial.exists() and (at == 0 or _chunk_count(partial) >= at):
                break
            time.sleep(0.01)
        assert proc.poll() is None, "the ingest ended before the kill"
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        assert partial.exists()
        assert not (work / "collections" / f"{cid}.zarr").exists()
        # a half-written collection is never listed
        assert main(["catalog", "list", "--archive", str(work)]) == 0
    done = subprocess.run(cmd + ["--archive", str(work)], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert "resumed" in done.stdout or "ingested" in done.stdout
    got = snapshot(work)
    index = "catalog/index.sqlite"  # same rows; its header counts the writes, which differ
    got.pop(index), expected.pop(index)
    assert got == expected
    assert search(work / index) == search(clean / index)


def _shorten_cube(d: Path, base: str, lines: int) -> None:
    f = {c.base: c for c in discover_flight(d).cubes}[base]
    cube = EnviCube(f.data)
    data = cube.read()[:, :lines]
    meta = {k: v for k, v in cube.header.metadata.items() if k not in ("lines", "samples", "bands")}
    write_envi(f.data, data, meta, interleave="bil")
    write_times(f.times, read_times(f.times)[:lines])


def test_unequal_cubes(tmp_path):
    d = tmp_path / "raw"
    truth = simulate_flight(d, cubes=4, bands=3, samples=32, lines=60, cubes_per_pass=2, seed=7)
    _shorten_cube(d, "sim_Pika_L_2", 37)
    assert chunk_lines_for([60, 37, 60, 60]) == 60
    (r,) = ingest([str(d)], tmp_path / "a", FOV, ground_height=truth.ground_height, progress=False)
    raw = RawFlightSource(d, PARAMS[1])
    col = open_source(r.cid, PARAMS[1], archive=tmp_path / "a")
    assert [c.lines for c in col.cubes] == [60, 37, 60, 60]
    for i in range(4):
        assert np.array_equal(col.read_bands(i, [0, 2]), raw.read_bands(i, [0, 2]))
        assert np.array_equal(col.poses(i).position, raw.poses(i).position)
    assert main(["verify", "--archive", str(tmp_path / "a"), "--quiet"]) == 0


def test_broken_cube_refused(flight, tmp_path, capsys):
    d, truth = flight
    bad = tmp_path / "bad"
    shutil.copytree(d, bad, ignore=shutil.ignore_patterns("truth"))
    data = bad / "sim_Pika_L_3.bil"
    data.write_bytes(data.read_bytes()[:-1000])
    # into a new archive: nothing is created
    target = tmp_path / "new-archive"
    with pytest.raises(FormatError, match="sim_Pika_L_3.bil.*truncated"):
        ingest([str(d), str(bad)], target, FOV, ground_height=truth.ground_height, progress=False)
    assert not target.exists()
    # into an existing archive: nothing changes (the good flight listed first is not ingested either)
    existing = tmp_path / "archive"
    ingest([str(d)], existing, FOV, ground_height=truth.ground_height, progress=False)
    shutil.rmtree(existing / "collections")
    (existing / "collections").mkdir()
    before = snapshot(existing)
    code = main(["ingest", str(d), str(bad), "--archive", str(existing), "--fov", str(FOV),
                 "--ground-height", str(truth.ground_height), "--quiet"])
    assert code == 2
    err = capsys.readouterr().err
    assert "sim_Pika_L_3.bil" in err and "truncated" in err
    assert snapshot(existing) == before
    # a cube missing its navigation file
    (bad / "sim_Pika_L_3.lcf").unlink()
    with pytest.raises(ArchiveError, match="sim_Pika_L_3"):
        ingest([str(bad)], target, FOV, ground_height=truth.ground_height, progress=False)
    assert not target.exists()


def test_archive_and_argument_errors(flight, ingested, tmp_path, capsys):
    d, truth = flight
    archive_dir, cid = ingested
    (tmp_path / "stuff").mkdir()
    (tmp_path / "stuff" / "x.txt").write_text("x")
    with pytest.raises(InputError, match="not an archive"):
        ingest([str(d)], tmp_path / "stuff", FOV, ground_height=truth.ground_height, progress=False)
    assert main(["verify", "--archive", str(tmp_path / "stuff")]) == 2
    assert "not an archive (no archive.json)" in capsys.readouterr().err
    assert main(["verify", "--archive", str(tmp_path / "nowhere")]) == 2
    assert "archive directory not found" in capsys.readouterr().err
    assert main(["verify", "--archive", str(archive_dir), "Pika_19990101T000000"]) == 2
    assert f"known ids: {cid}" in capsys.readouterr().err
    with pytest.raises(MissingInputError):
        open_source("nope", PARAMS[0], archive=archive_dir)
    # ground height: the headers' 'ground elevation', else --ground-height, else a clear error
    copy = tmp_path / "copy"
    shutil.copytree(d, copy, ignore=shutil.ignore_patterns("truth"))
    for hdr in copy.glob("*.hdr"):
        lines = [x for x in hdr.read_text().splitlines() if not x.startswith("ground elevation")]
        hdr.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match="no 'ground elevation' in its header.*--ground-height"):
        ingest([str(copy)], tmp_path / "a2", FOV, progress=False)
    for hdr in copy.glob("*.hdr"):
        hdr.write_text(hdr.read_text() + "ground elevation = 80.5\n")
    (r,) = ingest([str(copy)], tmp_path / "a3", FOV, progress=False)
    attrs = zarr.open_group(r.store, mode="r").attrs
    assert (attrs["ground_height"], attrs["ground_height_source"]) == (80.5, "header 'ground elevation'")
    with pytest.raises(InputError, match="field of view"):
        ingest([str(d)], tmp_path / "a2", 0.0, ground_height=80.0, progress=False)
    assert not (tmp_path / "a2").exists()


def test_real_headers_survive_the_store_attributes(resonon_samples, tmp_path):
    """Header metadata goes through JSON (Zarr attributes): tuples become lists, booleans stay."""
    from archive.ingest.command import _jsonable
    from archive.formats.envi import header_from_metadata

    headers = sorted(resonon_samples.rglob("*.hdr"))
    assert headers
    for path in headers:
        h = read_header(path)
        g = zarr.open_group(tmp_path / f"{path.stem}.zarr", mode="w")
        g.attrs.put({"header": _jsonable(h.metadata)})
        back = header_from_metadata(dict(zarr.open_group(tmp_path / f"{path.stem}.zarr", mode="r").attrs)["header"],
                                    path)
        for name in ("samples", "lines", "bands", "interleave", "data_type", "byte_order", "header_offset",
                     "wavelengths", "fwhm", "shutter", "gain", "framerate", "bit_depth", "flip_radiometric_calibration",
                     "sample_binning", "spectral_binning"):
            assert getattr(back, name) == getattr(h, name), (path.name, name)
        assert back.dtype == h.dtype
