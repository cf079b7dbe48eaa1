"""Publication a reader can trust (issue 30, finding 3), through the real CLI on real files:

- replacing an output (``--overwrite``) never leaves the new data beside the old STAC Item: a kill
  between the data's rename and the Item's write (the ARCHIVE_TEST_KILL_AT=after-data hook: the
  process SIGKILLs itself there) leaves data without an Item, which ``--resume`` renders again;
- the recipe a resume compares includes the inputs (a collection's content version and navigation
  parameters): a flight re-ingested with another sync offset is rendered again, not skipped.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers import FOV, ingest_each



@pytest.fixture(scope="module")
def flights(small_flights, tmp_path_factory):
    """(raw directories, archive, ids) of two small flights (seeds 0-1, conftest) ingested into one archive."""
    dirs = [small_flights(seed) for seed in range(2)]
    archive = tmp_path_factory.mktemp("publication") / "archive"
    return dirs, archive, ingest_each(dirs, archive)


def run(*args: str, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "archive", *args], capture_output=True, text=True, timeout=600,
                          env={**os.environ, **(env or {})}, start_new_session=True)


def batch(archive: Path, out: Path, gsd: str, *extra: str, env: dict | None = None) -> subprocess.CompletedProcess:
    return run("render", "--archive", str(archive), "--query-bbox", "-180,-90,180,90", "--gsd", gsd, "--out",
               str(out), "--format", "tif", "--quiet", "--workers", "1", *extra, env=env)


def values(path: Path) -> np.ndarray:
    import rasterio

    with rasterio.open(path) as src:
        return src.read()


def recipe(item: Path) -> dict:
    return json.loads(item.read_text())["properties"]["archive:recipe"]


def statuses(out: Path) -> dict:
    return {o["id"]: o["status"] for o in json.loads((out / "report.json").read_text())["outputs"]}


def test_kill_between_data_and_item_of_an_overwrite(flights, tmp_path):
    """A batch at 0.1 m, then --overwrite at 0.2 m killed right after its first output's data is in
    place: that output has no Item (the old one went first), so --resume of the 0.1 m request renders
    it again (before: "complete (same recipe)" over 0.2 m data) and every output equals a fresh render."""
    _, archive, ids = flights
    out = tmp_path / "out"
    assert batch(archive, out, "0.1").returncode == 0
    fresh = {cid: values(out / f"{cid}.tif") for cid in ids}
    killed = batch(archive, out, "0.2", "--overwrite", env={"ARCHIVE_TEST_KILL_AT": "after-data"})
    assert killed.returncode == -signal.SIGKILL, killed.stderr
    replaced = [cid for cid in ids if values(out / f"{cid}.tif").shape != fresh[cid].shape]
    assert len(replaced) == 1, "the kill lands after the first output's data is renamed into place"
    (cid,) = replaced
    assert not (out / f"{cid}.tif.json").exists(), "new data must never sit beside the old Item"
    resumed = batch(archive, out, "0.1", "--resume")
    assert resumed.returncode == 0, resumed.stderr
    assert statuses(out)[cid] == "done" and f"skipped {cid}" not in resumed.stdout
    for c in ids:
        assert np.array_equal(values(out / f"{c}.tif"), fresh[c], equal_nan=True)
        assert recipe(out / f"{c}.tif.json")["request"]["gsd"] == 0.1


def test_kill_between_data_and_item_of_a_single_render(flights, tmp_path):
    """`archive render ID --out X.tif --overwrite` killed between the rename and the Item: X.tif is the
    new data and no Item says it is complete (the old Item was removed first)."""
    _, archive, ids = flights
    out = tmp_path / "one.tif"
    first = run("render", ids[0], "--archive", str(archive), "--gsd", "0.1", "--out", str(out), "--quiet")
    assert first.returncode == 0, first.stderr
    old = values(out)
    killed = run("render", ids[0], "--archive", str(archive), "--gsd", "0.2", "--out", str(out), "--quiet",
                 "--overwrite", env={"ARCHIVE_TEST_KILL_AT": "after-data"})
    assert killed.returncode == -signal.SIGKILL, killed.stderr
    assert values(out).shape != old.shape and not Path(f"{out}.json").exists()
    # the next render (here: the first request again) takes over and leaves nothing hidden behind
    assert run("render", ids[0], "--archive", str(archive), "--gsd", "0.1", "--out", str(out), "--quiet",
               "--overwrite").returncode == 0
    assert np.array_equal(values(out), old, equal_nan=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["one.tif", "one.tif.json"]


def test_reingest_then_resume_renders_again(flights, tmp_path):
    """A flight re-ingested with another sync offset (`ingest --overwrite --sync-offset`): --resume of
    the same request renders it again (its output differs from the old one and equals a fresh render)
    and skips the flight that did not change; the Item records the inputs."""
    dirs, archive, ids = flights
    archive = Path(shutil.copytree(archive, tmp_path / "archive"))
    out = tmp_path / "out"
    assert batch(archive, out, "0.1").returncode == 0
    before = values(out / f"{ids[0]}.tif")
    inputs = recipe(out / f"{ids[0]}.tif.json")["inputs"]
    assert inputs[0]["source"] == ids[0] and inputs[0]["navigation_params"]["sync_offset"] == 0.0
    again = run("ingest", str(dirs[0]), "--archive", str(archive), "--fov", str(FOV), "--overwrite", "--sync-offset",
                "0.2", "--quiet")
    assert again.returncode == 0, again.stderr
    resumed = batch(archive, out, "0.1", "--resume")
    assert resumed.returncode == 0, resumed.stderr
    assert statuses(out) == {ids[0]: "done", ids[1]: "skipped"}, resumed.stdout
    assert f"archive render: stale {ids[0]}: its inputs changed since it was rendered ({ids[0]}: navigation_params " \
        in resumed.stdout and "'sync_offset': 0.2" in resumed.stdout and "rendering it again" in resumed.stdout
    assert recipe(out / f"{ids[0]}.tif.json")["inputs"][0]["navigation_params"]["sync_offset"] == 0.2
    fresh = tmp_path / "fresh.tif"
    assert run("render", ids[0], "--archive", str(archive), "--gsd", "0.1", "--out", str(fresh),
               "--quiet").returncode == 0
    after = values(out / f"{ids[0]}.tif")
    assert np.array_equal(after, values(fresh), equal_nan=True)
    assert after.shape != before.shape or not np.array_equal(after, before, equal_nan=True)
    # and now it is the same recipe again
    assert batch(archive, out, "0.1", "--resume").returncode == 0
    assert statuses(out) == {ids[0]: "skipped", ids[1]: "skipped"}


def test_a_single_render_records_its_inputs(flights, tmp_path):
    """``archive render ID`` (not a batch) records the same ``archive:recipe.inputs`` a batch does: the
    collection's content version and navigation parameters, so a later batch --resume can judge it."""
    from archive.run.options import RenderOptions
    from archive.run.pipeline import recipe_inputs

    _, archive, ids = flights
    out = tmp_path / "one.tif"
    done = run("render", ids[0], "--archive", str(archive), "--gsd", "0.5", "--out", str(out), "--quiet",
               "--workers", "1")
    assert done.returncode == 0, done.stderr
    recipe = json.loads(Path(f"{out}.json").read_text())["properties"]["archive:recipe"]
    (entry,) = recipe["inputs"]
    assert entry["source"] == ids[0] and entry["version"]
    options = RenderOptions.create(sources=[ids[0]], archive=str(archive), gsd=0.5)
    assert recipe["inputs"] == recipe_inputs(options)
