"""The local cluster started while ``archive render`` imports and plans (issue 37,
:class:`archive.run.cluster.ClusterStart`) and closed while it publishes (:class:`ClusterClose`): a
command that fails before it needs workers leaves none running; an error starting them is the
one-line error it was; a render through both gives its output and leaves no worker behind."""

from __future__ import annotations

import time

import psutil
import pytest

from archive.cli import main
from archive.run.cluster import ClusterStart
from archive.errors import InputError
from helpers import FOV


def _is_worker(p: psutil.Process) -> bool:
    """A live child process other than multiprocessing's resource tracker (which lives as long as
    this process, whatever the cluster does)."""
    try:
        return p.status() != psutil.STATUS_ZOMBIE and "resource_tracker" not in " ".join(p.cmdline())
    except psutil.Error:
        return False


def _children() -> set[int]:
    """The pids of this process's live child processes (the session's shared LocalCluster of
    conftest, where an earlier test started it, among them)."""
    return {p.pid for p in psutil.Process().children(recursive=True) if _is_worker(p)}


def _workers_left(before: set[int], timeout: float = 10.0) -> list:
    """This process's child processes not in ``before`` (those alive before the command) still
    alive after up to ``timeout`` s (workers being closed take a moment to exit)."""
    deadline = time.monotonic() + timeout
    while True:
        alive = [p for p in psutil.Process().children(recursive=True) if _is_worker(p) and p.pid not in before]
        if not alive or time.monotonic() > deadline:
            return alive
        time.sleep(0.2)


def test_a_command_failing_before_it_needs_workers_leaves_none(tmp_path, capsys):
    before = _children()
    code = main(["render", str(tmp_path / "no-such-flight"), "--fov", str(FOV), "--gsd", "0.1",
                 "--out", str(tmp_path / "m.zarr"), "--quiet"])
    assert code == 2 and "no-such-flight: flight directory not found" in capsys.readouterr().err
    assert _workers_left(before) == [] and not (tmp_path / "m.zarr").exists()


def test_an_error_starting_is_raised_where_the_cluster_is_taken():
    starting = ClusterStart(None, -1, lambda text: None)
    with pytest.raises(InputError, match="--workers: expected a positive number of worker processes"):
        starting.result()
    starting.close()   # taken: nothing to close


def test_a_render_through_both_leaves_no_worker(small_flight, tmp_path):
    out = tmp_path / "m.tif"
    before = _children()
    assert main(["render", str(small_flight), "--fov", str(FOV), "--gsd", "0.05", "--ground-height", "auto",
                 "--out", str(out), "--quiet"]) == 0
    assert out.stat().st_size > 0 and (tmp_path / "m.tif.json").exists()
    assert _workers_left(before) == []


def _warm_facts() -> dict:
    """On a worker: whether the render tasks' modules are imported and the band pass decided (the
    GL context made), and whether the test's own preload ran."""
    import os
    import sys

    from archive.graph.tasks import decided_band_pass

    return {"imported": all(m in sys.modules for m in ("archive.graph.tasks", "archive.outputs.registry",
                                                       "archive.sources")),
            "band_pass": decided_band_pass(), "preloaded": os.environ.get("ARCHIVE_TEST_PRELOADED")}


def test_workers_warm_up_before_any_task_and_keep_a_configured_preload(tmp_path):
    """A local cluster's workers import what the render tasks need and make their GL context while
    they start (``archive.run.cluster.dask_setup``, issue 37), with no task sent; a worker preload of the
    Dask configuration still runs too."""
    import importlib

    import dask

    importlib.import_module("distributed")   # its configuration defaults loaded before the set below, which drops what it adds

    from archive.run.cluster import start_cluster

    script = tmp_path / "mark_worker.py"
    script.write_text("import os\n\n\ndef dask_setup(worker):\n    os.environ['ARCHIVE_TEST_PRELOADED'] = 'yes'\n")
    before = _children()
    with dask.config.set({"distributed.worker.preload": [str(script)]}):
        client, cluster = start_cluster(None, 1, lambda text: None, 2)
    try:
        deadline = time.monotonic() + 60
        while True:
            (facts,) = client.run(_warm_facts).values()
            if facts["band_pass"] is not None or time.monotonic() > deadline:
                break
            time.sleep(0.1)
        assert facts["imported"] and facts["band_pass"]["method"] in ("cpu", "gl", "compute"), facts
        assert facts["preloaded"] == "yes"
    finally:
        client.close()
        cluster.close()
    assert _workers_left(before) == []
