"""Flight sources: the one reading interface the renderer, the catalog and the graph use.

- :mod:`~archive.sources.base`: the :class:`FlightSource` protocol, :class:`CubeInfo`,
  :class:`Radiometry`, the one radiometry function;
- :mod:`~archive.sources.navigation`: line times, the navigation tolerance rule and poses, for
  every source;
- :mod:`~archive.sources.raw`, :mod:`~archive.sources.collection`, :mod:`~archive.sources.memory`:
  the implementations;
- :func:`open_source`: a directory or a collection id of an archive -> a source.
"""

from archive.sources.base import MODES, CubeInfo, FlightSource, Radiometry, radiometry_for
from archive.sources.collection import CollectionSource
from archive.sources.memory import MemoryFlightSource
from archive.sources.navigation import NAV_TOLERANCE, SYNC_TOLERANCE, FlightNavigation
from archive.sources.open import open_source
from archive.sources.raw import RawFlightSource

__all__ = ["MODES", "NAV_TOLERANCE", "SYNC_TOLERANCE", "CollectionSource", "CubeInfo", "FlightNavigation",
           "FlightSource", "MemoryFlightSource", "Radiometry", "RawFlightSource", "open_source", "radiometry_for"]
