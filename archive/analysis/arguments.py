"""The parser of ``archive stats`` (registered by :mod:`archive.cli`; argparse only, nothing heavy)."""

from __future__ import annotations

__all__ = ["add_stats"]


def add_stats(sub) -> None:
    """Add the ``stats`` command to ``sub`` (what ``ArgumentParser.add_subparsers`` returned)."""
    p = sub.add_parser("stats", help="per-zone statistics of spectral indices, every flight on one grid", description=(
        "For each zone (field polygon) x flight x index: count, coverage, mean, std, min, p10, median, p90, max "
        "of the index over the zone's pixels, each weighted by the fraction of it inside the zone (exactextract). "
        "Every flight is rendered from its raw lines onto the one grid of the time stack of the flights "
        "(as 'archive render --stack'), only the bands the indices read and only the windows around the zones, "
        "as a Dask graph. From Python: archive.zonal_stats(ids_or_query, zones, indices=[...], ...)."))
    p.add_argument("sources", nargs="*", metavar="SOURCE",
                   help="raw flight directory, or a collection id of --archive (optional with --query-*)")
    p.add_argument("--archive", metavar="ARCHIVE", help="archive holding the collections (SOURCE or --query-*)")
    q = p.add_argument_group("catalog query (flights of --archive, as 'archive render')")
    q.add_argument("--query-bbox", metavar="W,S,E,N", help="flights whose footprint meets this lon/lat box, degrees")
    q.add_argument("--query-datetime", metavar="A/B", help="flights flown in this ISO 8601 range ('..': open end)")
    q.add_argument("--query-wavelength", type=float, metavar="NM", help="flights whose bands cover this wavelength, nm")
    p.add_argument("--zones", required=True, metavar="FIELDS.geojson|.gpkg|.shp",
                   help="zone polygons in any CRS (GeoJSON without one: WGS 84)")
    p.add_argument("--zone-id", metavar="PROP", help="the property naming each zone (default: the feature id, else "
                   "its number in the file)")
    p.add_argument("--index", nargs="+", action="extend", metavar="NAME", default=[],
                   help="spectral indices of the Awesome Spectral Indices catalogue (NDVI, EVI, GNDVI, ...), each "
                        "symbol on the band nearest the centre of its wavelength range")
    p.add_argument("--expression", action="append", metavar="NAME=EXPR", default=[],
                   help="band math, R<nm> the band nearest <nm> nm: 'NDVI2=(R800-R670)/(R800+R670)' (repeatable)")
    p.add_argument("--out", required=True, metavar="TABLE.csv|.parquet", help="the table (Parquet: GeoParquet "
                   "with --geometry)")
    p.add_argument("--geometry", action="store_true", help="keep each zone's geometry (GeoParquet, .parquet only)")
    p.add_argument("--gsd", type=float, metavar="M", help="pixel size of the stack's grid, metres (required unless "
                   "--like gives the grid)")
    p.add_argument("--like", metavar="X.zarr", help="take the grid of an existing stack or output (pixel for pixel)")
    p.add_argument("--fov", type=float, metavar="DEG", help="across-track field of view, degrees (raw sources)")
    p.add_argument("--mode", choices=["raw", "relative", "radiance", "reflectance"], default="reflectance",
                   help="what the indices are computed from (default reflectance: the sky sensor's downwelling "
                        "spectra, or --white-reference)")
    p.add_argument("--white-reference", metavar="FILE", help="white reference (nm, radiance) for --mode reflectance")
    p.add_argument("--ground-height", default="auto", metavar="M|auto", help="flat ground height, m (default auto)")
    p.add_argument("--dem", metavar="FILE", help="a DEM GeoTIFF the meshes follow")
    p.add_argument("--dem-datum", choices=["ellipsoid", "egm96", "egm2008"], default=None,
                   help="vertical datum of the DEM's heights when its CRS declares none")
    p.add_argument("--crs", metavar="EPSG:XXXX", help="the grid's projected CRS (default: the flights' UTM zone)")
    p.add_argument("--overlap", default="last", metavar="last|nadir|mean",
                   help="which line a pixel seen twice in one flight shows (default last)")
    p.add_argument("--scheduler", metavar="ADDRESS", help="a Dask scheduler (tcp://host:8786) whose workers have "
                   "--resources GPU=2; default: a local cluster")
    p.add_argument("--workers", type=int, metavar="N", help="local cluster: worker processes (default 1)")
    p.add_argument("--threads", type=int, metavar="N", help="local cluster: threads per worker (default the cores)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    p.add_argument("--quiet", action="store_true", help="no progress bar")

