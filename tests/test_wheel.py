"""The package as a cluster admin installs it (issue 29): ``pip wheel .``, then the wheel installed into
a fresh virtual environment that cannot see the checkout, then the commands run from there.

The fresh venv gets the wheel with ``pip install --no-deps`` and reaches the dependencies through a
``.pth`` line naming the test venv's site-packages directory. A path added that way is not a site
directory, so the editable install's import hook there (``__editable__*.pth``) is never run: the only
``archive`` the fresh venv can import is the wheel's (asserted). The commands run with the working
directory outside the checkout and no PYTHONPATH.

Checked: the wheel holds every subpackage, the shaders, the catalog schema and the viewer's page;
``simulate``, ``render`` to COG and to Zarr (values equal to the editable install's render of the same
request, bit for bit), ``ingest``, ``archive view`` serving its page and every script and style sheet
the page loads, and ``archive doctor``.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import site
import subprocess
import sys
import urllib.request
import zipfile
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import archive_view
from helpers import FOV

ROOT = Path(__file__).resolve().parents[1]


def _env() -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PYTHON", "VIRTUAL_ENV"))}
    env["PYTHONUNBUFFERED"] = "1"
    return env


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> Path:
    """The bin/ folder of a fresh venv holding the wheel built from this checkout."""
    base = tmp_path_factory.mktemp("wheel")
    src = base / "src"   # a copy: building writes build/ and *.egg-info beside the sources
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc", "*.egg-info", "build")
    for name in ("archive", "shaders", "catalogs"):
        shutil.copytree(ROOT / name, src / name, ignore=ignore)
    for name in ("pyproject.toml", "setup.py", "README.md"):
        shutil.copy2(ROOT / name, src / name)
    dist = base / "dist"
    built = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q",
                            "-w", str(dist), str(src)], capture_output=True, text=True, env=_env(), cwd=base)
    assert built.returncode == 0, built.stderr[-3000:]
    (wheel,) = dist.glob("archive-*.whl")
    venv = base / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    python = venv / "bin" / "python"
    done = subprocess.run([sys.executable, "-m", "pip", "--python", str(python), "install", "--no-deps", "-q",
                           str(wheel)], capture_output=True, text=True, env=_env(), cwd=base)
    assert done.returncode == 0, done.stderr[-3000:]
    purelib = subprocess.run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                             capture_output=True, text=True, check=True).stdout.strip()
    deps = [p for p in site.getsitepackages() if Path(p).is_dir()]
    Path(purelib, "zz_test_dependencies.pth").write_text("\n".join(deps) + "\n")
    return venv / "bin"


def run(bin_dir: Path, *args: str, cwd: Path, timeout: int = 600) -> subprocess.CompletedProcess:
    return subprocess.run([str(bin_dir / "archive"), *args], capture_output=True, text=True, cwd=cwd,
                          env=_env(), timeout=timeout)


def test_the_wheel_holds_every_package_and_its_data(installed):
    (wheel,) = installed.parents[1].glob("dist/archive-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    packages = {str(p.parent.relative_to(ROOT)) for p in (ROOT / "archive").rglob("*.py")
                if "__pycache__" not in p.parts}
    missing = sorted(p for p in packages if f"{p}/__init__.py" not in names)
    assert not missing, f"subpackages left out of the wheel: {missing}"
    for path in ["archive/outputs/cog.py", "archive/shaders/lookup.frag.glsl", "archive/shaders/bands.frag.glsl",
                 "archive/catalogs/schema.sql", "archive/view/static/index.html", "archive/view/static/app.js",
                 "archive/view/static/vendor/leaflet/leaflet.js",
                 "archive/view/static/vendor/leaflet/images/marker-icon.png"]:
        assert path in names, path
    shaders = {f"archive/shaders/{p.name}" for p in (ROOT / "shaders").glob("*.glsl")}
    assert shaders <= names, sorted(shaders - names)


def test_the_installed_wheel_imports_itself_not_the_checkout(installed, tmp_path):
    code = "import archive, archive.outputs, archive.render.context as c; print(archive.__file__)"
    done = subprocess.run([str(installed / "python"), "-c", code], capture_output=True, text=True, cwd=tmp_path,
                          env=_env())
    assert done.returncode == 0, done.stderr
    assert Path(done.stdout.strip()).is_relative_to(installed.parent), done.stdout


def test_the_installed_wheel_renders_what_the_checkout_renders(installed, tmp_path):
    flight = tmp_path / "flight"
    done = run(installed, "simulate", str(flight), "--cubes", "2", "--bands", "5", "--samples", "48",
               "--lines", "120", "--seed", "3", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    for ext in ("tif", "zarr"):
        common = [str(flight), "--fov", str(FOV), "--gsd", "0.5", "--quiet", "--workers", "1"]
        done = run(installed, "render", *common, "--out", str(tmp_path / f"wheel.{ext}"), cwd=tmp_path)
        assert done.returncode == 0, done.stderr
        editable = subprocess.run([sys.executable, "-m", "archive", "render", *common, "--out",
                                   str(tmp_path / f"editable.{ext}")], capture_output=True, text=True, cwd=ROOT)
        assert editable.returncode == 0, editable.stderr
        a, b = _values(tmp_path / f"wheel.{ext}"), _values(tmp_path / f"editable.{ext}")
        assert a.shape == b.shape and a.shape[0] == 5 and np.isfinite(a).mean() > 0.3
        assert np.array_equal(a, b, equal_nan=True)
        item = json.loads((tmp_path / f"wheel.{ext}.json").read_text())
        # the renderer the worker drew with is recorded (this machine: Mesa llvmpipe)
        assert item["properties"]["archive:recipe"]["renderers"], item["properties"]
        assert all(r["device"] is not None and r["renderer"] for r in item["properties"]["archive:renderers"])


def _values(path: Path) -> np.ndarray:
    if path.suffix == ".tif":
        import rasterio

        with rasterio.open(path) as src:
            return src.read()
    import xarray as xr

    with xr.open_zarr(path) as ds:
        (name,) = [v for v in ds.data_vars if ds[v].ndim == 3]
        return ds[name].values


def test_the_installed_wheel_serves_the_viewer_and_answers_doctor(installed, tmp_path):
    flight = tmp_path / "flight"
    assert run(installed, "simulate", str(flight), "--cubes", "2", "--bands", "4", "--samples", "40",
               "--lines", "100", cwd=tmp_path).returncode == 0
    done = run(installed, "ingest", str(flight), "--archive", str(tmp_path / "arc"), "--fov", str(FOV), "--quiet",
               cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    # the wheel's own console script, its environment without the checkout (_env: no PYTHONPATH)
    with archive_view([str(installed / "archive"), "view", "--archive", str(tmp_path / "arc"), "--port", "0"],
                      cwd=tmp_path, env=_env()) as (url, _):
        page = urllib.request.urlopen(url, timeout=30).read().decode()
        assets = re.findall(r'(?:src|href)="(/static/[^"]+)"', page)
        assert len(assets) >= 4 and any(a.endswith("app.js") for a in assets), page[:500]
        for asset in assets:
            with urllib.request.urlopen(url + asset.lstrip("/"), timeout=30) as r:
                assert r.status == 200 and len(r.read()) > 100, asset
        with urllib.request.urlopen(url + "stac/", timeout=30) as r:
            assert json.loads(r.read())["type"] == "Catalog"
    doctor = run(installed, "doctor", cwd=tmp_path)
    assert doctor.returncode == 0, doctor.stdout + doctor.stderr
    assert "ok    package data" in doctor.stdout and "this machine can render" in doctor.stdout
    assert str(installed.parent) in doctor.stdout   # the archive it checked is the wheel's
