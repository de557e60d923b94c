"""Numba kernel of the frame-to-frame patch alignment (robotd.frontend.align); numpy twin:
``align_numpy`` in tests/support/reference_frontend.py, which the tests hold it to.

One keypoint at a time: the previous frame's patch (bilinear samples around its keypoint, with a
one-pixel border for central-difference gradients) is the template, and the shift of the current
keypoint that best matches it in zero-mean squared difference is found by inverse-compositional
Gauss–Newton (module doc of robotd.frontend.align). A few hundred keypoints take well under a
millisecond.
"""

from __future__ import annotations

import math

import numpy as np

from robotd.core.jit import jit


@jit
def align_kernel(
    prev: np.ndarray,
    curr: np.ndarray,
    xp: np.ndarray,
    yp: np.ndarray,
    xc: np.ndarray,
    yc: np.ndarray,
    half: int,
    iterations: int,
    max_px: float,
    dx: np.ndarray,
    dy: np.ndarray,
    ok: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """Fill dx, dy, ok (N,) for the patches at (xp, yp) in ``prev`` and (xc, yc) in ``curr``
    (uint8 images of one size); ok False leaves dx = dy = 0."""
    rows, cols = prev.shape
    m = 2 * half + 1
    area = float(m * m)
    T = np.empty((m + 2, m + 2))
    gx = np.empty((m, m))
    gy = np.empty((m, m))
    margin = half + 2.0 + max_px
    for i in range(xp.size):
        ok[i] = False
        dx[i] = 0.0
        dy[i] = 0.0
        inside = True
        for x, y in ((xp[i], yp[i]), (xc[i], yc[i])):
            if not (x - margin >= 0.0 and y - margin >= 0.0 and x + margin < cols - 1 and y + margin < rows - 1):
                inside = False
        if not inside:
            continue
        x0 = math.floor(xp[i])
        y0 = math.floor(yp[i])
        ax = xp[i] - x0
        ay = yp[i] - y0
        for v in range(m + 2):
            r = y0 + v - half - 1
            for u in range(m + 2):
                c = x0 + u - half - 1
                T[v, u] = (1.0 - ay) * ((1.0 - ax) * prev[r, c] + ax * prev[r, c + 1]) + ay * (
                    (1.0 - ax) * prev[r + 1, c] + ax * prev[r + 1, c + 1]
                )
        gxm = 0.0
        gym = 0.0
        for v in range(m):
            for u in range(m):
                gx[v, u] = 0.5 * (T[v + 1, u + 2] - T[v + 1, u])
                gy[v, u] = 0.5 * (T[v + 2, u + 1] - T[v, u + 1])
                gxm += gx[v, u]
                gym += gy[v, u]
        gxm /= area
        gym /= area
        # zero-mean gradients: the patches' means (brightness) drop out of every sum below
        sxx = 0.0
        sxy = 0.0
        syy = 0.0
        tx = 0.0
        ty = 0.0
        for v in range(m):
            for u in range(m):
                gx[v, u] -= gxm
                gy[v, u] -= gym
                sxx += gx[v, u] * gx[v, u]
                sxy += gx[v, u] * gy[v, u]
                syy += gy[v, u] * gy[v, u]
                tx += gx[v, u] * T[v + 1, u + 1]
                ty += gy[v, u] * T[v + 1, u + 1]
        det = sxx * syy - sxy * sxy
        tr = sxx + syy
        lam_min = 0.5 * (tr - math.sqrt(max(tr * tr - 4.0 * det, 0.0)))
        if not (det > 0.0 and lam_min >= 1e-3 * area):
            continue  # no corner: a flat or one-directional patch fixes no 2-D shift
        sx = 0.0
        sy = 0.0
        for _ in range(iterations):
            px = xc[i] + sx
            py = yc[i] + sy
            x0 = math.floor(px)
            y0 = math.floor(py)
            ax = px - x0
            ay = py - y0
            w00 = (1.0 - ax) * (1.0 - ay)
            w01 = ax * (1.0 - ay)
            w10 = (1.0 - ax) * ay
            w11 = ax * ay
            bx = -tx
            by = -ty
            for v in range(m):
                r = y0 + v - half
                for u in range(m):
                    c = x0 + u - half
                    s = w00 * curr[r, c] + w01 * curr[r, c + 1] + w10 * curr[r + 1, c] + w11 * curr[r + 1, c + 1]
                    bx += gx[v, u] * s
                    by += gy[v, u] * s
            ux = (syy * bx - sxy * by) / det
            uy = (sxx * by - sxy * bx) / det
            sx -= ux
            sy -= uy
            if abs(sx) > max_px or abs(sy) > max_px:
                break
            if ux * ux + uy * uy < 1e-4:
                ok[i] = True
                dx[i] = sx
                dy[i] = sy
                break
