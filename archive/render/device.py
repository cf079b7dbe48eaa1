"""Which EGL device a process renders on, and why (issue 29; DESIGN.md section 11 "GPU workers").

EGL lists the machine's devices (``EGL_EXT_device_enumeration``): each NVIDIA GPU (with
``EGL_NV_device_cuda``, which maps it to its CUDA device number), each DRM render node Mesa can
drive, and Mesa's software device (``EGL_MESA_device_software``: llvmpipe). :func:`egl_devices`
enumerates them through ctypes (no GL context is made); :func:`choose_device` picks the one this
process opens, in this order:

1. ``ARCHIVE_GL_DEVICE=N``: EGL device N, as the user said.
2. The GPU the process was bound to: ``CUDA_VISIBLE_DEVICES`` (Dask-CUDA, Slurm with
   ``--gres=gpu``, container runtimes) or Slurm's ``SLURM_STEP_GPUS`` / ``SLURM_JOB_GPUS``, mapped
   to its EGL device through ``EGL_NV_device_cuda``. The NVIDIA driver numbers CUDA devices within
   the visible set (what nvdiffrast and PyTorch rely on), so with ``CUDA_VISIBLE_DEVICES`` set the
   bound GPU is CUDA device 0; with Slurm's variables alone, the first GPU they list.
3. The first hardware (non-software) EGL device, else EGL device 0.

A process that was *given* a GPU (rule 2, or ``ARCHIVE_REQUIRE_GPU=1``, which ``--job-gpus 1``
sets in Slurm jobs) must not render on a software rasteriser: :func:`check_renderer` raises a
one-line RenderError naming the cause instead of rendering on the CPU without a word.

Everything here is plain data and functions of it (``environ`` passed in), so that the choice can
be tested on a machine whose EGL shows one software device.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
from dataclasses import dataclass
from typing import Mapping, Sequence

from archive.errors import RenderError

__all__ = ["SOFTWARE_RENDERERS", "DeviceChoice", "EGLDevice", "bound_gpus", "check_renderer", "choose_device", "egl_devices",
           "gpu_required", "is_software_renderer", "probe_device", "spread_environments"]

#: EGL enums (EGL registry, eglext.h).
_EGL_EXTENSIONS = 0x3055
_EGL_DRM_DEVICE_FILE_EXT = 0x3233
_EGL_DRM_RENDER_NODE_FILE_EXT = 0x3377
_EGL_CUDA_DEVICE_NV = 0x323A
#: GL renderer names (substrings, lower case) of software rasterisers.
SOFTWARE_RENDERERS = ("llvmpipe", "softpipe", "swrast", "lavapipe")
#: Values of CUDA_VISIBLE_DEVICES that hide every GPU.
_NO_GPU = ("", "-1", "none", "nodevfiles", "void")


@dataclass(frozen=True)
class EGLDevice:
    """One EGL device: its index in EGL's enumeration (what ``device_index`` opens), its extension
    names, its DRM node (``/dev/dri/...``, or None), its CUDA device number (NVIDIA, or None)."""

    index: int
    extensions: tuple[str, ...] = ()
    drm: str | None = None
    cuda: int | None = None

    @property
    def software(self) -> bool:
        """Mesa's software device (llvmpipe), which renders on the CPU."""
        return "EGL_MESA_device_software" in self.extensions

    def describe(self) -> str:
        kind = "software (Mesa llvmpipe)" if self.software else (
            f"NVIDIA, CUDA device {self.cuda}" if self.cuda is not None else "hardware")
        return f"EGL device {self.index}: {kind}" + (f", {self.drm}" if self.drm else "")


@dataclass(frozen=True)
class DeviceChoice:
    """The EGL device to open (``index``; None: EGL's default display, when EGL lists no devices),
    why (``reason``, one phrase) and whether a software renderer there is an error (``gpu_required``,
    with ``required_by`` naming the setting that gave the process a GPU)."""

    index: int | None
    reason: str
    gpu_required: bool = False
    required_by: str = ""


def _egl_library():
    name = ctypes.util.find_library("EGL") or "libEGL.so.1"
    try:
        return ctypes.CDLL(name)
    except OSError:
        return None


def egl_devices() -> list[EGLDevice]:
    """The EGL devices of this machine, in EGL's order ([] when libEGL or its device enumeration
    extension is missing). Makes no GL context."""
    egl = _egl_library()
    if egl is None:
        return []
    egl.eglGetProcAddress.restype = ctypes.c_void_p
    egl.eglGetProcAddress.argtypes = [ctypes.c_char_p]

    def proc(name: str, restype, *argtypes):
        address = egl.eglGetProcAddress(name.encode())
        return ctypes.CFUNCTYPE(restype, *argtypes)(address) if address else None

    query_devices = proc("eglQueryDevicesEXT", ctypes.c_uint, ctypes.c_int, ctypes.POINTER(ctypes.c_void_p),
                         ctypes.POINTER(ctypes.c_int))
    query_string = proc("eglQueryDeviceStringEXT", ctypes.c_char_p, ctypes.c_void_p, ctypes.c_int)
    query_attrib = proc("eglQueryDeviceAttribEXT", ctypes.c_uint, ctypes.c_void_p, ctypes.c_int,
                        ctypes.POINTER(ctypes.c_ssize_t))
    if query_devices is None or query_string is None:
        return []
    count = ctypes.c_int(0)
    if not query_devices(0, None, ctypes.byref(count)) or count.value <= 0:
        return []
    handles = (ctypes.c_void_p * count.value)()
    if not query_devices(count.value, handles, ctypes.byref(count)):
        return []
    devices = []
    for i in range(count.value):
        raw = query_string(handles[i], _EGL_EXTENSIONS) or b""
        extensions = tuple(raw.decode("ascii", "replace").split())
        drm = None
        if "EGL_EXT_device_drm_render_node" in extensions:
            drm = query_string(handles[i], _EGL_DRM_RENDER_NODE_FILE_EXT)
        if not drm and "EGL_EXT_device_drm" in extensions:
            drm = query_string(handles[i], _EGL_DRM_DEVICE_FILE_EXT)
        cuda = None
        if "EGL_NV_device_cuda" in extensions and query_attrib is not None:
            value = ctypes.c_ssize_t(-1)
            if query_attrib(handles[i], _EGL_CUDA_DEVICE_NV, ctypes.byref(value)) and value.value >= 0:
                cuda = int(value.value)
        devices.append(EGLDevice(i, extensions, drm.decode() if isinstance(drm, bytes) else drm, cuda))
    return devices


def bound_gpus(environ: Mapping[str, str]) -> tuple[str, list[str]] | None:
    """(variable, GPU list) the process was bound to: ``CUDA_VISIBLE_DEVICES`` (indices or UUIDs),
    else ``SLURM_STEP_GPUS`` / ``SLURM_JOB_GPUS`` (physical indices); None when unbound.
    ``CUDA_VISIBLE_DEVICES`` set to hide every GPU ('', -1, NoDevFiles) counts as unbound."""
    for name in ("CUDA_VISIBLE_DEVICES", "SLURM_STEP_GPUS", "SLURM_JOB_GPUS"):
        value = environ.get(name)
        if value is None:
            continue
        if value.strip().lower() in _NO_GPU:
            if name == "CUDA_VISIBLE_DEVICES":
                return None
            continue
        return name, [v.strip() for v in value.split(",") if v.strip()]
    return None


def gpu_required(environ: Mapping[str, str]) -> str:
    """The setting that gave this process a GPU ('' when none): a software renderer is then an error."""
    if environ.get("ARCHIVE_REQUIRE_GPU", "").strip() in ("1", "true", "yes"):
        return "ARCHIVE_REQUIRE_GPU=1"
    bound = bound_gpus(environ)
    return f"{bound[0]}={environ[bound[0]]}" if bound else ""


def choose_device(devices: Sequence[EGLDevice], environ: Mapping[str, str] | None = None) -> DeviceChoice:
    """The EGL device this process opens (module docstring: ARCHIVE_GL_DEVICE, else the bound GPU,
    else the first hardware device, else device 0). Raises RenderError naming the variable when it
    points at no device."""
    environ = os.environ if environ is None else environ
    required = gpu_required(environ)
    listing = "; ".join(d.describe() for d in devices) or "none"
    explicit = environ.get("ARCHIVE_GL_DEVICE", "").strip()
    if explicit:
        try:
            index = int(explicit)
        except ValueError:
            index = -1
        if not devices and index == 0:
            return DeviceChoice(None, "ARCHIVE_GL_DEVICE=0 (EGL lists no devices: its default display)",
                                bool(required), required)
        if index < 0 or index >= len(devices):
            raise RenderError(f"ARCHIVE_GL_DEVICE={explicit!r} names no EGL device of this machine "
                              f"(found: {listing}); set it to one of their numbers or unset it "
                              "(`archive doctor` lists them)")
        return DeviceChoice(index, f"ARCHIVE_GL_DEVICE={index}", bool(required), required)
    bound = bound_gpus(environ)
    if bound is not None:
        name, gpus = bound
        if name == "CUDA_VISIBLE_DEVICES":
            target, why = 0, f"{name}={environ[name]}: the first visible GPU, CUDA device 0"
        else:
            try:
                target = int(gpus[0])
            except ValueError:
                target = 0
            why = f"{name}={environ[name]}: CUDA device {target}"
        for device in devices:
            if device.cuda == target:
                return DeviceChoice(device.index, f"{why} -> EGL device {device.index}", True, required)
        hardware = [d for d in devices if not d.software]
        if hardware:
            return DeviceChoice(hardware[0].index, f"{why}; no EGL device reports that CUDA device "
                                f"(EGL_NV_device_cuda): the first hardware one, EGL device {hardware[0].index}",
                                True, required)
        return DeviceChoice(devices[0].index if devices else None,
                            f"{why}; but EGL lists no GPU (found: {listing})", True, required)
    hardware = [d for d in devices if not d.software]
    if hardware:
        return DeviceChoice(hardware[0].index, f"default: the first hardware EGL device ({hardware[0].index})",
                            bool(required), required)
    if devices:
        return DeviceChoice(devices[0].index, "default: EGL device 0 (no hardware device listed)",
                            bool(required), required)
    return DeviceChoice(None, "default: EGL's default display (EGL lists no devices)", bool(required), required)


def is_software_renderer(renderer: str | None) -> bool:
    """True for a software GL renderer string (llvmpipe, softpipe...): it renders on the CPU (where
    band passes take the CPU gather, :mod:`archive.render.gather`)."""
    name = (renderer or "").lower()
    return any(s in name for s in SOFTWARE_RENDERERS)


def check_renderer(choice: DeviceChoice, renderer: str | None) -> None:
    """RenderError (one line, with the usual causes and fixes) when a process that was given a GPU
    got a software renderer."""
    if choice.gpu_required and is_software_renderer(renderer):
        raise RenderError(
            f"this worker was given a GPU ({choice.required_by}) but EGL gave it the software renderer "
            f"{renderer!r} ({choice.reason}): the NVIDIA EGL driver is not visible to this process (check that "
            "/usr/share/glvnd/egl_vendor.d/10_nvidia.json exists and that a container was started with the "
            "'graphics' driver capability, NVIDIA_DRIVER_CAPABILITIES=all); `archive doctor` shows what EGL "
            "finds; refusing to render on the CPU")


def spread_environments(devices: Sequence[EGLDevice], workers: int,
                        environ: Mapping[str, str] | None = None) -> list[dict[str, str]]:
    """Per-worker environment variables that spread ``workers`` local worker processes over the
    node's GPUs (round robin): with ``CUDA_VISIBLE_DEVICES`` set, each worker gets one of its
    entries (as Dask-CUDA does); else, with several hardware EGL devices, ``ARCHIVE_GL_DEVICE``.
    Empty dicts when there is nothing to spread (one GPU or none, or ARCHIVE_GL_DEVICE already set)."""
    environ = os.environ if environ is None else environ
    empty: list[dict[str, str]] = [{} for _ in range(workers)]
    if environ.get("ARCHIVE_GL_DEVICE", "").strip():
        return empty
    bound = bound_gpus(environ)
    if bound is not None:
        name, gpus = bound
        if name != "CUDA_VISIBLE_DEVICES" or len(gpus) < 2:
            return empty
        return [{"CUDA_VISIBLE_DEVICES": gpus[i % len(gpus)]} for i in range(workers)]
    hardware = [d for d in devices if not d.software]
    if len(hardware) < 2:
        return empty
    return [{"ARCHIVE_GL_DEVICE": str(hardware[i % len(hardware)].index)} for i in range(workers)]


def probe_device(index: int | None) -> dict:
    """Open a GL context on EGL device ``index`` (None: EGL's default display) in this process and
    describe it: renderer, vendor, version, GL version code, compute shaders (GL >= 4.3), max
    texture size (pixels); the context is released. Raises whatever the context creation raises
    (``archive doctor`` calls it in a child process, so that a crashing driver costs one line)."""
    import moderngl

    kwargs = {} if index is None else {"device_index": int(index)}
    ctx = moderngl.create_context(standalone=True, backend="egl", require=330, **kwargs)
    try:
        info = ctx.info
        return {"renderer": info.get("GL_RENDERER"), "vendor": info.get("GL_VENDOR"),
                "version": info.get("GL_VERSION"), "version_code": ctx.version_code,
                "compute": ctx.version_code >= 430, "max_texture_size": int(info.get("GL_MAX_TEXTURE_SIZE"))}
    finally:
        ctx.release()
