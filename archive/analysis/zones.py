"""Zones (fields) for zonal statistics: polygons read from GeoJSON, GeoPackage or Shapefile
(GDAL/OGR through ``geopandas``/``pyogrio``), in any CRS, checked and reprojected.

A zone's id (the table's ``zone``) is its ``zone_id`` property when one is named, else the
GeoJSON feature ``id`` (a string id comes as the ``id`` column, an integer one as the feature id),
else the feature's number in the file (its FID: 0, 1, ... for GeoJSON). Ids are text in the table.

Refused, each in one line naming the file and the zone: a file that is not there or not a vector
file, no feature, no CRS (a Shapefile without its ``.prj``), a feature without geometry, empty, not
a (multi)polygon, or invalid (self-intersecting, unclosed: shapely's reason given), a ``zone_id``
property the file has not, two zones with one id.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from archive.errors import InputError, MissingInputError

__all__ = ["SUFFIXES", "Zones", "read_zones"]

#: The zone files read (by suffix).
SUFFIXES = (".geojson", ".json", ".gpkg", ".shp")


@dataclass(frozen=True, eq=False)
class Zones:
    """Checked zones: ``frame`` (a ``geopandas.GeoDataFrame`` in the file's CRS, index 0..n-1) and
    ``ids`` (text, one per row, unique); ``path`` the file read."""

    path: str
    frame: object
    ids: tuple[str, ...]

    def __len__(self) -> int:
        return len(self.ids)

    def in_crs(self, epsg: int):
        """The zones' geometries (a ``geopandas.GeoSeries``) reprojected into EPSG:``epsg`` (pyproj)."""
        return self.frame.geometry.to_crs(epsg=int(epsg))


def read_zones(path: str | os.PathLike, zone_id: str | None = None) -> Zones:
    """The zones of ``path`` (see the module docstring), checked; ``zone_id``: the property that
    names each zone."""
    p = Path(path)
    where = str(path)
    if not p.exists():
        raise MissingInputError(path, "zones file", "give a .geojson, .gpkg or .shp of the fields")
    if p.suffix.lower() not in SUFFIXES:
        raise InputError(where, f"zones are read from {', '.join(SUFFIXES)} files, not {p.suffix or 'this'}",
                         "convert it with ogr2ogr or QGIS")
    import geopandas as gpd
    import shapely

    try:
        frame = gpd.read_file(p, fid_as_index=True)
    except Exception as exc:   # pyogrio's DataSourceError and friends: the file is not what it says
        why = " ".join(str(exc).split())[:200]
        raise InputError(where, f"cannot read the zones: {why}", "check it opens in QGIS or ogrinfo") from None
    if not len(frame):
        raise InputError(where, "holds no zone", "give a file with at least one polygon")
    if frame.crs is None:
        raise InputError(where, "has no coordinate reference system", "add its .prj (Shapefile) or write it with one")
    fids = [str(i) for i in frame.index]
    if zone_id is not None:
        if zone_id not in frame.columns or zone_id == frame.geometry.name:
            props = [c for c in frame.columns if c != frame.geometry.name]
            raise InputError("--zone-id", f"{zone_id!r} is not a property of the zones in {where}",
                             f"its properties: {', '.join(props) or 'none'}")
        ids = [None if v is None or (isinstance(v, float) and v != v) else str(v) for v in frame[zone_id]]
        for fid, v in zip(fids, ids):
            if v is None:
                raise InputError(where, f"zone (feature {fid}) has no {zone_id!r}", "give every zone an id")
    elif "id" in frame.columns and frame["id"].notna().all():
        ids = [str(v) for v in frame["id"]]
    else:
        ids = fids
    seen: dict[str, int] = {}
    for k, zid in enumerate(ids):
        if zid in seen:
            raise InputError(where, f"two zones are named {zid!r} (features {fids[seen[zid]]} and {fids[k]})",
                             "give each zone its own id, or name the property with --zone-id")
        seen[zid] = k
    for zid, geom in zip(ids, frame.geometry):
        if geom is None or geom.is_empty:
            raise InputError(where, f"zone {zid} has no geometry", "remove it or draw its polygon")
        if geom.geom_type not in ("Polygon", "MultiPolygon"):
            raise InputError(where, f"zone {zid} is a {geom.geom_type}, not a polygon",
                             "zones are polygons (buffer points or lines first)")
        if not geom.is_valid:
            raise InputError(where, f"zone {zid} has an invalid geometry ({shapely.is_valid_reason(geom)})",
                             "repair it (QGIS 'Fix geometries', shapely.make_valid)")
    frame = frame.reset_index(drop=True)
    return Zones(where, frame, tuple(ids))
