"""Render one cube's bands onto an output grid with OpenGL (inverse georectification), in two passes.

1. :func:`rasterize_lookup` draws the cube's ground mesh once, with an orthographic map projection,
   onto a float framebuffer that covers a window of the output grid; each fragment (= output pixel
   centre) records the line (floor(L + 0.5), discarded outside [0, lines)) and the sample
   (floor(samples * s), perspective-correct s, clamped) it sees. Later lines are drawn later and win
   where the mesh folds over itself; terrain meshes (:mod:`archive.render.mesh`, "Terrain meshes") are drawn
   with the depth test instead (depth = distance from the camera: the nearest ground wins) and
   leave out the triangles that span an occlusion (hidden ground stays uncovered). The result, a :class:`Lookup`, is a small picklable value:
   compute it once per cube and reuse it for every group of bands.
2. :func:`render_lookup` runs one full-screen pass per group of up to 8 bands (one R32F render
   target per band) over the covered rows of the grid: the fragment shader reads the pixel's
   (line, sample) from the lookup texture and fetches its DN from integer textures, 4 bands per
   RGBA texel fetch, then applies ``value = (DN - dark) * gain / response``; each target is read
   back straight into the output. Saturated DN are flagged from the same lookup on the CPU.

Pass 2 has two other implementations with the same values: the CPU gather
(:func:`archive.render.gather.gather_lookup`, cheapest on llvmpipe) and a GL compute shader
(:func:`archive.render.compute.compute_lookup`, for GPUs whose graphics units are few); render tasks
take the one :func:`archive.render.gather.band_pass_choice` names (``ARCHIVE_BAND_PASS``).

:func:`render_cube` = both. Rendering goes window by window (no side larger than the GL size
limit); cubes with more lines than the texture limit are uploaded in line chunks.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from archive.errors import InputError, RenderError
from archive.grid import Grid
from archive.render.context import get_context, get_program, park_framebuffer
from archive.render.context import max_size as gl_max_size
from archive.render.mesh import Mesh

# Largest framebuffer side by default (pixels): 4096^2 RGBA32F is 256 MiB, the GL limit (16384^2 on
# llvmpipe) would be 4 GiB. Bigger renders go window by window.
_WINDOW = 4096
# Line and sample indices travel as float32 in pass 1: exact below 2^24.
_MAX_INDEX = 1 << 24


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


@dataclass(frozen=True, eq=False)
class Lookup:
    """Which pixel of a cube each pixel centre of ``grid`` sees (pass 1 of the renderer).

    line: (height, width) int32 line index within the cube, -1 where not covered.
    sample: (height, width) int32 sample index, -1 where not covered.
    lines, samples: the cube's size. Picklable; holds no GL object.
    count: (height, width) uint16, how many layers of the cube's mesh cover each pixel centre (1
        in a plain strip; 2 or more where the strip folds over itself, e.g. in a turn), or None
        when not asked for (:func:`rasterize_lookup` ``count=True``).
    """

    grid: Grid
    line: np.ndarray
    sample: np.ndarray
    lines: int
    samples: int
    count: np.ndarray | None = None

    @property
    def covered(self) -> np.ndarray:
        """(height, width) bool: a line of the cube covers the pixel centre."""
        return self.line >= 0

    def box(self) -> tuple[int, int, int, int] | None:
        """(row0, col0, height, width) of the covered pixels' bounding box, None if none is covered."""
        cov = self.covered
        rows = np.flatnonzero(cov.any(axis=1))
        if rows.size == 0:
            return None
        cols = np.flatnonzero(cov.any(axis=0))
        return (int(rows[0]), int(cols[0]), int(rows[-1] - rows[0] + 1), int(cols[-1] - cols[0] + 1))


@dataclass(frozen=True, eq=False)
class GatherIndex:
    """A :class:`~archive.render.renderer.Lookup` as the gather uses it: for each pixel of the rows
    ``row0 .. row0 + height`` of ``grid`` (the covered rows; none when ``height`` is 0), its flat
    index ``line * samples + sample`` into a band's (lines * samples) plane, or ``lines * samples``
    (:attr:`sentinel`) where no line covers the pixel. index: (height * width,) int32 (intp when the
    plane has 2^31 or more values), row-major. Built once per cube (:func:`gather_index`) and shared
    by its band groups; picklable."""

    grid: Grid
    lines: int
    samples: int
    row0: int
    height: int
    index: np.ndarray

    @property
    def sentinel(self) -> int:
        """The index of a pixel no line covers (one past the plane)."""
        return self.lines * self.samples

    @property
    def covered(self) -> np.ndarray:
        """(grid height, grid width) bool: a line of the cube covers the pixel centre."""
        covered = np.zeros(self.grid.shape, bool)
        rows = covered[self.row0:self.row0 + self.height].reshape(-1)
        np.not_equal(self.index, self.sentinel, out=rows)
        return covered


def gather_index(lookup: Lookup) -> GatherIndex:
    """The :class:`GatherIndex` of ``lookup`` (pixels with line < 0 uncovered)."""
    box = lookup.box()
    row0, height = (0, 0) if box is None else (box[0], box[2])
    plane_size = lookup.lines * lookup.samples
    # int32 indices when they fit: half the bytes to pack and hold (the gather takes them as intp).
    line = lookup.line[row0:row0 + height]
    index = line.astype(np.int32 if plane_size < 2**31 - 1 else np.intp)
    index *= lookup.samples
    index += lookup.sample[row0:row0 + height]
    index[line < 0] = plane_size
    return GatherIndex(lookup.grid, int(lookup.lines), int(lookup.samples), int(row0), int(height), index.reshape(-1))


def flag_saturated(dn: np.ndarray, saturation: float, lookup: Lookup | GatherIndex, saturated: np.ndarray) -> None:
    """Set ``saturated`` (the lookup grid's (height, width) bool, C order) where any band of ``dn``
    (bands, lines, samples) is at or above ``saturation`` at the pixel's (line, sample): one
    ``np.take`` through the flat gather index (built from ``lookup`` only when some DN saturates)."""
    lines, samples = lookup.lines, lookup.samples
    flagged = np.zeros(lines * samples + 1, bool)     # the last element: not covered, never flagged
    np.greater_equal(dn.max(axis=0), float(saturation), out=flagged[:-1].reshape(lines, samples))
    if flagged.any():
        at = lookup if isinstance(lookup, GatherIndex) else gather_index(lookup)
        np.take(flagged, at.index, out=saturated[at.row0:at.row0 + at.height].reshape(-1), mode="clip")


def dn_texture_format(dn: np.ndarray) -> tuple[np.ndarray, str, tuple[str, ...]]:
    """DN as uploaded: (array, moderngl dtype, shader defines). Integer DN in 0..65535 go up as
    uint16, other integers (negative DN of signed cubes) as exact float32."""
    if dn.dtype == np.uint16:
        return dn, "u2", ()
    if np.issubdtype(dn.dtype, np.integer):
        lo = int(dn.min()) if dn.size else 0
        hi = int(dn.max()) if dn.size else 0
        if 0 <= lo and hi <= 65535:
            return dn.astype(np.uint16), "u2", ()
        if max(-lo, hi) > 2**24:  # float32 holds every integer up to 2^24 exactly
            raise InputError("dn", f"integer DN must lie in -2^24..2^24, found {lo}..{hi}",
                             "convert the cube to float32")
        # signed cubes (int16 with negative DN, e.g. dark-subtracted data): exact as float32
        return dn.astype(np.float32), "f4", ("DN_FLOAT",)
    if np.issubdtype(dn.dtype, np.floating):
        return dn.astype(np.float32, copy=False), "f4", ("DN_FLOAT",)
    raise InputError("dn", f"unsupported DN dtype {dn.dtype}", "use uint16, an integer type or float32")


def checked_cube(dn, lookup) -> tuple[np.ndarray, tuple[int, int, int]]:
    """(dn as an array, its (bands, lines, samples)): InputError unless a 3-D cube of the lookup's
    lines and samples (pass 2's input, GL or CPU)."""
    dn = np.asarray(dn)
    if dn.ndim != 3:
        raise InputError("dn", f"expected a (bands, lines, samples) cube, got shape {dn.shape}")
    nb, lines, samples = dn.shape
    if (lines, samples) != (lookup.lines, lookup.samples):
        raise InputError("dn", f"cube has {lines} lines x {samples} samples but its lookup "
                         f"{lookup.lines} x {lookup.samples}", "rasterize the lookup for this cube")
    return dn, (nb, lines, samples)


def gather_result(gather: "GatherIndex", nb: int, out: np.ndarray | None) -> RenderResult:
    """The result a pass-2 gather (CPU or compute) fills: values (nb, height, width) float32 in
    ``out`` when given (a C-contiguous float32 array of that shape; ValueError otherwise) or a new
    array, no pixel flagged saturated yet, coverage from ``gather``. All NaN when there is nothing to
    gather (no band, no covered row)."""
    grid = gather.grid
    shape = (nb, grid.height, grid.width)
    if out is None:
        values = np.empty(shape, np.float32)
    elif out.shape != shape or out.dtype != np.float32 or not out.flags.c_contiguous:
        raise ValueError(f"out must be a C-contiguous float32 array of shape {shape}, got {out.dtype} {out.shape}")
    else:
        values = out
    if nb == 0 or gather.height == 0:
        values[...] = np.nan
    return RenderResult(grid, values, np.zeros(grid.shape, bool), gather.covered)


def radiometry_arrays(radiometry, nb: int, lines: int, samples: int):
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


def _limits(max_size: int | None) -> tuple[int, int]:
    """(texture limit, framebuffer window side) in pixels."""
    limit = int(max_size) if max_size else gl_max_size()
    window = int(max_size) if max_size else min(limit, _WINDOW)
    return limit, window


def _check_gl(ctx, what: str) -> None:
    error = ctx.error
    if error != "GL_NO_ERROR":
        raise RenderError(f"OpenGL reported {error} while {what}")


class _Owned:
    """GL objects made by one call, released (in reverse order) when the call ends."""

    def __init__(self):
        self.objects = []

    def __call__(self, obj):
        self.objects.append(obj)
        return obj

    def release(self) -> None:
        park_framebuffer()
        while self.objects:
            self.objects.pop().release()


def rasterize_lookup(mesh: Mesh, grid: Grid, samples: int, *, max_size: int | None = None,
                     count: bool = False) -> Lookup:
    """Pass 1: draw ``mesh`` once onto ``grid`` and record each pixel centre's (line, sample).

    mesh: the cube's ground mesh (:func:`archive.render.mesh.build_mesh`), same EPSG as ``grid``.
    samples: samples per line of the cube (the mesh knows only the field of view's ends).
    max_size: largest framebuffer side in pixels (default min(4096, GL limit)); small values force
        window-by-window rendering (for tests).
    count: also count how many layers of the mesh cover each pixel centre (a second draw of the
        same mesh with additive blending and the same coverage rule, no depth test).
    Returns a :class:`Lookup` of (height, width) int32 arrays, north row first, -1 where not covered.
    """
    samples = int(samples)
    if samples < 1:
        raise InputError("samples", f"a cube needs at least one sample per line, got {samples}")
    if mesh.epsg != grid.epsg:
        raise InputError("grid", f"grid is EPSG:{grid.epsg} but the mesh EPSG:{mesh.epsg}",
                         "render on a grid in the flight's UTM zone")
    if mesh.lines >= _MAX_INDEX or samples >= _MAX_INDEX:
        raise RenderError(f"cube of {mesh.lines} lines x {samples} samples: indices of 2^24 or "
                          "more are not exact in the float lookup target; split the cube")
    line = np.full(grid.shape, -1, np.int32)
    sample = np.full(grid.shape, -1, np.int32)
    counts = np.zeros(grid.shape, np.uint16) if count else None
    lookup = Lookup(grid, line, sample, int(mesh.lines), samples, counts)
    crop = grid.crop(*mesh.bounds_utm()) if mesh.rows >= 2 else None
    if crop is None:
        return lookup
    row0, col0, sub = crop

    ctx = get_context()
    _, window = _limits(max_size)
    terrain = mesh.distance is not None   # terrain mesh: depth test on the distance from the camera
    vertex_shader = "terrain.vert.glsl" if terrain else "cube.vert.glsl"
    program = get_program(vertex_shader, "lookup.frag.glsl")

    # Vertex data: float32 metres relative to the mesh centre (float64 offsets go in uniforms).
    pos, attr = mesh.vertex_attributes()
    centre = pos.mean(axis=0)                        # (N, E) local metres
    vdata = np.empty((pos.shape[0], 6 if terrain else 5), np.float32)
    vdata[:, 0] = pos[:, 1] - centre[1]
    vdata[:, 1] = pos[:, 0] - centre[0]
    vdata[:, 2:5] = attr
    if terrain:
        vdata[:, 5] = mesh.distance.reshape(-1)
        far = float(np.max(mesh.distance, initial=0.0)) * 1.01 + 1.0
    centre_e = mesh.frame.origin_e + centre[1]
    centre_n = mesh.frame.origin_n + centre[0]
    # 2 triangles per quad in line order (later lines drawn later win where the mesh folds; terrain:
    # the nearest).
    triangles = mesh.triangles().reshape(-1).astype(np.int32)
    windows = sub.tiles(window)
    fbw = max(w.width for _, _, w in windows)
    fbh = max(w.height for _, _, w in windows)

    keep = _Owned()
    try:
        import moderngl

        ctx.disable(moderngl.BLEND | moderngl.DEPTH_TEST | moderngl.CULL_FACE)
        vbo = keep(ctx.buffer(vdata.tobytes()))
        ibo = keep(ctx.buffer(triangles.tobytes()))
        layout = (vbo, "2f 3f 1f", "in_pos", "in_attr", "in_dist") if terrain else (vbo, "2f 3f", "in_pos", "in_attr")

        def mesh_vao(prog):
            return keep(ctx.vertex_array(prog, [layout], index_buffer=ibo, index_element_size=4))

        vao = mesh_vao(program)
        index_rb = keep(ctx.renderbuffer((fbw, fbh), 2, dtype="f4"))
        if terrain:
            depth_rb = keep(ctx.depth_renderbuffer((fbw, fbh)))
            fbo = keep(ctx.framebuffer(color_attachments=[index_rb], depth_attachment=depth_rb))
            ctx.enable(moderngl.DEPTH_TEST)
            ctx.depth_func = "<"
        else:
            fbo = keep(ctx.framebuffer(color_attachments=[index_rb]))
        programs = [program]
        if count:   # the same mesh, its coverage counted: additive blending into a second target
            counter = get_program(vertex_shader, "lookup.frag.glsl", ("COUNT",))
            count_vao = mesh_vao(counter)
            count_rb = keep(ctx.renderbuffer((fbw, fbh), 2, dtype="f4"))
            count_fbo = keep(ctx.framebuffer(color_attachments=[count_rb]))
            programs.append(counter)
        for prog in programs:
            for name, value in (("u_inv_gsd", 1.0 / grid.gsd), ("u_samples", samples), ("u_lo", 0),
                                ("u_hi", int(mesh.lines)), *((("u_far", far),) if terrain else ())):
                if name in prog:
                    prog[name].value = value
        for wr, wc, win in windows:
            fbo.use()
            vp = (0, 0, win.width, win.height)
            ctx.viewport = vp
            if terrain:
                fbo.clear(-1.0, -1.0, 0.0, 0.0, depth=1.0, viewport=vp)
            else:
                fbo.clear(-1.0, -1.0, 0.0, 0.0, viewport=vp)
            for prog in programs:
                prog["u_size"].value = (float(win.width), float(win.height))
                prog["u_centre_px"].value = (
                    (centre_e - win.x0) / grid.gsd, (win.y0 - centre_n) / grid.gsd)
            vao.render(moderngl.TRIANGLES)
            idx = np.frombuffer(fbo.read(viewport=vp, components=2, dtype="f4"), np.float32)
            idx = idx.reshape(win.height, win.width, 2)
            rs = slice(row0 + wr, row0 + wr + win.height)
            cs = slice(col0 + wc, col0 + wc + win.width)
            line[rs, cs] = idx[..., 0]
            sample[rs, cs] = idx[..., 1]
            if count:
                count_fbo.use()
                count_fbo.clear(0.0, 0.0, 0.0, 0.0, viewport=vp)
                ctx.disable(moderngl.DEPTH_TEST)
                ctx.enable(moderngl.BLEND)
                ctx.blend_func = moderngl.ONE, moderngl.ONE
                try:
                    count_vao.render(moderngl.TRIANGLES)
                finally:
                    ctx.disable(moderngl.BLEND)
                    if terrain:
                        ctx.enable(moderngl.DEPTH_TEST)
                layers = np.frombuffer(count_fbo.read(viewport=vp, components=2, dtype="f4"), np.float32)
                counts[rs, cs] = layers.reshape(win.height, win.width, 2)[..., 0]
        _check_gl(ctx, f"rasterizing the lookup of a {mesh.lines}-line cube")
    finally:
        if terrain:
            import moderngl

            ctx.disable(moderngl.DEPTH_TEST)
        keep.release()
    return lookup


def render_lookup(
    lookup: Lookup,
    dn: np.ndarray,
    radiometry,
    bands_per_pass: int = 8,
    *,
    max_size: int | None = None,
) -> RenderResult:
    """Pass 2: the values of the bands of ``dn`` at each pixel of ``lookup.grid``.

    lookup: from :func:`rasterize_lookup` for this cube.
    dn: (bands, lines, samples) DN, uint16 (other integer types in 0..65535, or float32, accepted).
    radiometry: object with dark (bands, samples), gain (bands, samples), response (lines,),
        saturation (DN threshold or None), e.g. :class:`archive.sources.Radiometry`; None = raw DN.
    bands_per_pass: 1..8 bands per full-screen pass (one R32F render target each; 8 is fastest).
    max_size: largest texture and framebuffer side in pixels (default: the GL texture limit for the
        DN textures, min(4096, GL limit) for framebuffer windows); for tests.
    Returns a :class:`RenderResult` with values (bands, height, width) float32, north row first.

    Each pass uploads its bands as up to two RGBA16UI (RGBA32F for float DN) textures, 4 bands per
    texel (interleaved by one strided copy per band: 4 fetches per pixel and pass instead of 8 one-band
    fetches, which llvmpipe runs at half the speed), and reads each band's R32F target straight into
    ``values`` when the window spans whole output rows (else through one scratch block). The
    saturation flag is the lookup applied to the per-(line, sample) maximum DN over the bands (CPU).
    """
    dn, (nb, lines, samples) = checked_cube(dn, lookup)
    if not 1 <= bands_per_pass <= 8:
        raise InputError("bands_per_pass", f"must be 1..8, got {bands_per_pass}")
    dark, gain, resp, saturation = radiometry_arrays(radiometry, nb, lines, samples)
    dn_up, dn_dtype, defines = dn_texture_format(dn)

    grid = lookup.grid
    covered = lookup.covered
    box = lookup.box() if nb > 0 else None
    if box is None:
        values = np.full((nb, grid.height, grid.width), np.nan, np.float32)
        return RenderResult(grid, values, np.zeros(grid.shape, bool), covered)

    ctx = get_context()
    limit, window = _limits(max_size)
    if samples > limit:
        raise RenderError(f"cube has {samples} samples, more than the GL texture limit {limit}")
    # Rendered region: the covered rows; all columns when one window spans the grid's width (then
    # each window is whole output rows, contiguous in ``values``: read back in place), else the
    # covered columns. Only pixels outside it are filled with NaN here; the shader writes the rest.
    row0, col0, height, width = box
    if grid.width <= window:
        col0, width = 0, grid.width
    sub = grid.window(row0, col0, height, width)
    values = np.empty((nb, grid.height, grid.width), np.float32)
    values[:, :row0] = np.nan
    values[:, row0 + height:] = np.nan
    values[:, row0:row0 + height, :col0] = np.nan
    values[:, row0:row0 + height, col0 + width:] = np.nan
    result = RenderResult(grid, values, np.zeros(grid.shape, bool), covered)

    chunks = [(lo, min(lo + limit, lines)) for lo in range(0, lines, limit)]
    # Windows, and the line chunks each of them needs (windows without covered pixels: NaN only).
    windows = []
    for wr, wc, win in sub.tiles(window):
        rs = slice(row0 + wr, row0 + wr + win.height)
        cs = slice(col0 + wc, col0 + wc + win.width)
        wl = lookup.line[rs, cs]
        seen = wl[wl >= 0]
        if seen.size:
            lo, hi = int(seen.min()), int(seen.max())
            need = [i for i, (a, b) in enumerate(chunks) if a <= hi and b > lo]
            windows.append((rs, cs, win, need))
        else:
            values[:, rs, cs] = np.nan
    fbw = max(w.width for _, _, w, _ in windows)
    fbh = max(w.height for _, _, w, _ in windows)
    outs = min(bands_per_pass, nb)

    keep = _Owned()
    try:
        import moderngl

        def nearest(tex):
            tex.filter = (moderngl.NEAREST, moderngl.NEAREST)
            tex.repeat_x = tex.repeat_y = False
            return tex

        def texture(size, comps, data, dtype, objs):
            return nearest(objs(ctx.texture(size, comps, data, dtype=dtype, alignment=1)))

        ctx.disable(moderngl.BLEND | moderngl.DEPTH_TEST | moderngl.CULL_FACE)
        # Per call: lookup textures (one per window), response textures (one per chunk), targets.
        lookup_tex = [
            texture((win.width, win.height), 2,
                    np.stack([lookup.line[rs, cs], lookup.sample[rs, cs]], axis=-1), "i4", keep)
            for rs, cs, win, _ in windows
        ]
        resp_tex = [texture((hi - lo, 1), 1, np.ascontiguousarray(resp[lo:hi]), "f4", keep)
                    for lo, hi in chunks]
        targets = [keep(ctx.renderbuffer((fbw, fbh), 1, dtype="f4")) for _ in range(outs)]
        fbo = keep(ctx.framebuffer(color_attachments=targets))
        program = get_program("fullscreen.vert.glsl", "bands.frag.glsl", (*defines, f"NOUT {outs}"))
        vao = keep(ctx.vertex_array(program, []))
        program["u_nan"].value = float("nan")
        units = {"u_lookup": 0, "u_resp": 1, "u_dn0": 2, "u_dark0": 3, "u_gain0": 4,
                 "u_dn1": 5, "u_dark1": 6, "u_gain1": 7}
        for name, unit in units.items():
            if program.get(name, None) is not None:
                program[name].value = unit
        scratch = None
        if any(cs.stop - cs.start != grid.width for _, cs, _, _ in windows):
            scratch = np.empty(fbh * fbw, np.float32)
        row_bytes = grid.width * 4
        # 4 bands per texel: (lines, samples, 4) DN, interleaved by one strided copy per band.
        interleaved = np.empty((max(hi - lo for lo, hi in chunks), samples, 4), dn_up.dtype)
        per_sample = np.zeros((2, samples, 4), np.float32)  # dark, gain of one group

        for b0 in range(0, nb, outs):
            b1 = min(b0 + outs, nb)
            k = b1 - b0
            pass_objs = _Owned()
            try:
                dn_tex = []  # per group of 4 bands: [texture per line chunk]
                for g, g0 in enumerate(range(b0, b1, 4)):
                    g1 = min(g0 + 4, b1)
                    per_sample[0, :, : g1 - g0] = dark[g0:g1].T
                    per_sample[1, :, : g1 - g0] = gain[g0:g1].T
                    texture((samples, 1), 4, per_sample[0], "f4", pass_objs).use(3 + 3 * g)
                    texture((samples, 1), 4, per_sample[1], "f4", pass_objs).use(4 + 3 * g)
                    group_tex = []
                    for lo, hi in chunks:
                        block = interleaved[: hi - lo]
                        for c in range(g1 - g0):  # per band: contiguous reads (6x a transpose copy)
                            block[..., c] = dn_up[g0 + c, lo:hi]
                        group_tex.append(texture((samples, hi - lo), 4, block, dn_dtype, pass_objs))
                    dn_tex.append(group_tex)
                fbo.use()
                for (rs, cs, win, need), lk_tex in zip(windows, lookup_tex):
                    vp = (0, 0, win.width, win.height)
                    ctx.viewport = vp
                    lk_tex.use(0)
                    for c in need:
                        lo, hi = chunks[c]
                        program["u_lo"].value = lo
                        program["u_hi"].value = hi
                        resp_tex[c].use(1)
                        for g, group_tex in enumerate(dn_tex):
                            group_tex[c].use(2 + 3 * g)
                        vao.render(moderngl.TRIANGLES, vertices=3)
                    for i in range(k):
                        if scratch is None:  # whole rows: straight into values[b0 + i, rs, :]
                            offset = ((b0 + i) * grid.height + rs.start) * row_bytes
                            fbo.read_into(values, viewport=vp, components=1, attachment=i, dtype="f4",
                                          write_offset=offset)
                        else:
                            block = scratch[: win.height * win.width].reshape(win.height, win.width)
                            fbo.read_into(block, viewport=vp, components=1, attachment=i, dtype="f4")
                            values[b0 + i, rs, cs] = block
            finally:
                pass_objs.release()
        _check_gl(ctx, f"rendering a {nb}-band cube")
    finally:
        keep.release()
    if saturation is not None:  # any band's DN at or above the threshold at the pixel's (line, sample)
        flag_saturated(dn, saturation, lookup, result.saturated)
    return result


def render_cube(
    mesh: Mesh,
    dn: np.ndarray,
    radiometry,
    grid: Grid,
    bands_per_pass: int = 8,
    *,
    max_size: int | None = None,
) -> RenderResult:
    """Render the bands of one cube onto ``grid``: :func:`rasterize_lookup` then :func:`render_lookup`.

    mesh: the cube's ground mesh (:func:`archive.render.mesh.build_mesh`), same EPSG as ``grid``.
    dn: (bands, lines, samples) DN, uint16 (other integer types in 0..65535, or float32, accepted).
    radiometry: object with dark (bands, samples), gain (bands, samples), response (lines,),
        saturation (DN threshold or None), e.g. :class:`archive.sources.Radiometry`; None = raw DN.
    bands_per_pass: 1..8 bands per pass (up to 4 per texel fetch and render target).
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
    if not 1 <= bands_per_pass <= 8:
        raise InputError("bands_per_pass", f"must be 1..8, got {bands_per_pass}")
    if mesh.epsg != grid.epsg:
        raise InputError("grid", f"grid is EPSG:{grid.epsg} but the mesh EPSG:{mesh.epsg}",
                         "render on a grid in the flight's UTM zone")
    if nb == 0:
        empty = Lookup(grid, np.full(grid.shape, -1, np.int32), np.full(grid.shape, -1, np.int32),
                       lines, samples)
        return render_lookup(empty, dn, radiometry, bands_per_pass, max_size=max_size)
    lookup = rasterize_lookup(mesh, grid, samples, max_size=max_size)
    return render_lookup(lookup, dn, radiometry, bands_per_pass, max_size=max_size)
