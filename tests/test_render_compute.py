"""The GL compute-shader band gather (archive/render/compute.py) against the CPU gather
(archive/render/gather.py) on llvmpipe: bit for bit, NaN (with its bits) and saturation flags at
exactly the same pixels, for uint16 and float DN, any band-group size, row chunks; the choice of
band pass (ARCHIVE_BAND_PASS); a render task and an ``archive render`` with each method."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from archive.errors import InputError, RenderError
from archive.grid import Grid
from archive.render.compute import compute_lookup, compute_unsupported
from archive.render.gather import (BAND_PASS_SETTINGS, band_pass_choice, band_pass_method, gather_index, gather_lookup,
                                   use_cpu_gather)
from archive.render.mesh import build_mesh
from archive.render.renderer import rasterize_lookup
from tests.test_render import (FOV, FRAME, GSD, RATE, SHUTTER, flight, grid_around, no_gl_errors,  # noqa: F401
                               pattern, radiometry, rolled_pitched)

NB, LINES, SAMPLES = 11, 120, 200


@pytest.fixture(scope="module")
def lookup():
    mesh = rolled_pitched(LINES)
    return rasterize_lookup(mesh, grid_around(mesh), SAMPLES)


def cube(dtype: str) -> np.ndarray:
    """(NB, LINES, SAMPLES) DN of ``dtype``, band 9 saturated in a patch (float: not integers)."""
    dn = pattern(NB, LINES, SAMPLES).astype(np.int64)
    if dtype == "int16":
        dn = dn - 3000                    # negative DN: uploaded as exact float32
    elif dtype == "float32":
        dn = dn * 0.37
    dn = dn.astype(dtype)
    dn[9, 90:110, 50:90] = dn.max()
    return dn


def assert_same(compute, cpu):
    """Bit for bit, NaN bits included; same saturation and coverage."""
    assert compute.values.shape == cpu.values.shape and compute.values.dtype == np.float32
    assert np.array_equal(compute.values.view(np.uint32), cpu.values.view(np.uint32))
    np.testing.assert_array_equal(compute.saturated, cpu.saturated)
    np.testing.assert_array_equal(compute.covered, cpu.covered)


def test_compute_context_on_this_machine():
    assert compute_unsupported() is None   # Mesa llvmpipe: GL 4.5 core


@pytest.mark.parametrize("dtype", ["uint16", "float32", "int16"])
@pytest.mark.parametrize("group", [1, 3, 8, 16])   # 11 bands: 3 and 8 leave a short last group
def test_compute_equals_cpu_gather(lookup, dtype, group):
    dn = cube(dtype)
    rad = radiometry(NB, LINES, SAMPLES, saturation=float(dn.max()))
    cpu = gather_lookup(lookup, dn, rad)
    compute = compute_lookup(lookup, dn, rad, group)
    assert_same(compute, cpu)
    assert np.isnan(cpu.values).any() and (~np.isnan(cpu.values)).any()
    assert cpu.saturated.sum() > 300
    assert np.isnan(cpu.values[:, ~cpu.covered]).all()


def test_compute_raw_dn_gather_index_and_out(lookup):
    dn = cube("uint16")
    cpu = gather_lookup(lookup, dn, None)
    out = np.full((NB, *lookup.grid.shape), 7.0, np.float32)
    compute = compute_lookup(gather_index(lookup), dn, None, 4, out=out)
    assert compute.values is out
    assert_same(compute, cpu)
    assert not compute.saturated.any()
    with pytest.raises(ValueError, match="C-contiguous float32"):
        compute_lookup(lookup, dn, None, out=np.empty((NB, 3, 3), np.float32))
    with pytest.raises(InputError, match="lookup"):
        compute_lookup(lookup, dn[:, :, :-1], None)


@pytest.mark.parametrize("max_block", [100_000, 60_000 * 4])
def test_compute_in_row_chunks_and_small_groups(lookup, max_block):
    """A storage-block limit below one band of the grid: band by band in chunks of rows (100 kB: 24
    rows of 1012 px); 240 kB: groups shrink to what fits. Same values."""
    assert lookup.grid.shape[0] * lookup.grid.shape[1] * 4 > max_block
    dn = cube("uint16")
    rad = radiometry(NB, LINES, SAMPLES, saturation=float(dn.max()))
    assert_same(compute_lookup(lookup, dn, rad, 8, max_block=max_block), gather_lookup(lookup, dn, rad))
    with pytest.raises(RenderError, match="ARCHIVE_BAND_PASS"):   # one band's DN must fit
        compute_lookup(lookup, dn, rad, max_block=LINES * SAMPLES)


def test_compute_on_windows_partial_and_empty_grids():
    nb, lines, samples = 5, 200, 64
    mesh = build_mesh(flight(lines), FOV, 110.0, SHUTTER, RATE)
    dn = pattern(nb, lines, samples)
    rad = radiometry(nb, lines, samples, saturation=3000)
    whole = rasterize_lookup(mesh, grid_around(mesh), samples)
    row0 = whole.grid.height // 3    # rows above and below the covered ones: NaN from the shader
    part = rasterize_lookup(mesh, whole.grid.window(row0, 0, 50, whole.grid.width), samples)
    for lk in (whole, part):
        assert lk.grid.height * lk.grid.width * 4 > 30_000       # row chunks
        assert_same(compute_lookup(lk, dn, rad, 2, max_block=30_000), gather_lookup(lk, dn, rad))
        assert_same(compute_lookup(lk, dn, rad), gather_lookup(lk, dn, rad))
    far = Grid(FRAME.epsg, GSD, FRAME.origin_e + 100.0, FRAME.origin_n + 100.0, 20, 10)
    empty = compute_lookup(rasterize_lookup(mesh, far, samples), dn, rad)
    assert np.isnan(empty.values).all() and empty.values.shape == (nb, 10, 20) and not empty.saturated.any()
    none = compute_lookup(whole, dn[:0], None)
    assert none.values.shape == (0, *whole.grid.shape)


def test_band_pass_settings(monkeypatch):
    gpu, cpu = "NVIDIA H100 80GB HBM3/PCIe/SSE2", "llvmpipe (LLVM 15.0.6, 256 bits)"
    monkeypatch.delenv("ARCHIVE_BAND_PASS", raising=False)
    assert BAND_PASS_SETTINGS == ("auto", "cpu", "gl", "compute")
    assert band_pass_method(cpu) == "cpu" and band_pass_method(gpu) == "compute"
    assert "provisional" in band_pass_choice(gpu).reason and "bench/gpu.sh" in band_pass_choice(gpu).reason
    # auto on a GPU without compute shaders: the GL fragment passes, and why
    fallback = band_pass_choice(gpu, compute_unsupported="the GL context is version 4.1")
    assert fallback.method == "gl" and "version 4.1" in fallback.reason
    assert band_pass_method(cpu, compute_unsupported="no 4.3") == "cpu"
    for setting in ("cpu", "gl", "compute"):
        for renderer in (gpu, cpu):
            assert band_pass_method(renderer, setting) == setting
        monkeypatch.setenv("ARCHIVE_BAND_PASS", f" {setting.upper()} ")
        assert band_pass_choice(gpu) == (setting, f"ARCHIVE_BAND_PASS={setting}")
    assert not use_cpu_gather(cpu) and not use_cpu_gather(cpu, "gl")   # compute (set above) counts as GL
    monkeypatch.setenv("ARCHIVE_BAND_PASS", "auto")
    assert use_cpu_gather(cpu) and not use_cpu_gather(gpu)
    # compute forced where it cannot run: one line naming the setting
    with pytest.raises(RenderError, match="ARCHIVE_BAND_PASS=compute") as err:
        band_pass_choice(gpu, "compute", compute_unsupported="the GL context is version 3.3")
    assert "\n" not in str(err.value) and "version 3.3" in str(err.value)
    monkeypatch.setenv("ARCHIVE_BAND_PASS", "shader")
    with pytest.raises(InputError, match="ARCHIVE_BAND_PASS") as bad:
        band_pass_method(gpu)
    assert "compute" in str(bad.value)


def test_compute_unsupported_below_gl_43():
    old = SimpleNamespace(version_code=330, info={"GL_RENDERER": "Old GPU"}, compute_shader=None)
    reason = compute_unsupported(old)
    assert "4.3" in reason and "3.3" in reason and "Old GPU" in reason


class _Source:
    """The part of a flight source a render task uses: one cube in memory."""

    label = "fake flight"

    def __init__(self, dn, rad):
        self.dn, self.rad = dn, rad
        self.cubes = [SimpleNamespace(base="cube-0")]

    def read_bands(self, cube, bands):
        return self.dn[list(bands)]

    def radiometry(self, cube, bands, mode):
        b = list(bands)
        return SimpleNamespace(dark=self.rad.dark[b], gain=self.rad.gain[b], response=self.rad.response,
                               saturation=self.rad.saturation)


def test_render_task_runs_the_chosen_method(lookup, monkeypatch):
    from archive.graph import tasks
    from archive.render import compute

    dn = cube("uint16")
    rad = radiometry(NB, LINES, SAMPLES, saturation=float(dn.max()))
    source = _Source(dn, rad)
    calls = []
    real = compute.compute_lookup
    monkeypatch.setattr(compute, "compute_lookup", lambda *a, **k: calls.append(1) or real(*a, **k))
    packed = tasks.PackedLookup(lookup)
    results = {}
    monkeypatch.setattr(tasks, "_BAND_PASS", {})
    for method in ("cpu", "gl", "compute"):
        monkeypatch.setenv("ARCHIVE_BAND_PASS", method)
        assert tasks.decided_band_pass() is None       # nothing decided yet for this setting
        assert tasks.band_pass() == method and tasks.band_pass_choice().reason == f"ARCHIVE_BAND_PASS={method}"
        assert tasks.cpu_band_pass() == (method == "cpu")
        results[method] = tasks.render_task(source, 0, range(2, NB), packed, "radiance")
        assert tasks.decided_band_pass() == {"method": method, "reason": f"ARCHIVE_BAND_PASS={method}"}
    assert calls == [1]
    for method in ("gl", "compute"):
        values, saturated = results[method]
        assert np.array_equal(values.view(np.uint32), results["cpu"][0].view(np.uint32)), method
        np.testing.assert_array_equal(saturated, results["cpu"][1])
    monkeypatch.setenv("ARCHIVE_BAND_PASS", "auto")
    assert tasks.band_pass() == "cpu" and "llvmpipe" in tasks.band_pass_choice().reason


def test_archive_render_compute_equals_cpu(tmp_path, monkeypatch):
    """``archive render`` end to end (local worker processes inherit the setting): the Zarr of a
    render with the compute gather equals the CPU gather's, bit for bit."""
    import xarray as xr

    from archive.cli import main
    from archive.simulator.command import simulate_flight

    simulate_flight(tmp_path / "flight", cubes=2, bands=7, samples=48, lines=120, cubes_per_pass=2, seed=5)
    values = {}
    for method in ("cpu", "compute"):
        monkeypatch.setenv("ARCHIVE_BAND_PASS", method)
        out = tmp_path / f"{method}.zarr"
        assert main(["render", str(tmp_path / "flight"), "--fov", str(FOV), "--gsd", "0.03", "--ground-height", "auto",
                     "--out", str(out), "--quiet"]) == 0
        values[method] = xr.open_zarr(out)["radiance"].values
    assert np.isfinite(values["cpu"]).any() and np.isnan(values["cpu"]).any()
    assert np.array_equal(values["compute"].view(np.uint32), values["cpu"].view(np.uint32))


def test_render_task_on_a_context_without_compute(lookup, monkeypatch):
    """A GPU context without GL 4.3: auto falls back to the GL fragment passes and says why;
    ARCHIVE_BAND_PASS=compute stops the render task with one line naming the setting and the cube."""
    from archive.graph import tasks

    dn = cube("uint16")
    source = _Source(dn, radiometry(NB, LINES, SAMPLES))
    monkeypatch.setattr(tasks, "_BAND_PASS", {})
    monkeypatch.setattr(tasks, "_band_pass_facts", lambda: ("Old GPU", "the GL context is version 4.1"))
    monkeypatch.setenv("ARCHIVE_BAND_PASS", "auto")
    assert tasks.band_pass_choice() == ("gl", "auto: GPU renderer 'Old GPU', GL fragment passes "
                                              "(the GL context is version 4.1)")
    monkeypatch.setenv("ARCHIVE_BAND_PASS", "compute")
    with pytest.raises(RenderError, match="cube-0: ARCHIVE_BAND_PASS=compute, but the GL context is version 4.1") as err:
        tasks.render_task(source, 0, [0, 1], tasks.PackedLookup(lookup), "radiance")
    assert "\n" not in str(err.value)
