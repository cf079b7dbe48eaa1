"""archive: inverse georectification and archiving of airborne pushbroom hyperspectral flights.

The library API (:mod:`archive.api`), imported on first use so that ``import archive`` stays light
(no dask, no OpenGL)::

    arc = archive.open_archive("demo/archive")          # an Archive: .search(bbox=, datetime=, wavelength=)
    ds = archive.mosaic(ids, archive=arc, gsd=0.25)     # a lazy xarray.Dataset
    archive.georectify(["demo/flight"], "demo/mosaic.zarr", gsd=0.25, fov=47.5)   # `archive render`
    da = archive.stack(arc.search(bbox=...), archive=arc, gsd=0.25)   # lazy (time, band, y, x) on one grid
    df = archive.zonal_stats({"bbox": ...}, "fields.geojson", ["NDVI"], archive=arc, gsd=0.25)   # archive stats

``archive.render`` is the GL renderer's package (``archive/render/``), not a function.
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("archive")
except PackageNotFoundError:  # running from a source tree without install
    __version__ = "0.0.0+unknown"

__all__ = ["Archive", "__version__", "georectify", "mosaic", "open_archive", "stack", "zonal_stats"]

_API = ("Archive", "georectify", "mosaic", "open_archive", "stack")


def __getattr__(name: str):
    if name in _API:
        from archive import api

        return getattr(api, name)
    if name == "zonal_stats":   # archive stats (archive/analysis/)
        from archive.analysis.command import zonal_stats

        return zonal_stats
    raise AttributeError(f"module 'archive' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_API) | {"zonal_stats"})
