"""ENVI tiles written through the process's one writing thread (``archive.outputs.envi.WRITER``):
the bytes of every band of every tile where they belong, whoever wrote them (task threads at once,
each filling its next strip buffer while earlier ones are written), whole-width strips and row by
row (mosaics wider than ENVI_STRIP_MAX), every overlap rule's way of filling its buffers; a failed
write raised by the tile that wrote it; the writing thread started again in a forked child."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from archive.outputs.base import CHUNK
from archive.outputs.envi import ENVI_STRIP_MAX, WRITE_BUFFERS, EnviSink
from archive.overlap import overlap_rule


def _tiles(sink: EnviSink):
    th, tw = sink.tile_size
    for r in range(0, sink.height, th):
        for c in range(0, sink.width, tw):
            yield (r, c, min(th, sink.height - r), min(tw, sink.width - c))


def _write_tile(sink: EnviSink, truth: np.ndarray, band0: int, nbands: int, tile) -> None:
    r, c, h, w = tile
    with sink.open_tile(band0, tile, nbands) as writer:
        for b in range(nbands):
            buffer = writer.buffer()
            buffer[...] = -1.0   # outside the tile: never written
            buffer[:h, :w] = truth[band0 + b, r:r + h, c:c + w]
            writer.write(b, buffer)
        writer.close()


def _read(sink: EnviSink) -> np.ndarray:
    return np.fromfile(sink.data, "<f4").reshape(sink.nbands, sink.height, sink.width)


@pytest.mark.parametrize("width", [1500, ENVI_STRIP_MAX + 700])
def test_tiles_of_threads_at_once_land_where_they_belong(tmp_path, width):
    height, nbands = CHUNK + 300, 2 * WRITE_BUFFERS + 1
    truth = np.random.default_rng(5).normal(0, 100, (nbands, height, width)).astype(np.float32)
    truth[:, ::7, ::5] = np.nan
    sink = EnviSink.create(tmp_path / "m", nbands, height, width)
    jobs = [(band0, n, tile) for tile in _tiles(sink) for band0, n in ((0, 4), (4, nbands - 4))]
    with ThreadPoolExecutor(3) as pool:
        list(pool.map(lambda job: _write_tile(sink, truth, *job), jobs))
    assert len(jobs) == (2 if width <= ENVI_STRIP_MAX else 4) * 2
    np.testing.assert_array_equal(_read(sink), truth)   # NaN where NaN: equal_nan by default


@pytest.mark.parametrize("rule", ["last", "nadir", "mean"])
def test_each_rule_fills_a_buffer_per_band(tmp_path, rule):
    """Two overlapping parts mosaicked by each rule straight into the writer's buffers, which come in
    turn (more bands than buffers): band b holds band b's mosaic (its values are b + the part's)."""
    height, width, nbands = 300, 500, WRITE_BUFFERS * 2 + 1
    a = np.arange(nbands, dtype=np.float32)[:, None, None] + np.full((nbands, 200, 300), 1000, np.float32)
    b = np.arange(nbands, dtype=np.float32)[:, None, None] + np.full((nbands, 200, 300), 2000, np.float32)
    unsaturated = np.zeros((200, 300), bool)
    parts = [(a, unsaturated, slice(0, 200), slice(0, 300)), (b, unsaturated, slice(100, 300), slice(200, 500))]
    keys = [np.full((200, 300), 5.0, np.float32), np.full((200, 300), 1.0, np.float32)]
    chosen = overlap_rule(rule)
    sink = EnviSink.create(tmp_path / "m", nbands, height, width)
    with sink.open_tile(0, (0, 0, height, width), nbands) as writer:
        chosen.write_bands(writer, nbands, height, width, parts, keys if chosen.needs else None, False)
        writer.close()
    out = _read(sink)
    both = {"last": 2000, "nadir": 2000, "mean": 1500}[rule]   # the second part is closer to nadir
    for k in range(nbands):
        assert out[k, 0, 0] == 1000 + k
        assert out[k, 150, 250] == both + k
        assert out[k, 299, 499] == 2000 + k
        assert np.isnan(out[k, 299, 0]) and np.isnan(out[k, 0, 499])


def test_a_failed_write_is_raised_by_its_tile(tmp_path):
    """A write past the process's file size limit (EFBIG, the signal ignored) fails on the writing
    thread; the tile's close raises it; the next tile of the same thread writes."""
    script = textwrap.dedent(f"""
        import errno, resource, signal
        import numpy as np
        from archive.outputs.envi import EnviSink
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        sink = EnviSink.create({str(tmp_path / "m")!r}, 4, 1024, 1000)
        band = 1024 * 1000 * 4
        resource.setrlimit(resource.RLIMIT_FSIZE, (2 * band, resource.RLIM_INFINITY))
        writer = sink.open_tile(0, (0, 0, 1024, 1000), 4)
        for b in range(4):
            buffer = writer.buffer()
            buffer[...] = b
            writer.write(b, buffer)
        try:
            writer.close()
        except OSError as exc:
            assert exc.errno == errno.EFBIG, exc
        else:
            raise SystemExit("no error from close")
        writer = sink.open_tile(0, (0, 0, 1024, 1000), 2)
        for b in range(2):
            buffer = writer.buffer()
            buffer[...] = 10 + b
            writer.write(b, buffer)
        writer.close()
        data = np.fromfile(sink.data, "<f4")
        assert (data[:band // 4] == 10).all() and (data[band // 4:2 * band // 4] == 11).all()
        print("ok")
    """)
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and done.stdout.strip() == "ok", done.stderr


@pytest.mark.skipif(not hasattr(os, "fork"), reason="no fork")
def test_a_forked_child_starts_its_own_writing_thread(tmp_path):
    script = textwrap.dedent(f"""
        import os
        import numpy as np
        from archive.outputs.envi import EnviSink

        def tile(sink, value):
            with sink.open_tile(0, (0, 0, 64, 80), 1) as writer:
                buffer = writer.buffer()
                buffer[...] = value
                writer.write(0, buffer)
                writer.close()

        sink = EnviSink.create({str(tmp_path / "m")!r}, 1, 64, 80)
        tile(sink, 1.0)   # the parent's writing thread is running
        pid = os.fork()
        if pid == 0:
            tile(sink, 2.0)
            os._exit(0)
        _, status = os.waitpid(pid, 0)
        assert os.waitstatus_to_exitcode(status) == 0
        assert (np.fromfile(sink.data, "<f4") == 2.0).all()
        print("ok")
    """)
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0 and done.stdout.strip() == "ok", done.stderr
