"""Which EGL device a worker renders on (issue 29; archive.render.device), and archive doctor.

This machine's EGL (Mesa) lists one device, the software one (llvmpipe): the tests run the selection
rules on it for real (the default, ARCHIVE_GL_DEVICE, a process bound to a GPU that gets llvmpipe and
must refuse it, workers spread over CUDA_VISIBLE_DEVICES by a real local cluster), and on device
lists of GPU nodes as data, the form in which :func:`archive.render.device.egl_devices` gives them.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from archive.errors import RenderError
from archive.render.device import (EGLDevice, check_renderer, choose_device, egl_devices, gpu_required,
                                   spread_environments)
from archive.simulator import simulate_flight
from helpers import FOV

ROOT = Path(__file__).resolve().parents[1]
NV = ("EGL_NV_device_cuda", "EGL_EXT_device_drm")
MESA = ("EGL_MESA_device_software", "EGL_EXT_device_drm_render_node")
#: A 4-GPU node as the NVIDIA driver shows it to a process that sees all GPUs, plus Mesa's device.
NODE = [EGLDevice(0, NV, "/dev/dri/card1", 0), EGLDevice(1, NV, "/dev/dri/card2", 1),
        EGLDevice(2, NV, "/dev/dri/card3", 2), EGLDevice(3, NV, "/dev/dri/card4", 3), EGLDevice(4, MESA)]


def _clean_env(**extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items()
           if k not in ("ARCHIVE_GL_DEVICE", "CUDA_VISIBLE_DEVICES", "SLURM_STEP_GPUS", "SLURM_JOB_GPUS",
                        "ARCHIVE_REQUIRE_GPU")}
    return {**env, **extra}


def test_this_machine_lists_mesa_and_a_worker_opens_it_by_default():
    devices = egl_devices()
    assert devices and devices[0].index == 0
    assert any(d.software for d in devices)
    choice = choose_device(devices, {})
    assert choice.index == (next((d.index for d in devices if not d.software), 0))
    assert not choice.gpu_required


def test_the_rules_on_a_gpu_node():
    # nothing said: the first hardware device, not Mesa's
    assert choose_device(NODE, {}).index == 0
    assert choose_device([EGLDevice(0, MESA), EGLDevice(1, NV, None, 0), EGLDevice(2, NV, None, 1)], {}).index == 1
    # ARCHIVE_GL_DEVICE first, whatever else is set
    c = choose_device(NODE, {"ARCHIVE_GL_DEVICE": "2", "CUDA_VISIBLE_DEVICES": "3"})
    assert c.index == 2 and "ARCHIVE_GL_DEVICE=2" in c.reason and c.gpu_required
    # bound by CUDA_VISIBLE_DEVICES: the driver numbers CUDA devices within the visible set, so the
    # bound GPU is CUDA device 0 of this process; EGL still lists every GPU
    visible3 = [EGLDevice(0, NV, None, None), EGLDevice(1, NV, None, None), EGLDevice(2, NV, None, None),
                EGLDevice(3, NV, None, 0), EGLDevice(4, MESA)]
    c = choose_device(visible3, {"CUDA_VISIBLE_DEVICES": "3"})
    assert c.index == 3 and c.gpu_required and c.required_by == "CUDA_VISIBLE_DEVICES=3"
    # Slurm's binding alone names physical GPUs
    assert choose_device(NODE, {"SLURM_JOB_GPUS": "2"}).index == 2
    assert choose_device(NODE, {"SLURM_STEP_GPUS": "1,3", "SLURM_JOB_GPUS": "0,1,3"}).index == 1
    # a CUDA_VISIBLE_DEVICES that hides every GPU is no binding
    assert not choose_device(NODE, {"CUDA_VISIBLE_DEVICES": "-1"}).gpu_required
    # bound, but no EGL device speaks EGL_NV_device_cuda: the first hardware one, still a GPU required
    c = choose_device([EGLDevice(0, MESA), EGLDevice(1, ("EGL_EXT_device_drm",), "/dev/dri/card0")],
                      {"CUDA_VISIBLE_DEVICES": "0"})
    assert c.index == 1 and c.gpu_required


@pytest.mark.parametrize("value", ["7", "-1", "gpu0"])
def test_archive_gl_device_naming_no_device_is_one_clear_error(value):
    with pytest.raises(RenderError, match=f"ARCHIVE_GL_DEVICE='{value}' names no EGL device.*archive doctor"):
        choose_device(NODE, {"ARCHIVE_GL_DEVICE": value})


def test_a_process_given_a_gpu_refuses_a_software_renderer():
    assert gpu_required({"ARCHIVE_REQUIRE_GPU": "1"}) == "ARCHIVE_REQUIRE_GPU=1"
    assert gpu_required({}) == ""
    choice = choose_device([EGLDevice(0, MESA)], {"CUDA_VISIBLE_DEVICES": "0"})
    with pytest.raises(RenderError, match=r"given a GPU \(CUDA_VISIBLE_DEVICES=0\).*llvmpipe.*10_nvidia.json"):
        check_renderer(choice, "llvmpipe (LLVM 15.0.6, 256 bits)")
    check_renderer(choice, "NVIDIA H100 80GB HBM3/PCIe/SSE2")   # a GPU: fine
    check_renderer(choose_device([EGLDevice(0, MESA)], {}), "llvmpipe (LLVM 15.0.6, 256 bits)")  # not given one


def test_workers_spread_over_the_gpus():
    assert spread_environments(NODE, 6, {}) == [{"ARCHIVE_GL_DEVICE": str(i % 4)} for i in range(6)]
    assert spread_environments(NODE, 3, {"CUDA_VISIBLE_DEVICES": "1,3"}) == [
        {"CUDA_VISIBLE_DEVICES": "1"}, {"CUDA_VISIBLE_DEVICES": "3"}, {"CUDA_VISIBLE_DEVICES": "1"}]
    assert spread_environments(NODE, 2, {"ARCHIVE_GL_DEVICE": "1"}) == [{}, {}]   # the user's choice stands
    assert spread_environments(NODE[:1] + NODE[4:], 2, {}) == [{}, {}]             # one GPU: nothing to spread


def test_a_local_cluster_gives_each_worker_its_gpu(monkeypatch):
    """A real local cluster of 2 worker processes on a node bound to GPUs 5 and 6: each worker gets one."""
    from archive.run.cluster import start_cluster

    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "5,6")
    client, cluster = start_cluster(None, 2, lambda text: None, threads=1)
    try:
        seen = client.run(lambda: os.environ.get("CUDA_VISIBLE_DEVICES"))
    finally:
        client.close()
        cluster.close()
    assert sorted(seen.values()) == ["5", "6"]


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    d = tmp_path_factory.mktemp("device") / "flight"
    simulate_flight(d, cubes=2, bands=4, samples=40, lines=100, seed=5)
    return d


def _render(flight: Path, out: Path, **env: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "archive", "render", str(flight), "--fov", str(FOV), "--gsd", "0.5",
                           "--out", str(out), "--quiet", "--workers", "1"], capture_output=True, text=True,
                          cwd=ROOT, env=_clean_env(**env), timeout=600)


def test_a_render_bound_to_a_gpu_that_gets_llvmpipe_stops_in_one_line(flight, tmp_path):
    out = tmp_path / "bound.tif"
    done = _render(flight, out, CUDA_VISIBLE_DEVICES="0")
    assert done.returncode != 0
    lines = [ln for ln in done.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, done.stderr
    assert "given a GPU (CUDA_VISIBLE_DEVICES=0)" in lines[0] and "llvmpipe" in lines[0]
    assert not out.exists() and not list(tmp_path.glob("*partial*"))


def test_the_renderer_and_device_are_recorded_in_the_item(flight, tmp_path):
    out = tmp_path / "chosen.zarr"
    done = _render(flight, out, ARCHIVE_GL_DEVICE="0")
    assert done.returncode == 0, done.stderr
    props = json.loads(Path(f"{out}.json").read_text())["properties"]
    (opened,) = props["archive:renderers"]          # one worker, one GL thread: one context
    assert opened["device"] == 0 and opened["reason"] == "ARCHIVE_GL_DEVICE=0"
    assert opened["band_pass"]["method"] == "cpu"   # llvmpipe: the numpy gather
    assert "llvmpipe" in opened["renderer"] and props["archive:recipe"]["renderers"] == [opened["renderer"]]
    assert "renderers" not in props["archive:recipe"]["request"]   # a record of the run, not of the request


def _doctor(*args: str, **env: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "archive", "doctor", *args], capture_output=True, text=True,
                          cwd=ROOT, env=_clean_env(**env), timeout=300)


def test_doctor_says_this_machine_renders_on_llvmpipe():
    done = _doctor()
    assert done.returncode == 0, done.stdout + done.stderr
    out = done.stdout
    assert "EGL device 0: software (Mesa llvmpipe): llvmpipe" in out
    assert "worker device: a worker here opens EGL device 0" in out
    assert "band passes: cpu" in out and "this machine can render: llvmpipe" in out
    doc = json.loads(_doctor("--json", "--workers", "2").stdout)
    assert doc["ok"] is True
    worker = next(c for c in doc["checks"] if c["what"] == "worker device")
    assert worker["data"]["device"] == 0 and worker["data"]["compute"] in (True, False)


@pytest.mark.parametrize("env, says", [
    ({"CUDA_VISIBLE_DEVICES": "0"}, "given a GPU (CUDA_VISIBLE_DEVICES=0)"),
    ({"ARCHIVE_REQUIRE_GPU": "1"}, "given a GPU (ARCHIVE_REQUIRE_GPU=1)"),
    ({"ARCHIVE_GL_DEVICE": "9"}, "ARCHIVE_GL_DEVICE='9' names no EGL device"),
])
def test_doctor_fails_with_the_cause_when_rendering_is_impossible(env, says):
    done = _doctor(**env)
    assert done.returncode == 1
    assert says in done.stdout and "fix:" in done.stdout
    assert done.stderr.startswith("archive doctor: error: this machine cannot render") and says in done.stderr
