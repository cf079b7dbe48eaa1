"""Pass 2 of the renderer on the CPU: the bands of a cube gathered through its lookup with numpy.

On a CPU renderer (Mesa llvmpipe) a full-screen GL band pass is a gather through the (line, sample)
lookup that pass 1 (:func:`archive.render.renderer.rasterize_lookup`, still drawn by GL) gives, run
through a software rasteriser: :func:`gather_lookup` does the same gather with numpy, several times
cheaper in CPU-seconds (bench/RESULTS.md, issue 20), in whichever thread calls it (no GL context, so
the worker's other threads keep drawing and writing). On a real GPU the gather runs in GL: the
fragment band passes or a compute shader (:mod:`archive.render.compute`, the same operations);
:func:`band_pass_choice` decides from the GL renderer string, ``ARCHIVE_BAND_PASS`` overrides.

Values: the same float32 operations in the same order as ``bands.frag.glsl``,
``value = ((DN - dark) * gain) / response`` with DN converted exactly to float32, each operation
rounded to float32: computed once per (band, line, sample) of the cube, then copied to every
output pixel that sees that (line, sample); NaN where no line covers the pixel. Measured against
llvmpipe's band passes (Mesa 22.3, tests/test_render_gather.py): bit for bit equal. The documented
bound, which the test asserts for any GL driver: at most 2 units in the last place of float32
(a driver may compute ``a / b`` as ``a * (1 / b)``: two roundings instead of one), NaN at exactly the
same pixels.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from archive.errors import InputError
# software rasterisers (llvmpipe...), where the CPU gather wins: one list, archive.render.device's
from archive.render.device import SOFTWARE_RENDERERS as CPU_RENDERERS
from archive.render.device import is_software_renderer as is_cpu_renderer
from archive.render.renderer import (GatherIndex, Lookup, RenderResult, checked_cube, dn_texture_format, flag_saturated,
                                     gather_index, gather_result, radiometry_arrays)

__all__ = ["BAND_PASS_SETTINGS", "BandPass", "CPU_RENDERERS", "GatherIndex", "MAX_ULP", "band_pass_choice",
           "band_pass_method", "calibrate_plane", "gather_index", "gather_lookup", "is_cpu_renderer", "use_cpu_gather"]

#: The stated bound between :func:`gather_lookup` and the GL band passes, float32 ULP.
MAX_ULP = 2
#: Values of a band's plane computed per block (64K x 4 B: in a core's L2 cache).
_BLOCK_VALUES = 1 << 16


class BandPass(NamedTuple):
    """How render tasks compute pass 2 (the per-band gather through a cube's lookup).

    method: 'cpu' (:func:`gather_lookup`, numpy in the task's thread), 'gl' (the fragment band
    passes, :func:`archive.render.renderer.render_lookup`) or 'compute' (the GL compute-shader
    gather, :func:`archive.render.compute.compute_lookup`). reason: why, one line (the setting, the
    renderer, why compute was not taken), for logs, ``archive doctor`` and the output's metadata.
    """

    method: str
    reason: str


#: Values of ``ARCHIVE_BAND_PASS``: 'auto' picks per renderer, the others force one method.
BAND_PASS_SETTINGS = ("auto", "cpu", "gl", "compute")


def band_pass_choice(renderer: str | None, setting: str | None = None, *,
                     compute_unsupported: str | None = None) -> BandPass:
    """The band pass for a GL ``renderer`` string: ``setting`` (default: the environment variable
    ``ARCHIVE_BAND_PASS``, else 'auto') 'cpu', 'gl' or 'compute' forces one; 'auto' takes the CPU
    gather on software renderers (llvmpipe...: measured several times cheaper there, issue 20) and
    the compute-shader gather on GPUs, or the GL fragment passes where compute shaders are missing.
    Auto's choice on GPUs is provisional: compute because datacenter GPUs (H100/H200) run compute
    on the whole chip and graphics on few units, until bench/gpu.sh measures the three methods.

    compute_unsupported: why the context cannot run compute shaders
    (:func:`archive.render.compute.compute_unsupported`), None when it can. With 'compute' forced
    on such a context: RenderError, one line naming ARCHIVE_BAND_PASS. Unknown settings: InputError.
    """
    import os

    from archive.errors import RenderError

    setting = (setting or os.environ.get("ARCHIVE_BAND_PASS") or "auto").strip().lower()
    if setting not in BAND_PASS_SETTINGS:
        raise InputError("ARCHIVE_BAND_PASS", f"expected auto, cpu, gl or compute, got {setting!r}")
    if setting == "compute" and compute_unsupported:
        raise RenderError(f"ARCHIVE_BAND_PASS=compute, but {compute_unsupported}; "
                          "set ARCHIVE_BAND_PASS=auto, cpu or gl")
    if setting != "auto":
        return BandPass(setting, f"ARCHIVE_BAND_PASS={setting}")
    if is_cpu_renderer(renderer):
        return BandPass("cpu", f"auto: software GL renderer {renderer!r}, the numpy gather is cheaper")
    if compute_unsupported:
        return BandPass("gl", f"auto: GPU renderer {renderer!r}, GL fragment passes ({compute_unsupported})")
    return BandPass("compute", f"auto: GPU renderer {renderer!r}, compute-shader gather (provisional until "
                               "bench/gpu.sh measures it)")


def band_pass_method(renderer: str | None, setting: str | None = None, *,
                     compute_unsupported: str | None = None) -> str:
    """The method name ('cpu', 'gl' or 'compute') of :func:`band_pass_choice`."""
    return band_pass_choice(renderer, setting, compute_unsupported=compute_unsupported).method


def use_cpu_gather(renderer: str | None, setting: str | None = None) -> bool:
    """Whether render tasks gather bands on the CPU (:func:`gather_lookup`): :func:`band_pass_method`
    is 'cpu' (kept for callers that only tell the CPU from GL; 'compute' counts as GL)."""
    return band_pass_method(renderer, setting) == "cpu"


def calibrate_plane(dn: np.ndarray, dark: np.ndarray, gain: np.ndarray, response: np.ndarray,
                    out: np.ndarray) -> np.ndarray:
    """One band of a cube calibrated for every (line, sample): ``((DN - dark) * gain) / response``,
    each operation rounded to float32 in that order (the band pass's values, module docstring).

    dn (lines, samples) as uploaded (:func:`~archive.render.renderer.dn_texture_format`: uint16 or
    exact float32); dark, gain (samples,) float32; response (lines,) float32 (from
    :func:`~archive.render.renderer.radiometry_arrays`); out (lines, samples) float32, written in
    blocks of lines that stay in a core's cache, and returned. Used by :func:`gather_lookup` and by
    the viewer's band planes (the same values by construction)."""
    lines, samples = out.shape
    step = max(1, _BLOCK_VALUES // max(samples, 1))
    for l0 in range(0, lines, step):
        l1 = min(l0 + step, lines)
        w = out[l0:l1]
        w[...] = dn[l0:l1]                                # exact: integers below 2^24 / float32
        np.subtract(w, dark, out=w)
        np.multiply(w, gain, out=w)
        np.divide(w, response[l0:l1, None], out=w)
    return out


def gather_lookup(lookup: Lookup | GatherIndex, dn: np.ndarray, radiometry,
                  out: np.ndarray | None = None) -> RenderResult:
    """Pass 2 on the CPU: the values of the bands of ``dn`` at each pixel of ``lookup.grid``.

    Same arguments and result as :func:`archive.render.renderer.render_lookup` (without GL
    options): lookup a Lookup or its :class:`GatherIndex` (the same values); dn (bands, lines,
    samples) uint16 (other integers in 0..65535 or -2^24..2^24, or float32); radiometry with dark /
    gain (bands, samples), response (lines,), saturation, or None for raw DN. Returns values
    (bands, height, width) float32, NaN where not covered: written into ``out`` when given (a
    C-contiguous float32 array of that shape, e.g. a reused buffer: every value is overwritten).
    """
    gather = lookup if isinstance(lookup, GatherIndex) else gather_index(lookup)
    dn, (nb, lines, samples) = checked_cube(dn, gather)
    dark, gain, resp, saturation = radiometry_arrays(radiometry, nb, lines, samples)
    dn_up, _, _ = dn_texture_format(dn)   # the values the GL path uploads (exact in float32)
    result = gather_result(gather, nb, out)
    values = result.values
    if nb == 0 or gather.height == 0:
        return result
    row0, height, index = gather.row0, gather.height, gather.index
    values[:, :row0] = np.nan
    values[:, row0 + height:] = np.nan
    rows = slice(row0, row0 + height)
    plane_size = gather.sentinel

    # One band at a time, its plane computed in blocks of lines that stay in the core's cache (4
    # operations per value), then gathered while the plane is still in cache. The plane's extra last
    # element is NaN and stands for "not covered".
    plane = np.empty(plane_size + 1, np.float32)
    plane[plane_size] = np.nan
    work = plane[:plane_size].reshape(lines, samples)
    # np.take converts other index types to intp on every call: once here instead (numpy 2.4, a
    # paper cube's window: 2.35 -> 1.67 ms per band; 0.33 ms for the conversion)
    index = index.astype(np.intp, copy=False) if nb > 1 else index
    for b in range(nb):
        calibrate_plane(dn_up[b], dark[b], gain[b], resp, work)
        into = values[b, rows].reshape(-1)                # whole rows: contiguous, a view
        np.take(plane, index, out=into, mode="clip")      # "clip": unbuffered (all indices valid)
    if saturation is not None:  # as render_lookup: any band's DN at or above the threshold
        flag_saturated(dn, saturation, gather, result.saturated)
    return result
