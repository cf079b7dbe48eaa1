"""Spectral indices for analysis: named ones from the Awesome Spectral Indices catalogue (``spyndex``)
and ``NAME=EXPR`` band math (:mod:`archive.outputs.bandmath`, re-exported here: parsing, binding to a
camera's bands by wavelength, evaluation without ``eval``), and the lazy index of a stack or mosaic
(:func:`stack_index`, the ``.archive.index`` accessor).
"""

from __future__ import annotations

import numpy as np

from archive.outputs.bandmath import (FUNCTIONS, MAX_EXPRESSION, BoundIndex, IndexSpec, band_spacing, bind_indices,
                                      catalogue_names, evaluate, index_env, named_index, nearest_band,
                                      parse_expression, parse_indices, walk_index)

__all__ = ["FUNCTIONS", "MAX_EXPRESSION", "BoundIndex", "IndexSpec", "band_spacing", "bind_indices", "catalogue_names",
           "evaluate", "named_index", "parse_expression", "parse_indices", "stack_index"]


def stack_index(da, index: str):
    """The index ``index`` (a catalogue name, or ``NAME=EXPR``) of a lazy stack or mosaic ``da``
    (``archive.stack``, ``archive.mosaic(...)[variable]``: a DataArray with a ``band`` dimension and
    a ``wavelength`` coordinate, in nm), as a lazy DataArray without the ``band`` dimension (time, y,
    x for a stack), float32, NaN where not finite; named by the index, its band mapping in
    ``attrs["bands"]``. Only the bands the index reads are computed when it is. InputError when
    ``da`` lacks a band the index needs (render the stack with those wavelengths, or all bands)."""
    import xarray as xr

    spec = parse_expression(index) if "=" in str(index) else named_index(str(index))
    nms = np.asarray(da["wavelength"].values, float)
    (bound,) = bind_indices([spec], nms, "the stack")
    env = index_env(bound, lambda nm: da.isel(band=nearest_band(bound, nms, nm)).drop_vars(
        [c for c in da.coords if "band" in da[c].dims], errors="ignore").astype(np.float32))
    with np.errstate(all="ignore"):
        out = xr.DataArray(walk_index(bound, env)).astype(np.float32)
    out = out.where(np.isfinite(out))
    out.name = bound.name
    out.attrs = {"long_name": bound.name, "bands": bound.describe(), "formula": spec.text}
    return out


def register_accessor() -> None:
    """Register ``DataArray.archive`` (once): ``archive.stack(...).archive.index("NDVI")`` is
    :func:`stack_index` of the stack (``archive.stack`` and ``archive.mosaic`` call this)."""
    import xarray as xr

    if hasattr(xr.DataArray, "archive"):
        return

    @xr.register_dataarray_accessor("archive")
    class ArchiveAccessor:
        """What the archive adds to a lazy stack or mosaic variable: ``.archive.index(NAME|NAME=EXPR)``."""

        def __init__(self, da):
            self._da = da

        def index(self, index: str):
            """:func:`stack_index` of this DataArray."""
            return stack_index(self._da, index)
