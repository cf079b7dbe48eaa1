"""The Web-Mercator tile grid (:mod:`archive.grid`): tiles against the slippy-map formulas projected by
PROJ (an independent path), and :meth:`Grid.coarsened` as the previews' pyramid steps it."""

from __future__ import annotations

import math

import numpy as np
import pytest

from archive.errors import InputError
from archive.grid import HALF_WORLD, Grid, tile_grid, zoom_gsd


def _slippy_corner(z: int, x: int, y: int) -> tuple[float, float]:
    """Lon, lat (degrees) of the north-west corner of tile z/x/y (OpenStreetMap's formulas)."""
    n = 2.0**z
    return x / n * 360.0 - 180.0, math.degrees(math.atan(math.sinh(math.pi * (1 - 2 * y / n))))


@pytest.mark.parametrize("z, x, y", [(0, 0, 0), (3, 5, 2), (12, 2170, 1400), (17, 70124, 45011), (21, 1123456, 720001)])
def test_tile_grid_is_the_slippy_map_tile(z, x, y):
    from pyproj import Transformer

    to_mercator = Transformer.from_crs(4326, 3857, always_xy=True)
    grid = tile_grid(z, x, y)
    west, north = to_mercator.transform(*_slippy_corner(z, x, y))
    east, south = to_mercator.transform(*_slippy_corner(z, x + 1, y + 1))
    assert (grid.epsg, grid.width, grid.height) == (3857, 256, 256)
    tol = 1e-6 * 2 * HALF_WORLD / 2**z   # a millionth of a tile
    assert np.allclose(grid.bounds, (west, south, east, north), rtol=0, atol=max(tol, 1e-6))
    assert grid.gsd == zoom_gsd(z) and math.isclose(grid.gsd * 256, (east - west), rel_tol=1e-9)


def test_tile_grid_refuses_tiles_that_do_not_exist():
    for z, x, y in ((31, 0, 0), (-1, 0, 0), (2, 4, 0), (2, 0, -1)):
        with pytest.raises(InputError):
            tile_grid(z, x, y)
    with pytest.raises(InputError):
        tile_grid(2, 1.5, 0)


def test_coarsened_steps_the_previews_pyramid():
    from archive.drawing.preview_layout import PreviewLevel

    for level in (PreviewLevel(15, 1001, 777, 300, 41), PreviewLevel(9, 2, 3, 1, 1), PreviewLevel(12, 1000, 600, 64, 64)):
        coarse = level.grid().coarsened(2, origin=(-HALF_WORLD, HALF_WORLD))
        assert coarse == level.parent().grid()
    utm = Grid(32632, 0.5, 1000.25, 5000.0, 7, 3)
    c = utm.coarsened(4)   # edges on multiples of 2 m: covers 1000.25..1003.75 x 4998.5..5000
    assert (c.gsd, c.x0, c.y0, c.width, c.height) == (2.0, 1000.0, 5000.0, 2, 1)
    assert utm.coarsened(1) == Grid(32632, 0.5, 1000.0, 5000.0, 8, 3)
    with pytest.raises(InputError):
        utm.coarsened(0)
