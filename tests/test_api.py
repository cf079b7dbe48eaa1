"""The library API (``archive.open_archive``, ``archive.mosaic``, ``archive.georectify``) against the CLI.

A small simulated flight (4 cubes in 2 strips, 6 bands, 2 output tiles at 4 cm) rendered by the CLI
into Zarr; the lazy mosaic must give the same float32 values bit for bit, computing one band must
run only its band group's render tasks, and catalog searches must list what ``archive catalog
search`` lists. Real EGL, real Dask (threads in-process, and one spawned LocalCluster).
"""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

import archive
from archive.cli import main
from archive.errors import InputError, OutputExistsError
from helpers import FOV

GSD = 0.04  # 1570 x 780 px: 2 output tiles of 1024 px
DAY = 86400.0


@pytest.fixture(scope="module")
def flight(strips_flight):
    """(directory, Truth) of the shared 4-cube flight in 2 strips, 6 bands (conftest), read only."""
    return strips_flight


@pytest.fixture(scope="module")
def cluster(local_cluster):
    """The session's LocalCluster shaped like the command's own (spawned worker, GPU=2; conftest)."""
    return local_cluster


@pytest.fixture(scope="module")
def cli_zarr(flight, scheduler, tmp_path_factory):
    """The CLI's all-band Zarr mosaic of the flight."""
    out = tmp_path_factory.mktemp("cli") / "mosaic.zarr"
    assert main(["render", str(flight[0]), "--fov", str(FOV), "--gsd", str(GSD), "--out", str(out),
                 "--scheduler", scheduler, "--quiet"]) == 0
    return xr.open_zarr(out, decode_coords="all")


def _bits(a: np.ndarray) -> np.ndarray:
    a = np.ascontiguousarray(a, dtype=np.float32)
    return a.view(np.uint32)


class _Executed:
    """Keys of the tasks the local scheduler runs (a dask callback)."""

    def __init__(self):
        from dask.callbacks import Callback

        self.keys: list = []
        self.callback = Callback(posttask=lambda key, result, dsk, state, worker: self.keys.append(key))

    def __enter__(self):
        self.callback.__enter__()
        return self

    def __exit__(self, *exc):
        self.callback.__exit__(*exc)

    def count(self, prefix: str) -> int:
        return sum(1 for k in self.keys if isinstance(k, str) and k.startswith(prefix))


def test_mosaic_is_lazy_and_equals_the_cli_zarr(flight, cli_zarr):
    directory, truth = flight
    with _Executed() as ran:
        ds = archive.mosaic([directory], gsd=GSD, fov=FOV, ground_height="auto", band_group=4)
    assert ran.keys == []  # building renders nothing
    values = ds["radiance"]
    assert values.dims == ("band", "y", "x") and values.dtype == np.float32
    assert values.data.chunks == ((4, 2), (780,), (1024, 546))  # band groups x output tiles
    assert ds["saturated"].data.chunks == ((780,), (1024, 546))
    assert ds.rio.crs == cli_zarr.rio.crs and ds.rio.crs.to_epsg() == truth.epsg
    assert ds.rio.transform() == cli_zarr.rio.transform()
    for name in ("x", "y", "band", "wavelength"):
        np.testing.assert_array_equal(ds[name].values, cli_zarr[name].values)
    for key in ("mode", "gsd_m", "fov_deg", "ground_height_m", "sync_offset_s", "overlap", "sources"):
        assert ds.attrs[key] == cli_zarr.attrs[key], key
    computed = ds.compute()
    got, expected = computed["radiance"].values, cli_zarr["radiance"].values
    assert np.isfinite(got).mean() > 0.3
    np.testing.assert_array_equal(np.isnan(got), np.isnan(expected))
    np.testing.assert_array_equal(_bits(got), _bits(expected))  # bit for bit, NaN where NaN
    np.testing.assert_array_equal(computed["saturated"].values, cli_zarr["saturated"].values)


def test_one_band_renders_only_its_group(flight, cli_zarr):
    directory, _ = flight
    ds = archive.mosaic(str(directory), gsd=GSD, fov=FOV, band_group=4)
    graph = dict(ds["radiance"].data.__dask_graph__())
    renders = sum(1 for k in graph if str(k).startswith("render-"))
    assert renders == 4 * 2  # 4 cubes x 2 band groups
    with _Executed() as ran:
        band = ds["radiance"].sel(wavelength=880, method="nearest").compute()  # band 4: group 2
    assert band.band.item() == 4 and float(band.wavelength) == 880.0
    assert ran.count("render-") == 4 and ran.count("lookup-") == 4
    np.testing.assert_array_equal(_bits(band.values), _bits(cli_zarr["radiance"].values[4]))
    with _Executed() as ran:
        rgb = ds["radiance"].sel(wavelength=[640, 520, 400], method="nearest").values
    assert ran.count("render-") == 4  # bands 2, 1, 0: the first group only
    np.testing.assert_array_equal(_bits(rgb), _bits(cli_zarr["radiance"].values[[2, 1, 0]]))


def test_render_from_python_writes_what_the_cli_writes(flight, cli_zarr, scheduler, tmp_path):
    directory, _ = flight
    out = tmp_path / "out" / "m.zarr"
    summary = archive.georectify([directory], out, gsd=GSD, fov=FOV, wavelengths=[520, 880], scheduler=scheduler)
    assert summary["out"] == str(out) and summary["bands"] == 2 and summary["wavelengths"] == [520.0, 880.0]
    assert (summary["width"], summary["height"], summary["cubes"]) == (1570, 780, 4)
    assert summary["renders"] == 4 and summary["graph_seconds"] <= summary["seconds"]
    written = xr.open_zarr(out, decode_coords="all")
    assert written.rio.crs == cli_zarr.rio.crs and written.rio.transform() == cli_zarr.rio.transform()
    np.testing.assert_array_equal(_bits(written["radiance"].values), _bits(cli_zarr["radiance"].values[[1, 4]]))
    # the same keywords as the CLI's text, and the same refusal of an existing output
    with pytest.raises(OutputExistsError) as refused:
        archive.georectify(str(directory), out, gsd=GSD, fov=FOV, wavelengths="520,880", scheduler=scheduler)
    assert "overwrite=True" in str(refused.value) and "--overwrite" not in str(refused.value), refused.value
    assert sorted(p.name for p in out.parent.iterdir()) == ["m.zarr", "m.zarr.json"]


def test_bad_keywords_fail_like_the_cli(flight, tmp_path):
    """The CLI's checks, in the caller's words: the function and keyword, not the flag (issue 36)."""
    directory = flight[0]
    with pytest.raises(InputError, match=r"^archive\.mosaic\(fov=\.\.\.\): .*fov=DEG"):
        archive.mosaic([directory], gsd=GSD)
    with pytest.raises(InputError, match="no band near 2000"):
        archive.mosaic([directory], gsd=GSD, fov=FOV, wavelengths=[550, 2000])
    with pytest.raises(InputError, match=r"^archive\.mosaic\(gsd=\.\.\.\)"):
        archive.mosaic([directory], gsd=0, fov=FOV)
    with pytest.raises(InputError, match=r"^archive\.mosaic\(mode=\.\.\.\)"):
        archive.mosaic([directory], gsd=GSD, fov=FOV, mode="dn")
    with pytest.raises(InputError, match=r"^archive\.georectify\(overlap=\.\.\.\)"):
        archive.georectify([directory], tmp_path / "x.zarr", gsd=GSD, fov=FOV, overlap="first")
    assert not (tmp_path / "x.zarr").exists()
    # an error naming a path, whose fix names switches: the switches in Python's words
    (tmp_path / "s.zarr").mkdir()
    with pytest.raises(InputError, match=r"s\.zarr: output exists already \(pass resume=True .* overwrite=True"):
        archive.georectify([directory], tmp_path / "s.zarr", gsd=GSD, fov=FOV, stack=True)


@pytest.fixture(scope="module")
def catalog(flight, tmp_path_factory):
    """An archive of the flight and two copies flown a month and a year later, further east."""
    import shutil

    from archive.formats.flight import discover_flight
    from archive.formats.lcf import read_lcf, write_lcf
    from archive.ingest.command import ingest

    directory = flight[0]
    base = tmp_path_factory.mktemp("catalog")
    flights = [directory]
    for k, (days, east) in enumerate([(30, 0.3), (365, 0.6)]):
        copy = base / f"later-{k}"
        shutil.copytree(directory, copy)
        for c in discover_flight(copy).cubes:
            lcf = read_lcf(c.lcf)
            write_lcf(c.lcf, dataclasses.replace(lcf, time=lcf.time + days * DAY, lon=lcf.lon + east))
        flights.append(copy)
    archive_dir = base / "archive"
    ids = [r.cid for d in flights for r in ingest([str(d)], archive_dir, FOV, progress=False)]
    return archive_dir, ids


def _cli_search(archive_dir: Path, capsys, *args: str) -> list[str]:
    capsys.readouterr()
    assert main(["catalog", "search", "--archive", str(archive_dir), *args, "--json"]) == 0
    return [f["id"] for f in json.loads(capsys.readouterr().out)["features"]]


def test_search_lists_what_catalog_search_lists(catalog, capsys):
    archive_dir, ids = catalog
    arc = archive.open_archive(archive_dir)
    assert isinstance(arc, archive.Archive) and arc.collection_ids() == sorted(ids)
    assert arc.search() == _cli_search(archive_dir, capsys) == ids  # by start time
    everything = (-91.0, 34.0, -88.0, 36.0)
    text = ",".join(map(str, everything))
    assert arc.search(bbox=everything) == arc.search(bbox=text) == _cli_search(archive_dir, capsys, "--bbox", text)
    west = "-90.0,35.0,-89.8,35.3"  # the first flight only
    assert arc.search(bbox=west) == _cli_search(archive_dir, capsys, "--bbox", west) == ids[:1]
    when = "2024-06-01/2024-07-31"
    assert arc.search(datetime=when, wavelength=650) == _cli_search(
        archive_dir, capsys, "--datetime", when, "--wavelength", "650") == ids[:2]
    assert arc.search(bbox=(0, 0, 1, 1)) == _cli_search(archive_dir, capsys, "--bbox", "0,0,1,1") == []
    with pytest.raises(InputError, match=r"^Archive\.search\(bbox=\.\.\.\): expected 4"):
        arc.search(bbox=(1, 2, 3))


def test_mosaic_of_a_collection_equals_the_raw_mosaic(flight, catalog):
    directory = flight[0]
    archive_dir = catalog[0]
    arc = archive.open_archive(archive_dir)
    (cid,) = arc.search(bbox="-90.0,35.0,-89.8,35.3")
    from_archive = archive.mosaic([cid], archive=arc, gsd=GSD, wavelengths=[640])  # fov as ingested
    raw = archive.mosaic([directory], gsd=GSD, fov=FOV, wavelengths="640")
    assert from_archive.attrs["fov_deg"] == FOV
    np.testing.assert_array_equal(_bits(from_archive["radiance"].values), _bits(raw["radiance"].values))


def test_distributed_client_runs_the_mosaic(flight, cli_zarr, cluster):
    import dask
    from distributed import Client
    from distributed.diagnostics.plugin import SchedulerPlugin

    class Annotations(SchedulerPlugin):
        """Resource annotations of the GL tasks as the scheduler receives them."""

        name = "test-api-annotations"

        def __init__(self):
            self.resources = {}

        def update_graph(self, scheduler, *, annotations, **kwargs):
            self.resources.update({str(k): v for k, v in annotations.get("resources", {}).items()})

    seen = Annotations()
    cluster.scheduler.add_plugin(seen)  # the scheduler runs in this process
    directory, _ = flight
    try:
        with Client(cluster.scheduler_address) as client:
            ds = archive.mosaic([directory], gsd=GSD, fov=FOV, wavelengths=[760])
            with dask.config.set({"optimization.fuse.active": False}):  # keeps the GPU annotations
                got = client.compute(ds["radiance"].data).result()
    finally:
        cluster.scheduler.remove_plugin(name=seen.name)
    gl = {k for k in seen.resources if k.startswith(("render-", "lookup-"))}
    assert len(gl) == 4 + 4 and all(seen.resources[k] == {"GPU": 1} for k in gl)
    assert not {k for k in seen.resources if k not in gl}  # nothing else is pinned to the GPU
    np.testing.assert_array_equal(_bits(got), _bits(cli_zarr["radiance"].values[3:4]))


def test_import_archive_stays_light_and_georectify_is_the_library_function():
    """``archive.georectify`` writes outputs; ``archive.render`` is the GL package, a plain module
    (no class swap), whatever the import order."""
    code = ("import sys, types, archive; archive.open_archive; light = not any(m in sys.modules for m in "
            "('dask', 'moderngl', 'xarray')); import archive.render.mesh, archive.render.renderer; "
            "print(light, callable(archive.render), type(archive.render) is types.ModuleType, "
            "archive.render.mesh.__name__, archive.georectify.__module__, archive.mosaic.__module__)")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["True", "False", "True", "archive.render.mesh", "archive.api", "archive.api"]
