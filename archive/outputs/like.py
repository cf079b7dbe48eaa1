"""The grid of an existing output (``--like FILE``): :func:`read_grid`, metadata only."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

from archive.errors import InputError, MissingInputError
from archive.grid import Grid

__all__ = ["read_grid"]

_FIX = "give a .zarr, .tif or .hdr written by 'archive render'"


def read_grid(path) -> Grid:
    """The grid of an existing output (``--like``): a ``.zarr`` store written by ``archive render``
    (a mosaic or a stack: its ``archive_grid`` attribute, else its GeoZarr ``proj:code`` and
    ``spatial:transform``/``spatial:shape``), a GeoTIFF ``.tif`` or an ENVI ``.hdr`` (its data file
    beside it) with a projected CRS, north up and square pixels. Reads metadata only;
    :class:`~archive.errors.InputError` naming the file when it is none of these."""
    path = Path(os.fspath(path))
    if not path.exists():
        raise MissingInputError(path, "output to take the grid of (--like)")
    suffix = path.suffix.lower()
    fix = _FIX
    if suffix == ".zarr":
        import zarr

        try:
            attrs = dict(zarr.open_group(path, mode="r").attrs)
        except Exception as exc:  # noqa: BLE001 - any unreadable store is the same user error
            raise InputError("--like", f"{path} is not a readable Zarr store ({type(exc).__name__})", fix) from None
        if "archive_grid" in attrs:
            try:
                return Grid(**json.loads(attrs["archive_grid"]))
            except (TypeError, ValueError) as exc:
                raise InputError("--like", f"{path}: unreadable archive_grid attribute ({exc})", fix) from None
        code, transform, shape = attrs.get("proj:code"), attrs.get("spatial:transform"), attrs.get("spatial:shape")
        if not (code and transform and shape):
            raise InputError("--like", f"{path} has no grid (no archive_grid, proj:code or spatial:transform "
                             "attributes): not an output of 'archive render'", fix)
        return _grid_of(path, code, transform, shape)
    if suffix in (".tif", ".tiff", ".hdr"):
        import rasterio

        data = path.with_suffix("") if suffix == ".hdr" else path
        try:
            with rasterio.open(data) as ds:
                crs, transform, shape = ds.crs, ds.transform, (ds.height, ds.width)
        except rasterio.errors.RasterioIOError as exc:
            raise InputError("--like", f"{path} is not a readable raster ({' '.join(str(exc).split())})", fix) from None
        if crs is None:
            raise InputError("--like", f"{path} has no CRS", fix)
        epsg = crs.to_epsg()
        if epsg is None:
            raise InputError("--like", f"{path} has a CRS without an EPSG code ({crs.to_string()[:60]})",
                             "give an output in a projected CRS with an EPSG code")
        return _grid_of(path, f"EPSG:{epsg}", list(transform)[:6], shape)
    raise InputError("--like", f"{path} is not an output (.zarr, .tif or .hdr)", fix)


def _grid_of(path, code: str, transform, shape) -> Grid:
    """A :class:`Grid` from a CRS code and a rasterio affine [a, b, c, d, e, f]; InputError unless
    north-up, square pixels, in a projected CRS in metres."""
    from archive.geometry.navigation import projected_epsg

    a, b, c, d, e, f = (float(v) for v in transform)
    if b != 0 or d != 0 or a <= 0 or not math.isclose(-e, a, rel_tol=1e-9):
        raise InputError("--like", f"{path} is not north-up with square pixels (transform {a:g}, {b:g}, {d:g}, "
                         f"{e:g})", "give an output written by 'archive render'")
    try:
        epsg = projected_epsg(code)
    except InputError as exc:
        raise InputError("--like", f"{path}: {exc.problem}", _FIX) from None
    return Grid(epsg, a, c, f, int(shape[1]), int(shape[0]))
