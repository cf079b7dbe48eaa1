"""Command line: ``archive <command> ...`` (also ``python -m archive``).

This module only parses arguments; each command's work lives in its own module, imported when the
command runs, so that ``archive --help`` stays fast and never touches OpenGL.
"""

from __future__ import annotations

import argparse
import importlib
import math
import os
import re
import sys
from collections.abc import Sequence
from typing import NoReturn

from archive import __version__
from archive.api_errors import keep_cli_flags
from archive.errors import ArchiveError, file_system_refusal, warning_lines
from archive.overlap import LAST, RULES
from archive.params import DEFAULT_MAX_VIEW_ANGLE
from archive.analysis.arguments import add_stats
from archive.simulator.arguments import add_simulate
from archive.simulator.arguments import positive_int as _positive_int
from archive.watch.arguments import add_watch

# command name -> "module:function" taking the parsed argparse.Namespace and returning an exit code
HANDLERS = {
    "simulate": "archive.simulator.command:run",
    "render": "archive.run.command:run",
    "info": "archive.ingest.summary:run",
    "ingest": "archive.ingest.command:run",
    "verify": "archive.ingest.verify:run_verify",
    "catalog": "archive.catalog.command:run",
    "view": "archive.view.server:run",
    "calibrate": "archive.calibrate.command:run",
    "doctor": "archive.run.doctor:run",
    "stats": "archive.analysis.command:run",
    "watch": "archive.watch.command:run",
}


def _triple(text: str) -> tuple[float, float, float]:
    """'A,B,C' -> three finite floats (for --boresight and --lever-arm)."""
    try:
        values = tuple(float(v) for v in text.replace(" ", "").split(","))
    except ValueError:
        values = ()
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise argparse.ArgumentTypeError(f"expected three comma-separated numbers, got {text!r}")
    return values  # type: ignore[return-value]


def _command(sub, name: str, help: str, description: str) -> argparse.ArgumentParser:
    return sub.add_parser(name, help=help, description=description)   # ``sub``: what add_subparsers returned


def _add_run_flags(p: argparse.ArgumentParser, overwrite: str) -> None:
    """--overwrite (``overwrite`` says what it replaces) and --quiet."""
    p.add_argument("--overwrite", action="store_true", help=overwrite)
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def _add_dem(p: argparse.ArgumentParser, use: str) -> None:
    """--dem (``use``: what the command does with it) and --dem-datum."""
    p.add_argument("--dem", metavar="FILE",
                   help="digital elevation model, a GeoTIFF in any CRS and resolution (only the part under the "
                        f"flight is read): {use}")
    p.add_argument("--dem-datum", choices=["ellipsoid", "egm96", "egm2008"], default=None,
                   help="vertical datum of the DEM's heights, required when its CRS does not declare one "
                        "(geoid heights are converted to ellipsoidal ones with PROJ's grids)")


def _add_navigation(p: argparse.ArgumentParser, use: str) -> None:
    p.add_argument("--navigation", metavar="FILE|NAME", help="a post-processed trajectory, an Applanix SBET "
                   f"(.out, .sbet) or a CSV/ASCII export with a header row: {use}")
    p.add_argument("--navigation-columns", metavar="time=COL,lat=COL,...", help="a CSV export's column names when "
                   "not Inertial Explorer's (GPSTime, Latitude, Longitude, H-Ell, Roll, Pitch, Heading; degrees)")


def _add_mounting(p: argparse.ArgumentParser, recorded: bool) -> None:
    """--boresight and --lever-arm (and --sync-offset for ingest)."""
    default = "default: as ingested for a collection, else 0" if recorded else "default 0"
    p.add_argument("--boresight", type=_triple, metavar="ROLL,PITCH,YAW",
                   help="camera mounting angles in the body frame, degrees, aerospace signs (+roll: right wing "
                        f"down, +pitch: looks forward) ({default})")
    p.add_argument("--lever-arm", type=_triple, metavar="X,Y,Z",
                   help=f"camera position from the INS in the body frame (x forward, y right, z down), metres ({default})")


def _add_sources(p, nargs: str, note: str) -> None:
    """SOURCE... and --archive, as ``render`` and ``calibrate`` take them."""
    p.add_argument("sources", nargs=nargs, metavar="SOURCE",
                   help=f"raw flight directory, or a collection id of --archive ({note})")
    p.add_argument("--archive", metavar="ARCHIVE", help="archive holding the collections named as SOURCE")


def _add_fov(p, note: str) -> None:
    p.add_argument("--fov", type=float, metavar="DEG", help=f"across-track field of view of the camera, degrees ({note})")


def _add_render(sub) -> None:
    p = _command(sub, "render", "georectify flights into a mosaicked, georeferenced cube", (
        "Georectify one or more flights by the inverse (mesh + OpenGL) method and write one mosaic: Zarr (.zarr), "
        "Cloud-Optimized GeoTIFF (.tif) or ENVI BSQ (.hdr), float32 with NaN where no line covers a pixel. SOURCE "
        "is a raw flight directory (rendered without intermediate files). From Python: archive.georectify(sources, "
        "out, gsd=..., ...), keyword names as these options (--ground-height is ground_height)."))
    _add_sources(p, "*", "optional with --query-*")
    p.add_argument("--out", required=True, metavar="PATH", help="output path ending in .zarr, .tif or .hdr")
    p.add_argument("--gsd", type=float, metavar="M", help="output pixel size, metres (required unless --like gives it)")
    _add_fov(p, "required for raw sources; 47.5 for a Pika L and for 'archive simulate' flights")
    p.add_argument("--calibration", metavar="FILE.icp", help="radiometric calibration (default: the *.icp in the flight directory)")
    p.add_argument("--ground-height", default="auto", metavar="M|auto",
                   help="height of the flat ground, metres above the ellipsoid, or 'auto' (default auto)")
    bands = p.add_mutually_exclusive_group()
    bands.add_argument("--wavelengths", metavar="NM,NM,...", help="render the bands nearest to these wavelengths")
    bands.add_argument("--bands", metavar="all|I,J,...", default="all",
                       help="'all' bands (default) or band indices counted from 0 (GDAL and QGIS count from 1: docs/numbering.md)")
    p.add_argument("--index", nargs="+", action="extend", metavar="NAME", default=[],
                   help="write one band per spectral index instead of the bands (NDVI, EVI...: docs/stats.md)")
    p.add_argument("--expression", action="append", metavar="NAME=EXPR", default=[],
                   help="also one band of band math, repeatable: R<nm> is the band nearest <nm> nm")
    p.add_argument("--mode", choices=["raw", "relative", "radiance", "reflectance"], default=None,
                   help="radiometric mode (default radiance; raw DN, with a note, when the flight has no calibration)")
    p.add_argument("--white-reference", metavar="FILE", help="white reference for --mode reflectance: text file of "
                   "two columns, wavelength (nm) and radiance")
    p.add_argument("--irradiance-calibration", metavar="FILE.dcp",
                   help="the downwelling spectrometer's calibration pack when it is not in the flight directory "
                        "(--mode reflectance without --white-reference divides by the flight's sky spectra)")
    p.add_argument("--panels", metavar="FILE.geojson",
                   help="--mode reflectance by the empirical line: polygons (lon, lat) of panels with properties "
                        "'reflectance' (a number or a list) and 'wavelengths' (nm); two panels or more")
    p.add_argument("--sync-offset", type=float, default=None, metavar="S",
                   help="camera-to-navigation time offset, seconds (default: as ingested for a collection, else 0)")
    _add_navigation(p, "georectify raw flights from it instead of their .lcf; for a collection: lcf or the name "
                       "of a track it was ingested with (default: its default source)")
    _add_mounting(p, recorded=True)
    p.add_argument("--max-view-angle", type=float, default=DEFAULT_MAX_VIEW_ANGLE, metavar="DEG",
                   help="leave out lines whose field-of-view edge looks further than this off nadir, degrees "
                        f"(turns; default {DEFAULT_MAX_VIEW_ANGLE:g}; the summary says how many)")
    p.add_argument("--crs", metavar="EPSG:XXXX",
                   help="projected CRS of the output (default: the UTM zone holding most of the flights; "
                        "flights of other zones are rendered into it)")
    _add_dem(p, "the meshes follow it instead of the flat ground (no line sees: NaN); not with a numeric --ground-height")
    p.add_argument("--overlap", choices=list(RULES), default=LAST.name,
                   help="where lines overlap: the later line wins (default), the line seen closest to nadir "
                        "(smallest view zenith) wins, or the mean")
    g = p.add_argument_group("the output grid (default: the flights' footprint, pixel edges on multiples of --gsd)")
    g.add_argument("--bounds", metavar="W,S,E,N",
                   help="extent of the output, metres in the output CRS (--crs, else the flights' UTM zone): its "
                        "top-left pixel corner at W,N, whole pixels down to S and across to E (add --align to snap "
                        "the edges outward to multiples of --gsd, like gdalwarp -te/-tap)")
    g.add_argument("--align", action="store_true",
                   help="pixel edges on multiples of --gsd (gdalwarp -tap): outputs of one --gsd share pixels; "
                        "the footprint grid, tiles and stacks are aligned anyway")
    g.add_argument("--like", metavar="FILE",
                   help="take the CRS, GSD, corner and size of an existing output (.zarr, a stack's too, .tif or "
                        ".hdr): the flights are rendered from their raw lines onto that very grid (--gsd optional)")
    p.add_argument("--zarr-format", type=int, choices=[2, 3], default=2, metavar="2|3",
                   help="Zarr version of a .zarr output: 2 (default; GDAL >= 3.10, hence QGIS and rasterio, open "
                        "it) or 3 (zarr-python 3, xarray); the same arrays and attributes either way")
    p.add_argument("--compression", choices=["fast", "small", "none"], default="fast",
                   help="Zarr chunks and COG tiles: fast (default: Blosc LZ4 + shuffle / ZSTD -3 + predictor), "
                        "small (Blosc Zstd 1 / ZSTD 1: ~7 %% fewer bytes for 1.4-5x the compression CPU), none "
                        "(uncompressed); ENVI is never compressed. Measured table: docs/outputs.md 'Compression'")
    p.add_argument("--provenance", action="store_true",
                   help="also write per-pixel provenance layers: source cube/line/sample, time, view and sun "
                        "angles, path length, overlap count (variables of a .zarr; <stem>_provenance.tif/.hdr "
                        "beside a .tif/.hdr); needs --overlap "
                        + " or ".join(rule.name for rule in RULES.values() if rule.single_source))
    p.add_argument("--quicklook", metavar="PNG", help="also write an RGB preview (2%%/98%% stretch)")
    p.add_argument("--scheduler", metavar="ADDRESS",
                   help="Dask scheduler address, e.g. tcp://host:8786 (default: a local cluster). Workers need "
                        "--nthreads <cores> --resources GPU=2 and the same file paths (shared file system); see docs/deploy.md")
    p.add_argument("--workers", type=_positive_int, metavar="N", help="local cluster worker processes (default: 1; "
                   "raw flights of at most 16 MiB of DN render in this process unless --workers is given)")
    p.add_argument("--threads", type=_positive_int, metavar="N", help="threads per local worker (default: the "
                   "cores divided among the workers, at least 2): render tasks draw on the worker's GL thread while "
                   "the others mosaic, compress and write")
    p.add_argument("--cluster", choices=["slurm"],
                   help="start the Dask workers as Slurm batch jobs (dask-jobqueue's SLURMCluster; its scheduler runs "
                        "in this command): --jobs jobs of one worker each, sized by the --job-* options or "
                        "dask-jobqueue's 'jobqueue: slurm:' configuration; see docs/deploy.md")
    j = p.add_argument_group("--cluster slurm: the worker jobs (an option left out: the 'jobqueue: slurm:' "
                             "configuration of ~/.config/dask/jobqueue.yaml, /etc/dask or $DASK_CONFIG)")
    j.add_argument("--jobs", type=_positive_int, metavar="N", help="worker jobs kept running (default 1; a job that "
                   "ends early is submitted again)")
    j.add_argument("--job-queue", metavar="PARTITION", help="Slurm partition of the worker jobs")
    j.add_argument("--job-cores", type=_positive_int, metavar="N", help="CPUs per job: the worker's threads")
    j.add_argument("--job-memory", metavar="SIZE", help="memory per job, e.g. 16GB: the worker's memory limit")
    j.add_argument("--job-walltime", metavar="HH:MM:SS", help="time limit of each worker job")
    j.add_argument("--job-gpus", type=int, choices=[0, 1], metavar="0|1",
                   help="GPUs per job (--gres=gpu:1): a worker draws on one GPU; more GPUs, more --jobs")
    q = p.add_argument_group("batch jobs over the catalog of --archive (every given filter must match)")
    q.add_argument("--query-bbox", metavar="W,S,E,N", help="flights whose footprint meets this lon/lat box, degrees")
    q.add_argument("--query-datetime", metavar="A/B", help="flights flown in this ISO 8601 range ('..': open end)")
    q.add_argument("--query-wavelength", type=float, metavar="NM", help="flights whose bands cover this wavelength, nm")
    q.add_argument("--mosaic", action="store_true",
                   help="one mosaic of all matching flights at --out (default: one output per flight, "
                        "--out DIR/<id>.<format>)")
    q.add_argument("--stack", action="store_true",
                   help="one Zarr time stack at --out X.zarr: variable (time, band, y, x), time = each flight's "
                        "start, coordinate 'flight' = its id, every flight rendered from its raw lines onto one "
                        "aligned grid (the union of the footprints, or --bounds/--like); --resume adds the "
                        "flights it lacks")
    q.add_argument("--tiles", type=float, metavar="SIZE",
                   help="one output per tile of SIZE metres (edges on multiples of SIZE in the output CRS, SIZE a "
                        "multiple of --gsd) that a matching flight touches, --out DIR/<EPSG>_<E0>_<N0>.<format> (lower-"
                        "left corner): the mosaic (--overlap) of the tile's flights, each with its STAC Item; tiles "
                        "are the batch's units (report.json, --resume); --bounds selects tiles")
    q.add_argument("--format", default="zarr", metavar="FORMAT",
                   help="format of the per-flight outputs in --out DIR: zarr (default), tif or cog (Cloud-Optimized "
                        "GeoTIFF), hdr or envi (ENVI BSQ)")
    q.add_argument("--resume", action="store_true",
                   help="skip flights whose output in --out DIR is complete (its STAC Item exists) and was made "
                        "by the same request; redo incomplete ones (a different request is an error without "
                        "--overwrite)")
    _add_run_flags(p, "replace PATH if it exists")


def _add_info(sub) -> None:
    p = _command(sub, "info", "check a raw flight directory (or a collection) and print its summary", (
        "Read every cube of a raw flight directory (headers, .times, .lcf, calibration), check that each is "
        "complete and that navigation covers every line, and print a summary: cubes, lines, bands, wavelengths, "
        "time span, UTM zone, ground track length and altitude."))
    p.add_argument("directory", metavar="DIR", help="raw flight directory, or a collection id with --archive")
    p.add_argument("--archive", metavar="ARCHIVE", default=None, help="archive holding the collection DIR names "
                   "(its DEM, if ingested with --dem, is used unless --dem is given)")
    p.add_argument("--fov", type=float, default=None, metavar="DEG", help="field of view used for the swath width "
                   "(default: the collection's, else 47.5)")
    p.add_argument("--sync-offset", type=float, default=0.0, metavar="S", help="camera-to-navigation time offset, seconds (default 0)")
    _add_dem(p, "also check that it covers the swath and report the terrain under the flight")
    _add_navigation(p, "check and summarise the flight with it instead of its .lcf (its coverage of every line, "
                       "the track); for a collection: lcf or the name of a track it was ingested with (default: its "
                       "default source)")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")


def _add_ingest(sub) -> None:
    p = _command(sub, "ingest", "ingest raw flights into chunked Zarr collections and catalog them", (
        "Check each raw flight directory completely, then store it as ARCHIVE/collections/<id>.zarr (Zarr v3: DN "
        "chunked one band of one cube per chunk and compressed, per-line times and poses, the raw navigation, "
        "calibration, header metadata, source checksums) and describe it by a STAC Item in the archive's catalog. "
        "The id is <sensor>_<UTC start>. Ingesting a flight again is a no-op; an interrupted ingest resumes when "
        "rerun. The archive is created if needed."))
    p.add_argument("directories", nargs="+", metavar="RAW_DIR", help="raw flight directory")
    p.add_argument("--archive", required=True, metavar="ARCHIVE", help="archive directory (created if absent or empty)")
    p.add_argument("--fov", required=True, type=float, metavar="DEG",
                   help="across-track field of view of the camera, degrees (47.5 for a Pika L and for 'archive simulate')")
    p.add_argument("--calibration", metavar="FILE.icp", help="radiometric calibration (default: the *.icp in the flight directory)")
    p.add_argument("--irradiance-calibration", metavar="FILE.dcp",
                   help="the downwelling spectrometer's calibration pack (default: the *.dcp in the flight directory); "
                        "a flight's <set>_downwelling_<k>_pre.spec spectra are kept in the collection")
    p.add_argument("--ground-height", type=float, metavar="M", help="ground height, metres above the ellipsoid, "
                   "for the catalog footprint (default: the header's 'ground elevation')")
    _add_dem(p, "the catalog footprint follows the terrain; exclusive with --ground-height")
    p.add_argument("--sync-offset", type=float, default=0.0, metavar="S",
                   help="camera-to-navigation time offset, seconds (default 0); recorded, used by renders of the collection")
    _add_navigation(p, "stored with the flight as a named track (the file's stem), its default navigation source")
    _add_mounting(p, recorded=False)
    from archive.ingest.arguments import add_cluster_options

    add_cluster_options(p)   # --scheduler, --cluster slurm, --workers, --threads, --report, --compression, --checksum
    _add_run_flags(p, "re-ingest flights that are already in the archive")


def _add_verify(sub) -> None:
    p = _command(sub, "verify", "re-check stored collections against their recorded checksums", (
        "Decode every DN chunk and small array of a collection (or of all collections) and compare "
        "their checksums with those recorded at ingest (BLAKE3 or sha256: the store says which). Exit code 0 when all "
        "are intact, 1 otherwise."))
    p.add_argument("id", nargs="?", metavar="ID", help="collection id (default: every collection)")
    p.add_argument("--archive", required=True, metavar="ARCHIVE", help="archive directory")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def _add_catalog(sub) -> None:
    p = _command(sub, "catalog", "search, list, rebuild or validate an archive's catalog", (
        "Query the archive's catalog (STAC Items + SQLite index), rebuild the index and the STAC tree "
        "(ARCHIVE/catalog.json -> catalog/collection.json -> catalog/items/<id>.json) from the Items, or "
        "validate STAC files offline against the schemas shipped with archive."))
    csub = p.add_subparsers(dest="catalog_command", metavar="SUBCOMMAND", required=True)
    s = csub.add_parser(
        "search",
        help="find flights by place, time and wavelength",
        description=(
            "Print the flights whose footprint bbox intersects --bbox, whose time range meets --datetime "
            "and whose wavelength range holds --wavelength (all given filters must match)."
        ),
    )
    s.add_argument("--archive", required=True, metavar="ARCHIVE", help="archive directory")
    s.add_argument("--bbox", metavar="W,S,E,N", help="longitude/latitude box, degrees (west, south, east, north)")
    s.add_argument("--datetime", metavar="A/B",
                   help="ISO 8601 instant or range (UTC unless a zone is given; '..' for an open end)")
    s.add_argument("--wavelength", type=float, metavar="NM", help="a wavelength the flight must cover, nm")
    s.add_argument("--json", action="store_true", help="print a STAC ItemCollection instead of a table")
    ls = csub.add_parser("list", help="list every cataloged flight", description="List every cataloged flight.")
    ls.add_argument("--archive", required=True, metavar="ARCHIVE", help="archive directory")
    ls.add_argument("--json", action="store_true", help="print a STAC ItemCollection instead of a table")
    r = csub.add_parser("rebuild", help="rebuild the index and the STAC catalog from the STAC Item files",
                        description="Recreate catalog/index.sqlite from catalog/items/*.json, give every Item its "
                                    "collection and links, and rewrite the root catalog.json and "
                                    "catalog/collection.json (extent and links of every Item).")
    r.add_argument("--archive", required=True, metavar="ARCHIVE", help="archive directory")
    r.add_argument("--items", action="store_true",
                   help="also rewrite every Item from its collection store before indexing")
    v = csub.add_parser("validate", help="validate STAC files offline against the vendored schemas",
                        description="Check the archive's catalog.json, collection.json and every Item, and any STAC "
                                    "JSON files given (such as a rendered output's <out>.json), against the STAC "
                                    "1.1.0 and extension schemas shipped with archive; no network. Exit code 0 when "
                                    "all are valid, 1 otherwise.")
    v.add_argument("files", nargs="*", metavar="FILE.json", help="more STAC files to validate")
    v.add_argument("--archive", metavar="ARCHIVE", help="archive whose STAC tree to validate")
    a = csub.add_parser("add", help="link rendered outputs (their <out>.json) from their flights' Items",
                        description="Add each output, described by the STAC Item archive render wrote beside it "
                                    "(<out>.json), as an asset of the Items of the archive's collections it was "
                                    "rendered from (served by the STAC API of archive view).")
    a.add_argument("items_json", nargs="+", metavar="OUT.json", help="Items of rendered outputs")
    a.add_argument("--archive", required=True, metavar="ARCHIVE", help="archive directory")


def _add_view(sub) -> None:
    p = _command(sub, "view", "browse the archive's flights in a web browser, georectified on the fly", (
        "Start a local web server and print its URL: a map of the catalog's footprints; opening a "
        "flight draws it georectified by the inverse renderer as Web-Mercator tiles (RGB or grey "
        "bands, radiometric mode, stretch, cube range, ground height and sync offset), and a click "
        "shows the spectrum of that pixel. Serves only the collections of --archive and the flight "
        "directories named; binds 127.0.0.1 unless --host and --allow-remote say otherwise."))
    p.add_argument("directories", nargs="*", metavar="FLIGHT_DIR", help="raw flight directories to serve too (need --fov)")
    p.add_argument("--archive", metavar="ARCHIVE", help="archive whose cataloged collections are served")
    p.add_argument("--fov", type=float, metavar="DEG",
                   help="field of view, degrees (required for raw flight directories; default for a collection: as ingested)")
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1, loopback only)")
    p.add_argument("--port", type=int, default=8000, help="port (default 8000; 0 picks a free one)")
    p.add_argument("--allow-remote", action="store_true",
                   help="allow a --host that is not loopback (anyone who can reach it can read the flights)")
    p.add_argument("--cache-mb", type=int, default=512, metavar="MIB",
                   help="memory for the caches (tiles, band planes and previews, lookups, open flights), MiB "
                        "(default 512); the server needs about 250 MB more (Python, its libraries, software OpenGL)")
    p.add_argument("--stack", action="append", metavar="X.zarr",
                   help="also serve this time stack (archive render --stack; with --archive): the page shows one "
                        "time step at a time, a slider steps through its flights, values read from the Zarr "
                        "(repeatable)")
    p.add_argument("--navigation", metavar="lcf|NAME", help="the navigation source drawn first: lcf (the recorder's "
                   "real-time solution) or a stored trajectory's name (default: each collection's own); the page switches it")
    p.add_argument("--zones", metavar="FIELDS", help="polygons (.geojson, .gpkg, .shp; any CRS) drawn as outlines; a click "
                   "on one plots its time series, one point per flight, of the index shown (as archive stats computes it)")
    p.add_argument("--zone-id", metavar="PROP", help="the property naming each zone (default: the feature's id, else its number)")


def _add_calibrate(sub) -> None:
    p = _command(sub, "calibrate", "estimate boresight, sync offset and ground height from a flight's own overlaps, "
                 "or co-register flights to a reference flight", (
        "Render every pair of overlapping passes onto a common grid, measure their misregistration "
        "(sub-pixel, on textured windows) and solve by least squares for the boresight (roll, pitch, "
        "yaw), the camera-to-navigation sync offset (searched over +-1 s) and the flat ground height "
        "(or, with --dem, the DEM's vertical offset). Prints the estimates with 1-sigma uncertainties, "
        "what the flight cannot separate, the misregistration before and after, and the render/ingest "
        "flags; starts from the parameters the flight records (a collection's as ingested). With --reference REF "
        "the overlaps with REF (held fixed) also constrain the flight, and its position offset is estimated: "
        "the flights line up without ground control."))
    _add_sources(p, "*", "several: one camera, one estimate; with --reference each on its own")
    _add_fov(p, "required for raw sources; 47.5 for a Pika L")
    p.add_argument("--ground-height", type=float, metavar="M",
                   help="start ground height, metres above the ellipsoid (default: as ingested, else the headers'; "
                        "with --reference: the reference's)")
    _add_dem(p, "estimate its vertical offset instead of a flat ground height; exclusive with --ground-height")
    _add_navigation(p, "estimate from it instead of the .lcf; for a collection: lcf or a stored track's name "
                    "(default: the collection's default source); with --reference, the flights' (not REF's)")
    p.add_argument("--estimate", default=None, metavar="LIST",
                   help="parameters to estimate, comma-separated: boresight (or roll, pitch, yaw), sync, ground, "
                        "position (or east, north, up; with --reference) (default boresight,sync,ground; with "
                        "--reference position,sync,boresight)")
    c = p.add_argument_group("co-registration to a reference flight (no ground control)")
    c.add_argument("--reference", metavar="REF",
                   help="a collection id of --archive (or a raw flight directory) flown over the same ground, held "
                        "fixed: estimate each flight's position offset (dE, dN, dU m: a GNSS bias), sync offset "
                        "and boresight relative to it from where they overlap; --apply records them")
    c.add_argument("--query-bbox", metavar="W,S,E,N",
                   help="with --reference: co-register every flight of --archive whose footprint meets this lon/lat box")
    c.add_argument("--query-datetime", metavar="A/B", help="with --reference: ... flown in this ISO 8601 range")
    c.add_argument("--query-wavelength", type=float, metavar="NM", help="with --reference: ... whose bands cover this")
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    p.add_argument("--apply", action="store_true",
                   help="record the estimates: a collection's navigation parameters (renders, stacks and the viewer "
                        "default to them; with --reference its STAC Item says it is co-registered), a raw flight's "
                        "navigation_params.json sidecar")
    p.add_argument("--quiet", action="store_true", help="no progress lines")


def _add_doctor(sub) -> None:
    p = _command(sub, "doctor", "say whether this machine can render, and why not", (
        "Check the installation (package versions, the shaders, catalog schema and viewer page), the EGL "
        "devices and the GL renderer, vendor and version each one gives, which device a worker would open "
        "and why (ARCHIVE_GL_DEVICE, CUDA_VISIBLE_DEVICES, Slurm's GPU binding), whether band passes run in "
        "GL or on the CPU, and the optional parts (PROJ's geoid grid, chromium for the viewer tests, Slurm). "
        "Exit 1, with the fix, when rendering is impossible."))
    p.add_argument("--workers", type=_positive_int, default=1, metavar="N",
                   help="also say how N local worker processes would spread over the GPUs (default 1)")
    p.add_argument("--json", action="store_true", help="print the checks as JSON")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="archive",
        description=(
            "Turn airborne pushbroom hyperspectral flights (Resonon ENVI cubes + navigation) into "
            "georeferenced, mosaicked datacubes by inverse georectification on the GPU (OpenGL)."
        ),
    )
    parser.add_argument("--version", action="version", version=f"archive {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    add_simulate(sub)
    _add_render(sub)
    _add_info(sub)
    _add_ingest(sub)
    _add_verify(sub)
    _add_catalog(sub)
    _add_view(sub)
    _add_calibrate(sub)
    _add_doctor(sub)
    add_stats(sub)
    add_watch(sub)
    return parser


#: A negative number or a comma-separated list starting with one ('-0.5,1,0', '-90.1,35,-89.8,35.3').
NEGATIVE_VALUE = re.compile(r"^-\d+$|^-\d*\.\d+$|^-[\d.]+(,\s*-?[\d.]+)+$")


def join_negative_values(argv: Sequence[str]) -> list[str]:
    """``--option -0.5,1,0`` -> ``--option=-0.5,1,0``: argparse would take a negative value after an
    option for another option (``--boresight``, ``--lever-arm``, ``--bbox``, ``--query-bbox``...)."""
    out: list[str] = []
    for word in argv:
        if out and out[-1].startswith("--") and "=" not in out[-1] and NEGATIVE_VALUE.match(word):
            out[-1] = f"{out[-1]}={word}"
        else:
            out.append(word)
    return out


def _stdout_closed() -> int:
    """The reader of stdout went away (``archive ... --json | head``): no traceback, no message (the
    reader asked for no more), stdout pointed at /dev/null so that the interpreter's last flush
    cannot fail, and the exit code of a process killed by SIGPIPE (128 + 13)."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError):
        pass
    return 141


def exit_now(code: int) -> NoReturn:
    """End this process with ``code`` as the interpreter's own exit would, less its finalization:
    non-daemon threads joined (and what they registered, e.g. ``concurrent.futures``' executors),
    the ``atexit`` handlers run (multiprocessing's children, Dask's clusters, logging, ``weakref``
    finalizers), stdout and stderr flushed, then ``os._exit``. What is skipped is the teardown of
    every module and the collection of every object the command made: 0.2-0.5 s of wall after a
    render's output was published, on the 2-core VM (issue 37; ``bench/timeline.py``'s 'exit' phase). Only for the
    command run as a program (:func:`main` without ``argv``), never inside a caller's process."""
    import atexit
    import threading

    timeline = os.environ.get("ARCHIVE_TIMELINE")   # bench/timeline.py (archive.run.cluster.phase)
    if timeline:
        from archive.run.cluster import phase

        phase("main-returned")
    shutdown = getattr(threading, "_shutdown", None)   # what Py_Finalize calls first
    run_exitfuncs = getattr(atexit, "_run_exitfuncs", None)   # CPython's; elsewhere: the interpreter's own exit
    if shutdown is None or run_exitfuncs is None:
        sys.exit(code)
    shutdown()
    run_exitfuncs()
    if timeline:
        phase("atexit-done")
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except BrokenPipeError:
            code = _stdout_closed() if stream is sys.stdout else code
        except (OSError, ValueError):
            pass
    os._exit(code)


def main(argv: Sequence[str] | None = None) -> int:
    """``archive`` with ``argv`` (default: the program's arguments); the exit code. Run as the
    program (``argv`` None: the ``archive`` script, ``python -m archive``), it ends the process
    through :func:`exit_now` once the command is done."""
    code = _main(argv)
    if argv is None:
        exit_now(code)
    return code


def _main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(join_negative_values(sys.argv[1:] if argv is None else argv))
    except SystemExit as done:  # --help, --version, a usage error: their text may meet a closed stdout
        try:
            sys.stdout.flush()
        except BrokenPipeError:
            _stdout_closed()
        raise done
    module_name, func_name = HANDLERS[args.command].split(":")
    try:
        handler = getattr(importlib.import_module(module_name), func_name)
        if argv is None:   # the program (not a caller in Python): warnings as clean lines
            warning_lines(args.command)
        with keep_cli_flags():   # the library's messages name the flags typed here, not Python keywords
            code = int(handler(args) or 0)
        sys.stdout.flush()  # a closed pipe shows here, inside the try, not at interpreter exit
        return code
    except BrokenPipeError:
        return _stdout_closed()
    except ArchiveError as exc:
        print(f"archive {args.command}: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print(f"archive {args.command}: interrupted", file=sys.stderr)
        return 130
    except OSError as exc:   # the file system said no: one line naming the path, never a traceback
        if (line := file_system_refusal(exc)) is None:
            raise
        print(f"archive {args.command}: error: {line}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    raise SystemExit(main())
