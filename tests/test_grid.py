"""The output Grid: snapping, affine, windows, tiles, tokenizing."""

from __future__ import annotations

import numpy as np
import pytest
from dask.base import tokenize

from archive.errors import InputError
from archive.grid import Grid


def test_from_bounds_snaps_outward_to_multiples_of_gsd():
    g = Grid.from_bounds(32616, 500000.013, 3900000.01, 500001.001, 3900000.95, 0.04)
    assert g.x0 == pytest.approx(500000.0)
    assert g.y0 == pytest.approx(3900000.96)
    assert g.width == 26          # 500000.00 .. 500001.04
    assert g.height == 24         # 3900000.00 .. 3900000.96
    w, s, e, n = g.bounds
    assert w <= 500000.013 and e >= 500001.001 and s <= 3900000.01 and n >= 3900000.95
    assert e - 500001.001 < 0.04 and 500000.013 - w < 0.04
    # Bounds already on multiples do not grow by a pixel through float noise.
    g2 = Grid.from_bounds(32616, 0.12, 0.2, 0.4, 0.36, 0.04)
    assert (g2.width, g2.height) == (7, 4)
    assert g2.x0 == pytest.approx(0.12) and g2.y0 == pytest.approx(0.36)


def test_transform_crs_shape_and_centres():
    g = Grid(32616, 0.5, 1000.0, 2000.0, 4, 3)
    t = g.transform
    assert tuple(t)[:6] == (0.5, 0.0, 1000.0, 0.0, -0.5, 2000.0)
    assert t @ (0, 0) == (1000.0, 2000.0)
    assert t @ (4, 3) == (1002.0, 1998.5)
    assert g.shape == (3, 4)
    assert g.crs.to_epsg() == 32616
    x, y = g.xy_centres()
    np.testing.assert_allclose(x, [1000.25, 1000.75, 1001.25, 1001.75])
    np.testing.assert_allclose(y, [1999.75, 1999.25, 1998.75])
    r, c = g.rowcol(x[2], y[1])
    assert (r, c) == (1.5, 2.5)


def test_window_arithmetic():
    g = Grid(32616, 0.5, 1000.0, 2000.0, 10, 8)
    w = g.window(2, 3, 4, 5)
    assert (w.x0, w.y0, w.width, w.height) == (1001.5, 1999.0, 5, 4)
    xs, ys = g.xy_centres()
    wx, wy = w.xy_centres()
    np.testing.assert_allclose(wx, xs[3:8])
    np.testing.assert_allclose(wy, ys[2:6])
    assert w.window(1, 1, 2, 2) == g.window(3, 4, 2, 2)
    with pytest.raises(InputError, match="not inside"):
        g.window(6, 0, 3, 1)
    r0, c0, crop = g.crop(1001.6, 1997.1, 1002.4, 1998.9)
    assert (r0, c0, crop.height, crop.width) == (2, 3, 4, 2)
    assert g.crop(2000.0, 0.0, 2001.0, 1.0) is None
    r0, c0, inter = g.intersect(Grid(32616, 0.5, 999.0, 1999.0, 4, 100))
    assert (r0, c0, inter.width, inter.height) == (2, 0, 2, 6)
    with pytest.raises(InputError, match="aligned"):
        g.intersect(Grid(32616, 0.5, 999.1, 1999.0, 4, 100))


@pytest.mark.parametrize("size", [3, (4, 5), 100])
def test_tiles_cover_every_pixel_once(size):
    g = Grid(32616, 0.04, 500000.0, 3900000.0, 11, 9)
    count = np.zeros(g.shape, int)
    for r0, c0, tile in g.tiles(size):
        count[r0:r0 + tile.height, c0:c0 + tile.width] += 1
        assert tile == g.window(r0, c0, tile.height, tile.width)
        th, tw = (size, size) if isinstance(size, int) else size
        assert r0 % th == 0 and c0 % tw == 0 and tile.height <= th and tile.width <= tw
    assert (count == 1).all()


def test_validation_and_tokenize():
    with pytest.raises(InputError, match="gsd"):
        Grid(32616, 0.0, 0.0, 0.0, 1, 1)
    with pytest.raises(InputError, match="width"):
        Grid(32616, 1.0, 0.0, 0.0, 0, 1)
    with pytest.raises(InputError, match="height"):
        Grid(32616, 1.0, 0.0, 0.0, 1, -2)
    with pytest.raises(InputError, match="inverted"):
        Grid.from_bounds(32616, 1.0, 0.0, 0.0, 1.0, 0.1)
    a = Grid(32616, 0.04, 500000.0, 3900000.0, 11, 9)
    b = Grid(32616, 0.04, 500000.0, 3900000.0, 11, 9)
    assert tokenize(a) == tokenize(b)
    assert hash(a) == hash(b)
    assert tokenize(a) != tokenize(a.window(0, 0, 9, 10))
