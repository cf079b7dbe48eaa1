"""The CPU band gather (archive/render/gather.py) against llvmpipe's GL band passes: equal values
within the stated bound (MAX_ULP float32 units in the last place; bit for bit on Mesa llvmpipe),
NaN and saturation at exactly the same pixels."""

from __future__ import annotations

import numpy as np
import pytest

from archive.errors import InputError
from archive.grid import Grid
from archive.render.context import gl_info
from archive.render.gather import MAX_ULP, gather_lookup, is_cpu_renderer, use_cpu_gather
from archive.render.mesh import build_mesh
from archive.render.renderer import rasterize_lookup, render_lookup
from tests.test_render import (FOV, FRAME, GSD, RATE, SHUTTER, flight, grid_around, no_gl_errors,  # noqa: F401
                               pattern, radiometry, rolled_pitched)




def ulp_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """|a - b| in float32 units in the last place (finite values of the same sign)."""
    return np.abs(a.view(np.int32).astype(np.int64) - b.view(np.int32).astype(np.int64))


def check_within_bound(gl, cpu):
    np.testing.assert_array_equal(np.isnan(cpu.values), np.isnan(gl.values))
    np.testing.assert_array_equal(cpu.saturated, gl.saturated)
    np.testing.assert_array_equal(cpu.covered, gl.covered)
    finite = ~np.isnan(gl.values)
    assert finite.any()
    same_sign = np.signbit(gl.values[finite]) == np.signbit(cpu.values[finite])
    assert same_sign.all() or np.abs(gl.values[finite][~same_sign]).max() < 1e-30
    assert ulp_distance(gl.values[finite], cpu.values[finite]).max() <= MAX_ULP
    if is_cpu_renderer(gl_info()["renderer"]):   # measured on Mesa llvmpipe: bit for bit
        assert np.array_equal(gl.values.view(np.uint32), cpu.values.view(np.uint32))


@pytest.mark.parametrize("dtype", ["uint16", "int16", "float32", "int32"])
def test_gather_equals_gl_band_passes(dtype):
    nb, lines, samples = 11, 120, 200
    mesh = rolled_pitched(lines)
    dn = pattern(nb, lines, samples).astype(np.int64)
    if dtype == "int16":
        dn = dn - 3000                            # negative DN: uploaded as exact float32
    elif dtype == "float32":
        dn = dn * 0.37
    elif dtype == "int32":
        dn = dn + 70000                           # above 65535: float32 path too
    dn = dn.astype(dtype)
    dn[9, 90:110, 50:90] = dn.max()               # saturated in band 9 only
    rad = radiometry(nb, lines, samples, saturation=float(dn.max()))
    lookup = rasterize_lookup(mesh, grid_around(mesh), samples)
    gl = render_lookup(lookup, dn, rad, 8)
    cpu = gather_lookup(lookup, dn, rad)
    check_within_bound(gl, cpu)
    assert cpu.saturated.sum() > 300
    raw_gl, raw_cpu = render_lookup(lookup, dn, None), gather_lookup(lookup, dn, None)   # raw DN: exact
    assert np.array_equal(raw_gl.values.view(np.uint32), raw_cpu.values.view(np.uint32))


def test_gather_on_windows_partial_and_empty_grids():
    nb, lines, samples = 5, 200, 64
    mesh = build_mesh(flight(lines), FOV, 110.0, SHUTTER, RATE)
    dn = pattern(nb, lines, samples)
    rad = radiometry(nb, lines, samples, saturation=3000)
    lookup = rasterize_lookup(mesh, grid_around(mesh), samples, max_size=70)
    check_within_bound(render_lookup(lookup, dn, rad, 8, max_size=70), gather_lookup(lookup, dn, rad))
    # a window of the grid that covers part of the cube only (rows above and below not covered)
    row0 = lookup.grid.height // 3
    part = lookup.grid.window(row0, 0, 50, lookup.grid.width)
    sub = rasterize_lookup(mesh, part, samples)
    check_within_bound(render_lookup(sub, dn, rad), gather_lookup(sub, dn, rad))
    far = Grid(FRAME.epsg, GSD, FRAME.origin_e + 100.0, FRAME.origin_n + 100.0, 20, 10)
    empty = gather_lookup(rasterize_lookup(mesh, far, samples), dn, rad)
    assert np.isnan(empty.values).all() and empty.values.shape == (nb, 10, 20) and not empty.saturated.any()
    with pytest.raises(InputError, match="lookup"):
        gather_lookup(lookup, dn[:, :, :-1], None)


def test_band_pass_choice(monkeypatch):
    assert is_cpu_renderer("llvmpipe (LLVM 15.0.6, 256 bits)")
    assert not is_cpu_renderer("NVIDIA H100 80GB HBM3/PCIe/SSE2")
    monkeypatch.delenv("ARCHIVE_BAND_PASS", raising=False)
    assert use_cpu_gather("llvmpipe (LLVM 15.0.6, 256 bits)") and not use_cpu_gather("NVIDIA H100")
    monkeypatch.setenv("ARCHIVE_BAND_PASS", "gl")
    assert not use_cpu_gather("llvmpipe")
    monkeypatch.setenv("ARCHIVE_BAND_PASS", "cpu")
    assert use_cpu_gather("NVIDIA H100")
    monkeypatch.setenv("ARCHIVE_BAND_PASS", "compute")   # a GL method: not the CPU gather
    assert not use_cpu_gather("llvmpipe")
    monkeypatch.setenv("ARCHIVE_BAND_PASS", "fast")
    with pytest.raises(InputError, match="ARCHIVE_BAND_PASS"):
        use_cpu_gather("llvmpipe")
