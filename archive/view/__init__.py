"""``archive view``: the archive's flights in a web browser, georectified on the fly.

Modules: ``server`` (the Starlette app, its HTTP API and the command), ``registry`` (which flights
are served), ``flights`` (one flight's caches; tiles and view statistics drawn by the inverse
renderer), ``geometry`` (its meshes at a ground height), ``point`` (point spectra), ``worker``
(the one render thread, with cancellation of abandoned requests), ``tiles`` (Web-Mercator tile
grids, PNG encoding), ``query`` (request parameters), ``cache`` (byte-bounded LRU caches);
``static/`` holds the page and its vendored map library (Leaflet, BSD-2-Clause). Importing this
package imports nothing: import the module you need.
"""
