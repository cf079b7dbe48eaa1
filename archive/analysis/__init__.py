"""Analysis of the archive's flights on one grid: spectral indices and per-zone statistics.

- :mod:`archive.analysis.indices`: named indices of the Awesome Spectral Indices catalogue
  (``spyndex``) mapped to the camera's bands by wavelength, and ``NAME=EXPR`` band math
  (``R<nm>``: the band nearest ``<nm>``), parsed into a whitelist of arithmetic (no ``eval``).
- :mod:`archive.analysis.zones`: zone polygons read (GeoJSON, GeoPackage, Shapefile), checked and
  reprojected onto the stack's grid.
- :mod:`archive.analysis.zonal`: zone x flight x index statistics on the time stack's one grid,
  pixels weighted by the fraction of them inside the zone (``exactextract``), as a Dask graph
  (``archive stats``, ``archive.zonal_stats``).

Importing this package imports nothing heavy (no dask, no GL): the command line's parser lives in
:mod:`archive.analysis.arguments`.
"""
