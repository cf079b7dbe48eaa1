"""A slow numpy reference of the renderer's mapping, to cross-check the shaders in tests.

For each query point (UTM E, N) it finds, triangle by triangle in drawing order (later wins), the
barycentric weights b of the point in the mesh's ground triangles, then
L = sum b_k L_k, s = sum b_k lambda_k s_k / sum b_k lambda_k (perspective-correct, see mesh.py),
line = floor(L + 0.5) (discarded outside [0, lines)), sample = clamp(floor(samples * s)).
Points exactly on a shared edge may be given to either triangle (GL's fill rule decides there).
"""

from __future__ import annotations

import numpy as np

from archive.render.mesh import Mesh


def reference_lookup(
    mesh: Mesh, samples: int, e: np.ndarray, n: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(line (p,) int64, sample (p,) int64, covered (p,) bool) seen at UTM points e, n (p,) metres.

    line and sample are -1 where not covered.
    """
    e = np.asarray(e, np.float64).reshape(-1)
    n = np.asarray(n, np.float64).reshape(-1)
    pe = e - mesh.frame.origin_e
    pn = n - mesh.frame.origin_n
    pos, attr = mesh.vertex_attributes()         # (v, 2) N, E ; (v, 3) L, s, lambda
    line_out = np.full(e.shape, -1, np.int64)
    sample_out = np.full(e.shape, -1, np.int64)
    for tri in mesh.triangles():
        vn = pos[tri, 0]
        ve = pos[tri, 1]
        inside = (pe >= ve.min()) & (pe <= ve.max()) & (pn >= vn.min()) & (pn <= vn.max())
        idx = np.nonzero(inside)[0]
        if idx.size == 0:
            continue
        # Barycentric weights in the (E, N) plane.
        x0, y0 = ve[0], vn[0]
        d1 = np.array([ve[1] - x0, vn[1] - y0])
        d2 = np.array([ve[2] - x0, vn[2] - y0])
        det = d1[0] * d2[1] - d1[1] * d2[0]
        if det == 0:
            continue
        qx = pe[idx] - x0
        qy = pn[idx] - y0
        b1 = (qx * d2[1] - qy * d2[0]) / det
        b2 = (d1[0] * qy - d1[1] * qx) / det
        b0 = 1.0 - b1 - b2
        tol = -1e-12
        hit = (b0 >= tol) & (b1 >= tol) & (b2 >= tol)
        if not hit.any():
            continue
        idx = idx[hit]
        b = np.stack([b0[hit], b1[hit], b2[hit]], axis=1)
        a = attr[tri]
        big_l = b @ a[:, 0]
        s = (b @ (a[:, 2] * a[:, 1])) / (b @ a[:, 2])
        line = np.floor(big_l + 0.5).astype(np.int64)
        ok = (line >= 0) & (line < mesh.lines)
        line_out[idx[ok]] = line[ok]
        sample_out[idx[ok]] = np.clip(np.floor(samples * s[ok]).astype(np.int64), 0, samples - 1)
    return line_out, sample_out, line_out >= 0


def reference_values(
    mesh: Mesh, dn: np.ndarray, radiometry, e: np.ndarray, n: np.ndarray
) -> np.ndarray:
    """(bands, p) float64 values ``(DN - dark) * gain / response`` at UTM points, NaN uncovered.

    dn (bands, lines, samples); radiometry as for render_cube (None = raw DN).
    """
    nb, lines, samples = dn.shape
    line, sample, covered = reference_lookup(mesh, samples, e, n)
    out = np.full((nb, line.size), np.nan)
    li, si = line[covered], sample[covered]
    vals = dn[:, li, si].astype(np.float64)
    if radiometry is not None:
        dark = np.asarray(radiometry.dark, np.float64)
        gain = np.asarray(radiometry.gain, np.float64)
        resp = np.asarray(radiometry.response, np.float64)
        vals = (vals - dark[:, si]) * gain[:, si] / resp[li]
    out[:, covered] = vals
    return out
