"""Least squares over tie windows: the parameters that bring every window's two rays (one per pass)
onto the same ground point, their 1-sigma uncertainties and what the flight can separate.

A tie (see :mod:`archive.calibrate.match`) becomes an observation pair: pass A's ray (line, u)
through the window centre and pass B's ray through the centre + measured shift, both found by
inverting the model under the parameters it was measured with. The residual under trial
parameters is the difference of the two rays' ground points (N, E), in pixels of the flight's
nominal GSD: zero for every window when the parameters are right, whatever they were measured
under. Robust loss (soft L1): a few false matches do not pull the fit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from archive.calibrate.model import PARAM_NAMES, FlightModel, Params

__all__ = ["Anchored", "Observations", "Fit", "anchored", "observations", "fit", "residuals", "stacked", "SCALE"]

#: Typical size of each parameter's correction (deg, deg, deg, s, m, m, m, m): the optimiser's scale and
#: finite-difference steps are relative to it.
SCALE = np.array([0.05, 0.05, 0.05, 0.01, 0.5, 0.5, 0.5, 0.5])
#: Soft-L1 scale of the robust loss, pixels.
F_SCALE = 0.3
#: Residual charged for a tie whose ray loses its navigation under a trial (a sync offset moving its
#: line past the end of the navigation): more than any real misregistration, so that a trial cannot
#: win by pushing ties out of the flight.
LOST_PX = 1000.0


@dataclass(frozen=True, eq=False)
class Observations:
    """Tie rays: pass indices (n,), lines (n,) and focal-plane u (n,) for sides A and B."""

    pass_a: np.ndarray
    line_a: np.ndarray
    u_a: np.ndarray
    pass_b: np.ndarray
    line_b: np.ndarray
    u_b: np.ndarray

    def __len__(self) -> int:
        return int(self.pass_a.size)

    def subset(self, keep: np.ndarray) -> Observations:
        return Observations(*(getattr(self, f)[keep] for f in
                              ("pass_a", "line_a", "u_a", "pass_b", "line_b", "u_b")))


def observations(model: FlightModel, grids: dict, ties: list, params: Params) -> Observations:
    """Rays of ``ties`` (measured under ``params``) on the grids they were measured on
    (``grids[(a, b)]``)."""
    cols = {k: [] for k in ("pass_a", "line_a", "u_a", "pass_b", "line_b", "u_b")}
    by_pair: dict = {}
    for t in ties:
        by_pair.setdefault((t.a, t.b), []).append(t)
    for (a, b), group in by_pair.items():
        grid = grids[(a, b)]
        centre = np.array([t.centre for t in group])
        moved = centre + np.array([t.shift for t in group])
        for side, rc, p in (("a", centre, grid.a), ("b", moved, grid.b)):
            ne = grid.points(rc[:, 0], rc[:, 1])
            down = model.frame.origin_alt - model.ground_height_at(ne[:, 0], ne[:, 1], params)
            line, u = model.inverse(p, np.column_stack([ne, down]), params)
            cols[f"pass_{side}"].append(np.full(len(group), p.index))
            cols[f"line_{side}"].append(line)
            cols[f"u_{side}"].append(u)
    if not ties:
        return Observations(*(np.zeros(0, int if k.startswith("pass") else float) for k in cols))
    obs = Observations(*(np.concatenate(cols[k]) for k in cols))
    ok = np.isfinite(obs.line_a) & np.isfinite(obs.line_b) & np.isfinite(obs.u_a) & np.isfinite(obs.u_b)
    return obs.subset(ok)


@dataclass(frozen=True, eq=False)
class Anchored:
    """Tie rays of a flight against fixed ground points (a reference flight held fixed, DESIGN 11):
    the flight's pass indices (n,), lines (n,) and focal-plane u (n,), and where the reference sees
    the same ground, ``target`` (n, 2) N, E metres in the flight's frame."""

    pass_a: np.ndarray
    line_a: np.ndarray
    u_a: np.ndarray
    target: np.ndarray

    def __len__(self) -> int:
        return int(self.pass_a.size)

    def subset(self, keep: np.ndarray) -> Anchored:
        return Anchored(self.pass_a[keep], self.line_a[keep], self.u_a[keep], self.target[keep])


def anchored(model: FlightModel, grids: dict, ties: list, params: Params) -> Anchored:
    """Rays of the flight side of ``ties`` (measured under ``params`` on ``grids[(a, b)]``: pass a
    of the flight, pass b of the reference, rendered under its own fixed parameters) and the ground
    points where the reference sees them (the window centre + the measured shift)."""
    parts = []
    by_pair: dict = {}
    for t in ties:
        by_pair.setdefault((t.a, t.b), []).append(t)
    for (a, b), group in by_pair.items():
        grid = grids[(a, b)]
        centre = np.array([t.centre for t in group])
        target = grid.points(*(centre + np.array([t.shift for t in group])).T)
        ne = grid.points(centre[:, 0], centre[:, 1])
        down = model.frame.origin_alt - model.ground_height_at(ne[:, 0], ne[:, 1], params)
        line, u = model.inverse(grid.a, np.column_stack([ne, down]), params)
        parts.append((np.full(len(group), grid.a.index), line, u, target))
    if not parts:
        return Anchored(np.zeros(0, int), np.zeros(0), np.zeros(0), np.zeros((0, 2)))
    obs = Anchored(*(np.concatenate([p[k] for p in parts]) for k in range(4)))
    return obs.subset(np.isfinite(obs.line_a) & np.isfinite(obs.u_a))


def residuals(model: FlightModel, obs: Observations | Anchored, params: Params, pixel: float) -> np.ndarray:
    """(n, 2) ground distance N, E between the two rays of every tie under ``params`` (an
    :class:`Anchored` tie: between the flight's ray and the reference's fixed point), pixels."""
    out = np.full((len(obs), 2), np.nan)
    if isinstance(obs, Anchored):
        for k in np.unique(obs.pass_a):
            sel = obs.pass_a == k
            out[sel] = model.forward(model.passes[int(k)], obs.line_a[sel], obs.u_a[sel], params, strict=False)
        return (out - obs.target) / pixel
    for side in ("a", "b"):
        passes = getattr(obs, f"pass_{side}")
        for k in np.unique(passes):
            sel = passes == k
            xy = model.forward(model.passes[int(k)], getattr(obs, f"line_{side}")[sel],
                               getattr(obs, f"u_{side}")[sel], params, strict=False)
            if side == "a":
                out[sel] = xy
            else:
                out[sel] -= xy
    return out / pixel


@dataclass(frozen=True, eq=False)
class Fit:
    """A solution: params; free: names of the estimated parameters; cov: their covariance
    (free x free, units deg, s, m); residual_px: (n,) distances of the ties after the fit;
    inliers: (n,) bool; cost: robust cost."""

    params: Params
    free: tuple[str, ...]
    cov: np.ndarray
    residual_px: np.ndarray
    inliers: np.ndarray
    cost: float

    def sigma(self) -> dict[str, float]:
        return {name: float(np.sqrt(max(self.cov[i, i], 0.0))) for i, name in enumerate(self.free)}

    def correlation(self) -> np.ndarray:
        s = np.sqrt(np.maximum(np.diag(self.cov), 1e-300))
        return self.cov / np.outer(s, s)


def stacked(sets, params: Params, pixel: float) -> np.ndarray:
    """(n, 2) residuals of every (model, observations) of ``sets`` (one per flight) under the shared
    ``params``, pixels."""
    parts = [residuals(model, obs, params, pixel) for model, obs in sets]
    return np.concatenate(parts) if parts else np.zeros((0, 2))


def fit(sets, start: Params, free: tuple[str, ...], pixel: float, max_nfev: int = 200,
        bounds: tuple[np.ndarray, np.ndarray] | None = None) -> Fit:
    """Least squares over the ``free`` parameters from ``start`` (the others held), shared by the
    flights of ``sets`` ((model, observations) pairs). Ties whose rays lose their navigation under a
    trial (a sync offset moves lines past the ends) cost a constant: never zero. ``bounds``: (low,
    high) of all five parameters (model order), or None."""
    index = [PARAM_NAMES.index(n) for n in free]
    base = start.vector()

    def params_of(x):
        v = base.copy()
        v[index] = x
        return Params.from_vector(v)

    def fun(x):
        r = stacked(sets, params_of(x), pixel).ravel()
        return np.where(np.isfinite(r), r, LOST_PX)

    x0 = base[index]
    scale = SCALE[index]
    if index:
        lo, hi = (-np.inf * np.ones(len(index)), np.inf * np.ones(len(index))) if bounds is None else \
            (np.asarray(bounds[0], float)[index], np.asarray(bounds[1], float)[index])
        x0 = np.clip(x0, lo, hi)
        result = least_squares(fun, x0, x_scale=scale, diff_step=1e-4 * scale / np.maximum(np.abs(x0), 1.0),
                               bounds=(lo, hi),
                               loss="soft_l1", f_scale=F_SCALE, max_nfev=max_nfev, method="trf")
        x = result.x
        cost = float(result.cost)
    else:
        x = x0
        cost = float(0.5 * np.sum(fun(x0) ** 2))
    params = params_of(x)
    r = stacked(sets, params, pixel)
    dist = np.hypot(r[:, 0], r[:, 1])
    finite = np.isfinite(dist)
    mad = np.median(dist[finite]) if finite.any() else 0.0
    inliers = finite & (dist <= max(3.0 * 1.4826 * mad, 0.05) + 2.0 * mad)
    kept, start_row = [], 0
    for model, obs in sets:
        kept.append((model, obs.subset(inliers[start_row:start_row + len(obs)])))
        start_row += len(obs)
    cov = _covariance(kept, params, index, pixel) if index else np.zeros((0, 0))
    return Fit(params, tuple(free), cov, dist, inliers, cost)


def _covariance(sets, params: Params, index: list[int], pixel: float) -> np.ndarray:
    """Gauss-Newton covariance of the free parameters on the inlier ties: sigma^2 (J^T J)^-1, sigma
    from the residual scatter. Windows half overlap (neighbours share pixels), so the residuals of
    about four windows are not independent: the covariance is scaled by 4."""
    base = params.vector()
    r0 = stacked(sets, params, pixel).ravel()
    jac = np.zeros((r0.size, len(index)))
    for j, i in enumerate(index):
        step = 1e-3 * SCALE[i]
        hi, lo = base.copy(), base.copy()
        hi[i] += step
        lo[i] -= step
        jac[:, j] = (stacked(sets, Params.from_vector(hi), pixel).ravel()
                     - stacked(sets, Params.from_vector(lo), pixel).ravel()) / (2 * step)
    ok = np.isfinite(r0) & np.isfinite(jac).all(axis=1)
    jac, r0 = jac[ok], r0[ok]
    dof = max(r0.size - len(index), 1)
    sigma2 = float(np.sum(r0 ** 2) / dof)
    jtj = jac.T @ jac
    try:
        cov = np.linalg.inv(jtj)
    except np.linalg.LinAlgError:
        cov = np.linalg.pinv(jtj)
    return 4.0 * sigma2 * cov
