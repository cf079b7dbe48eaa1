"""Self-calibration: boresight, sync offset and ground height (or a DEM's vertical offset) estimated
from a flight's own overlapping passes (``archive calibrate``; DESIGN 10)."""

from archive.calibrate.estimate import Calibration, calibrate, parse_estimate
from archive.calibrate.model import PARAM_NAMES, FlightModel, Params

__all__ = ["Calibration", "FlightModel", "PARAM_NAMES", "Params", "calibrate", "parse_estimate"]
