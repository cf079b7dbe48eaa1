"""Render one cube's bands onto an output grid with OpenGL (inverse georectification).

The cube's ground mesh is drawn with an orthographic map projection onto a float framebuffer that
covers a window of the output grid; each fragment (= output pixel centre) finds its line
(floor(L + 0.5)) and sample (floor(samples * s), perspective-correct s) and fetches that pixel's
DN from an integer texture, up to 4 bands per RGBA fetch, then applies
``value = (DN - dark) * gain / response``. Later lines are drawn later and win where the mesh
folds over itself. A second render target records (covered, saturated).

Only the part of the grid under the mesh's bounding box is rendered, in windows no larger than the
GL size limit; cubes with more lines than the texture limit are drawn in line chunks.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from archive.errors import InputError, RenderError
from archive.grid import Grid
from archive.render.context import get_context, get_program, park_framebuffer
from archive.render.context import max_size as gl_max_size
from archive.render.mesh import Mesh

# No saturation threshold: larger than any DN.
_NO_SATURATION = 3.0e38
# Largest framebuffer side by default (pixels): 4096^2 RGBA32F is 256 MiB, the GL limit (16384^2 on
# llvmpipe) would be 4 GiB. Bigger renders go window by window.
_WINDOW = 4096


@dataclass(frozen=True, eq=False)
class RenderResult:
    """One cube rendered on ``grid``.

    values: (bands, height, width) float32, NaN where no line covers the pixel centre.
    saturated: (height, width) bool, the DN of some rendered band at that pixel was saturated.
    covered: (height, width) bool, a line of the cube covers the pixel centre.
    """

    grid: Grid
    values: np.ndarray
    saturated: np.ndarray
    covered: np.ndarray


def _dn_texture_format(dn: np.ndarray) -> tuple[np.ndarray, str, tuple[str, ...]]:
    """DN as uploaded: (array, moderngl dtype, shader defines). Integer DN must fit uint16."""
    if dn.dtype == np.uint16:
        return dn, "u2", ()
    if np.issubdtype(dn.dtype, np.integer):
        lo = int(dn.min()) if dn.size else 0
        hi = int(dn.max()) if dn.size else 0
        if lo < 0 or hi > 65535:
            raise InputError("dn", f"integer DN must lie in 0..65535, found {lo}..{hi}",
                             "convert the cube to uint16 or float32")
        return dn.astype(np.uint16), "u2", ()
    if np.issubdtype(dn.dtype, np.floating):
        return dn.astype(np.float32, copy=False), "f4", ("DN_FLOAT",)
    raise InputError("dn", f"unsupported DN dtype {dn.dtype}", "use uint16, an integer type or float32")


def _radiometry_arrays(radiometry, nb: int, lines: int, samples: int):
    if radiometry is None:
        return (np.zeros((nb, samples), np.float32), np.ones((nb, samples), np.float32),
                np.ones(lines, np.float32), None)
    dark = np.asarray(radiometry.dark, dtype=np.float32)
    gain = np.asarray(radiometry.gain, dtype=np.float32)
    resp = np.asarray(radiometry.response, dtype=np.float32).reshape(-1)
    for name, arr, shape in (("dark", dark, (nb, samples)), ("gain", gain, (nb, samples)),
                             ("response", resp, (lines,))):
        if arr.shape != shape:
            raise InputError("radiometry", f"{name} has shape {arr.shape}, expected {shape} "
                             "(bands, samples) / (lines,) to match the DN cube")
    if not np.all(np.isfinite(resp) & (resp > 0)):
        raise InputError("radiometry", "response must be finite and > 0 on every line",
                         "check shutter and gain of the cube")
    return dark, gain, resp, radiometry.saturation


def _pad(a: np.ndarray, comps: int) -> np.ndarray:
    """(n, ..., k) -> (n, ..., comps) with zeros appended on the last axis."""
    if a.shape[-1] == comps:
        return np.ascontiguousarray(a)
    out = np.zeros(a.shape[:-1] + (comps,), a.dtype)
    out[..., : a.shape[-1]] = a
    return out


def render_cube(
    mesh: Mesh,
    dn: np.ndarray,
    radiometry,
    grid: Grid,
    bands_per_pass: int = 4,
    *,
    max_size: int | None = None,
) -> RenderResult:
    """Render the bands of one cube onto ``grid``.

    mesh: the cube's ground mesh (:func:`archive.render.mesh.build_mesh`), same EPSG as ``grid``.
    dn: (bands, lines, samples) DN, uint16 (other integer types in 0..65535, or float32, accepted).
    radiometry: object with dark (bands, samples), gain (bands, samples), response (lines,),
        saturation (DN threshold or None), e.g. :class:`archive.source.Radiometry`; None = raw DN.
    bands_per_pass: 1..4 bands read per texel fetch and written per pass.
    max_size: largest texture and framebuffer side in pixels (default: the GL texture limit for the
        DN textures, min(4096, GL limit) for framebuffer windows); small values force
        window-by-window rendering and line chunks (for tests).
    Returns a :class:`RenderResult` with values (bands, height, width) float32, north row first.
    """
    dn = np.asarray(dn)
    if dn.ndim != 3:
        raise InputError("dn", f"expected a (bands, lines, samples) cube, got shape {dn.shape}")
    nb, lines, samples = dn.shape
    if lines != mesh.lines:
        raise InputError("dn", f"cube has {lines} lines but its mesh {mesh.lines}",
                         "build the mesh from this cube's poses")
    if not 1 <= bands_per_pass <= 4:
        raise InputError("bands_per_pass", f"must be 1..4, got {bands_per_pass}")
    if mesh.epsg != grid.epsg:
        raise InputError("grid", f"grid is EPSG:{grid.epsg} but the mesh EPSG:{mesh.epsg}",
                         "render on a grid in the flight's UTM zone")
    dark, gain, resp, saturation = _radiometry_arrays(radiometry, nb, lines, samples)
    dn_up, dn_dtype, defines = _dn_texture_format(dn)

    values = np.full((nb, grid.height, grid.width), np.nan, np.float32)
    covered = np.zeros(grid.shape, bool)
    saturated = np.zeros(grid.shape, bool)
    result = RenderResult(grid, values, saturated, covered)
    crop = grid.crop(*mesh.bounds_utm()) if mesh.rows >= 2 and nb > 0 else None
    if crop is None:
        return result
    row0, col0, sub = crop

    ctx = get_context()
    limit = int(max_size) if max_size else gl_max_size()
    window = int(max_size) if max_size else min(limit, _WINDOW)
    if samples > limit:
        raise RenderError(f"cube has {samples} samples, more than the GL texture limit {limit}")
    program = get_program("cube.vert.glsl", "cube.frag.glsl", defines)

    # Vertex data: float32 metres relative to the mesh centre (float64 offsets go in uniforms).
    pos, attr = mesh.vertex_attributes()
    centre = pos.mean(axis=0)                        # (N, E) local metres
    vdata = np.empty((pos.shape[0], 5), np.float32)
    vdata[:, 0] = pos[:, 1] - centre[1]
    vdata[:, 1] = pos[:, 0] - centre[0]
    vdata[:, 2:] = attr
    centre_e = mesh.frame.origin_e + centre[1]
    centre_n = mesh.frame.origin_n + centre[0]
    triangles = mesh.triangles()                     # 2 per quad, quad k between rows k and k+1

    chunks = [(lo, min(lo + limit, lines)) for lo in range(0, lines, limit)]
    windows = sub.tiles(window)
    fbw = max(w.width for _, _, w in windows)
    fbh = max(w.height for _, _, w in windows)

    owned = []   # every GL object made here, released in finally

    def keep(obj):
        owned.append(obj)
        return obj

    try:
        import moderngl

        ctx.disable(moderngl.BLEND | moderngl.DEPTH_TEST | moderngl.CULL_FACE)
        vbo = keep(ctx.buffer(vdata.tobytes()))
        vaos = []
        for lo, hi in chunks:
            # Quads whose rows k, k+1 hold lines that can round into [lo, hi).
            quads = np.nonzero((mesh.line[:-1] >= lo - 1) & (mesh.line[:-1] <= hi - 1))[0]
            if quads.size == 0:
                vaos.append(None)
                continue
            idx = triangles.reshape(-1, 2, 3)[quads].reshape(-1).astype(np.int32)
            ibo = keep(ctx.buffer(idx.tobytes()))
            vaos.append(keep(ctx.vertex_array(program, [(vbo, "2f 3f", "in_pos", "in_attr")],
                                              index_buffer=ibo, index_element_size=4)))
        value_rb = keep(ctx.renderbuffer((fbw, fbh), 4, dtype="f4"))
        flag_rb = keep(ctx.renderbuffer((fbw, fbh), 2, dtype="f1"))
        fbo = keep(ctx.framebuffer(color_attachments=[value_rb, flag_rb]))

        program["u_inv_gsd"].value = 1.0 / grid.gsd
        program["u_samples"].value = samples
        program["u_sat"].value = _NO_SATURATION if saturation is None else float(saturation)
        program["u_dn"].value = 0
        program["u_dark"].value = 1
        program["u_gain"].value = 2
        program["u_resp"].value = 3

        for b0 in range(0, nb, bands_per_pass):
            b1 = min(b0 + bands_per_pass, nb)
            k = b1 - b0
            comps = 4 if k == 3 else k
            program["u_bands"].value = k
            pass_objs = []

            def texture(size, data, dtype, comps_=comps):
                tex = ctx.texture(size, comps_, data, dtype=dtype, alignment=1)
                tex.filter = (moderngl.NEAREST, moderngl.NEAREST)
                tex.repeat_x = tex.repeat_y = False
                pass_objs.append(tex)
                return tex

            try:
                dark_tex = texture((samples, 1), _pad(dark[b0:b1].T, comps).tobytes(), "f4")
                gain_tex = texture((samples, 1), _pad(gain[b0:b1].T, comps).tobytes(), "f4")
                chunk_tex = []
                for lo, hi in chunks:
                    block = np.moveaxis(dn_up[b0:b1, lo:hi], 0, -1)     # (lines, samples, k)
                    chunk_tex.append((
                        texture((samples, hi - lo), _pad(block, comps).tobytes(), dn_dtype),
                        texture((hi - lo, 1), np.ascontiguousarray(resp[lo:hi]).tobytes(), "f4", 1),
                    ))
                for wr, wc, win in windows:
                    fbo.use()
                    fbo.clear(0.0, 0.0, 0.0, 0.0)
                    ctx.viewport = (0, 0, win.width, win.height)
                    program["u_size"].value = (float(win.width), float(win.height))
                    program["u_centre_px"].value = (
                        (centre_e - win.x0) / grid.gsd, (win.y0 - centre_n) / grid.gsd)
                    dark_tex.use(1)
                    gain_tex.use(2)
                    for (lo, hi), vao, (dn_tex, resp_tex) in zip(chunks, vaos, chunk_tex):
                        if vao is None:
                            continue
                        program["u_lo"].value = lo
                        program["u_hi"].value = hi
                        dn_tex.use(0)
                        resp_tex.use(3)
                        vao.render(moderngl.TRIANGLES)
                    vp = (0, 0, win.width, win.height)
                    val = np.frombuffer(fbo.read(viewport=vp, components=4, attachment=0, dtype="f4"),
                                        np.float32).reshape(win.height, win.width, 4)
                    rs = slice(row0 + wr, row0 + wr + win.height)
                    cs = slice(col0 + wc, col0 + wc + win.width)
                    values[b0:b1, rs, cs] = np.moveaxis(val[..., :k], -1, 0)
                    if b0 == 0 or saturation is not None:    # coverage is the same in every pass
                        flags = np.frombuffer(
                            fbo.read(viewport=vp, components=2, attachment=1, dtype="f1"), np.uint8
                        ).reshape(win.height, win.width, 2)
                        if b0 == 0:
                            covered[rs, cs] = flags[..., 0] > 127
                        saturated[rs, cs] |= flags[..., 1] > 127
            finally:
                for obj in pass_objs:
                    obj.release()
        error = ctx.error
        if error != "GL_NO_ERROR":
            raise RenderError(f"OpenGL reported {error} while rendering a {nb}-band cube")
    finally:
        park_framebuffer()
        for obj in reversed(owned):
            obj.release()
    values[:, ~covered] = np.nan
    saturated &= covered
    return result
