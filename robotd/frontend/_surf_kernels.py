"""numba kernels of the SURF hot loops (Bay et al., CVIU 2008); the readable algorithm is in ``surf.py``.

Two kernels only, to keep the first-call compile short (about 3 s for both on an idle 2-core
machine, then loaded from the disk cache in ~0.2 s). The helpers are inlined into their callers:
the larger ones by numba (``inline="always"``, measured 20 % faster than calls), the tiny
``_ii_at`` by LLVM: inlining its 48 call sites at numba IR level made the compile 5x slower (15 s)
for no run-time gain.

- :func:`hessian_layers`: the box-filter Hessian responses of one octave, every layer, and the
  octave's 3x3x3 local maxima.
- :func:`orient_and_describe`: per keypoint, the dominant orientation and the 64/128-D descriptor.

Both read a float64 integral image ``ii`` of shape (H+1, W+1) with a zero first row and column, so
``ii[r, c]`` is the sum of ``image[:r, :c]`` (OpenCV's ``cv2.integral`` layout). Pixel centres are at
integer coordinates (x = column, y = row).

Both are compiled by :func:`robotd.core.jit.jit` (disk cache, ``NUMBA_CACHE_DIR`` and the fallback for
read-only installs are explained there); they release the GIL, so the left and right images can be
processed in two threads. The helpers stay plain ``numba.njit``: they are compiled only into the
two kernels, whose cache entries hold them, and only the kernels' entry points release the GIL.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from robotd.core.jit import jit


@jit
def hessian_layers(
    ii: np.ndarray,
    sizes: np.ndarray,
    step: int,
    ny: int,
    nx: int,
    weight: float,
    det_out: np.ndarray,
    trace_out: np.ndarray,
    threshold: float,
    lo: np.ndarray,
    hi_i: np.ndarray,
    hi_j: np.ndarray,
    cand_out: np.ndarray,
) -> int:
    """Fill ``det_out``/``trace_out`` (n_layers, ny, nx) float32 with the SURF Hessian responses, then
    write the octave's local maxima as (layer, i, j) rows into ``cand_out`` and return their count.

    Layer k uses the box filters of side ``L = sizes[k]`` (odd, lobe ``l = L/3``) centred on the pixel
    (x, y) = (j*step, i*step). Bay et al. §3.1 / thesis eq. (4.1.13)–(4.1.14):

        Dyy = box(|dx| <= l-1, |dy| <= L//2) - 3 box(|dx| <= l-1, |dy| <= l//2)      (three lobes +1 -2 +1)
        Dxx = the transpose,
        Dxy = box(++) + box(--) - box(+-) - box(-+), lobes l x l separated by one row/column,
        det = (Dxx Dyy - (w Dxy)^2) / L^4,   trace = (Dxx + Dyy) / L^2,

    each response normalised by the filter area L^2 (so a threshold does not depend on scale and is
    in the units of OpenCV's ``hessianThreshold``). Samples where the filter does not fit inside the
    image are left at 0 (never a detection: thresholds are positive).

    Maxima: see :func:`_scan_maxima`; ``lo``, ``hi_i``, ``hi_j`` (n_layers,) are the inclusive index
    ranges searched per layer, ``cand_out`` (capacity, 3) int64. The returned count may exceed the
    capacity; then only the first rows were written.
    """
    h = ii.shape[0] - 1
    w = ii.shape[1] - 1
    for k in range(sizes.shape[0]):
        L = sizes[k]
        lobe = L // 3
        half = L // 2
        mid = lobe // 2
        band = lobe - 1
        inv_area = 1.0 / (L * L)
        det_out[k] = 0.0
        trace_out[k] = 0.0
        # Only centres whose whole filter lies inside the image (no clipping needed below).
        i0 = (half + step - 1) // step
        j0 = i0
        i1 = min((h - 1 - half) // step, ny - 1)  # inclusive
        j1 = min((w - 1 - half) // step, nx - 1)
        for i in range(i0, i1 + 1):
            y = i * step
            # The ten integral-image rows the three filters touch at this centre row.
            r_yy0 = ii[y - half]
            r_yy1 = ii[y + half + 1]
            r_ym0 = ii[y - mid]
            r_ym1 = ii[y + mid + 1]
            r_xx0 = ii[y - band]
            r_xx1 = ii[y + band + 1]
            r_t0 = ii[y - lobe]
            r_t1 = ii[y]
            r_b0 = ii[y + 1]
            r_b1 = ii[y + lobe + 1]
            det_row = det_out[k, i]
            trace_row = trace_out[k, i]
            for j in range(j0, j1 + 1):
                x = j * step
                c0 = x - band
                c1 = x + band + 1
                dyy = (r_yy1[c1] - r_yy0[c1] - r_yy1[c0] + r_yy0[c0]) - 3.0 * (
                    r_ym1[c1] - r_ym0[c1] - r_ym1[c0] + r_ym0[c0]
                )
                e0 = x - half
                e1 = x + half + 1
                m0 = x - mid
                m1 = x + mid + 1
                dxx = (r_xx1[e1] - r_xx0[e1] - r_xx1[e0] + r_xx0[e0]) - 3.0 * (
                    r_xx1[m1] - r_xx0[m1] - r_xx1[m0] + r_xx0[m0]
                )
                a0 = x - lobe
                a1 = x
                b0 = x + 1
                b1 = x + lobe + 1
                top_left = r_t1[a1] - r_t0[a1] - r_t1[a0] + r_t0[a0]
                top_right = r_t1[b1] - r_t0[b1] - r_t1[b0] + r_t0[b0]
                bottom_left = r_b1[a1] - r_b0[a1] - r_b1[a0] + r_b0[a0]
                bottom_right = r_b1[b1] - r_b0[b1] - r_b1[b0] + r_b0[b0]
                dxy = (top_left + bottom_right - top_right - bottom_left) * inv_area
                dxx *= inv_area
                dyy *= inv_area
                det_row[j] = dxx * dyy - (weight * dxy) * (weight * dxy)
                trace_row[j] = dxx + dyy
    return _scan_maxima(det_out, threshold, lo, hi_i, hi_j, cand_out)


@numba.njit(inline="always")
def _scan_maxima(
    det: np.ndarray, threshold: float, lo: np.ndarray, hi_i: np.ndarray, hi_j: np.ndarray, cand_out: np.ndarray
) -> int:
    """Samples of the interior layers above ``threshold`` that are maxima of their 3x3x3 neighbourhood.

    Bay et al. §3.3. Ties would suppress both samples of a blob centred exactly between two; so a
    sample must exceed the neighbours before it in (layer, row, column) order and at least equal
    those after it, and exactly one of two tied samples survives. Output in that order; returns the
    number of maxima, which may exceed the rows of ``cand_out`` (only those are written).
    """
    n = 0
    for k in range(1, det.shape[0] - 1):
        for i in range(lo[k], hi_i[k] + 1):
            for j in range(lo[k], hi_j[k] + 1):
                v = det[k, i, j]
                if v <= threshold:
                    continue
                is_max = True
                for dl in range(-1, 2):
                    for di in range(-1, 2):
                        for dj in range(-1, 2):
                            if dl == 0 and di == 0 and dj == 0:
                                continue
                            u = det[k + dl, i + di, j + dj]
                            before = dl < 0 or (dl == 0 and (di < 0 or (di == 0 and dj < 0)))
                            if (before and v <= u) or (not before and v < u):
                                is_max = False
                                break
                        if not is_max:
                            break
                    if not is_max:
                        break
                if is_max:
                    if n < cand_out.shape[0]:
                        cand_out[n, 0] = k
                        cand_out[n, 1] = i
                        cand_out[n, 2] = j
                    n += 1
    return n


@numba.njit
def _ii_at(ii: np.ndarray, r: int, c: int) -> float:
    """ii[r, c] with r, c clamped to the table: the integral image of the zero-padded image."""
    if r < 0:
        r = 0
    elif r > ii.shape[0] - 1:
        r = ii.shape[0] - 1
    if c < 0:
        c = 0
    elif c > ii.shape[1] - 1:
        c = ii.shape[1] - 1
    return ii[r, c]


@numba.njit(inline="always")
def _haar(ii: np.ndarray, x: float, y: float, half: int) -> tuple[float, float]:
    """Haar wavelet responses (hx, hy) of side 2*half near the point (x, y) [px]: right-left, bottom-top.

    An even-sided wavelet is symmetric about a pixel corner, so it is centred on the corner nearest
    to (x, y), at (floor(x) + 0.5, floor(y) + 0.5): the centre is never more than half a pixel off
    and, unlike centring on a rounded pixel, carries no systematic half-pixel shift (which would
    bias orientations of small features). With (r, c) the integral-image index of that corner,
    both responses need only eight table entries:
        hx = I[r+h, c+h] - I[r-h, c+h] - 2 I[r+h, c] + 2 I[r-h, c] + I[r+h, c-h] - I[r-h, c-h]
        hy = I[r+h, c+h] - I[r+h, c-h] - 2 I[r, c+h] + 2 I[r, c-h] + I[r-h, c+h] - I[r-h, c-h]
    """
    c = math.floor(x) + 1
    r = math.floor(y) + 1
    h = half
    pp = _ii_at(ii, r + h, c + h)
    mp = _ii_at(ii, r - h, c + h)
    pm = _ii_at(ii, r + h, c - h)
    mm = _ii_at(ii, r - h, c - h)
    hx = pp - mp - 2.0 * _ii_at(ii, r + h, c) + 2.0 * _ii_at(ii, r - h, c) + pm - mm
    hy = pp - pm - 2.0 * _ii_at(ii, r, c + h) + 2.0 * _ii_at(ii, r, c - h) + mp - mm
    return hx, hy


@numba.njit(inline="always")
def _haar_smooth(ii: np.ndarray, x: float, y: float, half: int) -> tuple[float, float]:
    """:func:`_haar` blended bilinearly over the four pixel corners around (x, y)."""
    tx = x + 0.5
    ty = y + 0.5
    c0 = math.floor(tx)
    r0 = math.floor(ty)
    fx = tx - c0
    fy = ty - r0
    hx00, hy00 = _haar(ii, c0 - 0.5, r0 - 0.5, half)
    hx01, hy01 = _haar(ii, c0 + 0.5, r0 - 0.5, half)
    hx10, hy10 = _haar(ii, c0 - 0.5, r0 + 0.5, half)
    hx11, hy11 = _haar(ii, c0 + 0.5, r0 + 0.5, half)
    w00 = (1 - fx) * (1 - fy)
    w01 = fx * (1 - fy)
    w10 = (1 - fx) * fy
    w11 = fx * fy
    return (w00 * hx00 + w01 * hx01 + w10 * hx10 + w11 * hx11, w00 * hy00 + w01 * hy01 + w10 * hy10 + w11 * hy11)


@numba.njit(inline="always")
def _box_mean(ii: np.ndarray, x: float, y: float, k: int) -> float:
    """Mean of a k x k pixel box centred on the real point (x, y), bilinear in the box position.

    The box whose top-left pixel is (c0, r0) is centred on (c0 + (k-1)/2, r0 + (k-1)/2); the four
    integer placements around the wanted centre are blended with bilinear weights, so the value
    moves smoothly with (x, y) (no pixel quantisation).
    """
    tx = x - 0.5 * (k - 1)
    ty = y - 0.5 * (k - 1)
    c = math.floor(tx)
    r = math.floor(ty)
    fx = tx - c
    fy = ty - r
    # Box with top-left pixel (r', c'): I[r'+k, c'+k] - I[r', c'+k] - I[r'+k, c'] + I[r', c'].
    b00 = _ii_at(ii, r + k, c + k) - _ii_at(ii, r, c + k) - _ii_at(ii, r + k, c) + _ii_at(ii, r, c)
    b01 = _ii_at(ii, r + k, c + k + 1) - _ii_at(ii, r, c + k + 1) - _ii_at(ii, r + k, c + 1) + _ii_at(ii, r, c + 1)
    b10 = _ii_at(ii, r + k + 1, c + k) - _ii_at(ii, r + 1, c + k) - _ii_at(ii, r + k + 1, c) + _ii_at(ii, r + 1, c)
    b11 = (
        _ii_at(ii, r + k + 1, c + k + 1)
        - _ii_at(ii, r + 1, c + k + 1)
        - _ii_at(ii, r + k + 1, c + 1)
        + _ii_at(ii, r + 1, c + 1)
    )
    top = b00 + fx * (b01 - b00)
    bottom = b10 + fx * (b11 - b10)
    return (top + fy * (bottom - top)) / (k * k)


@jit
def orient_and_describe(
    ii: np.ndarray,
    xy: np.ndarray,
    scale: np.ndarray,
    upright: bool,
    extended: bool,
    n_bins: int,
    window_bins: int,
    angle_out: np.ndarray,
    desc_out: np.ndarray,
) -> None:
    """Orientation (radians, into ``angle_out`` (N,)) and descriptor (into ``desc_out`` (N, 64|128)).

    ``xy`` (N, 2) float [px], ``scale`` (N,) the keypoint scale s = 1.2 L / 9 [px].

    Orientation (Bay et al. §4.1): Haar responses of side 4s at the points (u, v) s with u^2 + v^2 < 36
    (radius 6s, step s), weighted by a Gaussian of sigma 2s. The responses are bilinear in the
    sample position (:func:`_haar_smooth`): with pixel-rounded samples the median orientation
    error under a 1.5x zoom of a KITTI frame was 2.8 deg, bilinear 1.9 deg. Each response votes with
    its vector into one of ``n_bins`` angle bins; a window of ``window_bins`` consecutive bins
    (pi/3) slides around the circle and the longest summed vector gives the orientation
    theta = atan2(sum hy, sum hx) (image axes: x right, y down, so theta turns from +x towards +y).

    Descriptor (Bay et al. §4.2): a 20s square aligned with theta, 4x4 subregions of 5x5 samples
    spaced s. The window is resampled along the keypoint axes into a 21 x 21 patch of s x s box
    means (:func:`_box_mean`), and the Haar responses of side 2s are 2 x 2-cell differences of the
    patch, du along theta and dv perpendicular (wavelets rotated with the keypoint, as OpenCV's SURF
    does; more rotation-covariant than axis-aligned responses rotated afterwards), weighted by a
    Gaussian of sigma 3.3s centred on the keypoint, and summed per subregion as
    (sum du, sum |du|, sum dv, sum |dv|); the extended variant splits the du sums by the sign of dv
    and the dv sums by the sign of du (128-D). The vector is normalised to unit length.
    Subregion order: row-major over (v, u), i.e. index (4 * row + col) * 4 (or * 8).
    """
    n = xy.shape[0]
    two_pi = 2.0 * math.pi
    bin_x = np.zeros(n_bins)
    bin_y = np.zeros(n_bins)
    patch = np.empty((21, 21))
    # Gaussian weights depend only on the sample index (offsets are in units of s): tabulate once.
    g_ori = np.empty((13, 13))  # sigma = 2s over offsets -6..6
    for v in range(-6, 7):
        for u in range(-6, 7):
            g_ori[v + 6, u + 6] = math.exp(-(u * u + v * v) / 8.0)
    g_desc = np.empty((20, 20))  # sigma = 3.3s over offsets (k - 9.5)
    for row in range(20):
        for col in range(20):
            g_desc[row, col] = math.exp(-((col - 9.5) ** 2 + (row - 9.5) ** 2) / (2.0 * 3.3 * 3.3))
    for k in range(n):
        x = xy[k, 0]
        y = xy[k, 1]
        s = scale[k]
        theta = 0.0
        if not upright:
            half4 = round(2.0 * s)  # Haar side 4s -> half side 2s
            if half4 < 1:
                half4 = 1
            for b in range(n_bins):
                bin_x[b] = 0.0
                bin_y[b] = 0.0
            for v in range(-6, 7):
                for u in range(-6, 7):
                    r2 = u * u + v * v
                    if r2 >= 36:
                        continue
                    hx, hy = _haar_smooth(ii, x + u * s, y + v * s, half4)
                    if hx == 0.0 and hy == 0.0:
                        continue
                    g = g_ori[v + 6, u + 6]
                    a = math.atan2(hy, hx)
                    if a < 0.0:
                        a += two_pi
                    b = int(a * n_bins / two_pi)
                    if b >= n_bins:
                        b = n_bins - 1
                    bin_x[b] += g * hx
                    bin_y[b] += g * hy
            best = -1.0
            sx = 0.0
            sy = 0.0
            for b in range(window_bins):
                sx += bin_x[b]
                sy += bin_y[b]
            for b in range(n_bins):
                norm2 = sx * sx + sy * sy
                if norm2 > best:
                    best = norm2
                    theta = math.atan2(sy, sx)
                # Slide the window one bin: drop bin b, add bin b + window.
                e = (b + window_bins) % n_bins
                sx += bin_x[e] - bin_x[b]
                sy += bin_y[e] - bin_y[b]
            if theta < 0.0:
                theta += two_pi
        angle_out[k] = theta

        co = math.cos(theta)
        si = math.sin(theta)
        # The 20s window resampled along the keypoint axes: patch[r, c] is the mean of an s x s box at
        # offset ((c - 10) s, (r - 10) s) in the (u, v) frame, so each patch cell is one s x s cell
        # of the window and a 2 x 2 block of cells is a Haar wavelet of side 2s oriented with the
        # keypoint (truly rotated wavelets, as OpenCV's SURF does, instead of axis-aligned
        # responses rotated afterwards: more rotation-covariant).
        kbox = round(s)
        if kbox < 1:
            kbox = 1
        for r in range(21):
            b_ = (r - 10.0) * s
            for c in range(21):
                a_ = (c - 10.0) * s
                patch[r, c] = _box_mean(ii, x + a_ * co - b_ * si, y + a_ * si + b_ * co, kbox)
        per = 8 if extended else 4
        for d in range(desc_out.shape[1]):
            desc_out[k, d] = 0.0
        for row in range(20):
            for col in range(20):
                g = g_desc[row, col]
                du = g * (patch[row, col + 1] + patch[row + 1, col + 1] - patch[row, col] - patch[row + 1, col])
                dv = g * (patch[row + 1, col] + patch[row + 1, col + 1] - patch[row, col] - patch[row, col + 1])
                base = ((row // 5) * 4 + col // 5) * per
                if not extended:
                    desc_out[k, base + 0] += du
                    desc_out[k, base + 1] += abs(du)
                    desc_out[k, base + 2] += dv
                    desc_out[k, base + 3] += abs(dv)
                else:
                    if dv < 0.0:
                        desc_out[k, base + 0] += du
                        desc_out[k, base + 1] += abs(du)
                    else:
                        desc_out[k, base + 2] += du
                        desc_out[k, base + 3] += abs(du)
                    if du < 0.0:
                        desc_out[k, base + 4] += dv
                        desc_out[k, base + 5] += abs(dv)
                    else:
                        desc_out[k, base + 6] += dv
                        desc_out[k, base + 7] += abs(dv)
        norm2 = 0.0
        for d in range(desc_out.shape[1]):
            norm2 += desc_out[k, d] * desc_out[k, d]
        if norm2 > 0.0:
            inv = 1.0 / math.sqrt(norm2)
            for d in range(desc_out.shape[1]):
                desc_out[k, d] *= inv
