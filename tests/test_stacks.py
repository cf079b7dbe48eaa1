"""One grid for the whole archive (issue 32), through the real CLI: --bounds/--align/--like on a
render, time stacks (archive render --stack, --resume, archive.stack), the simulator flying the
same ground again.

Small flights (2 cubes x 60 lines x 32 samples x 4 bands) of one field flown on three days: seed k
with --scene-seed 0 (same ground and camera, its own wobble and noise), a week apart.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import xarray as xr
from helpers import FOV

GSD = "0.5"
SHAPE = ["--cubes", "2", "--samples", "32", "--lines", "60", "--bands", "4"]
DAYS = ("2024-06-12", "2024-06-19", "2024-06-26")


def cli(*args: str, cwd: Path | None = None, ok: bool = True) -> subprocess.CompletedProcess:
    """``python -m archive ARGS`` in a subprocess; asserts the exit code (0, or not 0 with ``ok=False``)."""
    proc = subprocess.run([sys.executable, "-m", "archive", *args], capture_output=True, text=True, cwd=cwd,
                          timeout=300)
    assert (proc.returncode == 0) == ok, (args, proc.returncode, proc.stdout, proc.stderr)
    return proc


@pytest.fixture(scope="module")
def field(tmp_path_factory):
    """(root, archive, ids): three flights of one field, a week apart; the first two ingested."""
    from archive.ingest.command import ingest

    root = tmp_path_factory.mktemp("field")
    ids = []
    for k, day in enumerate(DAYS):
        cli("simulate", str(root / f"day{k}"), *SHAPE, "--seed", str(k), "--scene-seed", "0",
            "--start", f"{day}T16:00:00Z", "--quiet")
        if k < 2:
            (r,) = ingest([str(root / f"day{k}")], root / "archive", FOV, progress=False)
            ids.append(r.cid)
    return root, root / "archive", ids


def values(path: Path, variable: str = "radiance") -> np.ndarray:
    with xr.open_zarr(path) as ds:
        return ds[variable].values


# ---------------------------------------------------------------------------------------------
# The simulator flies the same ground again
# ---------------------------------------------------------------------------------------------
def test_scene_seed_flies_the_same_ground(field, tmp_path):
    from archive.simulator.command import simulate_flight
    from archive.simulator.truth import load_truth

    root, _, _ = field
    t0, t1 = load_truth(root / "day0" / "truth"), load_truth(root / "day1" / "truth")
    assert t0.scene.to_dict() == t1.scene.to_dict()   # the same ground
    assert t0.cubes[0].line_time[0] + 7 * 86400 == pytest.approx(t1.cubes[0].line_time[0], abs=1e-6)
    assert not np.array_equal(t0.cubes[0].position_utm, t1.cubes[0].position_utm)   # its own wobble
    # a flight whose scene seed is its seed is that seed's flight, byte for byte
    small = dict(cubes=1, samples=16, lines=20, bands=2)
    simulate_flight(tmp_path / "a", seed=3, **small)
    simulate_flight(tmp_path / "b", seed=3, scene_seed=3, **small)
    for f in (tmp_path / "a").iterdir():
        if f.is_file():
            assert f.read_bytes() == (tmp_path / "b" / f.name).read_bytes(), f.name


# ---------------------------------------------------------------------------------------------
# Grid options
# ---------------------------------------------------------------------------------------------
def test_bounds_align_and_like(field, tmp_path):
    import rasterio

    root, _, _ = field
    day0, day1 = str(root / "day0"), str(root / "day1")
    cli("render", day0, "--fov", str(FOV), "--gsd", "0.1", "--out", str(tmp_path / "foot.tif"), "--quiet")
    with rasterio.open(tmp_path / "foot.tif") as ds:
        w, s, e, n = ds.bounds
    # --bounds without --align: the top-left corner exactly at W,N; with --align: edges on multiples of the GSD
    box = (w + 2.03, s + 3.01, e - 4.02, n - 2.07)
    text = ",".join(f"{v:.2f}" for v in box)
    cli("render", day0, "--fov", str(FOV), "--gsd", "0.1", "--bounds", text, "--out", str(tmp_path / "exact.zarr"),
        "--quiet")
    cli("render", day0, "--fov", str(FOV), "--gsd", "0.1", "--bounds", text, "--align", "--out",
        str(tmp_path / "part.zarr"), "--quiet")
    big = f"{np.floor(w) - 5:.0f},{np.floor(s) - 5:.0f},{np.ceil(e) + 5:.0f},{np.ceil(n) + 5:.0f}"
    cli("render", day0, "--fov", str(FOV), "--gsd", "0.1", "--bounds", big, "--align", "--out",
        str(tmp_path / "big.zarr"), "--quiet")
    from archive.outputs.like import read_grid

    exact, part, whole = (read_grid(tmp_path / f) for f in ("exact.zarr", "part.zarr", "big.zarr"))
    assert (exact.x0, exact.y0) == (float(f"{box[0]:.2f}"), float(f"{box[3]:.2f}"))
    for g in (part, whole):
        assert abs(g.x0 / 0.1 - round(g.x0 / 0.1)) < 1e-6 and abs(g.y0 / 0.1 - round(g.y0 / 0.1)) < 1e-6
    pw, ps, pe, pn = part.bounds
    assert pw <= box[0] < pw + 0.1 and pn - 0.1 < box[3] <= pn and pe - 0.1 < box[2] <= pe
    # alignment exact: the part's pixels are the big render's, bit for bit
    r0, c0 = round((whole.y0 - part.y0) / 0.1), round((part.x0 - whole.x0) / 0.1)
    cut = values(tmp_path / "big.zarr")[:, r0:r0 + part.height, c0:c0 + part.width]
    mine = values(tmp_path / "part.zarr")
    assert np.isfinite(mine).mean() > 0.2
    np.testing.assert_array_equal(cut, mine)
    # --like a COG: the other day's flight on that very grid, --gsd taken from it
    cli("render", day1, "--fov", str(FOV), "--like", str(tmp_path / "foot.tif"), "--out", str(tmp_path / "day1.tif"),
        "--quiet")
    with rasterio.open(tmp_path / "foot.tif") as a, rasterio.open(tmp_path / "day1.tif") as b:
        assert (a.crs, a.transform, a.shape) == (b.crs, b.transform, b.shape)


def test_bad_grid_input_is_refused_in_one_line(field, tmp_path):
    root, archive, ids = field
    day0 = str(root / "day0")
    (tmp_path / "notes.tif").write_text("not a raster")
    cases = [
        (["--like", str(tmp_path / "notes.tif")], "notes.tif"),
        (["--like", day0], "not an output"),
        (["--gsd", GSD, "--bounds", "1000,2000,1100,2100"], "holds no line"),
        (["--gsd", GSD, "--bounds", "5,5,1,1"], "not a box"),
        ([], "gsd"),
    ]
    for extra, words in cases:
        proc = cli("render", day0, "--fov", str(FOV), *extra, "--out", str(tmp_path / "x.zarr"), ok=False)
        err = proc.stderr.strip()
        assert len(err.splitlines()) == 1 and words in err and "Traceback" not in err, (extra, err)
    assert not (tmp_path / "x.zarr").exists()
    proc = cli("render", "--stack", "--gsd", GSD, "--out", str(tmp_path / "s.zarr"), ok=False)
    assert len(proc.stderr.strip().splitlines()) == 1 and "stack" in proc.stderr


# ---------------------------------------------------------------------------------------------
# Time stacks
# ---------------------------------------------------------------------------------------------
def test_stack_slices_equal_like_renders_and_resume_adds_only_the_missing(field, tmp_path):
    from archive.ingest.command import ingest
    from archive.outputs.like import read_grid

    root, archive, ids = field
    archive = Path(_copy(archive, tmp_path / "archive"))
    out = tmp_path / "field.zarr"
    query = ["--archive", str(archive), "--query-datetime", "2024-06-01/2024-07-01"]
    proc = cli("render", *query, "--stack", "--gsd", GSD, "--out", str(out), "--quiet")
    assert "2 added" in proc.stdout, proc.stdout
    with xr.open_zarr(out, decode_coords="all") as ds:
        assert ds.radiance.dims == ("time", "band", "y", "x")
        assert list(ds.flight.values) == ids
        assert [str(t)[:10] for t in ds.time.values] == list(DAYS[:2])
        assert ds.radiance.encoding["chunks"][:2] == (1, 1)   # chunks never hold two flights
    grid = read_grid(out)
    assert abs(grid.x0 / grid.gsd - round(grid.x0 / grid.gsd)) < 1e-6   # aligned
    # each slice is that flight rendered alone with --like the stack, bit for bit
    stack = values(out)
    one = tmp_path / "first.zarr"
    cli("render", ids[0], "--archive", str(archive), "--like", str(out), "--out", str(one), "--quiet")
    np.testing.assert_array_equal(stack[0], values(one))
    np.testing.assert_array_equal(values(out, "saturated")[0], values(one, "saturated"))
    # and a batch, one output per flight, --like the stack (the grid options of a batch)
    cli("render", *query, "--like", str(out), "--out", str(tmp_path / "each"), "--quiet")
    for t, cid in enumerate(ids):
        assert np.isfinite(stack[t]).mean() > 0.15
        assert read_grid(tmp_path / "each" / f"{cid}.zarr") == grid
        np.testing.assert_array_equal(stack[t], values(tmp_path / "each" / f"{cid}.zarr"))
    item = json.loads((tmp_path / "field.zarr.json").read_text())
    dims = item["properties"]["cube:dimensions"]
    assert dims["time"]["values"][0].startswith(DAYS[0]) and dims["x"]["step"] == float(GSD)
    assert item["properties"]["archive:recipe"]["sources"] == ids
    cli("catalog", "validate", str(tmp_path / "field.zarr.json"))   # valid STAC
    # a new flight of the field ingested: --resume renders it alone, at the end of time
    (r,) = ingest([str(root / "day2")], archive, FOV, progress=False)
    before = {p: p.stat().st_mtime_ns for p in (out / "radiance").glob("[01].*")}
    proc = cli("render", *query, "--stack", "--gsd", GSD, "--out", str(out), "--resume")
    lines = [line for line in proc.stdout.splitlines() if line.startswith("archive render: ")]
    assert sum("skipped" in line for line in lines) == 2 and sum(" done " in f" {line}" for line in lines) == 1
    assert "1 added, 2 already there" in proc.stdout
    assert {p: p.stat().st_mtime_ns for p in before} == before   # the old slices untouched
    np.testing.assert_array_equal(values(out)[:2], stack)
    with xr.open_zarr(out) as ds:
        assert list(ds.flight.values) == [*ids, r.cid]
    # the same stack asked with other options: refused in one line, the stack left as it is
    proc = cli("render", *query, "--stack", "--gsd", "0.25", "--out", str(out), "--resume", ok=False)
    assert len(proc.stderr.strip().splitlines()) == 1 and "gsd" in proc.stderr
    proc = cli("render", *query, "--stack", "--gsd", GSD, "--out", str(out), ok=False)
    assert "--resume" in proc.stderr
    # archive.stack: the same values, lazily; a window renders only its part
    import archive as lib

    da = lib.stack({"datetime": "2024-06-01/2024-07-01"}, archive=archive, like=out)
    assert list(da.flight.values) == [*ids, r.cid] and da.dims == ("time", "band", "y", "x")
    np.testing.assert_array_equal(da.values, values(out))
    window = da.isel(time=1, x=slice(5, 25), y=slice(3, 20))
    from collections import Counter

    from dask.diagnostics import Profiler

    with Profiler() as prof:
        got = window.compute(scheduler="threads")
    np.testing.assert_array_equal(got.values, values(out)[1, :, 3:20, 5:25])
    ran = Counter(str(r.key if isinstance(r.key, str) else r.key[0]).split("-")[0] for r in prof.results)
    assert 0 < ran["render"] <= 2 and ran["lookup"] <= 2   # that flight's cubes only (of 3 flights x 2 cubes)


def _copy(src: Path, dst: Path) -> Path:
    import shutil

    shutil.copytree(src, dst)
    return dst


# ---------------------------------------------------------------------------------------------
# Tiles
# ---------------------------------------------------------------------------------------------
def test_tiles_stitched_equal_the_union_render(field, tmp_path):
    import rasterio

    root, archive, ids = field
    query = ["--archive", str(archive), "--query-datetime", "2024-06-12/2024-06-20"]
    proc = cli("render", *query, "--tiles", "10", "--gsd", "0.1", "--out", str(tmp_path / "tiles"), "--format", "tif",
               "--quiet")
    tiles = sorted((tmp_path / "tiles").glob("*.tif"))
    assert len(tiles) >= 4 and f"{len(tiles)} tiles in" in proc.stdout
    report = json.loads((tmp_path / "tiles" / "report.json").read_text())
    assert report["done"] == len(tiles) and report["complete"]
    corners = []
    for path in tiles:
        epsg, e0, n0 = (int(v) for v in path.stem.split("_"))
        with rasterio.open(path) as ds:   # named by its lower-left corner, 10 m on multiples of 10 m
            assert ds.crs.to_epsg() == epsg and tuple(ds.bounds) == (e0, n0, e0 + 10, n0 + 10)
        item = json.loads(path.with_name(path.name + ".json").read_text())
        assert set(item["properties"]["archive:tile"]["flights"]) <= set(ids)
        corners.append((e0, n0))
    w, s = min(c[0] for c in corners), min(c[1] for c in corners)
    e, n = max(c[0] for c in corners) + 10, max(c[1] for c in corners) + 10
    union = tmp_path / "union.tif"
    cli("render", *ids, "--archive", str(archive), "--bounds", f"{w},{s},{e},{n}", "--align", "--gsd", "0.1",
        "--out", str(union), "--quiet")
    with rasterio.open(union) as ds:
        whole = ds.read()
    covered = np.zeros(whole.shape[1:], bool)
    for path, (e0, n0) in zip(tiles, corners):
        r0, c0 = round((n - n0 - 10) / 0.1), round((e0 - w) / 0.1)
        with rasterio.open(path) as ds:
            np.testing.assert_array_equal(ds.read(), whole[:, r0:r0 + 100, c0:c0 + 100], err_msg=path.name)
        covered[r0:r0 + 100, c0:c0 + 100] = True
    assert np.isnan(whole[:, ~covered]).all()   # no flight outside the tiles
    assert np.isfinite(whole).mean() > 0.1
    # --resume: every tile complete with the same recipe is skipped
    proc = cli("render", *query, "--tiles", "10", "--gsd", "0.1", "--out", str(tmp_path / "tiles"), "--format", "tif",
               "--resume", "--quiet")
    assert f"0 done, {len(tiles)} skipped" in proc.stdout


def test_tiles_need_an_archive(tmp_path):
    proc = cli("render", "somewhere", "--tiles", "10", "--gsd", "0.1", "--out", str(tmp_path / "t"), ok=False)
    err = proc.stderr.strip()
    assert len(err.splitlines()) == 1 and "tiles" in err and "--archive" in err
    assert not (tmp_path / "t").exists()


def test_a_killed_stack_is_resumed(field, tmp_path):
    import os
    import signal
    import time

    root, archive, ids = field
    out = tmp_path / "killed.zarr"
    query = ["--archive", str(archive), "--query-datetime", "2024-06-12/2024-06-20"]
    args = [sys.executable, "-m", "archive", "render", *query, "--stack", "--gsd", GSD, "--out", str(out), "--quiet"]
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
                            env={**os.environ, "ARCHIVE_TEST_HOLD_AFTER": "1"})
    try:
        deadline = time.monotonic() + 120
        while True:   # the first slice committed: the stack exists under its name, without its Item
            assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
            if (out / ".zmetadata").exists() and json.loads((out / ".zattrs").read_text()).get("archive_stack"):
                break
            time.sleep(0.2)
    finally:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.communicate()
    with xr.open_zarr(out) as ds:
        assert ds.sizes["time"] == 1
    assert not (tmp_path / "killed.zarr.json").exists()   # not complete
    proc = cli("render", *query, "--stack", "--gsd", GSD, "--out", str(out), "--quiet", ok=False)
    assert "--resume" in proc.stderr
    proc = cli("render", *query, "--stack", "--gsd", GSD, "--out", str(out), "--resume", "--quiet")
    assert "1 added, 1 already there" in proc.stdout
    assert (tmp_path / "killed.zarr.json").exists()
    assert not [p for p in tmp_path.iterdir() if ".partial-" in p.name]   # no temporaries left
    fresh = tmp_path / "fresh.zarr"
    cli("render", *query, "--stack", "--gsd", GSD, "--out", str(fresh), "--quiet")
    np.testing.assert_array_equal(values(out), values(fresh))
    with xr.open_zarr(out) as a, xr.open_zarr(fresh) as b:
        assert list(a.flight.values) == list(b.flight.values) == ids


def test_outputs_recorded_before_the_grid_options_resume_as_the_same_recipe(field, tmp_path):
    root, archive, ids = field
    batch = ["render", "--archive", str(archive), "--query-datetime", "2024-06-12", "--gsd", GSD,
             "--out", str(tmp_path / "b"), "--quiet"]
    cli(*batch)
    item_path = tmp_path / "b" / f"{ids[0]}.zarr.json"
    item = json.loads(item_path.read_text())
    request = item["properties"]["archive:recipe"]["request"]
    assert (request["bounds"], request["align"], request["like"]) == (None, False, None)
    for name in ("bounds", "align", "like"):   # as an Item written before these options existed
        del request[name]
    item_path.write_text(json.dumps(item))
    proc = cli(*batch, "--resume")
    assert "0 done, 1 skipped" in proc.stdout, proc.stdout


# ---------------------------------------------------------------------------------------------
# Two writers of one stack (issue 50)
# ---------------------------------------------------------------------------------------------
def _stack_args(archive: Path, when: str, out: Path, *extra: str) -> list[str]:
    return [sys.executable, "-m", "archive", "render", "--archive", str(archive), "--query-datetime", when,
            "--stack", "--gsd", GSD, "--out", str(out), "--quiet", *extra]


def _steps(path: Path) -> dict[str, np.ndarray]:
    with xr.open_zarr(path) as ds:
        return {str(f): ds.radiance.isel(time=t).values for t, f in enumerate(ds.flight.values)}


def test_a_second_writer_of_a_stack_is_refused_naming_the_holder(field, tmp_path):
    """While one run writes a stack (held after its first slice), a run with another query into the same
    --out is refused in one line naming the holder, and touches nothing; the first completes right
    (without the lock, 7 of 12 such pairs left steps of the other flight or NaN: issue 50)."""
    import os
    import time

    root, archive, ids = field
    out, hold = tmp_path / "s.zarr", tmp_path / "hold"
    hold.write_text("")
    first = subprocess.Popen(_stack_args(archive, "2024-06-01/2024-07-01", out), stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True, env={**os.environ, "ARCHIVE_TEST_HOLD_AFTER": f"1:{hold}"})
    try:
        deadline = time.monotonic() + 120
        while not (out / ".zattrs").exists() or "archive_stack" not in (out / ".zattrs").read_text():
            assert first.poll() is None and time.monotonic() < deadline, first.communicate()
            time.sleep(0.2)
        before = sorted(str(p.relative_to(out)) for p in out.rglob("*"))
        second = subprocess.run(_stack_args(archive, "2024-06-19", out, "--resume"), capture_output=True, text=True,
                                timeout=300)
        assert second.returncode != 0
        err = second.stderr.strip().splitlines()
        assert len(err) == 1 and "locked" in err[0] and f"PID {first.pid}" in err[0] and "--resume" in err[0], err
        assert sorted(str(p.relative_to(out)) for p in out.rglob("*")) == before   # nothing touched
    finally:
        hold.unlink()
        stdout, stderr = first.communicate(timeout=300)
    assert first.returncode == 0, stderr
    one = tmp_path / "one.zarr"
    cli("render", ids[1], "--archive", str(archive), "--like", str(out), "--out", str(one), "--quiet")
    steps = _steps(out)
    assert list(steps) == ids
    np.testing.assert_array_equal(steps[ids[1]], values(one)[...])
    assert not list(tmp_path.glob(".s.zarr.stack.lock*"))   # the lock given back


@pytest.mark.parametrize("round_", range(2))
def test_two_stacks_started_together_leave_only_their_own_steps(field, tmp_path, round_):
    """Two runs with different queries started at once into one --out (repeated): one writes, the other is
    refused (or, if it came after, finds the output there); every step of the stack holds its own flight's
    values, those of the same request run alone."""
    root, archive, ids = field
    out = tmp_path / "race.zarr"
    queries = ["2024-06-01/2024-07-01", "2024-06-19"]
    if round_:
        queries.reverse()
    procs = [subprocess.Popen(_stack_args(archive, q, out), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for q in queries]
    results = [(p.wait(timeout=300), *p.communicate()) for p in procs]
    winners = [i for i, (rc, _, _) in enumerate(results) if rc == 0]
    assert len(winners) == 1, results
    (loser,) = [r for i, r in enumerate(results) if i not in winners]
    assert len(loser[2].strip().splitlines()) == 1 and ("locked" in loser[2] or "exists already" in loser[2]), loser
    alone = tmp_path / "alone.zarr"
    subprocess.run(_stack_args(archive, queries[winners[0]], alone), check=True, timeout=300)
    got, want = _steps(out), _steps(alone)
    assert list(got) == list(want)
    for cid in want:
        np.testing.assert_array_equal(got[cid], want[cid], err_msg=cid)


def test_resume_refuses_a_step_of_another_recipe(field, tmp_path):
    """A step whose recorded recipe is not the request's (written by another run) is never kept by --resume."""
    root, archive, ids = field
    out = tmp_path / "r.zarr"
    query = ["--archive", str(archive), "--query-datetime", "2024-06-01/2024-07-01"]
    cli("render", *query, "--stack", "--gsd", GSD, "--out", str(out), "--quiet")
    attrs = json.loads((out / ".zattrs").read_text())
    meta = json.loads(attrs["archive_stack"])
    assert all(len(f["recipe"]) == 64 for f in meta["flights"])
    meta["flights"][1]["recipe"] = "0" * 64   # as if another request wrote that step
    attrs["archive_stack"] = json.dumps(meta)
    (out / ".zattrs").write_text(json.dumps(attrs))
    zmeta = json.loads((out / ".zmetadata").read_text())
    zmeta["metadata"][".zattrs"] = attrs
    (out / ".zmetadata").write_text(json.dumps(zmeta))
    proc = cli("render", *query, "--stack", "--gsd", GSD, "--out", str(out), "--resume", ok=False)
    err = proc.stderr.strip()
    assert len(err.splitlines()) == 1 and ids[1] in err and "another request" in err and "--overwrite" in err
    cli("render", *query, "--stack", "--gsd", GSD, "--out", str(out), "--resume", "--overwrite", "--quiet")
    assert json.loads(json.loads((out / ".zattrs").read_text())["archive_stack"])["flights"][1]["recipe"] != "0" * 64
