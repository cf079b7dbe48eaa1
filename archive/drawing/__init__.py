"""The viewer's drawing engine: a flight georectified on the fly by the inverse renderer, for the
viewer (``archive view``), the ingest's previews and the benches. It imports nothing of
:mod:`archive.view` (the server, its registry and its pages use it, never the other way).

Modules: ``flight`` (:class:`~archive.drawing.flight.ViewedFlight`: one viewed flight's caches; tiles and view
statistics), ``placement`` (its meshes at one ground height and sync offset, and small array helpers),
``planes`` (calibrated band planes and their box-filtered levels), ``point`` (the spectrum of one output
pixel), ``query`` (what a view asks: bands, mode, stretch, overlap), ``cache`` (byte-bounded LRU
caches), ``png`` (tile encodings), ``preview_layout`` (the stored overview previews: layout, read,
verify; :mod:`archive.ingest.previews` makes them). The Web-Mercator tile grids are :mod:`archive.grid`'s.
Importing this package imports nothing: import the module you need.
"""
