"""``archive view``: the archive's flights in a web browser, georectified on the fly.

Modules: ``server`` (the Starlette app, its HTTP API and the command), ``registry`` (which flights
are served), ``jobs`` (what the server asks of its render thread), ``worker`` (the one render
thread, with cancellation of abandoned requests), ``stacks`` and ``residual`` (time stacks and their
co-registration residuals); ``static/`` holds the page and its vendored map library (Leaflet,
BSD-2-Clause). The drawing itself is :mod:`archive.drawing`'s, the tile grids :mod:`archive.grid`'s.
Importing this package imports nothing: import the module you need.
"""
