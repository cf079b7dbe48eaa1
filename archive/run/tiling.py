"""Tiles: a fixed tiling of the output CRS, one output per tile that a flight touches (DESIGN 11).

``archive render --archive A --query-... --tiles SIZE --out DIR [--format F]`` cuts the output CRS
into squares of SIZE metres whose edges lie on multiples of SIZE (so on the GSD lattice: SIZE must
be a whole number of pixels), and writes one output per tile that any matching flight touches,
``DIR/<EPSG>_<E0>_<N0>.<format>`` named by its lower-left corner (integer metres): the mosaic (by
``--overlap``) of every matching flight over it, each flight rendered from its raw lines onto the
tile (``--bounds E0,N0,E0+SIZE,N0+SIZE --align``), with its STAC Item listing the tile's flights
(``archive:tile``). On the lattice a cube is drawn the same way whatever the tile
(:func:`archive.graph.plan.plan_render`), so the tiles stitched together equal one render of their
union with ``--bounds ... --align``, bit for bit: no seams, no tile-edge effects.

Tiles are the units of a batch (:func:`archive.run.batch.run_batch`): each succeeds or fails alone,
``DIR/report.json``, ``--resume`` (a tile whose flights changed is another recipe: ``--resume
--overwrite`` renders those again and skips the others) and waves, as for flights.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence

from archive.errors import InputError

__all__ = ["Tile", "check_size", "plan_tiles", "run_tiles", "tile_name"]


@dataclasses.dataclass(frozen=True)
class Tile:
    """One tile: EPSG code, lower-left corner (``e0``, ``n0``, integer metres), side ``size`` (m) and
    the flights touching it (sources of the request, in the request's order)."""

    epsg: int
    e0: int
    n0: int
    size: int
    sources: tuple[str, ...]

    @property
    def name(self) -> str:
        return tile_name(self.epsg, self.e0, self.n0)

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """(west, south, east, north), metres."""
        return (float(self.e0), float(self.n0), float(self.e0 + self.size), float(self.n0 + self.size))

    def properties(self, ids: Sequence[str]) -> dict:
        """The ``archive:tile`` property of its Item (``ids``: its flights' names)."""
        return {"archive:tile": {"epsg": self.epsg, "e0": self.e0, "n0": self.n0, "size_m": self.size,
                                 "flights": list(ids)}}


def tile_name(epsg: int, e0: int, n0: int) -> str:
    """``<EPSG>_<E0>_<N0>``: a tile's name by its lower-left corner (integer metres)."""
    return f"{int(epsg)}_{int(e0)}_{int(n0)}"


def check_size(size, gsd: float) -> int:
    """The tile side in metres (a positive whole number of metres and of ``gsd`` pixels); InputError otherwise."""
    try:
        value = float(size)
    except (TypeError, ValueError):
        value = math.nan
    if not (math.isfinite(value) and value >= 1 and value == int(value)):
        raise InputError("--tiles", f"expected a tile side in whole metres, got {size!r}", "e.g. --tiles 100")
    pixels = value / float(gsd)
    if abs(pixels - round(pixels)) > 1e-6:
        raise InputError("--tiles", f"{value:g} m is not a whole number of {gsd:g} m pixels",
                         "give a tile side that is a multiple of --gsd")
    return int(value)


def plan_tiles(options, nav, size: int, say: Callable[[str], None] | None = None,
               fov: float | None = None) -> list[Tile]:
    """The tiles of ``options.sources`` (metadata only: poses, no pixel; the flights' meshes with the
    field of view ``fov``, deg, decided for all of them): every tile of ``size`` m
    that some cube window of some flight touches, in the CRS ``options.crs`` or the UTM zone most
    flights are in; with ``options.bounds`` only the tiles meeting it. Row-major from the north-west."""
    from archive.run.pipeline import open_inputs, plan_output

    say = say or (lambda text: None)
    alone = [dataclasses.replace(options.with_sources([s]), bounds=None, align=False, like=None)
             for s in dict.fromkeys(options.sources)]
    zones: dict[str, int] = {}
    for one in alone:
        zones[one.sources[0]] = plan_output(open_inputs(one, nav, say, mosaic=True, fov=fov)).plan.grid.epsg
    counts = list(zones.values())
    epsg = min(set(counts), key=lambda e: (-counts.count(e), e))
    touched: dict[tuple[int, int], list[str]] = {}
    for one in alone:
        src = one.sources[0]
        if options.crs is None and zones[src] != epsg:
            one = dataclasses.replace(one, crs=f"EPSG:{epsg}")
        plan = plan_output(open_inputs(one, nav, say, mosaic=True, fov=fov)).plan
        for job in plan.jobs:
            w, s, e, n = job.window.bounds
            for i in range(math.floor(w / size), math.ceil(e / size)):
                for j in range(math.floor(s / size), math.ceil(n / size)):
                    names = touched.setdefault((i, j), [])
                    if src not in names:
                        names.append(src)
    tiles = []
    for (i, j), srcs in touched.items():
        tile = Tile(epsg, i * size, j * size, size, tuple(s for s in options.sources if s in srcs))
        if options.bounds is not None:
            bw, bs, be, bn = options.bounds
            tw, ts, te, tn = tile.bounds
            if not (tw < be and bw < te and ts < bn and bs < tn):
                continue
        tiles.append(tile)
    if not tiles:
        raise InputError("--bounds", "no tile of the flights meets the bounds", "give --bounds over the flights")
    return sorted(tiles, key=lambda t: (-t.n0, t.e0))


def run_tiles(options, out, size, *, format: str = "zarr", overwrite: bool = False, resume: bool = False,
              scheduler=None, workers: int | None = None, threads: int | None = None, quiet: bool = True,
              tell: Callable[[str], None] | None = None) -> dict:
    """Render the tiles of ``options`` (:func:`plan_tiles`) into ``out/<EPSG>_<E0>_<N0>.<format>``, each
    tile a unit of :func:`archive.run.batch.run_batch` (its summary, with ``tiles``: the tile names)."""
    from pathlib import Path

    from archive.run.batch import run_batch
    from archive.run.options import check_gsd

    check_gsd(options.gsd)
    if options.like is not None:
        raise InputError("--tiles", "tiles have their own grids, edges on multiples of the tile side",
                         "leave --like out (--bounds selects the tiles)")
    size = check_size(size, options.gsd)
    from archive.run.pipeline import field_of_view

    nav = options.check()
    tiles = plan_tiles(options, nav, size, fov=field_of_view(options))   # one field of view for all the tiles
    name = {s: Path(s).name if Path(s).is_dir() else str(s) for s in options.sources}
    units = []
    for tile in tiles:
        recipe = dataclasses.replace(options.with_sources(tile.sources), bounds=tile.bounds, align=True,
                                     crs=f"EPSG:{tile.epsg}")
        units.append((tile.name, recipe, tile.properties([name[s] for s in tile.sources])))
    summary = run_batch(options, out, format=format, overwrite=overwrite, resume=resume, scheduler=scheduler,
                        workers=workers, threads=threads, quiet=quiet, tell=tell, units=units)
    summary["tiles"] = [t.name for t in tiles]
    return summary
