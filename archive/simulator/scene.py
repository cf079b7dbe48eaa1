"""The simulated ground scene: a separable radiance ``L(E, N, lambda) = sum_m a_m(E, N) s_m(lambda)``.

``a_m`` are material abundances, evaluable at any UTM point (vectorised); ``s_m`` are smooth
material radiance spectra (reflectance x a solar-like illumination, in "microflick-like" units).
The map is a textured background (jittered-grid Voronoi cells of mixed materials, modulated by a
sum of sinusoids, defined everywhere from a hash of the cell index) under a list of painted shapes
(later shapes win): homogeneous rectangles, 1 m checkerboards, bar and line targets, a rotated
triangle and tiny over-bright "glint" squares that saturate the sensor.

Coordinates: UTM metres (E, N). Abundance arrays are (materials, *points.shape).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

__all__ = ["MATERIALS", "Scene", "material_spectra", "points_in_polygon"]

#: material names, in abundance order
MATERIALS = ("soil", "grass", "asphalt", "concrete", "red", "blue", "white", "glint")
_BACKGROUND = (0, 1, 2, 3)      # materials the textured background mixes
CHUNK = 1 << 18                 # points per evaluation chunk (memory bound)


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-x))


def material_spectra(wavelengths: np.ndarray) -> np.ndarray:
    """Radiance spectra (materials, bands) of :data:`MATERIALS` at ``wavelengths`` (nm).

    Reflectance curves times a smooth illumination peaking near 500 nm (~9000 units); "white" has
    reflectance 0.9, "glint" 4.0 (it saturates the sensor).
    """
    lam = np.asarray(wavelengths, float)
    x = (lam - 400.0) / 600.0
    refl = np.stack([
        0.10 + 0.22 * x + 0.04 * x**2,                                          # soil
        0.04 + 0.07 * np.exp(-((lam - 550.0) / 35.0) ** 2)
        + 0.42 * _sigmoid((lam - 715.0) / 15.0),                                 # grass
        0.06 + 0.03 * x,                                                         # asphalt
        0.30 + 0.08 * x - 0.03 * x**2,                                           # concrete
        0.06 + 0.55 * _sigmoid((lam - 600.0) / 15.0),                            # red paint
        0.07 + 0.35 * np.exp(-((lam - 460.0) / 45.0) ** 2)
        + 0.30 * _sigmoid((lam - 780.0) / 25.0),                                 # blue paint
        0.90 - 0.03 * x,                                                         # white panel
        np.full_like(lam, 4.0),                                                  # glint
    ])
    return refl * illumination(lam)[None, :]


def illumination(wavelengths: np.ndarray) -> np.ndarray:
    """Smooth solar-like radiance of a perfect reflector (units per nm ~ microflicks), peak ~9000."""
    lam = np.asarray(wavelengths, float)
    return 9000.0 * np.exp(-0.5 * ((lam - 500.0) / 330.0) ** 2) * (1.0 - 0.15 * _sigmoid((lam - 930.0) / 12.0))


# --- hashing: deterministic pseudo-random numbers of integer cell indices ----------------------------
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_GOLD = np.uint64(0x9E3779B97F4A7C15)


def _hash(i: np.ndarray, j: np.ndarray, salt: int) -> np.ndarray:
    """splitmix64 of (i, j, salt) -> uint64."""
    with np.errstate(over="ignore"):
        z = (i.astype(np.int64).astype(np.uint64) * np.uint64(0x1F1F1F1F1F1F1F1F)
             ^ j.astype(np.int64).astype(np.uint64) * np.uint64(0x7FEB352D)
             ^ np.uint64(salt) * _GOLD)
        z = z + _GOLD
        z = (z ^ (z >> np.uint64(30))) * _M1
        z = (z ^ (z >> np.uint64(27))) * _M2
        return z ^ (z >> np.uint64(31))


def _u01(i: np.ndarray, j: np.ndarray, salt: int) -> np.ndarray:
    return (_hash(i, j, salt) >> np.uint64(11)).astype(np.float64) * (1.0 / 9007199254740992.0)


# --- polygons ---------------------------------------------------------------------------------------
def points_in_polygon(poly: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Even-odd rule: True where (x, y) (flat arrays, m) lies inside ``poly`` (k, 2) (closed or not).

    Points are sorted by y once, so each edge only visits the points of its own y band; long thin
    polygons with many short edges (swath footprints) cost little more than a sort.
    """
    x = np.asarray(x, float).ravel()
    y = np.asarray(y, float).ravel()
    inside = np.zeros(x.shape, bool)
    if x.size == 0 or len(poly) < 3:
        return inside
    order = np.argsort(y, kind="stable")
    ys = y[order]
    x0, y0 = poly[:, 0], poly[:, 1]
    x1, y1 = np.roll(x0, -1), np.roll(y0, -1)
    lo, hi = np.minimum(y0, y1), np.maximum(y0, y1)
    start = np.searchsorted(ys, lo, side="left")
    stop = np.searchsorted(ys, hi, side="left")   # half-open [lo, hi): vertices counted once
    for k in np.nonzero(stop > start)[0]:
        idx = order[start[k]:stop[k]]
        xc = x0[k] + (y[idx] - y0[k]) * (x1[k] - x0[k]) / (y1[k] - y0[k])
        inside[idx[x[idx] < xc]] ^= True
    return inside


# --- the scene ----------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class Scene:
    """Abundance maps and spectra.

    origin_e / origin_n: UTM (m) of the texture's origin; seed: texture seed; cell: Voronoi cell
    size (m); waves: (k, 4) sinusoid terms (amplitude, wavenumber_e rad/m, wavenumber_n rad/m,
    phase); shapes: painted shapes (dicts, UTM metres, see :func:`archive.simulator.layout`);
    wavelengths (bands,) nm; spectra (materials, bands).
    """

    origin_e: float
    origin_n: float
    seed: int
    cell: float
    waves: np.ndarray
    shapes: tuple[dict, ...]
    wavelengths: np.ndarray
    spectra: np.ndarray
    materials: tuple[str, ...] = MATERIALS
    _bboxes: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        boxes = [_shape_bbox(s) for s in self.shapes]
        object.__setattr__(self, "_bboxes", np.array(boxes, float).reshape(-1, 4))

    # --- evaluation -----------------------------------------------------------------------------------
    def abundance(self, e, n) -> np.ndarray:
        """Abundances (materials, *e.shape) at UTM points (m): point values, no blur."""
        e, n = np.broadcast_arrays(np.asarray(e, float), np.asarray(n, float))
        shape = e.shape
        e, n = e.ravel(), n.ravel()
        out = np.empty((len(self.materials), e.size))
        for s0 in range(0, e.size, CHUNK):
            out[:, s0:s0 + CHUNK] = self._abundance_flat(e[s0:s0 + CHUNK], n[s0:s0 + CHUNK])
        return out.reshape((len(self.materials),) + shape)

    def radiance(self, e, n) -> np.ndarray:
        """True radiance (bands, *e.shape) at UTM points (point value, no blur)."""
        a = self.abundance(e, n)
        return np.tensordot(self.spectra.T, a, axes=(1, 0))

    def abundance_box(self, e, n, size: float, supersample: int = 8) -> np.ndarray:
        """Abundances (materials, *e.shape) averaged over size x size m squares centred at (e, n),
        by supersample x supersample midpoint sampling."""
        e, n = np.broadcast_arrays(np.asarray(e, float), np.asarray(n, float))
        offsets = ((np.arange(supersample) + 0.5) / supersample - 0.5) * float(size)
        oe, on = (g.ravel() for g in np.meshgrid(offsets, offsets))
        flat_e, flat_n = e.ravel(), n.ravel()
        out = np.zeros((len(self.materials), flat_e.size))
        step = max(1, CHUNK // oe.size)
        for s0 in range(0, flat_e.size, step):
            pe = flat_e[s0:s0 + step, None] + oe[None, :]
            pn = flat_n[s0:s0 + step, None] + on[None, :]
            a = self._abundance_flat(pe.ravel(), pn.ravel())
            out[:, s0:s0 + step] = a.reshape(len(self.materials), -1, oe.size).mean(axis=2)
        return out.reshape((len(self.materials),) + e.shape)

    def radiance_box(self, e, n, size: float, supersample: int = 8) -> np.ndarray:
        """True radiance (bands, *e.shape) averaged over size x size m squares centred at (e, n)."""
        a = self.abundance_box(e, n, size, supersample)
        return np.tensordot(self.spectra.T, a, axes=(1, 0))

    def _abundance_flat(self, e: np.ndarray, n: np.ndarray) -> np.ndarray:
        a = self._background(e - self.origin_e, n - self.origin_n)
        if e.size == 0 or not self.shapes:
            return a
        bb = self._bboxes
        hit = ((bb[:, 0] <= e.max()) & (bb[:, 2] >= e.min())
               & (bb[:, 1] <= n.max()) & (bb[:, 3] >= n.min()))
        for k in np.nonzero(hit)[0]:
            shape = self.shapes[k]
            w, s, ea, no = bb[k]
            cand = np.nonzero((e >= w) & (e < ea) & (n >= s) & (n < no))[0]
            if cand.size == 0:
                continue
            pe, pn = e[cand], n[cand]
            kind = shape["kind"]
            if kind == "rect":
                a[:, cand] = 0.0
                a[shape["material"], cand] = shape.get("abundance", 1.0)
            elif kind == "checker":
                sq = shape["square"]
                parity = (np.floor((pe - w) / sq) + np.floor((pn - s) / sq)).astype(np.int64) % 2
                m = np.asarray(shape["materials"])[parity]
                a[:, cand] = 0.0
                a[m, cand] = 1.0
            elif kind == "polygon":
                inside = cand[points_in_polygon(np.asarray(shape["vertices"], float), pe, pn)]
                a[:, inside] = 0.0
                a[shape["material"], inside] = 1.0
            else:  # pragma: no cover - shapes come from layout()
                raise ValueError(f"unknown shape kind {kind!r}")
        return a

    def _cells(self, i: np.ndarray, j: np.ndarray) -> dict[str, np.ndarray]:
        """Per-cell random parameters of Voronoi cells (i, j): seed point (local m), the two
        background materials (indices into _BACKGROUND), the main fraction and the brightness."""
        salt = self.seed * 8
        nb = len(_BACKGROUND)
        h = _hash(i, j, salt + 1)
        m1 = (h % np.uint64(nb)).astype(np.int64)
        step = 1 + ((h >> np.uint64(8)) % np.uint64(nb - 1)).astype(np.int64)
        return {
            "sx": (i + 0.2 + 0.6 * (h >> np.uint64(11)).astype(np.float64) / 9007199254740992.0) * self.cell,
            "sy": (j + 0.2 + 0.6 * _u01(i, j, salt + 2)) * self.cell,
            "m1": m1, "m2": (m1 + step) % nb,
            "frac": 0.55 + 0.45 * _u01(i, j, salt + 3),
            "bright": 0.6 + 0.4 * _u01(i, j, salt + 4),
        }

    def _background(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Textured background abundances (materials, n) at local coordinates (m from origin)."""
        c = self.cell
        i0 = np.floor(x / c).astype(np.int64)
        j0 = np.floor(y / c).astype(np.int64)
        a = np.zeros((len(self.materials), x.size))
        if x.size == 0:
            return a
        # Seeds are jittered within the central 60 % of their cell, so the nearest seed is always
        # one of the 2 x 2 cells on the point's side of its cell centre (an exact Voronoi test).
        si = np.where(x / c - i0 < 0.5, -1, 1)
        sj = np.where(y / c - j0 < 0.5, -1, 1)
        offsets = [(0, 0), (1, 0), (0, 1), (1, 1)]
        ilo, jlo = int(i0.min()) - 1, int(j0.min()) - 1
        ni, nj = int(i0.max()) + 2 - ilo, int(j0.max()) + 2 - jlo
        if ni * nj <= max(4 * x.size, 4096):
            # cells of this chunk's bounding box, hashed once and looked up per point
            ii, jj = np.meshgrid(np.arange(ilo, ilo + ni), np.arange(jlo, jlo + nj), indexing="ij")
            table = self._cells(ii.ravel(), jj.ravel())
            base = (i0 - ilo) * nj + (j0 - jlo)
            candidates = [base + di * si * nj + dj * sj for di, dj in offsets]
            best, best_d2 = candidates[0], None
            for k in candidates:
                d2 = (x - table["sx"][k]) ** 2 + (y - table["sy"][k]) ** 2
                if best_d2 is None:
                    best_d2 = d2
                    continue
                closer = d2 < best_d2
                best = np.where(closer, k, best)
                best_d2 = np.where(closer, d2, best_d2)
            cell = {key: value[best] for key, value in table.items()}
        else:
            seeds = [self._cells(i0 + di * si, j0 + dj * sj) for di, dj in offsets]
            d2 = np.stack([(x - q["sx"]) ** 2 + (y - q["sy"]) ** 2 for q in seeds])
            k = np.argmin(d2, axis=0)
            di = np.array([o[0] for o in offsets])[k]
            dj = np.array([o[1] for o in offsets])[k]
            cell = self._cells(i0 + di * si, j0 + dj * sj)
        mod = np.ones_like(x)
        for amp, ke, kn, phase in self.waves:
            mod += amp * np.sin(ke * x + kn * y + phase)
        bg = np.asarray(_BACKGROUND)
        cols = np.arange(x.size)
        weight = cell["bright"] * mod
        a[bg[cell["m1"]], cols] = weight * cell["frac"]
        a[bg[cell["m2"]], cols] = weight * (1.0 - cell["frac"])
        return a

    # --- serialisation ------------------------------------------------------------------------------
    def to_dict(self) -> dict:
        """JSON-able parameters (spectra and wavelengths go to the npz)."""
        return {"origin_e": self.origin_e, "origin_n": self.origin_n, "seed": self.seed,
                "cell": self.cell, "waves": self.waves.tolist(), "shapes": list(self.shapes),
                "materials": list(self.materials)}

    @classmethod
    def from_dict(cls, d: dict, wavelengths: np.ndarray, spectra: np.ndarray) -> Scene:
        return cls(float(d["origin_e"]), float(d["origin_n"]), int(d["seed"]), float(d["cell"]),
                   np.asarray(d["waves"], float).reshape(-1, 4), tuple(d["shapes"]),
                   np.asarray(wavelengths, float), np.asarray(spectra, float), tuple(d["materials"]))

    def homogeneous_patches(self) -> list[dict]:
        """The homogeneous rectangles: dicts with name, material (index), material_name, bounds
        (west, south, east, north) UTM m, and ``interior`` bounds shrunk by 0.3 m (safe to average)."""
        out = []
        for s in self.shapes:
            if s.get("homogeneous"):
                w, so, e, n = s["bounds"]
                out.append({"name": s["name"], "material": s["material"],
                            "material_name": self.materials[s["material"]], "bounds": (w, so, e, n),
                            "interior": (w + 0.3, so + 0.3, e - 0.3, n - 0.3)})
        return out


def _shape_bbox(shape: dict) -> tuple[float, float, float, float]:
    if shape["kind"] == "polygon":
        v = np.asarray(shape["vertices"], float)
        return float(v[:, 0].min()), float(v[:, 1].min()), float(v[:, 0].max()), float(v[:, 1].max())
    return tuple(float(b) for b in shape["bounds"])


def random_waves(rng: np.random.Generator, count: int = 6) -> np.ndarray:
    """(count, 4) sinusoid terms: amplitude 0.04-0.06, wavelength 0.6-3 m, random direction/phase."""
    amp = rng.uniform(0.04, 0.06, count)
    wavelength = np.exp(rng.uniform(math.log(0.6), math.log(3.0), count))
    theta = rng.uniform(0.0, np.pi, count)
    k = 2.0 * np.pi / wavelength
    return np.stack([amp, k * np.sin(theta), k * np.cos(theta), rng.uniform(0, 2 * np.pi, count)], axis=1)
