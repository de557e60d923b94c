"""Readable numpy twins of the front end's bucketing and stereo-matching kernels.

- :func:`bucket_select_numpy`: ``robotd.frontend.detectors.bucket_select`` (``_detect_kernels``).
- :func:`ratio_and_cross_check_numpy`, :func:`refine_disparity_numpy`, :func:`mutual_matches_numpy`,
  :func:`window_pairs_numpy`: the functions of the same name without ``_numpy`` in
  ``robotd.frontend.stereo_match`` (``_stereo_kernels``).

Moved here unchanged from the hot modules; tests/robotd/frontend/test_kernels.py holds the kernels to them.
"""

from __future__ import annotations

import numpy as np


def bucket_select_numpy(
    xy: np.ndarray, response: np.ndarray, shape: tuple[int, int], max_features: int, grid_rows: int, grid_cols: int
) -> np.ndarray:
    """Readable twin of :func:`robotd.frontend.detectors.bucket_select` and its kernel
    ``_detect_kernels.bucket_kernel``: the same grid quota and refill by numpy sorts and gathers.

    Agreement: the same indices in the same order (``assert_array_equal``, ties included;
    tests/robotd/frontend/test_kernels.py::test_bucket_kernel_equals_numpy).
    """
    n = xy.shape[0]
    if n <= max_features:
        return np.argsort(-response, kind="stable")
    h, w = shape
    col = np.clip((xy[:, 0] * grid_cols / max(w, 1)).astype(np.int64), 0, grid_cols - 1)
    row = np.clip((xy[:, 1] * grid_rows / max(h, 1)).astype(np.int64), 0, grid_rows - 1)
    cell = row * grid_cols + col
    # sort by cell, then by decreasing response; rank of each feature inside its cell. Two stable
    # sorts give lexsort's order; the cell key fits int16 (≤ 64 × 64 cells), which numpy sorts by
    # radix: ≈ 4× faster than np.lexsort on 4000 candidates
    key_type = np.int16 if grid_rows * grid_cols <= np.iinfo(np.int16).max else np.int64
    by_resp = np.argsort(-response, kind="stable")
    order = by_resp[np.argsort(cell[by_resp].astype(key_type), kind="stable")]
    cell_sorted = cell[order]
    starts = np.r_[0, np.flatnonzero(np.diff(cell_sorted)) + 1]
    counts = np.diff(np.r_[starts, n])
    rank = np.arange(n) - np.repeat(starts, counts)
    quota = -(-max_features // (grid_rows * grid_cols))
    first = order[rank < quota]
    if first.size >= max_features:
        keep = first[np.argsort(-response[first], kind="stable")[:max_features]]
    else:
        rest = order[rank >= quota]
        rest = rest[np.argsort(-response[rest], kind="stable")[: max_features - first.size]]
        keep = np.r_[first, rest]
    return keep[np.argsort(-response[keep], kind="stable")]


def ratio_and_cross_check_numpy(
    i: np.ndarray,
    j: np.ndarray,
    dist: np.ndarray,
    n_j: int,
    ratio: float,
    max_single: float,
    cross_check: bool = True,
) -> tuple[np.ndarray, dict[str, int]]:
    """Readable twin of :func:`robotd.frontend.stereo_match.ratio_and_cross_check` and its kernel
    ``_stereo_kernels.ratio_cross_kernel``, by segment reductions (``np.minimum.reduceat``).

    Agreement: the same accepted pairs in the same order and the same rejection counts
    (tests/robotd/frontend/test_kernels.py: random inputs full of ties, and a rendered ORB pair).

    ``i``, ``j``: (P,) indices of candidate pairs; ``dist``: (P,) their descriptor distances.
    For each i the best pair is kept if dist < ratio · second-best distance, or, when it is the
    only candidate, if dist ≤ ``max_single``. Then the cross-check keeps (i, j) only if i is also
    j's nearest candidate. Returns the indices (into the pair arrays) of accepted pairs and counts.
    """
    stats = {"pairs": int(i.size), "ratio_rejected": 0, "single_rejected": 0, "cross_rejected": 0}
    p = int(i.size)
    if p == 0:
        return np.zeros(0, np.int64), stats
    # Linear-time segment reductions instead of two lexsorts (≈ 3× faster on 9000 stereo pairs, same
    # result): every caller passes pairs grouped by i (row-major), so only an unsorted i is sorted.
    pos = np.arange(p)
    order = np.argsort(i, kind="stable") if np.any(i[1:] < i[:-1]) else None
    i_s = i if order is None else i[order]
    d_s = dist if order is None else dist[order]
    starts = np.flatnonzero(np.r_[True, i_s[1:] != i_s[:-1]])
    counts = np.diff(np.r_[starts, p])
    # best: the smallest distance of each group, the earliest pair among equal distances
    gmin = np.minimum.reduceat(d_s, starts)
    best_s = np.minimum.reduceat(np.where(d_s == np.repeat(gmin, counts), pos, p), starts)
    # second-best distance: the group's minimum with its best pair taken out
    d_wo = d_s.astype(np.float64)
    d_wo[best_s] = np.inf
    second_d = np.minimum.reduceat(d_wo, starts)
    best = best_s if order is None else order[best_s]
    has_second = counts > 1
    ok_ratio = dist[best] < ratio * second_d
    ok_single = dist[best] <= max_single
    ok = np.where(has_second, ok_ratio, ok_single)
    stats["ratio_rejected"] = int(np.sum(has_second & ~ok_ratio))
    stats["single_rejected"] = int(np.sum(~has_second & ~ok_single))
    best = best[ok]
    if not cross_check:
        return best, stats
    # cross-check: the nearest pair of each j over all of j's candidate pairs (earliest on ties)
    min_j = np.full(n_j, np.inf)
    np.minimum.at(min_j, j, dist)
    at_min = dist == min_j[j]
    best_pair_of_j = np.full(n_j, p, np.int64)
    np.minimum.at(best_pair_of_j, j[at_min], pos[at_min])
    mutual = best_pair_of_j[j[best]] == best
    stats["cross_rejected"] = int(np.sum(~mutual))
    return best[mutual], stats


def mutual_matches_numpy(
    a: np.ndarray, b: np.ndarray, binary: bool, max_dist: float, ratio: float, second_in_row: bool
) -> tuple[np.ndarray, np.ndarray]:
    """Readable twin of :func:`robotd.frontend.stereo_match.mutual_matches` and its kernel
    ``_stereo_kernels.mutual_binary_kernel``: the whole (N, M) distance matrix, its candidates within
    ``max_dist``, :func:`ratio_and_cross_check_numpy` on them, and (``second_in_row``, M > 1) the
    ratio against each row's second-smallest distance (the path frame-to-frame motion took before
    the kernel, session 29).

    Agreement: the same pairs in the same order (tests/robotd/frontend/test_kernels.py: random
    descriptors with many near duplicates, several ratios and limits, and a rendered ORB pair).
    """
    n, m = a.shape[0], b.shape[0]
    if n == 0 or m == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    if binary:
        D = np.bitwise_count(a[:, None, :] ^ b[None, :, :]).sum(axis=2, dtype=np.int32).astype(np.float32)
    else:
        # unit-norm descriptors: |a − b|² = 2 − 2 a·b, in float32 as the matcher computes it
        D = np.sqrt(np.maximum(2.0 - 2.0 * (a @ b.T), 0.0)).astype(np.float32)
    ii, jj = np.nonzero(D <= max_dist)
    sel, _ = ratio_and_cross_check_numpy(ii, jj, D[ii, jj], m, ratio, max_dist, True)
    ic, jc = ii[sel].astype(np.int64), jj[sel].astype(np.int64)
    if second_in_row and m > 1:
        second = np.sort(D, axis=1)[:, 1]
        ok = D[ic, jc] < ratio * second[ic]
        ic, jc = ic[ok], jc[ok]
    return ic, jc


def window_pairs_numpy(
    px: np.ndarray, predicted: np.ndarray, r: float, rows_known: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """Readable twin of :func:`robotd.frontend.stereo_match.window_pairs` and its kernel
    ``_stereo_kernels.window_pairs_kernel``: the three (N, K) masks guided identification built
    before session 29, and ``np.nonzero`` of their conjunction (row-major order).

    Agreement: the same pairs in the same order (tests/robotd/frontend/test_kernels.py: random
    pixels on a coarse grid, so that distances of exactly r are common, NaN and inf included).
    """
    near = np.abs(px[:, None, 0] - predicted[None, :, 0]) <= r
    if rows_known:
        near &= np.abs(px[:, None, 2] - predicted[None, :, 2]) <= r
    disp_m, disp_p = px[:, 0] - px[:, 1], predicted[:, 0] - predicted[:, 1]
    near &= np.abs(disp_m[:, None] - disp_p[None, :]) <= r
    ii, jj = np.nonzero(near)
    return ii.astype(np.int64), jj.astype(np.int64)


def refine_disparity_numpy(
    left_img: np.ndarray,
    right_img: np.ndarray,
    xl: np.ndarray,
    yl: np.ndarray,
    d0: np.ndarray,
    half: int = 3,
    search: int = 2,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Readable twin of :func:`robotd.frontend.stereo_match.refine_disparity` and its kernel
    ``_stereo_kernels.refine_kernel``: all ZSSD costs at once from one right strip per keypoint.

    Agreement: bit-identical ``d``, ``ok`` and ``edge``, ``sigma`` to rounding (the costs are exact integers;
    tests/robotd/frontend/test_kernels.py::test_refine_kernel_equals_numpy_on_random_points).

    ``xl``, ``yl``: (N,) [px] left keypoints; ``d0``: (N,) [px] initial disparities. Returns
    (d (N,) refined disparity at the left keypoint, ok (N,) refinement applied, edge (N,) minimum
    on the search border, sigma (N,) [px] the fit's precision). Where ``ok`` is False, ``d`` is
    ``d0`` and ``sigma`` inf.
    """
    n = xl.shape[0]
    h, w = left_img.shape
    u = np.rint(xl).astype(np.int64)
    v = np.rint(yl).astype(np.int64)
    di = np.rint(d0).astype(np.int64)
    inside = (
        (v - half >= 0)
        & (v + half < h)
        & (u - half >= 0)
        & (u + half < w)
        & (u - di - search - half >= 0)
        & (u - di + search + half < w)
    )
    d_out = np.asarray(d0, dtype=np.float64).copy()
    ok = np.zeros(n, bool)
    edge = np.zeros(n, bool)
    sigma = np.full(n, np.inf)
    idx = np.flatnonzero(inside)
    if idx.size == 0:
        return d_out, ok, edge, sigma
    r = np.arange(-half, half + 1)
    k = np.arange(-search, search + 1)
    rows = v[idx, None] + r[None, :]  # (M, P)
    cols_l = u[idx, None] + r[None, :]
    # gather from the uint8 images and convert only the patches (not two whole images)
    pl = left_img[rows[:, :, None], cols_l[:, None, :]].astype(np.int64)  # (M, P, P)
    # one right strip per keypoint, columns u − d0 − r − h … u − d0 + r + h: the patch for
    # disparity d0 + k (centre u − d0 − k) is the strip's window at offset r − k
    cols_s = (u[idx] - di[idx] - search - half)[:, None] + np.arange(2 * (search + half) + 1)[None, :]
    strip = right_img[rows[:, :, None], cols_s[:, None, :]].astype(np.int64)  # (M, P, P + 2r)
    pr = np.lib.stride_tricks.sliding_window_view(strip, 2 * half + 1, axis=2)[:, :, ::-1]  # (M, P, K, P)
    # P × ZSSD = P Σ diff² − (Σ diff)² with diff = pr − pl, exact in integers, laid out (M, K, P·P)
    # so that both sums run over a contiguous last axis
    npx = (2 * half + 1) ** 2
    diff = pr.transpose(0, 2, 1, 3).reshape(idx.size, k.size, npx) - pl.reshape(idx.size, 1, npx)
    cost = npx * np.einsum("mkq,mkq->mk", diff, diff) - diff.sum(axis=2) ** 2  # (M, K) int64
    kmin = np.argmin(cost, axis=1)
    at_edge = (kmin == 0) | (kmin == k.size - 1)
    kc = np.clip(kmin, 1, k.size - 2)
    m = np.arange(idx.size)
    c_m, c_0, c_p = (cost[m, kc + o].astype(np.float64) for o in (-1, 0, 1))
    den = c_m - 2.0 * c_0 + c_p
    delta = np.where(den > 0.5, 0.5 * (c_m - c_p) / np.where(den > 0.5, den, 1.0), 0.0)
    d_new = di[idx] + k[kc] + np.clip(delta, -0.5, 0.5)
    good = ~at_edge & (den > 0.5)
    # the cost was measured at the integer column u; the caller keeps the keypoint's sub-pixel
    # column and assumes the disparity is constant over that < 0.5 px offset
    d_out[idx[good]] = d_new[good]
    ok[idx[good]] = True
    edge[idx[at_edge]] = True
    # the fit's precision: var k* = s² / Σ g_x² with c_min ≈ P² s² and curvature ≈ 2 P Σ g_x²
    sigma[idx[good]] = np.sqrt(2.0 * (c_0[good] + 1.0) / (npx * den[good]))
    return d_out, ok, edge, sigma


def _bilinear_numpy(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear samples of ``img`` at (x, y) (any shape), inside the image."""
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    ax, ay = x - x0, y - y0
    f = img.astype(np.float64)
    top = (1.0 - ax) * f[y0, x0] + ax * f[y0, x0 + 1]
    bottom = (1.0 - ax) * f[y0 + 1, x0] + ax * f[y0 + 1, x0 + 1]
    return (1.0 - ay) * top + ay * bottom


def align_numpy(
    prev: np.ndarray,
    curr: np.ndarray,
    xp: np.ndarray,
    yp: np.ndarray,
    xc: np.ndarray,
    yc: np.ndarray,
    half: int,
    iterations: int,
    max_px: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Readable twin of ``robotd.frontend._align_kernels.align_kernel``: (dx, dy, ok) per point,
    the inverse-compositional Gauss–Newton written with whole-patch numpy arrays.

    Agreement: ``ok`` equal and shifts within 1e-9 px (the sums run in another order;
    tests/robotd/frontend/test_align.py)."""
    n = len(xp)
    dx, dy, ok = np.zeros(n), np.zeros(n), np.zeros(n, bool)
    rows, cols = prev.shape
    u = np.arange(-half - 1, half + 2, dtype=np.float64)
    margin = half + 2.0 + max_px
    for i in range(n):
        pts = ((xp[i], yp[i]), (xc[i], yc[i]))
        if not all(
            x - margin >= 0 and y - margin >= 0 and x + margin < cols - 1 and y + margin < rows - 1 for x, y in pts
        ):
            continue
        T = _bilinear_numpy(prev, xp[i] + u[None, :], yp[i] + u[:, None])  # (m+2, m+2), row = y
        gx = 0.5 * (T[1:-1, 2:] - T[1:-1, :-2])
        gy = 0.5 * (T[2:, 1:-1] - T[:-2, 1:-1])
        gx, gy = gx - gx.mean(), gy - gy.mean()
        Tc = T[1:-1, 1:-1]
        H = np.array([[np.sum(gx * gx), np.sum(gx * gy)], [np.sum(gx * gy), np.sum(gy * gy)]])
        if not (np.linalg.det(H) > 0 and np.linalg.eigvalsh(H)[0] >= 1e-3 * Tc.size):
            continue
        s = np.zeros(2)
        for _ in range(iterations):
            I = _bilinear_numpy(curr, xc[i] + s[0] + u[None, 1:-1], yc[i] + s[1] + u[1:-1, None])
            b = np.array([np.sum(gx * (I - Tc)), np.sum(gy * (I - Tc))])
            step = np.linalg.solve(H, b)
            s = s - step
            if np.any(np.abs(s) > max_px):
                break
            if step @ step < 1e-4:
                ok[i], dx[i], dy[i] = True, s[0], s[1]
                break
    return dx, dy, ok
