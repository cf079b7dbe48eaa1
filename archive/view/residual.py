"""Residual misregistration between two time steps of a stack (issue 33, item 5 of issue 23): where
two flights of one place line up, and where they do not, measured on the stack's own pixels.

``GET /api/stacks/{name}/residual?a=T&b=U[&band=B]`` -> JSON: the stack's GSD, the windows measured
(lon, lat of each window's centre; its shift from time step ``a`` to ``b`` east and north in pixels
and its length), their median and 95th percentile, and how many windows were tried, textured and
matched. The shift of a window is what :mod:`archive.calibrate.match` measures between passes:
an integer masked-NCC search (a few pixels), then Lucas-Kanade with a gain and offset per window
(robust to a different day's light). Windows without data in both steps, flat ones and ones that do
not correlate (changed ground) are left out and counted. Memory: one strip of ``WINDOW`` rows of
both steps at a time.
"""

from __future__ import annotations

import math

import numpy as np

from archive.errors import InputError

__all__ = ["MAX_WINDOWS", "WINDOW", "residual_routes", "stack_residual"]

#: Side of a measurement window, stack pixels.
WINDOW = 32
#: Most windows measured over a stack (the lattice step grows with its size).
MAX_WINDOWS = 600
#: Integer search of the coarse step, pixels either way (a GNSS bias of 3 m at 25 cm: 12 px).
SEARCH = 16
#: A window is textured when its RMS gradient exceeds this fraction of its mean (as the calibration).
TEXTURE = 0.02


def _index(value, count: int, what: str) -> int:
    try:
        k = int(value)
    except (TypeError, ValueError):
        raise InputError(what, f"expected an index, got {value!r}") from None
    if not 0 <= k < count:
        raise InputError(what, f"{k} is not in 0..{count - 1}")
    return k


def _strip(array, t: int, band: int, r: int, window: int, pad: int, width: int) -> np.ndarray:
    """Rows r - pad .. r + window + pad of time step ``t``, band ``band`` (float64, NaN beyond the
    stack), with ``pad`` NaN columns added on either side: (window + 2 pad, width + 2 pad)."""
    h = array.shape[2]
    out = np.full((window + 2 * pad, width + 2 * pad), np.nan)
    r0, r1 = max(0, r - pad), min(h, r + window + pad)
    out[r0 - (r - pad):r1 - (r - pad), pad:pad + width] = np.asarray(array[t, band, r0:r1, :], np.float64)
    return out


def stack_residual(view, a, b, band=None, window: int = WINDOW, max_windows: int = MAX_WINDOWS) -> dict:
    """Misregistration of time step ``b`` against ``a`` of ``view`` (an
    :class:`archive.view.stacks.StackView`) on ``band`` (stack band index, default the middle one):
    see the module docstring. Shifts are (east, north) stack pixels: the content of ``a`` at a
    window is seen by ``b`` that far away."""
    from pyproj import Transformer

    from archive.calibrate.match import lucas_kanade, masked_ncc

    steps = len(view.flights)
    ta, tb = _index(a, steps, "a"), _index(b, steps, "b")
    nb = len(view.layout.bands)
    band = nb // 2 if band in (None, "") else _index(band, nb, "band")
    grid = view.grid
    h, w = grid.height, grid.width
    step = max(window // 4, int(math.ceil(math.sqrt(h * w / max(max_windows, 1)))))
    xc, yc = grid.xy_centres()
    to_lonlat = Transformer.from_crs(grid.epsg, 4326, always_xy=True)
    found, tried, textured = [], 0, 0
    pad = SEARCH
    for r in range(0, h - window + 1, step):
        strip_a = _strip(view.array, ta, band, r, window, 0, w)
        strip_b = _strip(view.array, tb, band, r, window, pad, w)
        for c in range(0, w - window + 1, step):
            ref = strip_a[:, c:c + window]
            big = strip_b[:, c:c + window + 2 * pad]        # strip_b has pad NaN columns on either side
            if not np.isfinite(ref).all() or np.isfinite(big[pad:pad + window, pad:pad + window]).mean() < 0.9:
                continue
            tried += 1
            gy, gx = np.gradient(ref)
            if np.sqrt(np.mean(gx ** 2 + gy ** 2)) < TEXTURE * abs(np.mean(ref)):
                continue
            textured += 1
            fixed = np.full(big.shape, np.nan)
            fixed[pad:pad + window, pad:pad + window] = ref
            ncc, _ = masked_ncc(fixed, big, (pad, pad), min_overlap=0.99)
            iy, ix = np.unravel_index(int(np.argmax(ncc)), ncc.shape)
            if ncc[iy, ix] < 0.5:
                continue
            dy, dx = iy - pad, ix - pad
            img = big[pad + dy:pad + dy + window, pad + dx:pad + dx + window]
            if not np.isfinite(img).all():
                continue
            fine, ok = lucas_kanade(ref, img)
            if not ok or np.abs(fine).max() > 1.0:
                continue
            sy, sx = dy + fine[0], dx + fine[1]
            lon, lat = to_lonlat.transform(float(xc[c + window // 2]), float(yc[r + window // 2]))
            # rows grow southwards: a shift of +sy rows is -sy pixels north
            found.append({"lon": round(lon, 8), "lat": round(lat, 8), "east_px": round(float(sx), 4),
                          "north_px": round(float(-sy), 4), "px": round(float(math.hypot(sx, sy)), 4)})
    size = np.array([f["px"] for f in found])
    return {"stack": view.name, "a": {"time": ta, "flight": view.flights[ta].id},
            "b": {"time": tb, "flight": view.flights[tb].id}, "band": band, "gsd": grid.gsd, "window": window,
            "median": None if not found else round(float(np.median(size)), 4),
            "p95": None if not found else round(float(np.percentile(size, 95)), 4),
            "tried": tried, "textured": textured, "matched": len(found), "windows": found}


def residual_routes(stack_of) -> list:
    """The viewer's route ``/api/stacks/{name}/residual`` (``stack_of(request)``: the StackView the
    request names, as the server's other stack routes find it)."""
    from starlette.concurrency import run_in_threadpool
    from starlette.responses import JSONResponse
    from starlette.routing import Route

    async def residual(request):
        p = request.query_params
        view = stack_of(request)
        out = await run_in_threadpool(stack_residual, view, p.get("a", "0"), p.get("b", "1"), p.get("band"))
        return JSONResponse(out)

    return [Route("/api/stacks/{name}/residual", residual)]
