"""Every rendered output gets a STAC Item beside it (``<out>.json``, issue 12): valid offline
against the vendored schemas, naming its assets (the provenance sibling too), and holding the
recipe: its command renders the same output again, bit for bit."""

from __future__ import annotations

import json
import shlex

import numpy as np
import pytest
import rasterio

from archive.catalog.validate import validate
from archive.cli import main
from helpers import FOV



@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    from archive.simulator.command import simulate_flight

    directory = tmp_path_factory.mktemp("products") / "flight"
    simulate_flight(directory, cubes=2, bands=5, samples=48, lines=120, cubes_per_pass=2, seed=8)
    return directory


def test_the_item_of_a_render_validates_and_its_recipe_renders_the_same_output(flight, tmp_path):
    out = tmp_path / "first" / "m.tif"
    assert main(["render", str(flight), "--fov", str(FOV), "--gsd", "0.05", "--wavelengths", "550,650",
                 "--overlap", "nadir", "--provenance", "--out", str(out), "--quiet"]) == 0
    item_path = out.with_name("m.tif.json")
    item = json.loads(item_path.read_text())
    assert any("item-spec" in url for url in validate(item_path))
    assert set(item["assets"]) == {"data", "provenance"}
    assert item["assets"]["provenance"]["href"] == "./m_provenance.tif"
    recipe = item["properties"]["archive:recipe"]
    assert recipe["software"]["name"] == "archive"
    words = shlex.split(recipe["command"])
    assert words[:2] == ["archive", "render"] and "--provenance" in words and "nadir" in words
    again = tmp_path / "again" / "m.tif"
    words[words.index("--out") + 1] = str(again)
    assert main(words[1:] + ["--quiet"]) == 0
    for name in ("m.tif", "m_provenance.tif"):
        with rasterio.open(out.with_name(name)) as a, rasterio.open(again.with_name(name)) as b:
            assert np.array_equal(a.read(), b.read(), equal_nan=True), name
            assert a.transform == b.transform and a.crs == b.crs


def test_an_existing_item_is_kept_without_overwrite(flight, tmp_path, capsys):
    out = tmp_path / "m.zarr"
    (tmp_path / "m.zarr.json").write_text("{}")
    assert main(["render", str(flight), "--fov", str(FOV), "--gsd", "0.1", "--out", str(out), "--quiet"]) != 0
    assert "m.zarr.json" in capsys.readouterr().err
    assert (tmp_path / "m.zarr.json").read_text() == "{}"
    assert not out.exists()
    assert main(["render", str(flight), "--fov", str(FOV), "--gsd", "0.1", "--out", str(out), "--quiet",
                 "--overwrite"]) == 0
    assert json.loads((tmp_path / "m.zarr.json").read_text())["assets"]["data"]["href"] == "./m.zarr"
