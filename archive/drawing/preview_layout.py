"""Overview previews of a collection (issue 36): a few bands of the flight, georectified at coarse
pixel sizes when it is ingested, so that a zoomed-out viewer of hundreds of flights draws them
without opening the flights, building meshes or reading a DN chunk.

Layout, beside the collection's arrays (:mod:`archive.collection`), a Zarr v3 group
``<ARCHIVE>/collections/<id>.zarr/previews``::

    z<Z>    [band, y, x]  float32, the flight on the EPSG:3857 pixels of Web-Mercator zoom Z (pixel
            edges on that zoom's tile grid: x0 = -HALF_WORLD + column * gsd(Z), y0 = HALF_WORLD -
            row * gsd(Z)), NaN where no line covers; one chunk, compressed like the small arrays

and the group attribute ``archive:previews`` (written last, the previews' completion marker):
``version`` (:func:`archive.collection.content_version` of the collection they were made from: a
``calibrate --apply`` makes them stale, and stale previews are not used), ``mode`` and ``bands`` (the
viewer's defaults: true colour in radiance, raw DN without a calibration), ``wavelength`` (nm),
``flight_gsd`` (m, the catalog's nominal GSD), ``levels`` (finest first: zoom, column, row, width,
height, how it was made, and the sha256 of its values as :func:`archive.collection.array_digest`
writes them, which ``archive verify`` checks) and ``stats`` (the whole flight's 2/98 % of those bands
as the viewer's stats endpoint answers them).

The levels are a pyramid of consecutive zooms: the finest is the deepest zoom whose pixel is at
least MIN_FACTOR flight pixels and over which the flight spans at most MAX_SIDE pixels; each
further level is one zoom out, down to MIN_SIDE pixels. A level whose pixel spans at most
:data:`~archive.drawing.flight.MAX_MIP` flight pixels is drawn by the viewer's renderer (pass 1 of
the inverse renderer, then the band planes of ``archive render``'s calibration box-filtered over
the pixel's footprint): bit for bit the band-value tile the viewer draws from the DN at that zoom.
Coarser levels are the means of the finite values of 2 x 2 pixels of the level above (a mipmap).

This module owns the layout (written, read, verified); they are made after the collection is
published and cataloged (:func:`archive.ingest.previews.add_previews`, the hook of ``archive ingest``), under the collection's lock, into a temporary group renamed into place:
a collection without them (ingested before, or where no OpenGL is available) is complete and
viewed from its DN; ingesting it again adds them.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from archive.errors import FormatError

__all__ = ["GROUP", "PreviewLevel", "Previews", "is_current", "plan_levels", "read_previews", "rendered",
           "verify_previews", "write_previews"]

#: The group of a collection store holding its previews.
GROUP = "previews"
#: Attribute of that group (written last).
ATTRIBUTE = "archive:previews"
FORMAT_VERSION = 1
#: Longest side of the finest level, pixels.
MAX_SIDE = 1024
#: The finest level's pixel is at least this many flight pixels (finer zooms are drawn from the DN).
MIN_FACTOR = 2.0
#: The coarsest level: the flight spans at most this many pixels.
MIN_SIDE = 4
MAX_LEVELS = 12
#: Percentiles of the stored whole-flight statistics.
PERCENTILES = (2.0, 98.0)


@dataclass(frozen=True)
class PreviewLevel:
    """One level: zoom, the (column, row) of its north-west pixel on that zoom's pixel grid (x
    eastwards, y southwards from the north-west corner of the world square), width, height (px)."""

    zoom: int
    column: int
    row: int
    width: int
    height: int

    @property
    def name(self) -> str:
        return f"z{self.zoom}"

    def grid(self):
        """The EPSG:3857 :class:`~archive.grid.Grid` of this level."""
        from archive.grid import Grid
        from archive.grid import HALF_WORLD, MERCATOR_EPSG, zoom_gsd

        g = zoom_gsd(self.zoom)
        return Grid(MERCATOR_EPSG, g, -HALF_WORLD + self.column * g, HALF_WORLD - self.row * g, self.width,
                    self.height)

    def parent(self) -> PreviewLevel:
        """The level one zoom out covering this one (pixel edges on the coarser grid)."""
        c0, r0 = self.column // 2, self.row // 2
        c1, r1 = -(-(self.column + self.width) // 2), -(-(self.row + self.height) // 2)
        return PreviewLevel(self.zoom - 1, c0, r0, c1 - c0, r1 - r0)


def _level_over(bounds: Sequence[float], zoom: int) -> PreviewLevel:
    """The level of ``zoom`` covering W, S, E, N (EPSG:3857 m), one pixel of margin."""
    from archive.grid import HALF_WORLD, zoom_gsd

    g = zoom_gsd(zoom)
    c0 = math.floor((bounds[0] + HALF_WORLD) / g) - 1
    c1 = math.ceil((bounds[2] + HALF_WORLD) / g) + 1
    r0 = math.floor((HALF_WORLD - bounds[3]) / g) - 1
    r1 = math.ceil((HALF_WORLD - bounds[1]) / g) + 1
    n = 256 << zoom   # pixels a side of the world at this zoom
    c0, r0, c1, r1 = max(c0, 0), max(r0, 0), min(c1, n), min(r1, n)
    return PreviewLevel(zoom, c0, r0, c1 - c0, r1 - r0)


def plan_levels(bounds: Sequence[float], flight_gsd: float) -> list[PreviewLevel]:
    """The levels (finest first) of a flight whose meshes span ``bounds`` (W, S, E, N EPSG:3857 m)
    at a nominal pixel of ``flight_gsd`` m (see the module docstring)."""
    from archive.grid import MAX_ZOOM, zoom_gsd

    extent = max(bounds[2] - bounds[0], bounds[3] - bounds[1], 1e-6)
    finest = 0
    for z in range(MAX_ZOOM + 1):
        if zoom_gsd(z) >= MIN_FACTOR * flight_gsd and extent / zoom_gsd(z) <= MAX_SIDE:
            finest = z
    levels = [_level_over(bounds, finest)]
    while levels[-1].zoom > 0 and len(levels) < MAX_LEVELS and extent / zoom_gsd(levels[-1].zoom) > MIN_SIDE:
        levels.append(levels[-1].parent())
    return levels


def rendered(level: PreviewLevel, flight_gsd: float) -> bool:
    """Whether the viewer's renderer draws this level (its pixel spans at most MAX_MIP flight
    pixels), rather than the mean of the level above."""
    from archive.drawing.flight import MAX_MIP
    from archive.grid import zoom_gsd

    return 2 ** max(0, round(math.log2(zoom_gsd(level.zoom) / flight_gsd))) <= MAX_MIP


def halve(values: np.ndarray, level: PreviewLevel, parent: PreviewLevel) -> np.ndarray:
    """(bands, parent.height, parent.width): the mean of the finite values of each 2 x 2 block of
    ``values`` ((bands, level.height, level.width) on ``level``), NaN where none is."""
    k = values.shape[0]
    padded = np.full((k, parent.height * 2, parent.width * 2), np.nan, np.float32)
    r, c = level.row - 2 * parent.row, level.column - 2 * parent.column
    padded[:, r:r + level.height, c:c + level.width] = values
    blocks = padded.reshape(k, parent.height, 2, parent.width, 2)
    finite = np.isfinite(blocks)
    count = finite.sum(axis=(2, 4))
    total = np.where(finite, blocks, 0).sum(axis=(2, 4), dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, total / count, np.nan).astype(np.float32)


# ---- writing ----------------------------------------------------------------------------------
def write_previews(store: str | os.PathLike, attrs: dict, arrays: dict[str, np.ndarray]) -> None:
    """Write previews into the collection ``store``: a temporary group, its attribute last, renamed
    to ``previews`` (replacing older ones). Call it holding the collection's lock."""
    import zarr
    from zarr.codecs import BloscCodec

    from archive.collection import SMALL_CODEC
    from archive.files import remove_path, replace_path

    store = Path(store)
    for stray in store.glob(f".{GROUP}-*"):   # a killed writer's (the lock is ours now)
        remove_path(stray)
    tmp = store / f".{GROUP}-{os.getpid()}"
    group = zarr.open_group(tmp, mode="w", zarr_format=3)
    codec = BloscCodec(cname=SMALL_CODEC["cname"], clevel=SMALL_CODEC["clevel"], shuffle=SMALL_CODEC["shuffle"])
    for name, values in arrays.items():
        a = group.create_array(name, shape=values.shape, chunks=values.shape, dtype=np.float32,
                               compressors=[codec], fill_value=np.nan, dimension_names=("band", "y", "x"),
                               config={"write_empty_chunks": True})
        a[...] = values
    group.attrs.put({ATTRIBUTE: attrs})
    replace_path(tmp, store / GROUP)


def _attrs(store: Path) -> dict | None:
    import json

    try:
        meta = json.loads((store / GROUP / "zarr.json").read_text())
    except (OSError, ValueError):
        return None
    found = (meta.get("attributes") or {}).get(ATTRIBUTE) if isinstance(meta, dict) else None
    return found if isinstance(found, dict) else None


def is_current(store: str | os.PathLike) -> bool:
    """Whether ``store`` holds previews made from its present content (reads two zarr.json)."""
    from archive.collection import content_version

    attrs = _attrs(Path(store))
    version = content_version(store)
    return attrs is not None and version is not None and attrs.get("version") == version["version"] \
        and attrs.get("format_version") == FORMAT_VERSION


# ---- reading ----------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class Previews:
    """A collection's previews: the attribute's fields, its levels by zoom, and ``load(zoom)`` ->
    that level's (bands, height, width) float32 values (read when first needed: a zoomed-out screen
    reads one level of each flight)."""

    mode: str
    bands: tuple[int, ...]
    flight_gsd: float
    levels: dict
    stats: dict
    load: Callable[[int], np.ndarray]

    @property
    def nbytes(self) -> int:
        """What the description holds (the levels' values are loaded apart), bytes."""
        return 4096 + 256 * len(self.levels)

    @property
    def finest(self) -> int:
        return max(self.levels)

    def serves(self, bands: Sequence[int], mode: str | None, zoom: int) -> bool:
        """Whether values of ``bands`` in ``mode`` (None: the default, the previews') at ``zoom`` come
        from these previews: every band stored, and the zoom at or above the finest level (the
        caller checks that the drawing is the one ingested: every cube, the recorded ground height
        and sync offset, cubes combined 'last')."""
        return (mode is None or mode == self.mode) and 0 <= zoom <= self.finest \
            and all(int(b) in self.bands for b in bands)

    def values(self, grid, bands: Sequence[int]) -> np.ndarray | None:
        """(len(bands), height, width) float32 of the EPSG:3857 ``grid`` (a tile, on the pixel grid
        of a zoom at or above the finest level), NaN where no line covers; None when none does.
        At a stored level: its pixels; above the coarsest: the means of the finite values of the
        coarsest level's pixels in each of the grid's."""
        from archive.grid import HALF_WORLD, zoom_gsd

        zoom = round(math.log2(2 * HALF_WORLD / 256 / grid.gsd))
        use = zoom if zoom in self.levels else min(self.levels)
        level = self.levels[use]
        stored = self.load(use)
        f = 1 << (use - zoom) if zoom < use else 1
        g = zoom_gsd(use)
        c0 = round((grid.x0 + HALF_WORLD) / g)
        r0 = round((HALF_WORLD - grid.y0) / g)
        width, height = grid.width * f, grid.height * f   # the grid in the level's pixels
        # the part of the level under the grid, in the level's pixels
        a0, a1 = max(c0, level.column), min(c0 + width, level.column + level.width)
        b0, b1 = max(r0, level.row), min(r0 + height, level.row + level.height)
        if a0 >= a1 or b0 >= b1:
            return None
        index = [self.bands.index(int(b)) for b in bands]
        part = stored[index, b0 - level.row:b1 - level.row, a0 - level.column:a1 - level.column]
        out = np.full((len(index), grid.height, grid.width), np.nan, np.float32)
        if f == 1:
            out[:, b0 - r0:b1 - r0, a0 - c0:a1 - c0] = part
        else:   # each grid pixel the mean of the finite values of the level's f x f pixels in it
            rows = (np.arange(b0, b1) - r0) // f
            cols = (np.arange(a0, a1) - c0) // f
            cell = (rows[:, None] * grid.width + cols[None, :]).ravel()
            for i, plane in enumerate(part):
                v = plane.ravel()
                ok = np.isfinite(v)
                count = np.bincount(cell[ok], minlength=grid.width * grid.height)
                total = np.bincount(cell[ok], weights=v[ok], minlength=grid.width * grid.height)
                with np.errstate(invalid="ignore", divide="ignore"):
                    out[i] = np.where(count > 0, total / np.maximum(count, 1), np.nan).reshape(grid.shape)
        if not np.isfinite(out).any():
            return None
        return out

    def flight_stats(self, bands: Sequence[int], mode: str, percentiles) -> dict | None:
        """The whole flight's statistics of ``bands`` as the viewer's stats endpoint answers them,
        when stored (the same mode and percentiles, every band stored), else None."""
        s = self.stats
        if mode != self.mode or tuple(float(p) for p in percentiles) != tuple(s.get("percentiles", ())) \
                or not all(int(b) in self.bands for b in bands):
            return None
        index = [self.bands.index(int(b)) for b in bands]
        out = dict(s)
        out["band"] = [int(b) for b in bands]
        for name in ("wavelength", "low", "high"):
            if s.get(name) is not None:
                out[name] = [s[name][i] for i in index]
        return out


def read_previews(store: str | os.PathLike) -> Previews | None:
    """The current previews of the collection ``store``, None when it has none or they are stale
    (made before a ``calibrate --apply``) or unreadable: the viewer then draws from the DN."""
    import zarr

    store = Path(store)
    if not is_current(store):
        return None
    attrs = _attrs(store)
    try:
        levels, digests = {}, {}
        for rec in attrs["levels"]:
            level = PreviewLevel(int(rec["zoom"]), int(rec["column"]), int(rec["row"]), int(rec["width"]),
                                 int(rec["height"]))
            levels[level.zoom] = level
            digests[level.zoom] = rec["sha256"]

        def load(zoom: int) -> np.ndarray:
            """A level's values, checked against their recorded sha256 (FormatError if not them)."""
            from archive.collection import array_digest

            path = store / GROUP / levels[zoom].name
            values = np.asarray(zarr.open_array(path, mode="r")[...], np.float32)
            if array_digest(values) != digests[zoom]:
                raise FormatError(path, "overview preview level does not match its recorded sha256",
                                  "run 'archive verify'; ingest the flight again to remake its previews")
            return values

        return Previews(str(attrs["mode"]), tuple(int(b) for b in attrs["bands"]), float(attrs["flight_gsd"]),
                        levels, dict(attrs.get("stats") or {}), load)
    except (KeyError, TypeError, ValueError):
        return None


def verify_previews(store: str | os.PathLike) -> list[str]:
    """Problems of the previews of the collection ``store`` (``archive verify``): a level whose values'
    sha256 is not the recorded one, or unreadable. Empty when it has none (they are optional) or
    they are intact; stale ones (made before a ``calibrate --apply``, unused) are checked too."""
    import zarr

    from archive.collection import array_digest

    store = Path(store)
    attrs = _attrs(store)
    if attrs is None:
        if (store / GROUP).exists():
            return [f"{GROUP}: no '{ATTRIBUTE}' attribute (an interrupted write); ingest the flight again to remake them"]
        return []
    problems = []
    try:
        group = zarr.open_group(store / GROUP, mode="r")
    except Exception as exc:  # noqa: BLE001 - report anything unreadable
        return [f"{GROUP}: unreadable ({type(exc).__name__}: {exc})"]
    for rec in attrs.get("levels", []):
        name = f"z{rec.get('zoom')}"
        try:
            found = array_digest(np.asarray(group[name][...]))
        except Exception as exc:  # noqa: BLE001 - report any unreadable level
            problems.append(f"{GROUP}/{name}: unreadable ({type(exc).__name__})")
            continue
        if found != rec.get("sha256"):
            problems.append(f"{GROUP}/{name}: checksum mismatch (ingest the flight again to remake the previews)")
    return problems
