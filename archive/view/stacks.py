"""Time stacks in the viewer (``archive view --stack X.zarr``): the flights of one place on one grid,
shown one time step at a time, values read from the stack's Zarr (no rendering: what the page
shows is what the stack holds).

:class:`StackView` reads a stack written by ``archive render --stack`` (:mod:`archive.run.stacks`):
its description (:meth:`~StackView.info`: time steps, bands, grid and footprint), a Web-Mercator
tile of one time step (:meth:`~StackView.values`: each tile pixel takes the value of the stack pixel
under its centre, nearest neighbour, so every value shown is one of the Zarr's; :meth:`~StackView.png`
stretched to RGB) and the spectrum of the stack pixel under a point (:meth:`~StackView.point`).
"""

from __future__ import annotations

import io
import threading
from pathlib import Path

import numpy as np

from archive.errors import InputError, MissingInputError
from archive.grid import MERCATOR_EPSG, TILE, tile_grid

__all__ = ["StackView", "default_bands", "open_stacks", "parse_bands"]

#: Percentiles of a time step's band the PNG stretch spans by default.
STRETCH = (2.0, 98.0)


class StackView:
    """One stack, opened read-only (metadata read once; pixels read per request)."""

    def __init__(self, path: str | Path, name: str | None = None):
        import zarr

        from archive.outputs.stack import read_stack

        self.path = Path(path).absolute()
        if not self.path.exists():
            raise MissingInputError(self.path, "stack (--stack X.zarr)")
        try:
            layout, flights, _ = read_stack(self.path)
        except InputError as exc:
            raise InputError("--stack", f"{self.path}: {exc.problem}",
                             "give a stack written by 'archive render ... --stack --out X.zarr'") from None
        self.name = name or self.path.stem
        self.grid, self.flights, self.layout = layout.grid, flights, layout
        self.array = zarr.open_array(self.path, path=layout.variable, mode="r")
        self._lock = threading.Lock()
        self._ranges: dict[tuple[int, int], tuple[float, float]] = {}

    # ---- description -------------------------------------------------------------------------
    def info(self) -> dict:
        """What the page lists: name, time steps (flight id, start), bands (source index, nm),
        variable, grid (EPSG, GSD, bounds in metres) and the footprint's lon/lat bbox."""
        from archive.catalog.product import grid_footprint

        geometry, bbox = grid_footprint(self.grid)
        wl = self.layout.wavelengths
        return {"name": self.name, "variable": self.layout.variable,
                "times": [{"index": t, "flight": f.id, "start": f.start} for t, f in enumerate(self.flights)],
                "bands": [{"index": b, "band": int(i), "wavelength": None if wl is None else float(wl[b])}
                          for b, i in enumerate(self.layout.bands)],
                "epsg": self.grid.epsg, "gsd": self.grid.gsd, "bounds": list(self.grid.bounds),
                "bbox": bbox, "geometry": geometry}

    def _time(self, t) -> int:
        try:
            t = int(t)
        except (TypeError, ValueError):
            raise InputError("time", f"expected a time step index, got {t!r}") from None
        if not 0 <= t < len(self.flights):
            raise InputError("time", f"time step {t} is not in 0..{len(self.flights) - 1}")
        return t

    def _bands(self, bands) -> list[int]:
        out = list(bands)
        for b in out:
            if not 0 <= b < len(self.layout.bands):
                raise InputError("bands", f"band {b} is not in 0..{len(self.layout.bands) - 1}")
        if not 1 <= len(out) <= 3:
            raise InputError("bands", "give one band (grey) or three (R,G,B)")
        return out

    # ---- pixels ------------------------------------------------------------------------------
    def _pixels(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """(row, col) int arrays of the stack pixels holding the EPSG:3857 points (x, y); -1 outside."""
        from pyproj import Transformer

        to = Transformer.from_crs(MERCATOR_EPSG, self.grid.epsg, always_xy=True)
        e, n = to.transform(np.asarray(x, np.float64), np.asarray(y, np.float64))
        rows, cols = self.grid.rowcol(e, n)
        rows, cols = np.floor(rows).astype(np.int64), np.floor(cols).astype(np.int64)
        outside = (rows < 0) | (cols < 0) | (rows >= self.grid.height) | (cols >= self.grid.width)
        rows[outside] = -1
        cols[outside] = -1
        return rows, cols

    def values(self, z: int, x: int, y: int, t, bands) -> np.ndarray | None:
        """(len(bands), 256, 256) float32 of time step ``t`` on tile z/x/y: each tile pixel the stack
        pixel under its centre (NaN outside the stack); None when the tile misses the stack."""
        t, bands = self._time(t), self._bands(bands)
        tile = tile_grid(z, x, y)
        cx, cy = tile.xy_centres()
        rows, cols = self._pixels(*np.meshgrid(cx, cy))
        inside = rows >= 0
        if not inside.any():
            return None
        r0, r1 = int(rows[inside].min()), int(rows[inside].max()) + 1
        c0, c1 = int(cols[inside].min()), int(cols[inside].max()) + 1
        out = np.full((len(bands), TILE, TILE), np.nan, np.float32)
        for k, b in enumerate(bands):
            block = np.asarray(self.array[t, b, r0:r1, c0:c1], np.float32)
            out[k][inside] = block[rows[inside] - r0, cols[inside] - c0]
        return out

    def point(self, lon: float, lat: float, t) -> dict | None:
        """The stack pixel under (lon, lat) at time step ``t``: row, col, its centre (metres), and
        every band's value (None for NaN); None outside the stack."""
        from pyproj import Transformer

        t = self._time(t)
        x, y = Transformer.from_crs(4326, MERCATOR_EPSG, always_xy=True).transform(float(lon), float(lat))
        rows, cols = self._pixels([x], [y])
        if rows[0] < 0:
            return None
        r, c = int(rows[0]), int(cols[0])
        spectrum = np.asarray(self.array[t, :, r, c], np.float32)
        xc, yc = self.grid.xy_centres()
        return {"time": t, "flight": self.flights[t].id, "start": self.flights[t].start, "row": r, "col": c,
                "x": float(xc[c]), "y": float(yc[r]),
                "values": [None if not np.isfinite(v) else float(v) for v in spectrum]}

    def _range(self, t: int, b: int) -> tuple[float, float]:
        """The STRETCH percentiles of band ``b`` at time step ``t`` (computed once, on a decimated read)."""
        with self._lock:
            if (t, b) in self._ranges:
                return self._ranges[(t, b)]
        step = max(1, int(max(self.grid.height, self.grid.width) // 1024))
        v = np.asarray(self.array[t, b, ::step, ::step], np.float32)
        v = v[np.isfinite(v)]
        lo, hi = (np.percentile(v, STRETCH) if v.size else (0.0, 1.0))
        found = (float(lo), float(hi) if hi > lo else float(lo) + 1.0)
        with self._lock:
            self._ranges[(t, b)] = found
        return found

    def png(self, z: int, x: int, y: int, t, bands) -> bytes | None:
        """Tile z/x/y of time step ``t`` as an RGBA PNG (one band grey, three R,G,B), each band
        stretched over its time step's 2-98 % range; transparent where the stack has no value."""
        from PIL import Image

        values = self.values(z, x, y, t, bands)
        if values is None:
            return None
        t = self._time(t)
        channels = []
        for k, b in enumerate(self._bands(bands)):
            lo, hi = self._range(t, b)
            channels.append(np.clip((values[k] - lo) / (hi - lo) * 255.0, 0, 255))
        if len(channels) == 1:
            channels *= 3
        rgb = np.stack([np.nan_to_num(c) for c in channels], axis=-1).astype(np.uint8)
        alpha = np.where(np.isfinite(values).all(axis=0), 255, 0).astype(np.uint8)
        buffer = io.BytesIO()
        Image.fromarray(np.dstack([rgb, alpha]), "RGBA").save(buffer, format="PNG")
        return buffer.getvalue()


def open_stacks(paths) -> dict[str, StackView]:
    """The stacks named on the command line, by name (the file's stem; a repeated stem gets a suffix)."""
    out: dict[str, StackView] = {}
    for path in paths or ():
        view = StackView(path)
        name, k = view.name, 2
        while name in out:
            name, k = f"{view.name}-{k}", k + 1
        view.name = name
        out[name] = view
    return out


def parse_bands(text: str | None, default: list[int]) -> list[int]:
    """'I,J,K' (0-based stack band indices) or the default."""
    if not text:
        return default
    try:
        return [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise InputError("bands", f"expected band indices I or I,J,K, got {text!r}") from None


def default_bands(view: StackView) -> list[int]:
    """The bands nearest 640, 550, 460 nm (true colour), else the first (grey)."""
    wl = view.layout.wavelengths
    if wl is None or len(wl) < 3:
        return [0]
    w = np.asarray(wl)
    return [int(np.argmin(np.abs(w - nm))) for nm in (640.0, 550.0, 460.0)]
