"""COG and ENVI written by the render graph's own tile tasks (issue 10), on a small simulated flight.

Checked against the Zarr mosaic of the same render, bit for bit: ENVI BSQ by positioned writes into
a preallocated file; COG from tiles compressed by the writer tasks, overviews computed from the tiles
inside the graph, laid out without recompression (GDAL's COG checks, every tile's leader and
trailer, band-interleaved). A render SIGKILLed while writing leaves no output and the rerun is
identical; an unwritable or full output folder is a one-line error with nothing left behind.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import shutil
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
import rasterio
import xarray as xr

from archive.cli import main
from archive.outputs.cog_check import check_cog, file_layout
from archive.outputs.tiff import downsample2, level_shapes
from archive.grid import Grid
from archive.outputs.base import CHUNK, OutputMeta
from archive.outputs.cog import CogSink
from archive.outputs.envi import EnviSink
from archive.outputs.publish import Output

FOV = 47.5
GSD = 0.015  # 4185 x 2079 px: 15 output tiles, 2 of them touched by no cube; 4 COG overview levels


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    from archive.simulator.command import simulate_flight

    directory = tmp_path_factory.mktemp("formats") / "flight"
    simulate_flight(directory, cubes=4, bands=6, samples=64, lines=150, cubes_per_pass=2, seed=3)
    return directory


@pytest.fixture(scope="module")
def scheduler():
    """A LocalCluster shaped like the command's own: 1 spawned worker, 2 threads, GPU=2."""
    from distributed import LocalCluster

    with LocalCluster(n_workers=1, threads_per_worker=2, processes=True, resources={"GPU": 2},
                      dashboard_address=":0", silence_logs=logging.ERROR) as cluster:
        yield cluster.scheduler_address


def _args(flight, out, *extra) -> list[str]:
    return ["render", str(flight), "--fov", str(FOV), "--gsd", str(GSD), "--ground-height", "auto",
            "--out", str(out), "--quiet", *extra]


@pytest.fixture(scope="module")
def rendered(flight, scheduler, tmp_path_factory):
    """The same render as Zarr, COG and ENVI (one shared cluster); the Zarr values (band, y, x)."""
    folder = tmp_path_factory.mktemp("rendered")
    for name in ("m.zarr", "m.tif", "m.hdr"):
        assert main(_args(flight, folder / name, "--scheduler", scheduler)) == 0
    values = xr.open_zarr(folder / "m.zarr", decode_coords="all")["radiance"].values
    return folder, values


def _bits(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, np.float32).view(np.uint32)


def test_envi_equals_zarr_bit_for_bit(rendered):
    folder, values = rendered
    data = folder / "m"
    assert data.stat().st_size == values.size * 4
    np.testing.assert_array_equal(_bits(np.fromfile(data, "<f4").reshape(values.shape)), _bits(values))
    assert np.isnan(values).any() and np.isfinite(values).any()
    text = (folder / "m.hdr").read_text()
    assert "interleave = bsq" in text and "map info = {UTM, 1, 1," in text
    with rasterio.open(data) as ds:
        assert ds.driver == "ENVI" and ds.crs.to_epsg() == 32616 and ds.count == values.shape[0]
        z = xr.open_zarr(folder / "m.zarr", decode_coords="all")
        assert tuple(ds.transform)[:6] == tuple(z.rio.transform())[:6]
        assert float(ds.tags(2)["wavelength"]) == pytest.approx(float(z["wavelength"][1]))


def test_cog_equals_zarr_and_is_a_valid_cog(rendered):
    folder, values = rendered
    path = folder / "m.tif"
    assert check_cog(path) == []
    layout = file_layout(path)
    nb, height, width = values.shape
    shapes = level_shapes(height, width)
    assert len(shapes) == 5  # full resolution + 4 overviews
    assert [(im["height"], im["width"]) for im in layout["images"]] == shapes
    assert all(im["planar"] == 2 and im["samples"] == nb and im["predictor"] == 3 for im in layout["images"])
    z = xr.open_zarr(folder / "m.zarr", decode_coords="all")
    with rasterio.open(path) as ds:
        assert ds.crs.to_epsg() == 32616 and tuple(ds.transform)[:6] == tuple(z.rio.transform())[:6]
        assert ds.tags(ns="IMAGE_STRUCTURE")["LAYOUT"] == "COG" and ds.interleaving.value == "BAND"
        assert np.isnan(ds.nodata) and ds.block_shapes == [(512, 512)] * nb
        assert ds.overviews(1) == [2, 4, 8, 16]
        wl = [float(ds.tags(b + 1)["wavelength"]) for b in range(nb)]
        np.testing.assert_allclose(wl, z["wavelength"].values)
        assert ds.descriptions[0] == f"{wl[0]:.1f} nm"
        np.testing.assert_array_equal(_bits(ds.read()), _bits(values))
    # overviews: NaN-aware 2 x 2 means, each level from the one below
    expected = values
    for level in range(1, len(shapes)):
        expected = downsample2(expected)
        with rasterio.open(path, overview_level=level - 1) as ov:
            np.testing.assert_array_equal(_bits(ov.read()), _bits(expected))
    assert np.isfinite(expected).any()


def test_cog_bands_are_contiguous_and_a_few_bands_read_a_few_bytes(rendered):
    folder, values = rendered
    layout = file_layout(folder / "m.tif")
    nb = values.shape[0]
    for im in layout["images"]:
        offsets = im["offsets"].reshape(nb, -1)
        ends = offsets + im["counts"].reshape(nb, -1)
        assert all(ends[b].max() <= offsets[b + 1].min() for b in range(nb - 1))  # band after band
    # bytes a reader fetches for a 512 x 512 window: one tile per band
    main = layout["images"][0]
    counts = main["counts"].reshape(nb, -1)
    k = np.flatnonzero(counts[0] > counts[0].min())[0]  # a tile with data
    assert counts[:1, k].sum() < counts[:, k].sum() / (nb - 1)


def test_cog_laid_out_band_group_by_group_is_one_file_with_or_without_insert_range(flight, scheduler, rendered,
                                                                                 tmp_path, monkeypatch):
    """The graph lays the full resolution out in the COG's own file band group by band group
    (layout tasks), the header and overviews are put in front of it at the end without moving it
    (FALLOC_FL_INSERT_RANGE) or, where the file system cannot (tmpfs, NFS), by copying it: the
    same bytes either way, a valid COG, the Zarr render's values."""
    import archive.graph.build as build
    import archive.outputs.tiff as tiff

    _, values = rendered
    monkeypatch.setattr(build, "TASK_VALUES_BYTES", 1)   # the smallest band groups: 4 + 2 bands
    inserted, copied = tmp_path / "inserted.tif", tmp_path / "copied.tif"
    calls = []
    real = tiff._insert_front
    monkeypatch.setattr(tiff, "_insert_front", lambda path, n: calls.append(n) or real(path, n))
    assert main(_args(flight, inserted, "--scheduler", scheduler)) == 0
    assert len(calls) == 1 and calls[0] % tiff.DATA_ALIGN == 0
    monkeypatch.setattr(tiff, "_insert_front", lambda path, n: False)
    assert main(_args(flight, copied, "--scheduler", scheduler)) == 0
    assert inserted.read_bytes() == copied.read_bytes()
    assert check_cog(inserted) == []
    first = file_layout(inserted)["images"][0]["offsets"]
    assert (first.min() - 4) % tiff.DATA_ALIGN == 0   # level 0 starts where the room was made
    with rasterio.open(inserted) as ds:
        np.testing.assert_array_equal(_bits(ds.read()), _bits(values))
    assert not [p.name for p in tmp_path.iterdir() if p.suffix not in (".tif", ".json")]   # no spools left


def test_cog_layout_task_is_idempotent_and_names_a_missing_spool(tmp_path):
    rng = np.random.default_rng(0)
    sink = CogSink.create(tmp_path / "c", 3, 1500, 1100)
    values = rng.random((3, 1500, 1100), np.float32)
    for r in range(0, 1500, CHUNK):
        for c in range(0, 1100, CHUNK):
            tile = (r, c, min(CHUNK, 1500 - r), min(CHUNK, 1100 - c))
            with sink.open_tile(0, tile, 2) as writer:
                buffer = writer.buffer()
                for b in range(2):
                    buffer[...] = np.nan
                    buffer[:tile[2], :tile[3]] = values[b, r:r + tile[2], c:c + tile[3]]
                    writer.write(b, buffer)
                writer.close()
    end = sink.lay_out(0, 2, 0)
    assert end == os.path.getsize(sink.data_path) > 0
    assert not [n for n in os.listdir(sink.spool) if n.startswith("L0-")]   # its spools are gone
    assert sink.lay_out(0, 2, 0) == end    # run again (a retried task): what it recorded
    with pytest.raises(ValueError, match=r"L0-0-0-2\.tiles: missing: a writer task of bands 2\.\. did not complete"):
        sink.lay_out(2, 1, end)


def test_cog_runs_copied_through_a_buffer_or_in_the_kernel_are_the_same_bytes(tmp_path, monkeypatch):
    """Layout and assembly copy runs of spool files through one buffer per thread (pread + pwrite),
    or by copy_file_range where the file system copies on the server: the same file either way,
    runs longer than the buffer included."""
    import archive.outputs.tiff as tiff

    rng = np.random.default_rng(3)
    sources = []
    for k in range(3):
        path = tmp_path / f"s{k}"
        path.write_bytes(rng.integers(0, 256, 300_000 + k * 1000, np.uint8).tobytes())
        sources.append(str(path))
    runs = [(sources[0], 10, 70_000, 0), (sources[1], 0, 250_000, 70_000), (sources[2], 5, 1000, 320_000),
            (sources[0], 200_000, 100_000, 321_000)]
    expected = b"".join(open(p, "rb").read()[a:a + n] for p, a, n, _ in runs)
    monkeypatch.setattr(tiff, "COPY_BUFFER", 64_000)   # runs span several buffers
    for kernel in (False, True):
        monkeypatch.setattr(tiff, "SERVER_COPY_FS", (tiff._fs_type(os.stat(tmp_path).st_dev),) if kernel else ())
        for threads in (1, 3):
            dest = tmp_path / f"d{kernel}{threads}"
            fd = os.open(dest, os.O_WRONLY | os.O_CREAT | os.O_TRUNC)
            try:
                tiff._copy_runs(fd, runs, threads)
            finally:
                os.close(fd)
            assert dest.read_bytes() == expected


@pytest.mark.parametrize("shape", [(1024, 1024), (2, 513, 1023), (3, 3)])
def test_overview_downsampling_is_the_mean_of_the_finite_pixels(shape):
    rng = np.random.default_rng(4)
    block = (rng.random(shape) * 300).astype(np.float32)
    holes = block.copy()
    holes[rng.random(shape) < 0.2] = np.nan
    holes.flat[::101] = np.inf
    holes[..., :2, :2] = np.nan   # one window with nothing finite
    down = downsample2(holes)
    h, w = shape[-2:]
    padded = np.full((*shape[:-2], h + h % 2, w + w % 2), np.nan)
    padded[..., :h, :w] = np.where(np.isfinite(holes), holes, np.nan)
    windows = padded.reshape(*shape[:-2], (h + h % 2) // 2, 2, (w + w % 2) // 2, 2)
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        expected = np.nanmean(windows, axis=(-3, -1))
    assert down.dtype == np.float32 and down.shape == expected.shape
    assert np.array_equal(np.isnan(down), np.isnan(expected)) and np.isnan(down).any()
    np.testing.assert_allclose(down, expected, rtol=1e-6)
    # a tile whose pixels are all finite takes a shorter way: the same bits as where one NaN elsewhere
    # sends it the NaN-aware way
    full, one = downsample2(block), block.copy()
    one.flat[0] = np.nan
    partial = downsample2(one)
    assert np.array_equal(full.view(np.uint32).flat[1:], partial.view(np.uint32).flat[1:])
    if h % 2 == 0 and w % 2 == 0:
        np.testing.assert_allclose(full, block.astype(np.float64).reshape(windows.shape).mean(axis=(-3, -1)), rtol=1e-6)


def _window_means(block: np.ndarray) -> np.ndarray:
    """The 2 x 2 NaN-aware means of a (h, w) float32 block, window by window in float32 as
    downsample2 documents: (tl + bl) + (tr + br) of the finite pixels (others +0), / their count."""
    h, w = block.shape
    out = np.empty((-(-h // 2), -(-w // 2)), np.float32)
    zero = np.float32(0)
    for r in range(out.shape[0]):
        for c in range(out.shape[1]):
            px = [block[y, x] if y < h and x < w else np.float32(np.nan)
                  for y, x in ((2 * r, 2 * c), (2 * r + 1, 2 * c), (2 * r, 2 * c + 1), (2 * r + 1, 2 * c + 1))]
            z = [p if np.isfinite(p) else zero for p in px]
            n = sum(bool(np.isfinite(p)) for p in px)
            out[r, c] = np.nan
            if n:
                out[r, c] = ((z[0] + z[1]) + (z[2] + z[3])) / np.uint8(n)
    return out


@pytest.mark.parametrize("nan_share", [0.0, 0.02, 0.6])
@pytest.mark.parametrize("shape", [(40, 58), (37, 51), (1, 9), (9, 1)])
def test_overview_downsampling_bits_window_by_window(shape, nan_share):
    """downsample2's bits equal the documented per-window float32 sum and count, whichever way it
    takes (all finite; a few windows with a NaN, averaged one by one; many, all at once; the odd
    edges), on a view of a wider chunk and into a slice of a larger buffer (as the COG writer does)."""
    rng = np.random.default_rng(8)
    chunk = (rng.random((shape[0] + 3, shape[1] + 5)) * 300 - 20).astype(np.float32)
    chunk[rng.random(chunk.shape) < nan_share] = np.nan
    block = chunk[1:1 + shape[0], 2:2 + shape[1]]
    if nan_share:
        block.flat[3] = np.inf
        block.flat[5] = -0.0
        block[:2, :2] = 3.4e38   # a window whose sum overflows
    with np.errstate(over="ignore", invalid="ignore"):
        expected = _window_means(block)
        assert np.array_equal(_bits(downsample2(block)), _bits(expected))
        buffer = np.full((40, 40), 7, np.float32)
        oh, ow = expected.shape
        downsample2(block, out=buffer[:oh, :ow])
        assert np.array_equal(_bits(buffer[:oh, :ow]), _bits(expected)) and (buffer[oh:] == 7).all()
        stacked = downsample2(np.stack([block, block[::-1]]))   # leading axes
        assert np.array_equal(_bits(stacked[0]), _bits(expected))
        assert np.array_equal(_bits(stacked[1]), _bits(_window_means(np.ascontiguousarray(block[::-1]))))


def test_blank_tiles_are_nan(rendered):
    folder, values = rendered
    untouched = [(r, c) for r in range(0, values.shape[1], CHUNK) for c in range(0, values.shape[2], CHUNK)
                 if np.isnan(values[:, r:r + CHUNK, c:c + CHUNK]).all()]
    assert untouched  # written by blank-tile tasks in ENVI and COG (checked equal above)


# ---------------------------------------------------------------------------------------------
# A render killed while writing, then run again
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["m.zarr", "m.tif", "m.hdr"])
def test_killed_while_writing_leaves_nothing_and_rerun_is_identical(flight, rendered, tmp_path, name):
    folder, values = rendered
    out = tmp_path / name
    cmd = [sys.executable, "-m", "archive", *_args(flight, out)]
    # each worker writes one tile, then its next tile write waits while the hold file exists (the
    # ARCHIVE_TEST_HOLD_WRITES hook): the kill lands mid-job however loaded the machine
    hold = tmp_path.parent / f"{tmp_path.name}.hold"
    hold.touch()
    job = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True,
                           env={**os.environ, "ARCHIVE_TEST_HOLD_WRITES": f"1:{hold}"})
    try:
        deadline = time.monotonic() + 120
        while not Path(f"{hold}.reached").exists():
            assert job.poll() is None, job.stderr.read().decode()
            assert time.monotonic() < deadline
            time.sleep(0.02)
        os.killpg(job.pid, signal.SIGKILL)  # the command and its cluster: no cleanup code runs
        job.wait(30)
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(job.pid, signal.SIGKILL)
        job.wait(30)
    assert job.returncode == -signal.SIGKILL
    left = sorted(p.name for p in tmp_path.iterdir())
    assert left and all(".partial-" in n and n.startswith(".") for n in left), left
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    finals = {"m.zarr": ["m.zarr", "m.zarr.json"], "m.tif": ["m.tif", "m.tif.json"],
              "m.hdr": ["m", "m.hdr", "m.hdr.json"]}[name]  # the output and its STAC Item
    assert sorted(p.name for p in tmp_path.iterdir()) == finals  # the killed run's temporaries are gone
    if name == "m.zarr":
        got = xr.open_zarr(out)["radiance"].values
    elif name == "m.tif":
        with rasterio.open(out) as ds:
            got = ds.read()
        assert (out.read_bytes() == (folder / name).read_bytes())  # the very same file
    else:
        got = np.fromfile(tmp_path / "m", "<f4").reshape(values.shape)
    np.testing.assert_array_equal(_bits(got), _bits(values))


# ---------------------------------------------------------------------------------------------
# Output folders that cannot take the output
# ---------------------------------------------------------------------------------------------
@contextlib.contextmanager
def _read_only(folder: Path):
    """Make ``folder`` unwritable for this process (chmod, or the immutable flag when root)."""
    folder.chmod(0o555)
    immutable = False
    try:
        if not os.access(folder, os.W_OK):
            yield
            return
        if shutil.which("chattr") is None or subprocess.run(["chattr", "+i", str(folder)],
                                                            capture_output=True).returncode != 0:
            pytest.skip("cannot make a folder read-only for this user (root without chattr +i)")
        immutable = True
        yield
    finally:
        if immutable:
            subprocess.run(["chattr", "-i", str(folder)], check=True)
        folder.chmod(0o755)


@pytest.mark.parametrize("name", ["m.zarr", "m.tif", "m.hdr"])
def test_read_only_folder_is_a_clear_error(flight, tmp_path, capsys, name):
    folder = tmp_path / "ro"
    folder.mkdir()
    with _read_only(folder):
        rc = main(_args(flight, folder / "sub" / name, "--gsd", "0.5"))
        err = capsys.readouterr().err.strip()
        assert rc != 0 and len(err.splitlines()) == 1, err
        assert err.startswith("archive render: error:") and "not writable" in err and str(folder) in err
        assert list(folder.iterdir()) == []


def test_full_folder_is_a_clear_error_before_rendering(tmp_path, monkeypatch):
    grid = Grid(epsg=32616, gsd=0.5, x0=771000.0, y0=3891500.0, width=300, height=200)

    def full(fd, offset, length):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "posix_fallocate", full)
    out = Output(tmp_path / "new" / "m.hdr")
    try:
        with pytest.raises(Exception, match="not enough free space for a 0.0 GB output") as info:
            out.sink(OutputMeta(grid, (0, 1)))
        assert "\n" not in str(info.value)
    finally:
        out.cleanup()
    assert list(tmp_path.iterdir()) == []


def test_sinks_refuse_tiles_off_the_chunk_grid(tmp_path):
    envi = EnviSink.create(tmp_path / "e", 2, 1500, 1100)
    cog = CogSink.create(tmp_path / "c", 2, 1500, 1100)
    for sink in (envi, cog):
        with pytest.raises(ValueError, match="is not one 1024 x 1[01][02][04] px tile"):
            sink.open_tile(0, (512, 0, 1024, 1024), 2)
        whole = (0, 0, 1024, sink.tile_size[1] if sink is envi else 1024)
        with pytest.raises(ValueError, match="bands"):
            sink.open_tile(1, whole, 2)
    # ENVI tiles are whole-width row strips (one write per band); a chunk-wide tile is refused
    assert envi.tile_size == (1024, 1100)
    with pytest.raises(ValueError, match="not one 1024 x 1100 px tile"):
        envi.open_tile(0, (0, 0, 1024, 1024), 2)
