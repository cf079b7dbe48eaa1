"""The one place where OpenGL contexts are made.

A moderngl context is tied to the thread that created it and cannot be pickled or survive a fork,
so :func:`get_context` creates a headless EGL context lazily, on first use in each thread, and
caches it in a ``threading.local``. Nothing is created at import and nothing global is set.
Compiled shader programs are cached per context too (:func:`get_program`).

The EGL device a context opens is chosen by :func:`archive.render.device.choose_device`
(``ARCHIVE_GL_DEVICE``, else the GPU the process was bound to, else the first hardware device); a
process that was given a GPU and gets a software renderer stops with a RenderError. What each
context opened is recorded in :data:`OPENED` (read by the command from its workers with
:func:`opened_renderers`, for the output's metadata).
"""

from __future__ import annotations

import os
import threading
from importlib.resources import files

from archive.errors import RenderError
from archive.render.device import check_renderer, choose_device, egl_devices

_local = threading.local()
#: What the contexts of this process opened: one dict per context (device, reason, renderer, vendor).
OPENED: list[dict[str, object]] = []

_INSTALL_HINT = (
    "headless OpenGL needs EGL and Mesa: on Debian/Ubuntu `apt-get install libegl1 libgl1 "
    "libegl-mesa0` (llvmpipe works without a GPU); with a GPU, its vendor's EGL library"
)


def get_context():
    """This thread's headless EGL ``moderngl.Context`` (GL >= 3.3 core), created on first call.

    Raises RenderError naming the packages to install when EGL cannot start.
    """
    ctx = getattr(_local, "ctx", None)
    if ctx is not None:
        return ctx
    try:
        import moderngl
    except ImportError as exc:  # pragma: no cover - moderngl is a dependency
        raise RenderError(f"cannot import moderngl ({exc}); pip install moderngl") from exc
    choice = choose_device(egl_devices(), os.environ)
    device = {} if choice.index is None else {"device_index": choice.index}
    try:
        ctx = moderngl.create_context(standalone=True, backend="egl", require=330, **device)
    except Exception as exc:
        raise RenderError(f"cannot create a headless OpenGL (EGL) context on {choice.reason}: {exc}; "
                          f"{_INSTALL_HINT}") from exc
    renderer = ctx.info.get("GL_RENDERER")
    try:
        check_renderer(choice, renderer)
    except RenderError:
        ctx.release()
        raise
    OPENED.append({"device": choice.index, "reason": choice.reason, "renderer": renderer,
                   "vendor": ctx.info.get("GL_VENDOR"), "version": ctx.info.get("GL_VERSION")})
    _local.ctx = ctx
    _local.choice = choice
    _local.programs = {}
    return ctx


def park_framebuffer() -> None:
    """Bind this thread's 1 x 1 "parking" framebuffer.

    Standalone contexts have no default framebuffer, and moderngl rebinds the last used one when it
    creates the next: bind this before releasing a framebuffer so that the next creation does not
    touch a deleted one (GL_INVALID_OPERATION).
    """
    ctx = get_context()
    fbo = getattr(_local, "parking", None)
    if fbo is None:
        fbo = ctx.framebuffer(color_attachments=[ctx.renderbuffer((1, 1), 1, dtype="f1")])
        _local.parking = fbo
    fbo.use()


def opened_renderers() -> list[dict[str, object]]:
    """What this process's contexts opened so far (:data:`OPENED`; no context is made): a function
    the command runs on each worker (``client.run``) to record the renderers in the output's Item."""
    return [dict(o) for o in OPENED]


def gl_info() -> dict[str, object]:
    """Facts about this thread's context: renderer, vendor, GL version, size limits (pixels), the
    EGL device it opened and why."""
    ctx = get_context()
    info = ctx.info
    choice = _local.choice
    return {
        "device": choice.index,
        "device_reason": choice.reason,
        "renderer": info.get("GL_RENDERER"),
        "vendor": info.get("GL_VENDOR"),
        "version": info.get("GL_VERSION"),
        "version_code": ctx.version_code,
        "max_texture_size": int(info.get("GL_MAX_TEXTURE_SIZE")),
        "max_renderbuffer_size": int(info.get("GL_MAX_RENDERBUFFER_SIZE")),
        "max_viewport_dims": tuple(info.get("GL_MAX_VIEWPORT_DIMS", ())),
    }


def max_size() -> int:
    """Largest texture / framebuffer side (pixels) this thread's context supports."""
    info = gl_info()
    sizes = [info["max_texture_size"], info["max_renderbuffer_size"], *info["max_viewport_dims"]]
    return int(min(s for s in sizes if s))


def load_shader(name: str) -> str:
    """Source text of ``shaders/<name>`` (shipped as the package ``archive.shaders``)."""
    try:
        return (files("archive.shaders") / name).read_text(encoding="utf-8")
    except FileNotFoundError as exc:
        raise RenderError(f"shader {name!r} is missing from archive.shaders; reinstall archive") from exc


def get_program(vertex: str, fragment: str, defines: tuple[str, ...] = ()):
    """Compiled program of two shader files (names in archive.shaders), cached in this thread.

    defines: preprocessor symbols inserted after each shader's ``#version`` line.
    """
    ctx = get_context()
    key = (vertex, fragment, defines)
    program = _local.programs.get(key)
    if program is None:
        try:
            program = ctx.program(
                vertex_shader=with_defines(load_shader(vertex), defines),
                fragment_shader=with_defines(load_shader(fragment), defines),
            )
        except Exception as exc:
            raise RenderError(f"shaders {vertex} / {fragment} do not compile: {exc}") from exc
        _local.programs[key] = program
    return program


def with_defines(source: str, defines: tuple[str, ...]) -> str:
    """Shader ``source`` with ``#define`` lines for ``defines`` inserted after its ``#version`` line."""
    head, _, rest = source.partition("\n")
    if not head.startswith("#version"):
        raise RenderError("a shader must start with its #version line")
    return "\n".join([head, *(f"#define {d}" for d in defines), rest])
