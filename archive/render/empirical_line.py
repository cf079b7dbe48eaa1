"""The empirical line: reflectance = a[band] x radiance + c[band], fitted on panels of known
reflectance seen in the flight (the alternative to the sky spectrometer, issue 34).

Panels come as GeoJSON (RFC 7946: longitude, latitude in WGS 84): a FeatureCollection of Polygons,
each with ``properties.reflectance`` (one number for a grey panel, or a list) and, for a list,
``properties.wavelengths`` (nm, increasing; the list is interpolated onto the bands) or exactly one
value per band of the flight. Radiance at a panel is the median of the pixels the CPU reference
lookup (:mod:`archive.render.reference`) finds inside it, ``margin`` metres in from its edges, over
every cube that sees it. The fit is least squares per band over the panels (at least two).

The band pass carries the line exactly: ``((DN - dark') x gain') / response`` with ``gain' = gain x a``
and ``dark' = dark - c x response / gain'``, which needs one response per cube (a cube of constant
exposure; a sky spectrometer's per-line factor is not combined with panels).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from archive.errors import FormatError, InputError, MissingInputError
from archive.render.reference import reference_values
from archive.sources.base import Radiometry

__all__ = ["EmpiricalLine", "Panel", "PanelledSource", "empirical_radiometry", "fit_empirical_line", "panelled",
           "read_panels"]

_MAX_BYTES = 16 << 20


@dataclass(frozen=True, eq=False)
class Panel:
    """name; ring: (k, 2) lon, lat degrees (outer ring); reflectance: (m,) 0..1;
    wavelengths: (m,) nm, or None (one value per band, or m == 1: grey)."""

    name: str
    ring: np.ndarray
    reflectance: np.ndarray
    wavelengths: np.ndarray | None

    def on_bands(self, bands_nm) -> np.ndarray:
        """(bands,) reflectance at the bands' wavelengths (nm)."""
        n = len(bands_nm)
        if self.reflectance.size == 1:
            return np.full(n, float(self.reflectance[0]))
        if self.wavelengths is None:
            if self.reflectance.size != n:
                raise InputError(self.name, f"{self.reflectance.size} reflectance values for {n} bands",
                                 "give one per band, or 'wavelengths' with them")
            return self.reflectance.astype(float)
        return np.interp(np.asarray(bands_nm, float), self.wavelengths, self.reflectance)


def read_panels(path: str | os.PathLike) -> list[Panel]:
    """Panels of a GeoJSON file (module docstring); InputError naming the file and the feature."""
    path = Path(path)
    if not path.is_file():
        raise MissingInputError(path, "panels (GeoJSON)", "check --panels")
    if path.stat().st_size > _MAX_BYTES:
        raise FormatError(path, f"is larger than {_MAX_BYTES} bytes", "give the panels' polygons only")
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise FormatError(path, f"is not JSON ({exc})", "give a GeoJSON FeatureCollection") from None
    features = doc.get("features") if isinstance(doc, dict) else None
    if not isinstance(features, list) or not features:
        raise FormatError(path, "has no 'features'", "give a GeoJSON FeatureCollection of panel polygons")
    panels = []
    for i, f in enumerate(features):
        props = (f or {}).get("properties") or {}
        name = f"{path} feature {i}" + (f" ({props['name']})" if "name" in props else "")
        geom = (f or {}).get("geometry") or {}
        try:
            if geom.get("type") != "Polygon":
                raise ValueError("geometry must be a Polygon")
            ring = np.asarray(geom["coordinates"][0], float)[:, :2]
            if ring.shape[0] < 4 or not np.all(np.isfinite(ring)):
                raise ValueError("polygon ring needs at least 4 finite positions")
            refl = np.atleast_1d(np.asarray(props["reflectance"], float))
            wl = None if props.get("wavelengths") is None else np.asarray(props["wavelengths"], float)
            if wl is not None and (wl.shape != refl.shape or np.any(np.diff(wl) <= 0)):
                raise ValueError("'wavelengths' must be increasing, one per reflectance value")
            if not np.all(np.isfinite(refl) & (refl >= 0)):
                raise ValueError("reflectance must be finite and >= 0")
        except (KeyError, TypeError, ValueError, IndexError) as exc:
            raise FormatError(name, f"is not a panel: {exc}",
                              "each feature: a Polygon with properties.reflectance (and wavelengths, nm)") from None
        panels.append(Panel(name, ring, refl, wl))
    return panels


@dataclass(frozen=True, eq=False)
class EmpiricalLine:
    """a, c: (bands,) reflectance = a x radiance + c; radiance: (panels, bands) the panels' medians;
    reflectance: (panels, bands) their known values; pixels: (panels,) pixels each rests on."""

    a: np.ndarray
    c: np.ndarray
    radiance: np.ndarray
    reflectance: np.ndarray
    pixels: np.ndarray


def _inside(ring: np.ndarray, e: np.ndarray, n: np.ndarray) -> np.ndarray:
    inside = np.zeros(e.shape, bool)
    x0, y0 = ring[-1]
    for x1, y1 in ring:
        cross = ((y0 > n) != (y1 > n)) & (e < (x1 - x0) * (n - y0) / np.where(y1 != y0, y1 - y0, 1e-300) + x0)
        inside ^= cross
        x0, y0 = x1, y1
    return inside


def fit_empirical_line(source, meshes: dict, bands, panels: list[Panel], spacing: float = 0.05,
                       margin: float = 0.5) -> EmpiricalLine:
    """Fit a, c per band of ``bands`` on ``panels`` in ``source``'s radiance.

    meshes: {cube: Mesh} (flat or terrain) of the source, in its UTM zone; spacing: metres between
    sampled points inside a panel; margin: metres kept from its edges (a sample's footprint stays
    inside). InputError naming the panel when no cube sees it, and when fewer than two remain."""
    from pyproj import Transformer

    bands = list(bands)
    nb = len(bands)
    epsg = next(iter(meshes.values())).epsg
    to_utm = Transformer.from_crs(4326, epsg, always_xy=True)
    wl = source.wavelengths
    rad, refl, pixels = [], [], []
    for panel in panels:
        e, n = to_utm.transform(panel.ring[:, 0], panel.ring[:, 1])
        ring = np.stack([np.asarray(e), np.asarray(n)], axis=1)
        ge, gn = np.meshgrid(np.arange(ring[:, 0].min(), ring[:, 0].max(), spacing),
                             np.arange(ring[:, 1].min(), ring[:, 1].max(), spacing))
        keep = _inside(ring, ge, gn)
        for dx, dy in ((margin, 0), (-margin, 0), (0, margin), (0, -margin)):
            keep &= _inside(ring, ge + dx, gn + dy)
        pe, pn = ge[keep], gn[keep]
        values = []
        for k, mesh in meshes.items():
            if pe.size == 0:
                break
            v = reference_values(mesh, source.read_bands(k, bands), source.radiometry(k, bands, "radiance"), pe, pn)
            values.append(v[:, ~np.isnan(v[0])])
        seen = np.concatenate(values, axis=1) if values else np.zeros((nb, 0))
        if seen.shape[1] < 4:
            raise InputError(panel.name, f"is seen by {seen.shape[1]} pixels ({margin} m in from its edges)",
                             "check its coordinates (GeoJSON: longitude, latitude) or draw it larger")
        rad.append(np.median(seen, axis=1))
        refl.append(panel.on_bands([wl[b] for b in bands] if wl is not None else list(range(nb))))
        pixels.append(seen.shape[1])
    if len(rad) < 2:
        raise InputError(panels[0].name if panels else "--panels", "the empirical line needs at least two panels",
                         "add a darker or brighter panel")
    rad, refl = np.array(rad), np.array(refl)
    a, c = np.empty(nb), np.empty(nb)
    for b in range(nb):
        A = np.stack([rad[:, b], np.ones(len(rad))], axis=1)
        (a[b], c[b]), *_ = np.linalg.lstsq(A, refl[:, b], rcond=None)
    return EmpiricalLine(a, c, rad, refl, np.array(pixels))


def empirical_radiometry(radiance: Radiometry, line: EmpiricalLine, bands_in_fit) -> Radiometry:
    """The radiance terms of a cube (``source.radiometry(cube, bands, 'radiance')``, bands in the
    order of ``bands_in_fit`` positions) turned into reflectance terms (module docstring)."""
    resp = np.asarray(radiance.response, np.float64)
    if resp.size and not np.all(resp == resp[0]):
        raise InputError("--panels", "the cube's exposure changes line by line",
                         "the empirical line takes cubes of constant exposure")
    idx = list(bands_in_fit)
    a, c = line.a[idx][:, None], line.c[idx][:, None]
    gain = np.asarray(radiance.gain, np.float64) * a
    dark = np.asarray(radiance.dark, np.float64) - c * (resp[0] if resp.size else 1.0) / gain
    return Radiometry(dark.astype(np.float32), gain.astype(np.float32), radiance.response, radiance.saturation)


class PanelledSource:
    """A flight source whose 'reflectance' is the empirical line fitted on it (:func:`panelled`);
    every other mode and attribute is the wrapped source's. Picklable, tokenized by the wrapped
    source and the fit."""

    def __init__(self, inner, bands, line: EmpiricalLine):
        self.inner = inner
        self.fit = {int(b): (float(line.a[i]), float(line.c[i])) for i, b in enumerate(bands)}
        self.line = line

    def __getstate__(self) -> dict:
        return self.__dict__.copy()

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)

    def __getattr__(self, name: str):
        if name.startswith("__") or name in ("inner", "fit", "line"):
            raise AttributeError(name)
        return getattr(self.inner, name)

    def __repr__(self) -> str:
        return f"PanelledSource({self.inner!r})"

    def __dask_tokenize__(self):
        from dask.base import tokenize

        return ("PanelledSource", tokenize(self.inner), sorted(self.fit.items()))

    def radiometry(self, cube: int, bands, mode: str, white_reference=None) -> Radiometry:
        if mode != "reflectance":
            return self.inner.radiometry(cube, bands, mode, white_reference)
        missing = [b for b in bands if int(b) not in self.fit]
        if missing:
            raise InputError("--panels", f"bands {missing} were not fitted on the panels")
        a = np.array([self.fit[int(b)][0] for b in bands])
        c = np.array([self.fit[int(b)][1] for b in bands])
        one = EmpiricalLine(a, c, self.line.radiance, self.line.reflectance, self.line.pixels)
        return empirical_radiometry(self.inner.radiometry(cube, bands, "radiance"), one, range(len(bands)))


def panelled(source, meshes: dict, bands, panels_path: str | os.PathLike) -> PanelledSource:
    """``source`` with reflectance from the panels of ``panels_path`` (fitted on ``bands``)."""
    return PanelledSource(source, list(bands), fit_empirical_line(source, meshes, list(bands),
                                                                  read_panels(panels_path)))
