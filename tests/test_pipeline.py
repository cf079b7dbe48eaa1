"""``archive render`` end to end on a small simulated flight: real Dask cluster, real EGL, real files.

Most renders go to one shared LocalCluster through ``--scheduler`` (that path is tested too); the
subprocess test uses the command's own local cluster.
"""

from __future__ import annotations

import logging
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import rasterio
import xarray as xr

from archive.cli import main
from archive.errors import InputError
from archive.grid import Grid
from archive.params import MeshSpec, NavigationParams
from helpers import FOV

GSD = 0.04  # ~1570 x 780 px: 2 output tiles of 1024 px, cube windows straddling the tile edge


@pytest.fixture(scope="module")
def flight(strips_flight):
    """(directory, Truth) of the shared 4-cube flight in 2 strips (2 passes), 6 bands 400-1000 nm
    (conftest), read only; ``scheduler`` is the session's LocalCluster shaped like the command's own."""
    return strips_flight


def _render(flight, out, *extra, scheduler=None) -> int:
    directory, truth = flight
    args = ["render", str(directory), "--fov", str(FOV), "--gsd", str(GSD), "--out", str(out),
            "--quiet", *extra]  # ground height 'auto': the simulator's headers give it
    if scheduler:
        args += ["--scheduler", scheduler]
    return main(args)


def _grid_of(ds) -> Grid:
    t = ds.rio.transform()
    return Grid(ds.rio.crs.to_epsg(), t.a, t.c, t.f, ds.sizes["x"], ds.sizes["y"])


def _direct_renders(flight, grid: Grid, bands):
    """Each cube rendered in this process with render_cube on the whole grid, in capture order."""
    from archive.render.mesh import build_mesh
    from archive.render.renderer import render_cube
    from archive.sources import RawFlightSource

    directory, truth = flight
    src = RawFlightSource(directory, NavigationParams())
    poses = [src.poses(i) for i in range(len(src.cubes))]
    out = {}
    for strip in truth.strips:
        for k, i in enumerate(strip):
            info = src.cubes[i]
            mesh = build_mesh(poses[i], FOV, truth.ground_height, info.shutter_ms, info.framerate,
                              closing=poses[strip[k + 1]] if k + 1 < len(strip) else None,
                              opening=poses[strip[k - 1]] if k > 0 else None,
                              closing_shutter_ms=src.cubes[strip[k + 1]].shutter_ms if k + 1 < len(strip) else None,
                              opening_shutter_ms=src.cubes[strip[k - 1]].shutter_ms if k > 0 else None)
            out[i] = render_cube(mesh, src.read_bands(i, bands), src.radiometry(i, bands, "radiance"), grid)
    return [out[i] for i in sorted(out)]


@pytest.fixture(scope="module")
def rendered(flight, scheduler, tmp_path_factory):
    """The all-band Zarr mosaic (overlap 'last') and the direct in-process renders of its cubes."""
    out = tmp_path_factory.mktemp("zarr") / "mosaic.zarr"
    assert _render(flight, out, scheduler=scheduler) == 0
    ds = xr.open_zarr(out, decode_coords="all")
    renders = _direct_renders(flight, _grid_of(ds), list(range(6)))
    return out, ds, renders


def _same(a, b) -> None:
    np.testing.assert_array_equal(np.isnan(a), np.isnan(b))
    np.testing.assert_array_equal(np.nan_to_num(a, nan=0), np.nan_to_num(b, nan=0))


def test_zarr_equals_direct_render_mosaic(rendered, flight):
    out, ds, renders = rendered
    directory, truth = flight
    grid = _grid_of(ds)
    assert grid.epsg == truth.epsg == 32616 and grid.gsd == GSD
    assert np.isclose(grid.x0 / GSD, round(grid.x0 / GSD)) and np.isclose(grid.y0 / GSD, round(grid.y0 / GSD))
    assert grid.width > 1024  # several output tiles
    np.testing.assert_allclose(ds["wavelength"].values, truth.wavelengths)
    assert ds["radiance"].attrs["long_name"] == "radiance" and ds.attrs["mode"] == "radiance"
    expected = np.full((6,) + grid.shape, np.nan, np.float32)
    for r in renders:  # capture order, later covering pixels win
        np.copyto(expected, r.values, where=np.isfinite(r.values))
    got = ds["radiance"].values
    _same(got, expected)  # bit-identical
    assert np.isfinite(got[0]).mean() > 0.3
    # the grid holds the true footprint, with less than 2 pixels to spare on each side
    ring = np.concatenate(truth.footprint())
    w, s, e, n = grid.bounds
    margins = np.array([ring[:, 0].min() - w, ring[:, 1].min() - s, e - ring[:, 0].max(), n - ring[:, 1].max()])
    assert (margins > -0.01).all() and (margins < 2 * GSD).all(), margins
    # and the pixels are right: close to the simulator's true radiance (box of one pixel)
    x, y = grid.xy_centres()
    e, n = np.meshgrid(x[::9], y[::9])
    sub = got[2, ::9, ::9]
    inside = np.isfinite(sub) & truth.covered(e, n)
    true = truth.radiance_box(e[inside], n[inside], truth.nominal_gsd)[2]  # a sample's size
    assert np.corrcoef(sub[inside], true)[0, 1] > 0.9
    assert not list(out.parent.glob(".*"))


def test_overlap_mean_differs_from_last_only_in_overlaps(rendered, flight, scheduler, tmp_path):
    _, last_ds, renders = rendered
    out = tmp_path / "mean.zarr"
    assert _render(flight, out, "--overlap", "mean", "--wavelengths", "400,1000", scheduler=scheduler) == 0
    mean = xr.open_zarr(out, decode_coords="all")["radiance"].values
    last = last_ds["radiance"].values[[0, 5]]
    count = sum(np.isfinite(r.values[0]).astype(int) for r in renders)
    single = count == 1
    assert (count >= 2).sum() > 100, "the simulated strips should overlap"
    _same(mean[:, single], last[:, single])
    _same(np.isnan(mean), np.isnan(last))
    differ = (mean != last) & (count >= 2)[None]
    assert differ[:, count >= 2].mean() > 0.5
    # where two cubes overlap (and nothing saturated), the mean is their mean
    r0, r1 = [r for r in renders if (np.isfinite(r.values[0]) & (count == 2)).any()][:2]
    both = np.isfinite(r0.values[0]) & np.isfinite(r1.values[0]) & (count == 2) & ~r0.saturated & ~r1.saturated
    pair = (r0.values[[0, 5]][:, both] + r1.values[[0, 5]][:, both]) / 2
    np.testing.assert_allclose(mean[:, both], pair, rtol=1e-6)


def test_cog_and_envi_with_selected_wavelengths(rendered, flight, scheduler, tmp_path):
    _, ds, _ = rendered
    full = ds["radiance"].values
    tif, hdr, png = tmp_path / "m.tif", tmp_path / "m.hdr", tmp_path / "q.png"
    assert _render(flight, tif, "--wavelengths", "550,800", "--quicklook", str(png), scheduler=scheduler) == 0
    with rasterio.open(tif) as cog:
        assert cog.count == 2 and cog.crs.to_epsg() == 32616
        assert tuple(cog.transform)[:6] == tuple(_grid_of(ds).transform)[:6]
        assert cog.descriptions == ("520.0 nm", "760.0 nm")
        assert cog.tags(ns="IMAGE_STRUCTURE")["LAYOUT"] == "COG"
        _same(cog.read(), full[[1, 3]])
    assert png.stat().st_size > 0
    assert _render(flight, hdr, "--wavelengths", "760", scheduler=scheduler) == 0
    text = hdr.read_text()
    assert "wavelength = {760.0000}" in text and "map info = {UTM, 1, 1," in text
    _same(np.fromfile(tmp_path / "m", "<f4").reshape(full[3:4].shape), full[3:4])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m", "m.hdr", "m.hdr.json", "m.tif", "m.tif.json", "q.png"]


def test_subprocess_with_its_own_local_cluster(flight, tmp_path):
    directory, truth = flight
    out = tmp_path / "m.tif"
    done = subprocess.run(
        [sys.executable, "-m", "archive", "render", str(directory), "--fov", str(FOV), "--gsd", "0.5",
         "--out", str(out), "--ground-height", str(truth.ground_height), "--wavelengths", "640", "--quiet"],
        capture_output=True, text=True, timeout=300,
    )
    assert done.returncode == 0, done.stderr
    assert "EPSG:32616" in done.stdout and "1 band (640.0-640.0 nm)" in done.stdout
    with rasterio.open(out) as cog:
        assert cog.res == (0.5, 0.5) and np.isfinite(cog.read(1)).mean() > 0.3


def _with_ground_elevation(directory: Path, tmp: Path, values) -> Path:
    """A copy of the flight whose headers say 'ground elevation = v' (one value per cube; None: no key)."""
    copy = tmp / "flight"
    shutil.copytree(directory, copy)
    for header, value in zip(sorted(copy.glob("*.bil.hdr")), values, strict=True):
        lines = [x for x in header.read_text().splitlines() if not x.lower().startswith("ground elevation")]
        if value is not None:
            lines.append(f"ground elevation = {value}")
        header.write_text("\n".join(lines) + "\n")
    return copy


def _broken_navigation(directory: Path, tmp: Path) -> Path:
    copy = tmp / "broken"
    shutil.copytree(directory, copy)
    next(copy.glob("*.lcf")).unlink()
    return copy


@pytest.mark.parametrize("case", [
    "unknown wavelength", "zero gsd", "negative gsd", "existing output", "absurd gsd",
    "missing navigation", "missing source", "no fov", "bad suffix", "auto ground height",
])
def test_bad_inputs_fail_cleanly(case, flight, tmp_path, capsys):
    directory, truth = flight
    out = tmp_path / "out" / "m.tif"
    src = str(directory)
    extra = {"unknown wavelength": ["--wavelengths", "550,2000"], "zero gsd": ["--gsd", "0"],
             "negative gsd": ["--gsd", "-1"], "absurd gsd": ["--gsd", "1e-5"]}.get(case, [])
    if case == "existing output":
        out.parent.mkdir()
        out.write_bytes(b"keep me")
    if case == "missing navigation":
        src = str(_broken_navigation(directory, tmp_path))
    if case == "auto ground height":
        src = str(_with_ground_elevation(directory, tmp_path, [None] * 4))
    if case == "missing source":
        src = str(tmp_path / "nowhere")
    if case == "bad suffix":
        out = out.with_suffix(".png")
    args = ["render", src, "--out", str(out), "--gsd", str(GSD), "--quiet"]
    if case != "no fov":
        args += ["--fov", str(FOV)]
    if case != "auto ground height":
        args += ["--ground-height", str(truth.ground_height)]
    rc = main(args + extra)
    err = capsys.readouterr().err.strip()
    assert rc != 0
    assert len(err.splitlines()) == 1 and err.startswith("archive render: error:"), err
    expected = {"unknown wavelength": "2000", "zero gsd": "--gsd", "negative gsd": "--gsd",
                "existing output": "--overwrite", "absurd gsd": "--gsd", "missing navigation": ".lcf",
                "missing source": "nowhere", "no fov": "--fov", "bad suffix": ".png",
                "auto ground height": "--ground-height"}[case]
    assert expected in err
    if case == "existing output":
        assert out.read_bytes() == b"keep me"
    else:
        assert not out.parent.exists()  # not even the directory it would have made
    if case == "absurd gsd":
        assert "use --gsd" in err


def _failing_flight(flight, tmp_path: Path) -> tuple[Path, Path]:
    """(directory, failing cube) of a copy of ``flight`` whose last cube fails in its render task, after
    others may have been written: int32 DN beyond 2^24 (float32 cannot hold them exactly), refused by
    the render task only (signed int16 DN, what this used before, are rendered since signed cubes are
    supported)."""
    broken = tmp_path / "flight"
    shutil.copytree(flight[0], broken)
    bil = sorted(broken.glob("*.bil"))[-1]
    dn = np.fromfile(bil, "<u2").astype("<i4")
    dn[100] = 2**25
    dn.tofile(bil)
    header = bil.with_name(bil.name + ".hdr")
    header.write_text(header.read_text().replace("data type = 12", "data type = 3"))
    return broken, bil


def test_failing_render_task_leaves_nothing(flight, scheduler, tmp_path, capsys):
    broken, bil = _failing_flight(flight, tmp_path)
    out = tmp_path / "out" / "m.tif"
    rc = _render((broken, flight[1]), out, "--quicklook", str(tmp_path / "out" / "q.png"), scheduler=scheduler)
    err = capsys.readouterr().err.strip()
    assert rc != 0 and "2^24" in err and bil.stem in err and len(err.splitlines()) == 1, err
    assert not out.parent.exists()


def test_a_cluster_that_does_not_close_after_a_failed_render_keeps_the_renders_error(flight, scheduler, tmp_path,
                                                                                    capsys, monkeypatch):
    """A failed render whose client's close then fails too (Dask's TimeoutError on a loaded machine)
    reports the render's own error and one warning line, and leaves nothing: the close's error used
    to replace the render's, and skipped the removal of the output's temporaries."""
    from archive.run import cluster

    close = cluster.close_client
    closes = []

    def late(client, cluster) -> None:
        close(client, cluster)
        closes.append(client)
        raise TimeoutError("no worker left in time")

    monkeypatch.setattr(cluster, "close_client", late)
    broken, bil = _failing_flight(flight, tmp_path)
    out = tmp_path / "out" / "m.hdr"
    rc = _render((broken, flight[1]), out, scheduler=scheduler)
    err = capsys.readouterr().err.strip().splitlines()
    assert rc != 0 and len(closes) == 1, (rc, err)
    warning = (f"archive render: warning: {out}: the Dask cluster did not close cleanly "
               "(TimeoutError: no worker left in time)")
    assert len(err) == 2 and warning in err, err   # printed while closing, before the error
    (error,) = [line for line in err if line != warning]
    assert "2^24" in error and bil.stem in error, err
    assert not out.parent.exists()


def test_scheduler_without_gpu_workers_is_refused(flight, tmp_path, capsys):
    from distributed import LocalCluster

    out = tmp_path / "new" / "m.zarr"
    with LocalCluster(n_workers=1, processes=False, dashboard_address=":0",
                      silence_logs=logging.ERROR) as cluster:
        rc = _render(flight, out, scheduler=cluster.scheduler_address)
    err = capsys.readouterr().err.strip()
    assert rc != 0 and "GPU" in err and len(err.splitlines()) == 1, err
    assert not out.parent.exists()  # the store it had begun is gone


def test_ground_height_auto_reads_headers(flight, tmp_path):
    from archive.sources.select import resolve_ground_height
    from archive.sources import RawFlightSource

    directory, truth = flight
    nav = NavigationParams()
    assert resolve_ground_height("auto", [RawFlightSource(directory, nav)]) == truth.ground_height
    assert resolve_ground_height("79", [RawFlightSource(directory, nav)]) == 79.0
    copy = _with_ground_elevation(directory, tmp_path, [81.5, 81.5, 90, 81.5])
    with pytest.raises(InputError, match="disagree"):
        resolve_ground_height("auto", [RawFlightSource(copy, nav)])


def test_select_bands(flight):
    from archive.sources.select import select_bands
    from archive.sources import RawFlightSource

    src = RawFlightSource(flight[0], NavigationParams())
    assert select_bands(src) == list(range(6))
    assert select_bands(src, [1000, 400, 410]) == [5, 0]
    assert select_bands(src, None, "2,4") == [2, 4]
    assert select_bands(src, [1170]) == [5]      # 170 nm = 1.42 band widths
    with pytest.raises(InputError, match="no band near 1190"):
        select_bands(src, [1190])
    with pytest.raises(InputError, match="out of range"):
        select_bands(src, None, "6")


@pytest.mark.parametrize("overlap", ["last", "nadir"])
def test_write_graph_and_lazy_arrays_share_their_nodes(flight, tmp_path, overlap):
    """``archive render``'s write graph and ``archive.mosaic``'s lazy arrays build the same lookup,
    render, per-cube layer and rule-key nodes for the same request: their keys are equal (both come
    from :mod:`archive.graph.nodes`), so the two cannot drift apart."""
    import archive
    from archive.api import plan
    from archive.outputs.publish import Output
    from archive.run.pipeline import build_output

    directory, truth = flight
    request = dict(gsd=GSD, fov=FOV, ground_height=truth.ground_height, overlap=overlap, band_group=4)
    output = Output(tmp_path / "m.zarr")
    try:
        _, graph = build_output(plan([directory], **request), output)
        written = set().union(*(dict(d.__dask_graph__()) for d in graph.writes))
    finally:
        output.cleanup()
    lazy = set(dict(archive.mosaic([directory], **request)["radiance"].data.__dask_graph__()))

    def nodes(keys, kind):
        return {k for k in keys if isinstance(k, str) and k.startswith(f"{kind}-")}

    for kind in ("lookup", "render", "mesh", "source"):
        assert nodes(written, kind) and nodes(written, kind) == nodes(lazy, kind), kind
    assert len(nodes(written, "lookup")) == 4 and len(nodes(written, "render")) == 4 * 2
    for kind in ("layers", "key"):   # only the 'nadir' rule compares a layer (the view zenith)
        assert nodes(written, kind) == nodes(lazy, kind) and bool(nodes(lazy, kind)) == (overlap == "nadir"), kind


def test_graph_is_deterministic_and_annotated(flight, tmp_path):
    from archive.graph.build import build_render_graph
    from archive.graph.plan import cube_meshes, plan_render
    from archive.outputs.zarr import MosaicStore
    from archive.overlap import LAST
    from archive.sources import RawFlightSource

    directory, truth = flight
    store = MosaicStore(str(tmp_path / "never-written.zarr"), "radiance")

    def build(bands):
        src = RawFlightSource(directory, NavigationParams())
        plan = plan_render([src], [cube_meshes(src, FOV, truth.ground_height)], [bands], GSD)
        return plan, build_render_graph(plan, [src], store, mode="radiance", overlap=LAST,
                                        mesh_spec=MeshSpec(FOV, truth.ground_height))

    plan, graph = build(list(range(6)))
    _, again = build(list(range(6)))
    _, other = build([0, 1])
    keys = [d.key for d in graph.writes]
    assert keys == [d.key for d in again.writes]
    assert not set(keys) & {d.key for d in other.writes}
    assert not (tmp_path / "never-written.zarr").exists()  # building computes nothing
    assert plan.groups == ((0, 4), (4, 6)) and len(plan.jobs) == 4
    assert graph.renders == 4 * 2
    tiles = len(plan.grid.tiles(1024))
    assert len(graph.writes) == graph.assemblies + tiles - sum(
        1 for r, c, g in plan.grid.tiles(1024)
        if not any(job.window.intersect(g) for job in plan.jobs)) and graph.assemblies <= 2 * tiles
    # what the scheduler is sent: per key annotations of the writes' graph
    from dask.base import collections_to_expr

    expr = collections_to_expr(list(graph.writes)).optimize()
    annotations = expr.__dask_annotations__()
    annotated = {k for k, v in annotations["resources"].items() if v == {"GPU": 1}}
    keys = set(dict(expr.__dask_graph__()))
    renders = {k for k in keys if str(k).startswith("render-")}
    lookups = {k for k in keys if str(k).startswith("lookup-")}
    assert renders and lookups and annotated == renders | lookups
    priority = annotations["priority"]
    tasks = {k for k in keys if str(k).startswith(("lookup-", "render-", "write-", "gate-", "saturated-"))}
    assert tasks and all(isinstance(priority[k], int) for k in tasks)
    # every render has a priority of its own (band group first, then render order)
    assert len({priority[k] for k in renders}) == len(renders)
    assert all(len(d.__dask_graph__().layers) == 1 for d in graph.writes)   # one shared graph, not one per task


def test_mosaic_rules_last_and_mean_with_saturation():
    from archive.graph.tasks import assemble_task
    from archive.overlap import LAST, MEAN

    a = np.full((2, 4, 4), np.nan, np.float32)
    a[:, :, :3] = 1.0
    b = np.full((2, 4, 4), np.nan, np.float32)
    b[:, :, 1:] = 3.0
    sat_a = np.zeros((4, 4), bool)
    sat_b = np.zeros((4, 4), bool)
    sat_b[0, 2] = True  # b is saturated there: the mean leaves it out
    tile = (0, 0, 4, 5)  # the renders cover columns 0-3 of a 5-column tile
    boxes = [(0, 0, 4, 4), (0, 0, 4, 4)]
    last, lsat = assemble_task(LAST, tile, 2, boxes, (a, sat_a), (b, sat_b))
    mean, msat = assemble_task(MEAN, tile, 2, boxes, (a, sat_a), (b, sat_b))
    assert last.shape == (2, 4, 5) and np.isnan(last[:, :, 4]).all()
    np.testing.assert_array_equal(last[0, 1], [1, 3, 3, 3, np.nan])
    np.testing.assert_array_equal(mean[0, 1], [1, 2, 2, 3, np.nan])
    assert mean[0, 0, 2] == 1.0 and last[0, 0, 2] == 3.0
    assert lsat[0, 2] and msat[0, 2] and lsat.sum() == msat.sum() == 1
    # all samples saturated: the mean of the saturated ones, still flagged
    only, osat = assemble_task(MEAN, (0, 0, 4, 4), 2, boxes[:1], (a, np.ones((4, 4), bool)))
    assert only[0, 0, 0] == 1.0 and osat[0, 0]
    # a render offset into the tile lands at its box
    off, _ = assemble_task(LAST, (1024, 0, 10, 10), 2, [(1030, 2, 4, 4)], (a, sat_a))
    assert np.isfinite(off[0, 6:10, 2:5]).all() and np.isfinite(off).sum() == 2 * 12


def test_local_workers_start_with_the_malloc_threshold(monkeypatch):
    """glibc reads MALLOC_MMAP_THRESHOLD_ at process start: the local cluster's worker processes
    must be spawned with it (Dask's pre-spawn environment), and the command's own Dask config is left
    as it was."""
    import os

    import dask
    import distributed  # noqa: F401  (loads Dask's distributed config)

    from archive.run.cluster import MALLOC_MMAP_THRESHOLD, MALLOC_TRIM_THRESHOLD, start_cluster

    before = dict(dask.config.get("distributed.nanny.pre-spawn-environ"))
    # an earlier Dask cluster of this process (here: the session's) left Dask's 64 KiB in the environment
    monkeypatch.setenv("MALLOC_TRIM_THRESHOLD_", str(before.get("MALLOC_TRIM_THRESHOLD_", 65536)))
    client, cluster = start_cluster(None, 1, lambda text: None, threads=2)
    try:
        seen = client.run(lambda: (os.environ.get("MALLOC_MMAP_THRESHOLD_"), os.environ.get("MALLOC_TRIM_THRESHOLD_")))
        assert list(seen.values()) == [(str(MALLOC_MMAP_THRESHOLD), str(MALLOC_TRIM_THRESHOLD))]
        assert all((w.get("resources") or {}).get("GPU") == 2 for w in client.scheduler_info()["workers"].values())
    finally:
        client.close()
        cluster.close()
    assert dict(dask.config.get("distributed.nanny.pre-spawn-environ")) == before


def test_a_cluster_that_does_not_close_in_time_is_a_warning_after_publishing(flight, scheduler, tmp_path, capsys,
                                                                           monkeypatch, rendered):
    """The cluster's close failing once every task ended (Dask's TimeoutError: a worker process still
    alive, seen once with the cores loaded) leaves the published output as it is: exit code 0, one
    warning line, the values those of the same render, no temporary or lock file left."""
    import xarray as xr

    from archive.run import cluster

    join = cluster.ClusterClose.join

    def late(self) -> None:
        join(self)
        raise TimeoutError()

    monkeypatch.setattr(cluster.ClusterClose, "join", late)
    out = tmp_path / "out" / "m.zarr"
    capsys.readouterr()
    assert _render(flight, out, scheduler=scheduler) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "warning" in err[0] and "did not close cleanly (TimeoutError)" in err[0], err
    assert sorted(p.name for p in out.parent.iterdir()) == ["m.zarr", "m.zarr.json"]
    with xr.open_zarr(out) as got:
        np.testing.assert_array_equal(got["radiance"].values, rendered[1]["radiance"].values)
