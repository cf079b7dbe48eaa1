"""archive: inverse georectification and archiving of airborne pushbroom hyperspectral flights.

The library API (:mod:`archive.api`), imported on first use so that ``import archive`` stays light
(no dask, no OpenGL)::

    arc = archive.open_archive("demo/archive")          # an Archive: .search(bbox=, datetime=, wavelength=)
    ds = archive.mosaic(ids, archive=arc, gsd=0.25)     # a lazy xarray.Dataset
    archive.render(["demo/flight"], "demo/mosaic.zarr", gsd=0.25, fov=47.5)

``archive.render`` is also the name of the GL renderer's package (``archive/render/``): the package
module is made callable, calling :func:`archive.api.render` (see :class:`_CallablePackage`).
"""

from importlib import import_module
from importlib.metadata import PackageNotFoundError, version
from types import ModuleType

try:
    __version__ = version("archive")
except PackageNotFoundError:  # running from a source tree without install
    __version__ = "0.0.0+unknown"

__all__ = ["Archive", "__version__", "mosaic", "open_archive", "render"]

_API = ("Archive", "mosaic", "open_archive")


class _CallablePackage(ModuleType):
    """The ``archive.render`` package, callable as :func:`archive.api.render`.

    Python binds a subpackage to its parent's attribute of the same name whenever the subpackage
    is first imported, so a plain function ``archive.render`` would be replaced by the package as
    soon as anything imports ``archive.render.mesh``. Giving the package module this class keeps
    ``archive.render.renderer`` and ``archive.render(...)`` both working, whatever the import order.
    """

    def __call__(self, *args, **kwargs):
        from archive.api import render

        return render(*args, **kwargs)

    @property
    def __signature__(self):
        import inspect

        from archive.api import render

        return inspect.signature(render)


def _callable_render_package() -> ModuleType:
    package = import_module("archive.render")  # its __init__ imports nothing (no moderngl)
    if not isinstance(package, _CallablePackage):
        package.__class__ = _CallablePackage
    return package


render = _callable_render_package()


def __getattr__(name: str):
    if name in _API:
        from archive import api

        return getattr(api, name)
    raise AttributeError(f"module 'archive' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_API))
