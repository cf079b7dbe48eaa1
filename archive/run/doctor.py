"""``archive doctor``: whether this machine can render, and why not (issue 29).

Checks, each a line ``ok`` / ``FAIL`` / ``warn`` / ``--`` (optional, absent):

- Python and the versions of the packages the job uses (GDAL and PROJ through rasterio and pyproj);
- the package's own data: the shaders, the catalog schema, the viewer's page (a wheel that left one
  out cannot render or serve);
- EGL: the library, its devices, and for each device the GL renderer, vendor and version a context
  there gets (each opened in a child process, so that a crashing driver costs only its line) and
  whether it offers compute shaders (GL 4.3);
- which device a worker would open and why (``ARCHIVE_GL_DEVICE``, ``CUDA_VISIBLE_DEVICES``, Slurm's
  GPU binding, :mod:`archive.render.device`), whether it was given a GPU, and how ``--workers N``
  would spread over the GPUs;
- whether band passes would run in GL or on the CPU;
- PROJ's geoid grid for ``--dem-datum egm96`` (optional), chromium for the viewer's browser tests
  (optional), Slurm's commands and dask-jobqueue for ``--cluster slurm`` (optional).

Exit 0 when rendering works here, 1 (with the fix on the failing lines) when it cannot.
"""

from __future__ import annotations

import importlib
import importlib.metadata
import json
import os
import platform
import shutil
import subprocess
import sys
from dataclasses import asdict, dataclass, field
from importlib.resources import files

__all__ = ["Check", "report", "run"]

#: Distributions whose versions the report lists (distribution name, module to find it by).
PACKAGES = ("numpy", "scipy", "pyproj", "zarr", "dask", "distributed", "xarray", "rioxarray", "rasterio",
            "moderngl", "glcontext", "starlette", "uvicorn", "cql2", "shapely", "pvlib", "dask-jobqueue")
#: Seconds a child process may take to open one EGL device.
PROBE_SECONDS = 60


@dataclass
class Check:
    """One line of the report: status 'ok' | 'warn' | 'FAIL' | '--' (optional and absent), what was
    checked, what was found, and the fix when it failed."""

    status: str
    what: str
    found: str
    fix: str = ""
    data: dict = field(default_factory=dict)

    def line(self) -> str:
        text = f"  {self.status:<5} {self.what}: {self.found}"
        return text + (f"\n        fix: {self.fix}" if self.fix else "")


def _version(dist: str) -> str | None:
    try:
        return importlib.metadata.version(dist)
    except importlib.metadata.PackageNotFoundError:
        return None


def _packages() -> list[Check]:
    import archive

    checks = [Check("ok", "python", f"{platform.python_version()} ({sys.executable})"),
              Check("ok", "archive", f"{archive.__version__} ({os.path.dirname(archive.__file__)})")]
    found, missing = [], []
    for dist in PACKAGES:
        v = _version(dist)
        (found if v else missing).append(f"{dist} {v}" if v else dist)
    checks.append(Check("ok", "packages", ", ".join(found)))
    if missing:
        checks.append(Check("FAIL", "packages missing", ", ".join(missing),
                            "pip install archive (or pip install -e . in a checkout) installs them"))
    try:
        import pyproj
        import rasterio

        checks.append(Check("ok", "GDAL / PROJ", f"GDAL {rasterio.__gdal_version__} (rasterio), "
                                                 f"PROJ {pyproj.proj_version_str} (pyproj)"))
    except Exception as exc:   # reported, not raised: the doctor says what is wrong
        checks.append(Check("FAIL", "GDAL / PROJ", f"cannot import: {exc}", "pip install rasterio pyproj"))
    return checks


def _package_data() -> Check:
    """The shaders, catalog schema and viewer page shipped inside the package."""
    wanted = {"archive.shaders": ("lookup.frag.glsl", "bands.frag.glsl", "cube.vert.glsl"),
              "archive.catalogs": ("schema.sql",),
              "archive.view.static": ("index.html", "app.js", "vendor/leaflet/leaflet.js")}
    missing = []
    for package, names in wanted.items():
        for name in names:
            try:
                if not (files(package) / name).is_file():
                    missing.append(f"{package}/{name}")
            except ModuleNotFoundError:
                missing.append(f"{package}/{name}")
    if missing:
        return Check("FAIL", "package data", "missing " + ", ".join(missing),
                     "this installation is incomplete: reinstall archive from a complete wheel or checkout")
    return Check("ok", "package data", "shaders, catalog schema, viewer page")


def _probe_in_child(index: int | None) -> dict:
    """:func:`archive.render.device.probe_device` in a child interpreter (a driver that crashes costs only its line)."""
    code = ("import json, sys; from archive.render.device import probe_device; "
            f"print(json.dumps(probe_device({index!r})))")
    try:
        done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=PROBE_SECONDS)
    except subprocess.TimeoutExpired:
        return {"error": f"no context within {PROBE_SECONDS} s"}
    if done.returncode != 0:
        lines = [ln for ln in done.stderr.strip().splitlines() if ln.strip()]
        return {"error": lines[-1] if lines else f"exit {done.returncode}"}
    try:
        return json.loads(done.stdout.strip().splitlines()[-1])
    except (ValueError, IndexError):
        return {"error": f"unreadable answer: {done.stdout[-200:]!r}"}


def _gl(workers: int) -> list[Check]:
    """EGL devices, what each renders with, the device a worker would use, the band pass (a FAIL
    check where rendering is impossible; the later checks are then left out)."""
    from archive.errors import ArchiveError, RenderError
    from archive.render.gather import band_pass_choice
    from archive.render.device import check_renderer, choose_device, egl_devices, spread_environments

    checks: list[Check] = []
    import importlib.util

    if importlib.util.find_spec("moderngl") is None:
        return [Check("FAIL", "moderngl", "not installed", "pip install moderngl")]
    devices = egl_devices()
    if not devices:
        checks.append(Check("warn", "EGL devices", "none listed (no libEGL, or no EGL_EXT_device_enumeration): "
                            "contexts open EGL's default display",
                            "apt-get install libegl1 libgl1 libegl-mesa0 (and the GPU vendor's EGL library)"))
    probes: dict[int | None, dict] = {}
    for device in devices or []:
        probe = probes[device.index] = _probe_in_child(device.index)
        if "error" in probe:
            checks.append(Check("warn", device.describe(), f"no context: {probe['error']}",
                                "a device that cannot open is skipped only if no worker is bound to it"))
        else:
            checks.append(Check("ok", device.describe(),
                                f"{probe['renderer']} ({probe['vendor']}), GL {probe['version']}, compute shaders "
                                f"{'yes' if probe['compute'] else 'no'}, textures up to {probe['max_texture_size']} px",
                                data=probe))
    try:
        choice = choose_device(devices, os.environ)
    except RenderError as exc:
        checks.append(Check("FAIL", "worker device", str(exc), "fix or unset ARCHIVE_GL_DEVICE"))
        return checks
    probe = probes.get(choice.index) if choice.index in probes else _probe_in_child(choice.index)
    where = "EGL's default display" if choice.index is None else f"EGL device {choice.index}"
    data = {"device": choice.index, "reason": choice.reason, "gpu_required": choice.gpu_required, **probe}
    if "error" in probe:
        checks.append(Check("FAIL", "worker device", f"a worker here would open {where} ({choice.reason}) and "
                            f"fails: {probe['error']}",
                            "apt-get install libegl1 libgl1 libegl-mesa0; on a GPU node its vendor's EGL library "
                            "(NVIDIA: /usr/share/glvnd/egl_vendor.d/10_nvidia.json); `archive doctor` again",
                            data=data))
        return checks
    try:
        check_renderer(choice, probe.get("renderer"))
    except RenderError as exc:
        checks.append(Check("FAIL", "worker device", str(exc), "make the NVIDIA EGL driver visible to the process, "
                            "or unset CUDA_VISIBLE_DEVICES / ARCHIVE_REQUIRE_GPU to render on the CPU", data=data))
        return checks
    given = f"; it was given a GPU ({choice.required_by})" if choice.gpu_required else ""
    checks.append(Check("ok", "worker device", f"a worker here opens {where}: {probe.get('renderer')} "
                        f"({choice.reason}){given}", data=data))
    spread = spread_environments(devices, workers, os.environ)
    if any(spread):
        checks.append(Check("ok", f"--workers {workers}", "; ".join(
            f"worker {i}: {' '.join(f'{k}={v}' for k, v in env.items())}" for i, env in enumerate(spread))))
    elif workers > 1:
        checks.append(Check("ok", f"--workers {workers}", "all workers open the same device (one GPU or none)"))
    unsupported = None if probe.get("compute") else f"GL {probe.get('version')} has no compute shaders (4.3)"
    try:
        band = band_pass_choice(probe.get("renderer"), compute_unsupported=unsupported)
    except ArchiveError as exc:
        checks.append(Check("FAIL", "band passes", str(exc), "set ARCHIVE_BAND_PASS to auto, cpu, gl or compute, or unset it"))
        return checks
    checks.append(Check("ok", "band passes", f"{band.method} ({band.reason})",
                        data={"method": band.method, "reason": band.reason}))
    return checks


def _optional() -> list[Check]:
    checks = []
    try:
        import pyproj.datadir

        dirs = [*pyproj.datadir.get_data_dir().split(os.pathsep), "/usr/share/proj"]
        grids = [os.path.join(d, n) for d in dirs for n in ("egm96_15.gtx", "us_nga_egm96_15.tif")
                 if os.path.exists(os.path.join(d, n))]
        checks.append(Check("ok", "PROJ geoid grid", grids[0]) if grids else Check(
            "--", "PROJ geoid grid", "egm96_15 not found (optional: --dem-datum egm96)", "apt-get install proj-data"))
    except Exception as exc:
        checks.append(Check("--", "PROJ geoid grid", f"cannot look: {exc}"))
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    playwright = _version("playwright")
    if chromium and playwright:
        checks.append(Check("ok", "viewer browser tests", f"{chromium}, playwright {playwright}"))
    else:
        checks.append(Check("--", "viewer browser tests", f"chromium {chromium or 'not found'}, playwright "
                            f"{playwright or 'not installed'} (optional)", "apt-get install chromium; pip install playwright"))
    slurm = [t for t in ("sbatch", "squeue", "scancel") if shutil.which(t) is None]
    jobqueue = _version("dask-jobqueue")
    if not slurm and jobqueue:
        checks.append(Check("ok", "Slurm", f"sbatch, squeue, scancel on PATH; dask-jobqueue {jobqueue}"))
    else:
        checks.append(Check("--", "Slurm", f"{', '.join(slurm) or 'commands found'}"
                            f"{' not on PATH' if slurm else ''}; dask-jobqueue {jobqueue or 'not installed'} "
                            "(optional: --cluster slurm, from a login node)"))
    return checks


def report(workers: int = 1) -> tuple[list[Check], bool]:
    """Every check of the module docstring: (checks, whether this machine can render)."""
    checks = [*_packages(), _package_data(), *_gl(workers), *_optional()]
    return checks, not any(c.status == "FAIL" for c in checks)


def run(args) -> int:
    """The ``archive doctor`` command: print the report (or ``--json``); exit 1 when rendering is impossible."""
    checks, ok = report(workers=int(getattr(args, "workers", None) or 1))
    worker = next((c for c in checks if c.what == "worker device"), None)
    renderer = (worker.data.get("renderer") if worker else None) or "none"
    if ok:
        verdict = f"this machine can render: {renderer}"
    else:
        verdict = "this machine cannot render: " + "; ".join(f"{c.what}: {c.found}" for c in checks if c.status == "FAIL")
    if getattr(args, "json", False):
        print(json.dumps({"ok": ok, "verdict": verdict, "checks": [asdict(c) for c in checks]}, indent=1))
    else:
        print("archive doctor")
        for c in checks:
            print(c.line())
        print(verdict)
    if not ok:
        print(f"archive doctor: error: {verdict}", file=sys.stderr)
    return 0 if ok else 1
