"""archive: inverse georectification and archiving of airborne pushbroom hyperspectral flights."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("archive")
except PackageNotFoundError:  # running from a source tree without install
    __version__ = "0.0.0+unknown"

__all__ = ["__version__"]
