"""Pass 2 of the renderer as a GL compute shader: the CPU gather's operations, run on the GPU's whole chip.

Datacenter GPUs (H100/H200 class) have few graphics units: the mesh rasterisation (pass 1,
:func:`archive.render.renderer.rasterize_lookup`, one draw per cube) stays a draw, while the per-band
gather, a pure memory gather, runs here as a GLSL 4.3 compute shader (``shaders/gather.comp.glsl``)
over shader storage buffers: the cube's :class:`~archive.render.renderer.GatherIndex` (one int32
flat index per pixel of the covered rows), the DN of a group of bands as uploaded by the other paths
(uint16 two per word, or exact float32), dark / gain / response as float32. One invocation per output
pixel computes every band of its group (several bands per dispatch: the index is read once per
pixel and group).

Values: ``((float(DN) - dark) * gain) / response``, each operation rounded to float32 in that order
and marked ``precise`` (no FMA contraction), NaN (0x7fc00000) where not covered: the values of
:func:`archive.render.gather.gather_lookup`, bit for bit on Mesa llvmpipe (tests/test_render_compute.py);
on other drivers within :data:`archive.render.gather.MAX_ULP` (GLSL allows 2.5 ULP for ``a / b``).
Saturation is flagged on the CPU from the same index, as the other paths do.

Readback without stalls: each dispatch covers a group of bands over whole output rows, written
band-major so that the group is one contiguous block of the caller's (band, row, col) values and is
read back with one ``glGetBufferSubData``; output, DN and per-group buffers come in pairs used in
rotation, and group k is read only after group k + 1 was dispatched (the GPU computes one group while
the CPU copies the previous one out).

Buffers are bounded by the context's ``GL_MAX_SHADER_STORAGE_BLOCK_SIZE`` (128 MiB on llvmpipe; 16
MiB is the GL minimum): groups shrink to fit, and a grid whose one band does not fit goes band by band
in chunks of rows. The compiled program and the buffers are kept per thread (:func:`gather_program`,
:func:`release_buffers`), on the thread's context from :func:`archive.render.context.get_context`.
"""

from __future__ import annotations

import threading

import numpy as np

from archive.errors import RenderError
from archive.render.context import get_context, load_shader, with_defines
from archive.render.renderer import (GatherIndex, Lookup, RenderResult, checked_cube, dn_texture_format, flag_saturated,
                                     gather_index, gather_result, radiometry_arrays)

__all__ = ["COMPUTE_VERSION", "compute_lookup", "compute_unsupported", "gather_program", "release_buffers"]

#: GL version (code) that compute shaders and shader storage buffers need.
COMPUTE_VERSION = 430
#: Invocations per work group (a multiple of every GPU's SIMD width).
_LOCAL = 256
#: Work groups per dispatch dimension that every GL 4.3 context allows.
_MAX_GROUPS = 65535

_local = threading.local()


def gather_program(defines: tuple[str, ...] = ()):
    """The compiled ``gather.comp.glsl`` (with ``defines`` after its ``#version`` line), cached per
    thread and context. RenderError when the context has no compute shaders or the shader does not
    compile (the message says why)."""
    ctx = get_context()
    cache = getattr(_local, "programs", None)
    if cache is None or _local.ctx is not ctx:
        _local.ctx, _local.programs = ctx, {}
        cache = _local.programs
    program = cache.get(defines)
    if program is None:
        missing = _missing(ctx)
        if missing is not None:
            raise RenderError(missing)
        try:
            program = ctx.compute_shader(with_defines(load_shader("gather.comp.glsl"),
                                                      (f"LOCAL {_LOCAL}", *defines)))
        except Exception as exc:
            raise RenderError(f"the compute gather (gather.comp.glsl) does not compile on "
                              f"{ctx.info.get('GL_RENDERER')}: {exc}") from exc
        cache[defines] = program
    return program


def _missing(ctx) -> str | None:
    if not hasattr(ctx, "compute_shader"):
        return "this moderngl has no compute shaders (moderngl >= 5.6 needed)"
    if ctx.version_code < COMPUTE_VERSION:
        code = ctx.version_code
        return (f"the GL context of {ctx.info.get('GL_RENDERER')} is version {code // 100}.{code % 100 // 10}; "
                "compute shaders need GL 4.3")
    return None


def compute_unsupported(ctx=None) -> str | None:
    """Why a GL context cannot run the compute gather (no GL 4.3, a moderngl without compute
    shaders, a shader the driver does not compile), or None when it can. ctx: a moderngl context
    (only its version is checked), default this thread's, whose programs are also compiled (then
    cached)."""
    if ctx is not None and ctx is not get_context():
        return _missing(ctx)
    try:
        gather_program()
        gather_program(("DN_FLOAT",))
    except RenderError as exc:
        return str(exc)
    return None


class _BufferPool:
    """This thread's storage buffers, reused from call to call (a render task's band groups and the
    next cube's: no allocation of hundreds of MB per call), grown when a call needs more; the
    buffers of a call are its ``get`` calls in order. Held until :func:`release_buffers`."""

    def __init__(self, ctx):
        self.ctx, self.buffers = ctx, {}

    def get(self, key: str, nbytes: int):
        nbytes = max(4, (int(nbytes) + 3) // 4 * 4)
        buf = self.buffers.get(key)
        if buf is None or buf.size < nbytes:
            if buf is not None:
                buf.release()
            buf = self.buffers[key] = self.ctx.buffer(reserve=nbytes)
        return buf

    def release(self) -> None:
        while self.buffers:
            self.buffers.popitem()[1].release()


def _buffer_pool(ctx) -> _BufferPool:
    pool = getattr(_local, "pool", None)
    if pool is None or pool.ctx is not ctx:
        pool = _local.pool = _BufferPool(ctx)
    return pool


def release_buffers() -> None:
    """Release this thread's compute-gather buffers (the next call allocates them again)."""
    pool = getattr(_local, "pool", None)
    if pool is not None:
        pool.release()


def _block_limit(ctx) -> int:
    """Largest shader storage block the context allows, bytes (below 2^31: int indices)."""
    limit = ctx.info.get("GL_MAX_SHADER_STORAGE_BLOCK_SIZE") or (1 << 24)
    return int(min(int(limit), (1 << 31) - 4))


def compute_lookup(lookup: Lookup | GatherIndex, dn: np.ndarray, radiometry, bands_per_dispatch: int = 8, *,
                   out: np.ndarray | None = None, max_block: int | None = None) -> RenderResult:
    """Pass 2 in a GL compute shader: the values of the bands of ``dn`` at each pixel of ``lookup.grid``.

    Same arguments and result as :func:`archive.render.gather.gather_lookup`: lookup a Lookup or its
    :class:`GatherIndex`; dn (bands, lines, samples) uint16 (other integers in 0..65535 or
    -2^24..2^24, or float32); radiometry with dark / gain (bands, samples), response (lines,),
    saturation, or None for raw DN; out an optional C-contiguous float32 (bands, height, width)
    array to write into (every value is overwritten). bands_per_dispatch: bands computed per
    dispatch (>= 1; fewer when the buffers would pass the GL limit). max_block: storage buffer
    limit in bytes instead of the context's (for tests: forces small groups and row chunks).
    Returns values (bands, height, width) float32, north row first, NaN where not covered. Runs
    GL: call it on the thread that owns the context (the render tasks' GL thread).
    """
    if bands_per_dispatch < 1:
        raise ValueError(f"bands_per_dispatch must be >= 1, got {bands_per_dispatch}")
    gather = lookup if isinstance(lookup, GatherIndex) else gather_index(lookup)
    dn, (nb, lines, samples) = checked_cube(dn, gather)
    dark, gain, resp, saturation = radiometry_arrays(radiometry, nb, lines, samples)
    dn_up, _, defines = dn_texture_format(dn)
    dn_up = np.ascontiguousarray(dn_up)
    grid = gather.grid
    height, width = grid.shape
    result = gather_result(gather, nb, out)
    values = result.values
    if nb == 0 or gather.height == 0:
        return result

    ctx = get_context()
    program = gather_program(tuple(defines))
    block = int(max_block) if max_block else _block_limit(ctx)
    plane = gather.sentinel
    plane_bytes = plane * dn_up.itemsize
    where = f"a {lines}-line x {samples}-sample cube"
    if gather.index.dtype != np.int32 or plane_bytes > block:
        raise RenderError(f"{where}: one band ({plane_bytes} B of DN) is larger than a GL shader storage block "
                          f"({block} B) on this context; set ARCHIVE_BAND_PASS=cpu or gl")
    row_bytes = width * 4
    rows = min(height, block // row_bytes)
    if rows < 1:
        raise RenderError(f"{where}: an output row of {width} px is larger than a GL shader storage block ({block} B); "
                          "set ARCHIVE_BAND_PASS=cpu or gl")
    if rows == height:   # whole rows: a group of bands is one contiguous block of ``values``
        group = max(1, min(bands_per_dispatch, nb, block // (height * row_bytes), block // plane_bytes))
    else:                # a band larger than a block: band by band, in chunks of rows
        group = 1
    chunks = [(r0, min(r0 + rows, height)) for r0 in range(0, height, rows)]
    pieces = [(b0, min(b0 + group, nb), r0, r1) for b0 in range(0, nb, group) for r0, r1 in chunks]

    pool = _buffer_pool(ctx)

    def bind(binding: int, name: str, nbytes: int, data: np.ndarray | None = None):
        """Pool buffer ``name`` (at least ``nbytes``), ``data`` written at its start, bound to
        ``binding`` over ``nbytes`` only (a pooled buffer may be larger than the storage-block limit)."""
        buf = pool.get(name, nbytes)
        if data is not None and data.size:
            buf.write(data)
        buf.bind_to_storage_buffer(binding, size=max(4, (int(nbytes) + 3) // 4 * 4))
        return buf

    try:
        covered = gather.index.size
        per_chunk = len(chunks) > 1       # the index of each chunk's rows goes up with its pieces
        if not per_chunk:
            bind(0, "index", gather.index.nbytes, gather.index)
        bind(4, "resp", resp.nbytes, np.ascontiguousarray(resp))
        program["u_samples"].value = samples
        program["u_plane"].value = plane
        program["u_nan"].value = float("nan")
        out_bytes = group * rows * row_bytes

        def read(piece, buf):
            b0, b1, r0, r1 = piece
            nbytes = (b1 - b0) * (r1 - r0) * row_bytes
            buf.read_into(values, size=nbytes, write_offset=(b0 * height + r0) * row_bytes)

        pending = None
        group_no = -1
        for k, piece in enumerate(pieces):
            b0, b1, r0, r1 = piece
            if r0 == 0:                   # a new group of bands: its DN and calibration up
                group_no += 1
                slot = group_no % 2
                bind(1, f"dn{slot}", group * plane_bytes, dn_up[b0:b1])
                bind(2, f"dark{slot}", group * samples * 4, np.ascontiguousarray(dark[b0:b1]))
                bind(3, f"gain{slot}", group * samples * 4, np.ascontiguousarray(gain[b0:b1]))
                program["u_bands"].value = b1 - b0
            # index entries of rows r0..r1 of the grid: the covered rows start at gather.row0
            first = (r0 - gather.row0) * width
            if per_chunk:
                lo, hi = max(first, 0), min(first + (r1 - r0) * width, covered)
                bind(0, f"index{k % 2}", rows * row_bytes, gather.index[lo:hi] if hi > lo else None)
                program["u_first"].value = first - lo
                program["u_covered"].value = max(hi - lo, 0)
            else:
                program["u_first"].value = first
                program["u_covered"].value = covered
            pixels = (r1 - r0) * width
            program["u_pixels"].value = pixels
            out = bind(5, f"out{k % 2}", out_bytes)
            groups = -(-pixels // _LOCAL)
            gx = min(groups, _MAX_GROUPS)
            program.run(gx, -(-groups // gx))
            ctx.memory_barrier()
            if pending is not None:       # the previous piece, while this one computes
                read(*pending)
            pending = (piece, out)
        read(*pending)
        error = ctx.error
        if error != "GL_NO_ERROR":
            raise RenderError(f"OpenGL reported {error} while gathering {nb} bands of {where} in a compute shader")
    except BaseException:
        pool.release()    # a failed call leaves no buffer behind (nor one in an unknown state)
        raise
    if saturation is not None:  # as the other paths: any band's DN at or above the threshold
        flag_saturated(dn, saturation, gather, result.saturated)
    return result
