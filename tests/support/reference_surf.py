"""Readable numpy/Python twins of the SURF kernels (robotd/frontend/_surf_kernels.py).

- :func:`hessian_layer_reference`: the box-filter responses of ``hessian_layers``, by dense
  correlation with :func:`box_filter_kernels` (no integral image).
- :func:`describe_reference`: orientation and descriptor of ``orient_and_describe``, sample by
  sample with explicit pixel sums.

Moved here unchanged from robotd/frontend/surf.py, with their helpers :func:`box_filter_kernels`
(also used by tests/robotd/frontend/test_surf.py to check the filters and a blob's scale) and :func:`_box_ref`.
Constants and the integral image come from robotd.frontend.surf, so twin and detector share them.
The maxima scan's numpy version is not here: it is the detector's runtime fallback,
``robotd.frontend.surf.local_maxima_numpy``.
"""

from __future__ import annotations

import math

import numpy as np

from robotd.frontend.surf import _ORI_BINS, _ORI_WINDOW_BINS, HESSIAN_WEIGHT, integral_image


def _box_ref(ii: np.ndarray, r0: int, r1: int, c0: int, c1: int) -> float:
    """Sum of the pixels in rows r0..r1, columns c0..c1 (inclusive) that lie in the image, from ``ii``."""
    h, w = ii.shape[0] - 1, ii.shape[1] - 1
    r0, c0, r1, c1 = max(r0, 0), max(c0, 0), min(r1, h - 1), min(c1, w - 1)
    if r0 > r1 or c0 > c1:
        return 0.0
    return float(ii[r1 + 1, c1 + 1] - ii[r0, c1 + 1] - ii[r1 + 1, c0] + ii[r0, c0])


def box_filter_kernels(size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Dense (L, L) weights of the box filters Dxx, Dyy, Dxy of side ``size`` (Bay et al. Fig. 1).

    Dyy: three lobes of ``L/3`` rows (+1, -2, +1) over ``2 L/3 - 1`` columns; Dxx its transpose;
    Dxy: four ``L/3`` x ``L/3`` lobes (+1 top-left and bottom-right, -1 elsewhere) around a cross
    of zeros. Rows are y (down), columns x (right); the centre is element (L//2, L//2).
    """
    L, lobe, half = size, size // 3, size // 2
    mid, band = lobe // 2, lobe - 1
    kyy = np.zeros((L, L))
    kyy[:, half - band : half + band + 1] = 1.0
    kyy[half - mid : half + mid + 1, half - band : half + band + 1] = -2.0
    kxx = kyy.T.copy()
    kxy = np.zeros((L, L))
    kxy[half - lobe : half, half - lobe : half] = 1.0
    kxy[half + 1 : half + lobe + 1, half + 1 : half + lobe + 1] = 1.0
    kxy[half - lobe : half, half + 1 : half + lobe + 1] = -1.0
    kxy[half + 1 : half + lobe + 1, half - lobe : half] = -1.0
    return kxx, kyy, kxy


def hessian_layer_reference(image: np.ndarray, size: int, step: int) -> tuple[np.ndarray, np.ndarray]:
    """det and trace maps (ny, nx) of one filter side ``size`` by explicit correlation with
    :func:`box_filter_kernels` at the grid (j*step, i*step); zeros where the filter does not fit.

    Independent of the integral image, so it checks the kernel's box arithmetic. Slow (Python loop).

    Readable twin of the response maps of ``_surf_kernels.hessian_layers``. Agreement: det and
    trace of every layer to rtol 1e-5 and atol 1e-5 of the map's largest value (the kernel writes
    float32; tests/robotd/frontend/test_surf.py::test_hessian_kernel_matches_dense_box_filters).
    """
    img = image.astype(np.float64)
    h, w = img.shape
    L, half = size, size // 2
    kxx, kyy, kxy = box_filter_kernels(size)
    ny, nx = (h - 1) // step + 1, (w - 1) // step + 1
    det = np.zeros((ny, nx))
    trace = np.zeros((ny, nx))
    for i in range(ny):
        y = i * step
        if y - half < 0 or y + half > h - 1:
            continue
        for jx in range(nx):
            x = jx * step
            if x - half < 0 or x + half > w - 1:
                continue
            patch = img[y - half : y + half + 1, x - half : x + half + 1]
            dxx = float((patch * kxx).sum()) / L**2
            dyy = float((patch * kyy).sum()) / L**2
            dxy = float((patch * kxy).sum()) / L**2
            det[i, jx] = dxx * dyy - (HESSIAN_WEIGHT * dxy) ** 2
            trace[i, jx] = dxx + dyy
    return det, trace


def describe_reference(
    image: np.ndarray, x: float, y: float, size: float, upright: bool = False
) -> tuple[float, np.ndarray]:
    """Orientation [rad] and 64-D descriptor of one keypoint, in plain Python (Bay §4.1–4.2).

    The same mathematics as the kernel, written sample by sample with explicit pixel sums;
    ``size`` is the filter side L (scale s = 1.2 L / 9).

    Readable twin of ``_surf_kernels.orient_and_describe`` (64-D). Agreement: the orientation to
    1e-3 deg and the descriptor to atol 2e-5, oriented and upright, including a keypoint whose
    window leaves the image (tests/robotd/frontend/test_surf.py::test_descriptor_kernel_matches_reference).
    """
    img = image.astype(np.float64)
    ii = integral_image(image)
    s = 1.2 * size / 9.0

    def haar_at_corner(c: int, r: int, half: int) -> tuple[float, float]:
        # Wavelet centred on the pixel corner (c - 0.5, r - 0.5).
        right = _box_ref(ii, r - half, r + half - 1, c, c + half - 1)
        left = _box_ref(ii, r - half, r + half - 1, c - half, c - 1)
        bottom = _box_ref(ii, r, r + half - 1, c - half, c + half - 1)
        top = _box_ref(ii, r - half, r - 1, c - half, c + half - 1)
        return right - left, bottom - top

    def haar_smooth(px: float, py: float, half: int) -> tuple[float, float]:
        c0, r0 = math.floor(px + 0.5), math.floor(py + 0.5)
        fx, fy = px + 0.5 - c0, py + 0.5 - r0
        out = np.zeros(2)
        for dr, wr in ((0, 1 - fy), (1, fy)):
            for dc, wc in ((0, 1 - fx), (1, fx)):
                out += wr * wc * np.array(haar_at_corner(c0 + dc, r0 + dr, half))
        return float(out[0]), float(out[1])

    def box_mean(px: float, py: float, k: int) -> float:
        tx, ty = px - 0.5 * (k - 1), py - 0.5 * (k - 1)
        c0, r0 = math.floor(tx), math.floor(ty)
        fx, fy = tx - c0, ty - r0
        total = 0.0
        for dr, wr in ((0, 1 - fy), (1, fy)):
            for dc, wc in ((0, 1 - fx), (1, fx)):
                r, c = r0 + dr, c0 + dc
                # Explicit sum over the pixels of the box that lie in the image (zero padding).
                block = img[max(r, 0) : max(r + k, 0), max(c, 0) : max(c + k, 0)]
                total += wr * wc * float(block.sum())
        return total / (k * k)

    theta = 0.0
    if not upright:
        half4 = max(1, round(2.0 * s))
        votes = []
        for v in range(-6, 7):
            for u in range(-6, 7):
                if u * u + v * v >= 36:
                    continue
                hx, hy = haar_smooth(x + u * s, y + v * s, half4)
                if hx == 0 and hy == 0:
                    continue
                g = math.exp(-(u * u + v * v) / 8.0)
                votes.append((math.atan2(hy, hx) % (2 * math.pi), g * hx, g * hy))
        ang = np.array([a for a, _, _ in votes])
        vx = np.array([b for _, b, _ in votes])
        vy = np.array([c for _, _, c in votes])
        bins = np.minimum((ang * _ORI_BINS / (2 * math.pi)).astype(int), _ORI_BINS - 1)
        best = -1.0
        for b0 in range(_ORI_BINS):
            inwin = ((bins - b0) % _ORI_BINS) < _ORI_WINDOW_BINS
            sx, sy = vx[inwin].sum(), vy[inwin].sum()
            if sx * sx + sy * sy > best:
                best = sx * sx + sy * sy
                theta = math.atan2(sy, sx) % (2 * math.pi)
    co, si = math.cos(theta), math.sin(theta)
    k = max(1, round(s))
    patch = np.zeros((21, 21))
    for r in range(21):
        for c in range(21):
            a, b = (c - 10) * s, (r - 10) * s
            patch[r, c] = box_mean(x + a * co - b * si, y + a * si + b * co, k)
    desc = np.zeros((4, 4, 4))
    for row in range(20):
        for col in range(20):
            g = math.exp(-((col - 9.5) ** 2 + (row - 9.5) ** 2) / (2 * 3.3**2))
            cell = patch[row : row + 2, col : col + 2]
            du = g * float(cell[:, 1].sum() - cell[:, 0].sum())
            dv = g * float(cell[1, :].sum() - cell[0, :].sum())
            desc[row // 5, col // 5] += (du, abs(du), dv, abs(dv))
    flat = desc.reshape(-1)
    return theta, flat / max(float(np.linalg.norm(flat)), 1e-300)
