"""The STAC Item of a rendered output: a sidecar ``<out>.json`` saying what the output is and how
to make it again.

The Item (STAC 1.1.0; extensions projection v2.0.0, raster v1.1.0, eo v1.1.0, processing v1.2.0,
zarr v1.0.0 for a Zarr output; valid against the schemas vendored in ``catalogs/schemas/``) holds:

- ``geometry``/``bbox``: the output grid's bounds reprojected to lon/lat (degrees), edges densified;
- properties: ``datetime`` (= ``start_datetime``, the first line) and ``end_datetime`` (the last),
  ``gsd`` (m), the grid (``proj:code`` ``EPSG:<n>``, ``proj:bbox`` west, south, east, north in CRS
  metres, ``proj:shape`` [rows, cols], ``proj:transform`` the affine [a, b, c, d, e, f] of pixel
  corners), ``eo:bands``, ``processing:*`` (level by variable, lineage, software, datetime), the
  processing attributes as ``archive:<name>`` (mode, gsd_m, fov_deg, ground_height_m or dem,
  sync_offset_s, overlap, sources...), ``archive:source_bands``/``archive:wavelengths`` (nm), and
  ``archive:recipe``: {command, request, sources, software {name, version}}, the one command that
  renders the same output again;
- assets, hrefs relative to the Item file: ``data`` (the COG, the ENVI data file, or the Zarr
  store) with ``proj:*``, ``raster:bands`` (float32, nodata NaN, unit :data:`UNITS`, scale 1,
  offset 0) and ``eo:bands`` on it so that a loader reads it without looking further (odc-stac
  names its bands by the eo:bands names ``b<source band>``); ``header`` (ENVI ``.hdr``);
  ``provenance`` (the sibling provenance raster, when there is one: a Zarr output keeps its
  provenance layers as variables of the same store, then listed in ``archive:provenance`` only); for
  a Zarr v2 output also ``<variable>``, the values array as GDAL's Zarr driver opens it, with the
  same projection and raster fields and the eo:bands (which the store asset then leaves out, so
  that odc-stac's aliases name one asset: :meth:`archive.outputs.zarr.ZarrFormat.stac_assets`);
- a time stack's Item (:func:`stack_item`) adds the datacube fields and its flights.

Processing levels: ``L1A`` orthorectified DN (modes raw and relative), ``L1B`` orthorectified
radiance, ``L2A`` orthorectified reflectance (collections themselves are ``L0``).

Loaders (docs/ecosystem.md, whose recipes tests/test_ecosystem.py runs): odc-stac opens the COG
and a Zarr v2 output or stack (its ``<variable>`` asset) from the Item as they are. ENVI has no
registered media type (``image/x-envi``); GDAL finds the header beside the data file only when it
may list the folder, which odc-stac forbids by default, so call
``odc.stac.configure_rio(GDAL_DISABLE_READDIR_ON_OPEN="FALSE")`` first. xarray opens a Zarr output,
v2 or v3, from the ``data`` asset: ``xr.open_zarr(href)``, CRS included (rioxarray).
"""

from __future__ import annotations

import dataclasses
import math
import os
import shlex
from collections.abc import Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from archive import storage
from archive.catalog.stac import (EO_EXTENSION, PROCESSING_EXTENSION, PROJECTION_EXTENSION, RASTER_EXTENSION,
                                  STAC_VERSION, ZARR_EXTENSION, eo_bands, rfc3339, software_version, write_item)
from archive.errors import InputError, MissingInputError
from archive.overlap import OverlapRule

COG_MEDIA_TYPE = "image/tiff; application=geotiff; profile=cloud-optimized"
GEOTIFF_MEDIA_TYPE = "image/tiff; application=geotiff"
TEXT_MEDIA_TYPE = "text/plain"
#: ENVI has no registered media type: an unregistered image type, so that loaders which go by the
#: media type (odc-stac: image/* is raster) take the data file, whose header GDAL finds beside it.
ENVI_MEDIA_TYPE = "image/x-envi"
#: processing:level of a rendered output, by its data variable.
LEVELS = {"dn": "L1A", "relative": "L1A", "radiance": "L1B", "reflectance": "L2A"}
#: Units of each data variable, UDUNITS strings: the CF ``units`` of the Zarr variable, GDAL's band
#: unit type of every output and the ``raster:bands`` unit of its Item (an output's ``units``
#: attribute overrides it). Counts and ratios "1"; radiance in the units of Resonon's calibration
#: files (.icp), microflicks (uW cm-2 sr-1 um-1 = 1e-5 W m-2 sr-1 nm-1).
UNITS = {"dn": "1", "relative": "1", "reflectance": "1", "radiance": "uW cm-2 sr-1 um-1"}
# Variables of a Zarr output that are not provenance layers.
_NOT_PROVENANCE = {"x", "y", "band", "wavelength", "fwhm", "spatial_ref", "saturated"}


def product_item_path(out: str | os.PathLike) -> Path:
    """Where the Item of output ``out`` goes: ``<out>.json`` beside it (``mosaic.tif.json``,
    ``mosaic.zarr.json``, ``mosaic.hdr.json``)."""
    out = Path(out)
    return out.with_name(out.name + ".json")


def grid_footprint(grid, points_per_edge: int = 21) -> tuple[dict, list[float]]:
    """(GeoJSON Polygon, bbox [west, south, east, north]) in lon/lat degrees of a grid's bounds
    (:class:`archive.grid.Grid`): each edge densified to ``points_per_edge`` points before the
    reprojection, the ring counter-clockwise (RFC 7946) and closed. Grids across the antimeridian
    are not handled."""
    from pyproj import Transformer

    w, s, e, n = grid.bounds
    t = np.linspace(0.0, 1.0, points_per_edge, endpoint=False)
    x = np.concatenate([w + (e - w) * t, np.full_like(t, e), e - (e - w) * t, np.full_like(t, w)])
    y = np.concatenate([np.full_like(t, s), s + (n - s) * t, np.full_like(t, n), n - (n - s) * t])
    lon, lat = Transformer.from_crs(int(grid.epsg), 4326, always_xy=True).transform(x, y)
    lon, lat = np.asarray(lon, float), np.asarray(lat, float)
    if not (np.isfinite(lon).all() and np.isfinite(lat).all()):
        raise InputError("grid", f"its bounds {grid.bounds} in EPSG:{grid.epsg} do not map to longitude/latitude")
    ring = [[round(float(a), 9), round(float(b), 9)] for a, b in zip(lon, lat, strict=True)]
    ring.append(ring[0])
    bbox = [round(float(lon.min()), 9), round(float(lat.min()), 9), round(float(lon.max()), 9),
            round(float(lat.max()), 9)]
    return {"type": "Polygon", "coordinates": [ring]}, bbox


def _href(target: Path, item_dir: Path) -> str:
    """``target`` relative to the Item's folder, POSIX separators, './' first."""
    rel = Path(os.path.relpath(Path(target).absolute(), Path(item_dir).absolute())).as_posix()
    return rel if rel.startswith("../") else "./" + rel


def _jsonable(value: Any) -> Any:
    """Plain JSON values of a request or attributes: tuples as lists, paths as text, numpy scalars
    as numbers, NaN/inf as null, dataclasses as dicts."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        value = {f.name: getattr(value, f.name) for f in dataclasses.fields(value)}
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if value is None or isinstance(value, str | int | float | bool):
        return value
    return str(value)


def _grid_fields(grid) -> dict:
    return {"proj:code": f"EPSG:{int(grid.epsg)}", "proj:bbox": [float(v) for v in grid.bounds],
            "proj:shape": [int(grid.height), int(grid.width)],
            "proj:transform": [float(v) for v in tuple(grid.transform)[:6]]}


def _raster_file_bands(path: Path) -> tuple[list[dict], list[str]]:
    """raster:bands and band descriptions of a raster file, read from it (rasterio)."""
    import rasterio

    try:
        with rasterio.open(path) as ds:
            bands = []
            for b in range(ds.count):
                band: dict[str, Any] = {"data_type": str(ds.dtypes[b])}
                if ds.nodata is not None:
                    band["nodata"] = "nan" if math.isnan(ds.nodata) else float(ds.nodata)
                if ds.units and ds.units[b]:
                    band["unit"] = ds.units[b]
                bands.append(band)
            names = [d or f"band {b + 1}" for b, d in enumerate(ds.descriptions)]
    except rasterio.errors.RasterioIOError as exc:
        raise InputError(path, f"not a readable raster: {exc}", "give the provenance file the render wrote") from exc
    return bands, names


def _zarr_layers(store: Path, variable: str) -> list[dict]:
    """The provenance layers kept in a Zarr output: [{name, units}] of its other variables."""
    import zarr

    group = zarr.open_group(store, mode="r")
    layers = []
    for name, array in sorted(group.arrays()):
        if name in _NOT_PROVENANCE or name == variable:
            continue
        units = array.attrs.get("units")
        layers.append({"name": name, **({"units": str(units)} if units is not None else {})})
    return layers


def _describe_layers(variable: str):
    """``describe(path)`` for :meth:`~archive.outputs.base.OutputFormat.provenance_assets`: (raster:bands,
    layer names) of a provenance raster file, read from it; (None, layer names) of a Zarr store."""
    def describe(path: Path) -> tuple[list[dict] | None, list[str]]:
        if Path(path).is_dir():
            return None, [layer["name"] for layer in _zarr_layers(path, variable)]
        return _raster_file_bands(path)
    return describe


def _provenance(provenance: Path, out: Path, fmt, variable: str, grid, item_dir: Path
                ) -> tuple[dict[str, dict], dict]:
    """(assets, properties) describing the provenance layers of an output of format ``fmt``."""
    provenance = Path(provenance)
    if not provenance.exists():
        raise MissingInputError(provenance, "provenance output")
    if provenance.absolute() == out.absolute():   # the layers are variables of the output (Zarr)
        return {}, {"archive:provenance": {"asset": "data", "layers": _zarr_layers(out, variable)}}
    if provenance.suffix not in fmt.suffixes:
        raise InputError(provenance, f"not a provenance output of a {fmt.label} output",
                         f"give the {'/'.join(fmt.suffixes)} provenance file the render wrote")
    return fmt.provenance_assets(provenance, lambda path: _href(path, item_dir), _grid_fields(grid),
                                 _describe_layers(variable)), {}


def product_item(out: str | os.PathLike, *, fmt, grid, band_indices: Sequence[int],
                 wavelengths: Sequence[float] | None, fwhm: Sequence[float] | None, variable: str, attrs: dict,
                 start: datetime, end: datetime, sources: Sequence[str], command: str, request: dict,
                 provenance: str | os.PathLike | None = None, created: datetime | None = None) -> dict:
    """The STAC Item (a dict) of the output written at ``out`` (see the module docstring).

    out: the final output path, ``.zarr`` store, ``.tif`` COG or ENVI ``.hdr`` (its data file is
    ``out`` without ``.hdr``); fmt: its format (:class:`archive.outputs.base.OutputFormat`, as
    :func:`archive.outputs.registry.output_format` gives it: it builds the format's assets); grid: the output
    :class:`archive.grid.Grid`; band_indices: source band (0-based) of each output band;
    wavelengths, fwhm: nm per output band, or None; variable: the data variable ('radiance',
    'dn'...); attrs: the output's processing attributes; start, end: UTC times of its first and
    last line; sources: the flights (directories or collection ids); command: the shell command
    that renders it again (:func:`render_command`); request: the render request (JSON-able dict,
    or the request dataclass); provenance: the provenance output (a sibling ``.tif``/``.hdr``, or
    ``out`` itself for a Zarr output holding the layers); created: when it was made (default now).
    The Item is meant to be written to :func:`product_item_path` (``write_product_item``).
    """
    out = Path(out)
    if not callable(getattr(fmt, "stac_assets", None)):
        raise InputError(out, f"unknown output format {fmt!r}",
                         "pass the output's format object (archive.outputs.registry.output_format(out))")
    nb = len(band_indices)
    for name, values in (("wavelengths", wavelengths), ("fwhm", fwhm)):
        if values is not None and len(values) != nb:
            raise InputError(out, f"{len(values)} {name} for {nb} bands")
    if nb == 0:
        raise InputError(out, "an output has at least one band")
    item_dir = out.absolute().parent
    created = (created or datetime.now(UTC)).astimezone(UTC)
    version = software_version()
    geometry, bbox = grid_footprint(grid)
    grid_fields = _grid_fields(grid)
    unit = str(attrs.get("units") or UNITS.get(variable, ""))
    raster_bands = [{"data_type": "float32", "nodata": "nan", "sampling": "area", "scale": 1.0, "offset": 0.0,
                     "spatial_resolution": float(grid.gsd), **({"unit": unit} if unit else {})}
                    for _ in range(nb)]
    bands_eo = None if wavelengths is None else eo_bands(wavelengths, fwhm, [f"b{int(i)}" for i in band_indices])
    data: dict[str, Any] = {"roles": ["data"], **grid_fields, "raster:bands": raster_bands}
    if bands_eo is not None:
        data["eo:bands"] = bands_eo
    assets: dict[str, dict] = fmt.stac_assets(out, lambda path: _href(path, item_dir), variable, data)
    props: dict[str, Any] = {f"archive:{k}": _jsonable(v) for k, v in (attrs or {}).items()}
    props.update({
        "datetime": rfc3339(start),
        "start_datetime": rfc3339(start),
        "end_datetime": rfc3339(end),
        "created": rfc3339(created),
        "gsd": float(grid.gsd),
        **grid_fields,
        "processing:level": LEVELS.get(variable, "L1"),
        "processing:lineage": f"{variable} of {len(sources)} flight{'s' if len(sources) != 1 else ''} orthorectified "
                              f"onto EPSG:{int(grid.epsg)} at {float(grid.gsd):g} m by inverse (mesh + OpenGL) "
                              "georectification; archive:recipe.command renders it again",
        "processing:software": {"archive": version},
        "processing:datetime": rfc3339(created),
        "archive:format": fmt.name,
        "archive:variable": variable,
        "archive:source_bands": [int(i) for i in band_indices],
        "archive:recipe": {"command": str(command), "request": _jsonable(request),
                           "sources": [str(s) for s in sources],
                           "software": {"name": "archive", "version": version}},
    })
    if wavelengths is not None:
        props["archive:wavelengths"] = [float(w) for w in wavelengths]
        props["eo:bands"] = [dict(b) for b in bands_eo]
    if provenance is not None:
        more_assets, more_props = _provenance(Path(provenance), out, fmt, variable, grid, item_dir)
        assets.update(more_assets)
        props.update(more_props)
    zarr = any(k.startswith("zarr:") for asset in assets.values() for k in asset)
    extensions = [PROJECTION_EXTENSION, RASTER_EXTENSION, *([EO_EXTENSION] if bands_eo else []),
                  PROCESSING_EXTENSION, *([ZARR_EXTENSION] if zarr else [])]
    return {
        "type": "Feature",
        "stac_version": STAC_VERSION,
        "stac_extensions": extensions,
        "id": out.name,
        "geometry": geometry,
        "bbox": bbox,
        "properties": props,
        "links": [],
        "assets": assets,
    }


#: The datacube extension a stack's Item declares when its schema is vendored (else its ``cube:*``
#: fields stand as additional properties: valid STAC either way).
DATACUBE_EXTENSION = "https://stac-extensions.github.io/datacube/v2.2.0/schema.json"


def stack_item(out: str | os.PathLike, *, fmt, grid, band_indices: Sequence[int],
               wavelengths: Sequence[float] | None, fwhm: Sequence[float] | None, variable: str, attrs: dict,
               flights: Sequence[dict], command: str, request) -> dict:
    """The STAC Item (a dict) of a time stack at ``out`` (a Zarr store whose ``variable`` is (time,
    band, y, x), one time step per flight): :func:`product_item` of its grid and bands over the time
    span of its flights, plus the datacube extension's ``cube:dimensions`` / ``cube:variables`` and
    ``archive:stack`` (the flights).

    flights: per time step, in order, the flight's record (``id``, ``source``, ``start``, ``end``:
    ISO 8601 UTC, and its processing attributes; :meth:`archive.outputs.stack.StackFlight.to_dict`);
    the other arguments as :func:`product_item`'s. The GDAL asset ``<variable>`` (a Zarr v2 stack) is
    one raster of time x band bands, time-major (band ``t * bands + b + 1`` = time step ``t``, band
    ``b``): its ``raster:bands`` and ``eo:bands`` list them all, the ``eo:bands`` names
    ``b<source band>_t<time step>`` (odc-stac's band aliases)."""
    from archive.catalog.validate import vendored_schemas

    flights = [dict(f) for f in flights]
    if not flights:
        raise InputError(out, "a stack has at least one time step")
    start = datetime.fromisoformat(min(f["start"] for f in flights).replace("Z", "+00:00"))
    end = datetime.fromisoformat(max(f["end"] for f in flights).replace("Z", "+00:00"))
    sources = [str(f.get("source", f["id"])) for f in flights]
    item = product_item(out, fmt=fmt, grid=grid, band_indices=band_indices, wavelengths=wavelengths, fwhm=fwhm,
                        variable=variable, attrs=attrs, start=start, end=end, sources=sources, command=command,
                        request=request)
    steps = len(flights)
    dims = "time, band, y, x"
    data = item["assets"]["data"]
    data["title"] = data["title"].replace("(band, y, x)", f"({dims})")
    raster = item["assets"].get(variable)
    if raster is not None:
        raster["title"] = (f"{variable} ({dims}) as one raster of {steps} x {len(band_indices)} bands, time-major "
                           "(GDAL's Zarr driver: rasterio, odc-stac, QGIS)")
        raster["raster:bands"] = [dict(b) for _ in range(steps) for b in raster["raster:bands"]]
        if "eo:bands" in raster:
            raster["eo:bands"] = [{**b, "name": f"{b['name']}_t{t}"} for t in range(steps) for b in raster["eo:bands"]]
    w, s, e, n = grid.bounds
    props = item["properties"]
    props["cube:dimensions"] = {
        "time": {"type": "temporal", "extent": [flights[0]["start"], flights[-1]["start"]],
                 "values": [f["start"] for f in flights]},
        "band": {"type": "bands", "values": [f"b{int(b)}" for b in band_indices]},
        "y": {"type": "spatial", "axis": "y", "extent": [s, n], "step": -grid.gsd, "reference_system": grid.epsg},
        "x": {"type": "spatial", "axis": "x", "extent": [w, e], "step": grid.gsd, "reference_system": grid.epsg},
    }
    props["cube:variables"] = {
        variable: {"type": "data", "dimensions": ["time", "band", "y", "x"],
                   "description": f"{variable} of each flight on the stack's grid, NaN where it has no line"},
        "saturated": {"type": "auxiliary", "dimensions": ["time", "y", "x"]},
        "flight": {"type": "auxiliary", "dimensions": ["time"], "values": [f["id"] for f in flights]},
    }
    props["archive:stack"] = {"flights": flights}
    if DATACUBE_EXTENSION in vendored_schemas():
        item["stac_extensions"].append(DATACUBE_EXTENSION)
    return item


def write_product_item(out: str | os.PathLike, item: dict) -> Path:
    """Write ``item`` to :func:`product_item_path` of ``out`` (temporary name, then rename)."""
    return write_item(product_item_path(out), item)


# ---------------------------------------------------------------------------------------------
# The command that renders an output again
# ---------------------------------------------------------------------------------------------
#: Request fields that name files: made absolute, so that the command works from any folder.
_PATH_FIELDS = ("archive", "calibration", "white_reference", "dem")


def _number(value: float) -> str:
    text = repr(float(value))
    return text[:-2] if text.endswith(".0") else text


def _cli_value(name: str, value: Any) -> str:
    if isinstance(value, int | float | np.integer | np.floating):
        return _number(value)
    if isinstance(value, list | tuple):
        return ",".join(_cli_value(name, v) for v in value)
    if isinstance(value, str | os.PathLike):
        return os.fspath(value)
    if isinstance(value, OverlapRule):
        return value.name
    raise InputError("request", f"field {name}={value!r} has no command-line form")


def render_command(request, out: str | os.PathLike, *, quicklook: str | os.PathLike | None = None,
                   provenance: bool = False, overwrite: bool = False) -> str:
    """The ``archive render`` command line (shell-quoted) that renders ``request`` (an
    :class:`archive.run.options.RenderOptions`) into ``out`` again: SOURCE... then ``--out``, then
    one option per request field that differs from its default (``--ground-height``,
    ``--wavelengths``, ``--sync-offset``...; a field ``x_y`` is option ``--x-y``). Paths (sources
    that exist, ``out``, archive, calibration, white reference, DEM, quicklook) are made absolute;
    collection ids stay as they are. quicklook/provenance/overwrite: the render options of those
    names. How it runs (scheduler, workers, threads, progress) is left out: it does not change the
    output."""
    if not dataclasses.is_dataclass(request) or isinstance(request, type):
        raise InputError("request", f"expected render options (RenderOptions), got {type(request).__name__}")
    words = ["archive", "render"]
    def absolute(p) -> str:   # a URL (s3://) stays as it is
        return str(p) if storage.is_url(p) else os.path.abspath(p)

    options: list[str] = ["--out", absolute(out)]
    for f in dataclasses.fields(request):
        value = getattr(request, f.name)
        if f.name == "sources":
            words += [os.path.abspath(s) if os.path.exists(s) else str(s) for s in value]
            continue
        default = f.default if f.default_factory is dataclasses.MISSING else f.default_factory()
        if value is None or (default is not dataclasses.MISSING and value == default):
            continue
        flag = "--" + f.name.replace("_", "-")
        if isinstance(value, bool):
            if value:
                options.append(flag)
            continue
        text = absolute(value) if f.name in _PATH_FIELDS else _cli_value(f.name, value)
        # '--boresight=-0.5,1,0': a value starting with '-' would read as an option
        options += [f"{flag}={text}"] if text.startswith("-") else [flag, text]
    if quicklook is not None:
        options += ["--quicklook", absolute(quicklook)]
    if provenance and "--provenance" not in options:
        options.append("--provenance")
    if overwrite:
        options.append("--overwrite")
    return shlex.join(words + options)
