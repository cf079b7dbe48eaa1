"""The empirical line (--panels alternative, issue 34): two panels of known reflectance fit a and c
per band; the other homogeneous patches of the simulator's truth come out within 2 %."""

from __future__ import annotations

import json

import numpy as np
import pytest
from pyproj import Transformer

from archive.errors import FormatError, InputError
from archive.graph.plan import cube_meshes
from archive.grid import Grid
from archive.params import NavigationParams
from archive.render.empirical_line import empirical_radiometry, fit_empirical_line, read_panels
from archive.render.renderer import render_cube
from archive.simulator.clouds import truth_reflectance
from archive.simulator.command import simulate_flight
from archive.sources import RawFlightSource
from helpers import FOV

BANDS = 8


def _geojson(path, truth, patches):
    to_ll = Transformer.from_crs(truth.epsg, 4326, always_xy=True)
    features = []
    for p in patches:
        w, s, e, n = p["interior"]
        lon, lat = to_ll.transform([w, e, e, w, w], [s, s, n, n, s])
        refl = truth_reflectance(truth, np.array([(w + e) / 2]), np.array([(s + n) / 2]))[:, 0]
        features.append({"type": "Feature", "geometry": {"type": "Polygon", "coordinates": [list(zip(lon, lat))]},
                         "properties": {"name": p["name"], "reflectance": refl.tolist(),
                                        "wavelengths": [float(w) for w in truth.wavelengths]}})
    path.write_text(json.dumps({"type": "FeatureCollection", "features": features}))
    return path


def test_two_panels_give_reflectance_within_2_percent(tmp_path):
    directory = tmp_path / "flight"
    truth = simulate_flight(directory, cubes=2, bands=BANDS, samples=96, lines=150, seed=0, cubes_per_pass=2)
    source = RawFlightSource(directory, NavigationParams())
    meshes = dict(enumerate(cube_meshes(source, truth.fov_deg, truth.ground_height)))
    patches = truth.homogeneous_patches()
    # the brightest and the darkest patch seen as panels; the others are checked
    level = {p["name"]: float(np.mean(truth_reflectance(truth, np.array([sum(p["interior"][0::2]) / 2]),
                                                        np.array([sum(p["interior"][1::2]) / 2])))) for p in patches}
    ordered = sorted(patches, key=lambda p: level[p["name"]])
    panels = read_panels(_geojson(tmp_path / "panels.geojson", truth, [ordered[0], ordered[-1]]))
    bands = list(range(BANDS))
    line = fit_empirical_line(source, meshes, bands, panels)
    assert line.pixels.min() > 20
    bounds = np.array([m.bounds_utm() for m in meshes.values()])
    grid = Grid.from_bounds(truth.epsg, bounds[:, 0].min(), bounds[:, 1].min(), bounds[:, 2].max(),
                            bounds[:, 3].max(), truth.nominal_gsd)
    x, y = grid.xy_centres()
    xx, yy = np.meshgrid(x, y)
    checked = 0
    for k, mesh in meshes.items():
        r = render_cube(mesh, source.read_bands(k, bands),
                        empirical_radiometry(source.radiometry(k, bands, "radiance"), line, bands), grid)
        for p in ordered[1:-1]:
            w, s, e, n = p["interior"]
            m = 1.5 * grid.gsd
            use = r.covered & (xx > w + m) & (xx < e - m) & (yy > s + m) & (yy < n - m)
            if use.sum() < 10:
                continue
            expected = truth_reflectance(truth, np.array([(w + e) / 2]), np.array([(s + n) / 2]))[:, 0]
            rel = np.median(r.values[:, use], axis=1) / expected - 1
            assert np.all(np.abs(rel) < 0.02), (p["name"], rel)
            checked += 1
    assert checked >= 2
    # the command: --mode reflectance --panels FILE, the fit recorded in the output's Item
    import subprocess
    import sys

    import rasterio

    out = tmp_path / "refl.tif"
    done = subprocess.run([sys.executable, "-m", "archive", "render", str(directory), "--fov", str(FOV), "--gsd",
                           str(grid.gsd), "--mode", "reflectance", "--panels", str(tmp_path / "panels.geojson"),
                           "--out", str(out), "--quiet"], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    record = json.loads(out.with_name(out.name + ".json").read_text())["properties"]["archive:reflectance"]
    assert record["source"] == "panels"
    np.testing.assert_allclose(record["flights"][0]["a"], line.a, rtol=1e-9)
    with rasterio.open(out) as ds:
        values = ds.read()
        t = ds.transform
    ex, ny = np.meshgrid(t.c + (np.arange(values.shape[2]) + 0.5) * t.a, t.f + (np.arange(values.shape[1]) + 0.5) * t.e)
    seen = 0
    for p in ordered[1:-1]:
        w, s, e, n = p["interior"]
        m = 1.5 * grid.gsd
        use = (ex > w + m) & (ex < e - m) & (ny > s + m) & (ny < n - m) & ~np.isnan(values[0])
        if use.sum() < 10:
            continue
        expected = truth_reflectance(truth, np.array([(w + e) / 2]), np.array([(s + n) / 2]))[:, 0]
        assert np.all(np.abs(np.median(values[:, use], axis=1) / expected - 1) < 0.02), p["name"]
        seen += 1
    assert seen >= 2
