"""Self-calibration: boresight, sync offset and ground height (or a DEM's vertical offset) estimated
from a flight's own overlapping passes (``archive calibrate``; DESIGN 10), and co-registration of a
flight to a reference flight held fixed: its position offset besides (``--reference``; DESIGN 11).

The names below load on first use (the catalog imports :mod:`archive.calibrate.apply` alone)."""

from importlib import import_module

__all__ = ["Calibration", "FlightModel", "PARAM_NAMES", "Params", "calibrate", "coregister", "parse_estimate"]

_WHERE = {"Calibration": "estimate", "calibrate": "estimate", "parse_estimate": "estimate",
          "FlightModel": "model", "PARAM_NAMES": "model", "Params": "model", "coregister": "coregister"}


def __getattr__(name: str):
    if name in _WHERE:
        return getattr(import_module(f"archive.calibrate.{_WHERE[name]}"), name)
    raise AttributeError(f"module 'archive.calibrate' has no attribute {name!r}")
