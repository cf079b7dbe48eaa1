"""Misregistration between two overlapping passes: both are rendered (bilinear, from the raw lines,
through :class:`~archive.calibrate.model.FlightModel` under the trial parameters) onto one common
grid aligned with the first pass, then a coarse masked normalised cross-correlation finds the
integer shift (large errors: a sync offset of 1 s moves opposite passes 20 m apart) and Lucas-Kanade
on textured windows refines it to sub-pixel, with a gain and offset per window (robust to the
radiometric differences between passes: view angle, exposure).

Grid axes: rows along the first pass's direction of flight (row 0 first), columns across it (to
its right); ``spacing`` metres per grid pixel. Shifts are (rows, columns) in grid pixels: the
content of pass A at grid point q is seen by pass B at q + shift.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from archive.calibrate.model import FlightModel, Params, Pass

__all__ = ["PairGrid", "Tie", "lucas_kanade", "masked_ncc", "measure_pair", "pair_grid"]

#: Coarse level: grid pixels averaged per coarse pixel (side).
COARSE = 4
#: Coarse search range, metres (a sync offset of 1 s moves opposite passes ~20 m apart).
SEARCH_M = 24.0
#: Least overlap of the coarse correlation, fraction of the fixed image's pixels.
MIN_OVERLAP = 0.3
#: A window is textured when its mean gradient exceeds this fraction of its mean (as the truth test).
TEXTURE = 0.02


@dataclass(frozen=True, eq=False)
class PairGrid:
    """The common grid of passes ``a`` and ``b``: origin (N, E) of grid point (0, 0), unit vectors
    along (rows) and across (columns) in (N, E), ``spacing`` metres, ``shape`` (rows, columns)
    and ``inside`` (rows, columns) bool: points in the overlap of both footprints."""

    a: Pass
    b: Pass
    origin: np.ndarray
    along: np.ndarray
    across: np.ndarray
    spacing: float
    shape: tuple[int, int]
    inside: np.ndarray

    def points(self, rows, cols) -> np.ndarray:
        """(n, 2) N, E of grid coordinates (fractional allowed)."""
        rows = np.asarray(rows, float).ravel()
        cols = np.asarray(cols, float).ravel()
        return (self.origin[None, :] + rows[:, None] * self.spacing * self.along[None, :]
                + cols[:, None] * self.spacing * self.across[None, :])


def pair_grid(model: FlightModel, a: Pass, b: Pass, params: Params, spacing: float,
              grow: float = 8.0, inner: float = 1.0, model_b: FlightModel | None = None,
              params_b: Params | None = None) -> PairGrid | None:
    """The common grid of passes ``a`` and ``b`` under ``params``, None when they do not overlap.
    ``model_b`` / ``params_b``: pass ``b`` belongs to another flight (a reference, its model in
    ``model``'s frame) seen under its own parameters (default: ``model`` / ``params``).

    The grid covers their overlap grown by ``grow`` metres (pass B's content may lie that far from
    where the start parameters put it); ``inside`` marks the overlap grown by ``inner`` metres:
    where pass A's windows are taken."""
    import shapely

    fa = model.footprint(a, params)
    fb = (model_b or model).footprint(b, params if params_b is None else params_b)
    if fa is None or fb is None:
        return None
    overlap = fa.intersection(fb)
    if overlap.is_empty or overlap.area <= 0:
        return None
    pos, _, valid = model.line_poses(a, params)
    track = pos[valid][:, :2]
    along = track[-1] - track[0]
    along = along / np.linalg.norm(along)
    across = np.array([-along[1], along[0]])          # right of the direction of flight (N, E)
    region = overlap.buffer(grow)
    ring = np.asarray(region.convex_hull.exterior.coords)
    ra, rc = ring @ along, ring @ across
    origin = ra.min() * along + rc.min() * across
    shape = (int(np.floor((ra.max() - ra.min()) / spacing)) + 1, int(np.floor((rc.max() - rc.min()) / spacing)) + 1)
    grid = PairGrid(a, b, origin, along, across, float(spacing), shape, np.zeros(shape, bool))
    rr, cc = np.mgrid[0:shape[0], 0:shape[1]]
    pts = grid.points(rr, cc)
    inside = shapely.contains_xy(overlap.buffer(inner), pts[:, 0], pts[:, 1]).reshape(shape)
    return PairGrid(a, b, origin, along, across, float(spacing), shape, inside)


def render_pass(model: FlightModel, p: Pass, image: np.ndarray, grid: PairGrid, params: Params,
                rows: np.ndarray | None = None, cols: np.ndarray | None = None) -> np.ndarray:
    """Pass ``p``'s ``image`` ((lines, samples) float) bilinearly resampled at the grid points
    (all of them, or the given fractional ``rows``/``cols``), NaN where the pass does not see them."""
    if rows is None:
        rr, cc = np.mgrid[0:grid.shape[0], 0:grid.shape[1]]
        shape = grid.shape
    else:
        rr, cc = np.asarray(rows, float), np.asarray(cols, float)
        shape = rr.shape
    ne = grid.points(rr, cc)
    down = model.frame.origin_alt - model.ground_height_at(ne[:, 0], ne[:, 1], params)
    points = np.column_stack([ne, down])
    line, u = model.inverse(p, points, params)
    sample = model.sample_coordinate(p, u)
    ok = np.isfinite(line) & (line >= 0) & (line <= p.lines - 1) & (sample >= -0.5) & (sample <= p.samples - 0.5)
    coords = np.stack([np.where(ok, line, 0.0), np.clip(np.where(ok, sample, 0.0), 0, p.samples - 1)])
    values = ndimage.map_coordinates(image, coords, order=1, mode="nearest")
    values = np.where(ok, values, np.nan)
    return values.reshape(shape)


def _block_mean(image: np.ndarray, k: int) -> np.ndarray:
    h, w = image.shape[0] // k, image.shape[1] // k
    blocks = image[:h * k, :w * k].reshape(h, k, w, k)
    with np.errstate(invalid="ignore"):
        out = blocks.mean(axis=(1, 3))     # NaN where any pixel of the block is NaN
    return out


def masked_ncc(fixed: np.ndarray, moving: np.ndarray, max_shift: tuple[int, int],
               min_overlap: float = MIN_OVERLAP) -> tuple[np.ndarray, np.ndarray]:
    """Normalised cross-correlation of ``moving`` against ``fixed`` (NaN = no data) for every
    integer shift s with |s| <= max_shift: ncc[s] compares fixed(p) with moving(p + s) over the
    pixels both have (Padfield's masked NCC, by FFT). Returns (ncc (2 my + 1, 2 mx + 1), overlap
    counts); shifts overlapping less than ``min_overlap`` of ``fixed``'s pixels get -1."""
    mf, mm = np.isfinite(fixed), np.isfinite(moving)
    f = np.where(mf, fixed, 0.0)
    m = np.where(mm, moving, 0.0)
    scale = max(np.abs(f).max(), np.abs(m).max(), 1e-30)
    f, m = f / scale, m / scale
    shape = (fixed.shape[0] + moving.shape[0], fixed.shape[1] + moving.shape[1])

    def corr(a, b):   # sum_p a(p) b(p + s), index s mod shape
        return np.fft.irfft2(np.conj(np.fft.rfft2(a, shape)) * np.fft.rfft2(b, shape), shape)

    mf_, mm_ = mf.astype(float), mm.astype(float)
    n = corr(mf_, mm_)
    sf, sm = corr(f, mm_), corr(mf_, m)
    sfm = corr(f, m)
    sff, smm = corr(f * f, mm_), corr(mf_, m * m)
    my, mx = max_shift
    iy = np.arange(-my, my + 1) % shape[0]
    ix = np.arange(-mx, mx + 1) % shape[1]
    sel = np.ix_(iy, ix)
    n, sf, sm, sfm, sff, smm = (v[sel] for v in (n, sf, sm, sfm, sff, smm))
    n = np.round(n)
    with np.errstate(divide="ignore", invalid="ignore"):
        num = sfm - sf * sm / n
        den = np.sqrt(np.maximum(sff - sf * sf / n, 0) * np.maximum(smm - sm * sm / n, 0))
        ncc = num / den
    least = min_overlap * mf.sum()
    ncc = np.where((n >= max(least, 16)) & np.isfinite(ncc), ncc, -1.0)
    return ncc, n


def _peak(ncc: np.ndarray) -> tuple[np.ndarray, float]:
    """Sub-pixel (parabola) position of the maximum, as a shift from the centre, and its value."""
    iy, ix = np.unravel_index(int(np.argmax(ncc)), ncc.shape)
    best = float(ncc[iy, ix])
    out = np.array([iy, ix], float)
    for axis, i in ((0, iy), (1, ix)):
        if 0 < i < ncc.shape[axis] - 1:
            lo = ncc[(i - 1, ix) if axis == 0 else (iy, i - 1)]
            hi = ncc[(i + 1, ix) if axis == 0 else (iy, i + 1)]
            den = lo - 2 * best + hi
            if den < 0:
                out[axis] += 0.5 * (lo - hi) / den
    return out - (np.array(ncc.shape) - 1) / 2.0, best


def lucas_kanade(reference: np.ndarray, image: np.ndarray, start=(0.0, 0.0), iterations: int = 8
                 ) -> tuple[np.ndarray, bool]:
    """Shift (dy, dx) px such that image(p) ~ a * reference(p - shift) + b (gain and offset per
    window), Gauss-Newton from ``start``; converged when the last update is below 0.005 px."""
    shift = np.asarray(start, float).copy()
    core = (slice(3, -3), slice(3, -3))
    target = image[core].ravel()
    for _ in range(iterations):
        moved = ndimage.shift(reference, shift, order=3, mode="nearest")
        gy, gx = np.gradient(moved)
        a = np.stack([gy[core].ravel(), gx[core].ravel(), moved[core].ravel(), np.ones(target.size)], axis=1)
        coef, *_ = np.linalg.lstsq(a, target, rcond=None)
        if not np.isfinite(coef).all() or abs(coef[2]) < 1e-6:
            return shift, False
        step = -coef[:2] / coef[2]
        shift = shift + step
        if np.abs(shift).max() > 3.0:
            return shift, False
        if np.abs(step).max() < 0.005:
            return shift, True
    return shift, False


@dataclass(frozen=True)
class Tie:
    """One measured window: pass indices, grid centre (row, col), shift (rows, cols) grid pixels
    (pass B sees at centre + shift what pass A sees at the centre), NCC of the coarse match."""

    a: int
    b: int
    centre: tuple[float, float]
    shift: tuple[float, float]
    score: float


def measure_pair(model: FlightModel, grid: PairGrid, image_a: np.ndarray, image_b: np.ndarray,
                 params: Params, window: int = 24, prior: np.ndarray | None = None,
                 model_b: FlightModel | None = None, params_b: Params | None = None,
                 fallback: np.ndarray | None = None, max_windows: int | None = None) -> tuple[list[Tie], dict]:
    """Tie windows between the passes of ``grid`` under ``params``.

    image_a/b: (lines, samples) float images of the passes. window: side (grid pixels) of the
    square windows (every fully covered textured one, half overlapping). prior: an expected shift
    (rows, cols) grid pixels, or None: a coarse masked NCC over SEARCH_M finds it. model_b /
    params_b: pass B's flight and parameters when it is another flight's (see :func:`pair_grid`).
    fallback: the shift (rows, cols) to assume where no block of the coarse search correlates
    clearly (ground that changed between two flights), or None: then nothing is measured.
    max_windows: measure at most this many windows (spread evenly over the overlap), None: all.
    Returns the ties and counts (overlap pixels, windows tried, textured, matched)."""
    ra = render_pass(model, grid.a, image_a, grid, params)
    rb = render_pass(model_b or model, grid.b, image_b, grid, params if params_b is None else params_b)
    ra[~grid.inside] = np.nan      # A's windows: in the overlap; B: all it sees around it
    stats = {"overlap_px": int(np.count_nonzero(np.isfinite(ra) & np.isfinite(rb))), "windows": 0,
             "textured": 0, "matched": 0}
    ca, cb = _block_mean(ra, COARSE), _block_mean(rb, COARSE)
    reach = int(np.ceil(SEARCH_M / (grid.spacing * COARSE)))
    block = max(16, ca.shape[1])
    blocks = []       # (first fine row, last fine row, shift (rows, cols) fine px, score)
    for b0 in range(0, ca.shape[0], block):
        b1 = min(b0 + block, ca.shape[0])
        if prior is not None:
            blocks.append((b0 * COARSE, b1 * COARSE, np.asarray(prior, float), 1.0))
            continue
        lo, hi = max(0, b0 - reach), min(ca.shape[0], b1 + reach)
        fixed = np.full((hi - lo, ca.shape[1]), np.nan)
        fixed[b0 - lo:b1 - lo] = ca[b0:b1]
        if np.count_nonzero(np.isfinite(fixed)) < 32:
            continue
        ncc, _ = masked_ncc(fixed, cb[lo:hi], (reach, max(2, reach // 2)), min_overlap=0.5)
        shift, score = _peak(ncc)
        if score >= 0.5:
            blocks.append((b0 * COARSE, b1 * COARSE, shift * COARSE, score))
    if not blocks and fallback is not None:
        blocks = [(0, ca.shape[0] * COARSE, np.asarray(fallback, float), 0.0)]
    if not blocks:
        return [], stats
    shifts = np.array([b[2] for b in blocks])
    median = np.median(shifts, axis=0)
    # a block far from its neighbours' consensus is a false match: use the median instead
    blocks = [(b[0], b[1], b[2] if np.abs(b[2] - median).max() <= 2.5 * COARSE + 0.5 * reach * COARSE else median,
               b[3]) for b in blocks]
    ties = []
    h, w = grid.shape
    step = max(4, window // 2)
    # every fully covered window position of pass A; at most max_windows of them, spread evenly
    covered = np.isfinite(ra)
    places = [(r, c) for r in range(0, h - window + 1, step) for c in range(0, w - window + 1, step)
              if covered[r:r + window, c:c + window].all()]
    if max_windows is not None and len(places) > max_windows:
        places = [places[int(k)] for k in np.linspace(0, len(places) - 1, max_windows)]
    for r, c in places:
        ref = ra[r:r + window, c:c + window]
        stats["windows"] += 1
        gy, gx = np.gradient(ref)
        if np.sqrt(np.mean(gx ** 2 + gy ** 2)) < TEXTURE * abs(np.mean(ref)):
            continue
        stats["textured"] += 1
        centre_row = r + window // 2
        near = min(blocks, key=lambda b: 0 if b[0] <= centre_row < b[1] else min(abs(centre_row - b[0]),
                                                                                  abs(centre_row - b[1])))
        coarse, score = near[2], near[3]
        local = _local_shift(ra, rb, r, c, window, coarse)
        if local is None:
            continue
        offset = np.round(local).astype(int)
        fine, ok, best = None, False, 0.0
        for _ in range(3):
            r0, c0 = r + offset[0], c + offset[1]
            if r0 < 0 or c0 < 0 or r0 + window > h or c0 + window > w:
                break
            img = rb[r0:r0 + window, c0:c0 + window]
            if not np.isfinite(img).all():
                break
            fine, ok = lucas_kanade(ref, img, start=local - offset)
            if not ok or np.abs(fine).max() <= 0.6:
                break
            offset = offset + np.round(fine).astype(int)   # re-centre the window and refine again
            local = offset + (fine - np.round(fine))
        if fine is None or not ok or np.abs(fine).max() > 0.6:
            continue
        total = offset + fine
        ties.append(Tie(grid.a.index, grid.b.index, (r + (window - 1) / 2.0, c + (window - 1) / 2.0),
                        (float(total[0]), float(total[1])), float(score)))
        stats["matched"] += 1
    return ties, stats


def _local_shift(ra, rb, r, c, window, coarse, pad: int = 3 * COARSE) -> np.ndarray | None:
    """Shift of one window (integer + parabola) from a masked NCC search within ``pad`` grid
    pixels of ``coarse``; None without a clear match."""
    base = np.round(coarse).astype(int)
    r0, c0 = r + base[0] - pad, c + base[1] - pad
    h, w = rb.shape
    if r0 < 0 or c0 < 0 or r0 + window + 2 * pad > h or c0 + window + 2 * pad > w:
        return None
    big = rb[r0:r0 + window + 2 * pad, c0:c0 + window + 2 * pad]
    fixed = np.full(big.shape, np.nan)
    fixed[pad:pad + window, pad:pad + window] = ra[r:r + window, c:c + window]
    ncc, _ = masked_ncc(fixed, big, (pad, pad), min_overlap=0.99)
    peak, best = _peak(ncc)
    if best < 0.5:
        return None
    return base + peak
