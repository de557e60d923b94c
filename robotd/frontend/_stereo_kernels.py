"""numba kernels of the stereo matcher's per-pair loops; readable numpy twins: tests/support/reference_frontend.py.

Each kernel computes exactly what its numpy reference computes (``tests/robotd/frontend/test_kernels.py``
checks equality on random and rendered inputs), in one pass and without the numpy version's
temporaries: at 1000 ORB features per image the three together took ≈ 2.2 ms per frame in numpy
and take ≈ 0.3 ms here. ``nogil=True`` lets the camera and detection threads run meanwhile.

- :func:`candidate_pairs_kernel`: the (i, j) pairs inside the row band and the disparity range.
- :func:`ratio_cross_kernel`: ratio test (or lone-candidate limit) and cross-check.
- :func:`refine_kernel`: ZSSD patch cost at integer disparities and the parabola fit.
- :func:`mutual_binary_kernel`: every binary descriptor of one set against every one of another,
  and the mutual best matches among them (frame-to-frame motion and the disparity offset's pairs;
  ``stereo_match.mutual_matches``), without the (N, M) distance matrix.
- :func:`window_pairs_kernel`: the (measurement, landmark) pairs of guided identification whose
  column, row and disparity all lie within a radius of the prediction
  (``association.LandmarkDescriptors.identify_guided``), from a column-sorted search instead of
  three (N, K) masks.

Compiled by :func:`robotd.core.jit.jit` (disk cache; ``NUMBA_CACHE_DIR`` for read-only installs).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

from robotd.core.jit import jit


def _ctpop64(typingctx, x):  # type: ignore[no-untyped-def]
    """Typing and code of :func:`_popcount64`."""
    sig = types.uint64(types.uint64)

    def codegen(context, builder, signature, args):  # type: ignore[no-untyped-def]
        fnty = ir.FunctionType(ir.IntType(64), [ir.IntType(64)])
        fn = cgutils.get_or_insert_function(builder.module, fnty, "llvm.ctpop.i64")
        return builder.call(fn, args)

    return sig, codegen


# _popcount64(x): the number of set bits of a uint64, as LLVM's ``ctpop`` (one POPCNT instruction
# on x86-64 and ARMv8 CPUs that have it; numba compiles for the host CPU). Callable from kernels only.
_popcount64: Any = intrinsic(_ctpop64)


@jit
def candidate_pairs_kernel(
    xl: np.ndarray,
    xr: np.ndarray,
    lap_l: np.ndarray,
    lap_r: np.ndarray,
    use_lap: bool,
    order_r: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    d_min: float,
    d_max: float,
    out_i: np.ndarray,
    out_j: np.ndarray,
) -> int:  # pragma: no cover - compiled
    """Write the pairs (i, order_r[p]) for lo[i] ≤ p < hi[i] with d_min ≤ xl[i] − xr[j] ≤ d_max (in
    float64) and, when ``use_lap``, compatible Laplacian signs (0 = unknown passes); grouped by i,
    in the band's order. ``out_i``/``out_j`` hold at least Σ(hi − lo) entries; returns the count."""
    n = 0
    for i in range(xl.shape[0]):
        x = np.float64(xl[i])
        li = lap_l[i]
        for p in range(lo[i], hi[i]):
            j = order_r[p]
            d = x - np.float64(xr[j])
            if d < d_min or d > d_max:
                continue
            if use_lap:
                lj = lap_r[j]
                if li != 0 and lj != 0 and li != lj:
                    continue
            out_i[n] = i
            out_j[n] = j
            n += 1
    return n


@jit
def ratio_cross_kernel(
    i_s: np.ndarray,
    d_s: np.ndarray,
    order: np.ndarray,
    j: np.ndarray,
    dist: np.ndarray,
    n_j: int,
    ratio: float,
    max_single: np.float32,
    cross_check: bool,
    out: np.ndarray,
    counts: np.ndarray,
) -> int:  # pragma: no cover - compiled
    """Mutual best matches among candidate pairs (``stereo_match.ratio_and_cross_check``).

    ``i_s``/``d_s``: (P,) the pairs' left indices and float32 distances sorted by i (stable);
    ``order``: (P,) their positions in the original arrays ``j``/``dist``. The best pair of a
    group is its smallest distance, the earliest in sorted order on ties; it passes if its distance
    is below ``ratio`` × the group's second-best (float64), or, alone, ≤ ``max_single`` (float32).
    The cross-check keeps it if it is also the nearest pair of its j over all pairs (earliest in
    original order on ties). Writes accepted original positions into ``out`` in group order and
    [ratio_rejected, single_rejected, cross_rejected] into ``counts``; returns how many.
    """
    p = i_s.shape[0]
    best_of_j = np.full(n_j, p, np.int64)
    if cross_check:
        min_j = np.full(n_j, np.inf)
        for q in range(p):
            dq = np.float64(dist[q])
            jq = j[q]
            if dq < min_j[jq]:
                min_j[jq] = dq
                best_of_j[jq] = q
    n = 0
    s = 0
    while s < p:
        e = s + 1
        while e < p and i_s[e] == i_s[s]:
            e += 1
        b = s
        for q in range(s + 1, e):
            if d_s[q] < d_s[b]:
                b = q
        if e - s > 1:
            second = np.inf
            for q in range(s, e):
                if q != b and np.float64(d_s[q]) < second:
                    second = np.float64(d_s[q])
            ok = np.float64(d_s[b]) < ratio * second
            if not ok:
                counts[0] += 1
        else:
            ok = d_s[b] <= max_single
            if not ok:
                counts[1] += 1
        if ok:
            bo = order[b]
            if cross_check and best_of_j[j[bo]] != bo:
                counts[2] += 1
            else:
                out[n] = bo
                n += 1
        s = e
    return n


@jit
def refine_kernel(
    left: np.ndarray,
    right: np.ndarray,
    u: np.ndarray,
    v: np.ndarray,
    di: np.ndarray,
    half: int,
    search: int,
    d_out: np.ndarray,
    ok: np.ndarray,
    edge: np.ndarray,
    sigma: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """Sub-pixel disparity of keypoint (u, v) [px, integers] around integer disparity ``di``.

    For k = −search … search: the zero-mean SSD Σ (e − ē)² over the P = (2h+1)² patch pixels,
    e = right[v+r, u−di−k+c] − left[v+r, u+c], computed exactly in integers as
    P·Σe² − (Σe)² (P × the ZSSD: the same minimum and parabola, and ties go to the first k rather
    than to rounding). Minimum on the window's border: ``edge``; else the parabola through the
    minimum and its neighbours, when it curves up, gives d_out = di + k + δ (|δ| ≤ 0.5) and
    ``ok``, and ``sigma`` the fit's own precision √(2 (c_min + 1) / (P · curvature)) [px]: near its
    minimum the cost is c_min + ½·curvature·(k − k*)², and with a residual of s² per pixel
    c_min ≈ P² s², curvature ≈ 2 P Σ g_x², so var k* = s² / Σ g_x² (g_x: the patch's column
    gradient). A flat cost valley (little texture along the row, or a residual as large as the
    texture) gives a large σ. Patches that leave either image are skipped (``sigma`` untouched).
    """
    h, w = left.shape
    k_n = 2 * search + 1
    npx = (2 * half + 1) * (2 * half + 1)
    cost = np.empty(k_n, np.int64)
    for m in range(u.shape[0]):
        uu, vv, dd = u[m], v[m], di[m]
        if vv - half < 0 or vv + half >= h or uu - half < 0 or uu + half >= w:
            continue
        if uu - dd - search - half < 0 or uu - dd + search + half >= w:
            continue
        for kk in range(k_n):
            k = kk - search
            s1 = np.int64(0)
            s2 = np.int64(0)
            for r in range(-half, half + 1):
                for c in range(-half, half + 1):
                    x = np.int64(right[vv + r, uu - dd - k + c]) - np.int64(left[vv + r, uu + c])
                    s1 += x
                    s2 += x * x
            cost[kk] = npx * s2 - s1 * s1
        kmin = 0
        for kk in range(1, k_n):
            if cost[kk] < cost[kmin]:
                kmin = kk
        if kmin == 0 or kmin == k_n - 1:
            edge[m] = True
            continue
        c_m, c_0, c_p = np.float64(cost[kmin - 1]), np.float64(cost[kmin]), np.float64(cost[kmin + 1])
        den = c_m - 2.0 * c_0 + c_p
        if den > 0.5:
            delta = min(max(0.5 * (c_m - c_p) / den, -0.5), 0.5)
            d_out[m] = dd + (kmin - search) + delta
            ok[m] = True
            sigma[m] = math.sqrt(2.0 * (c_0 + 1.0) / (npx * den))


@jit
def mutual_binary_kernel(
    a: np.ndarray,
    b: np.ndarray,
    max_d: int,
    ratio: float,
    second_in_row: bool,
    out_i: np.ndarray,
    out_j: np.ndarray,
) -> int:  # pragma: no cover - compiled
    """Mutual best matches between binary descriptor sets ``a`` (N, W) and ``b`` (M, W) of uint64
    words, by Hamming distance (``stereo_match.mutual_matches``, which documents the rule).

    One pass over the N × M distances keeps, per row i, the smallest distance (the first j on
    ties), the second smallest (equal to it on a tie) and how many are ≤ ``max_d`` (the
    candidates), and per column j the row of its smallest candidate (the first i on ties). A row
    with candidates passes when its best is below ``ratio`` × its second-best (float64) if it has
    two or more, and, with ``second_in_row`` and M > 1, also below ``ratio`` × the second-best of
    the whole row in float32 (as numpy computes ``D < ratio * second`` on float32 distances); then
    when its best column's smallest candidate is this row (cross-check). Writes the accepted (i, j)
    in ascending i to ``out_i``/``out_j`` (length ≥ N); returns how many.
    """
    n, w = a.shape
    m = b.shape[0]
    big = np.int64(1) << 40
    col_best = np.full(m, big, np.int64)
    col_row = np.full(m, -1, np.int64)
    best = np.empty(n, np.int64)
    best_j = np.empty(n, np.int64)
    second = np.empty(n, np.int64)
    count = np.zeros(n, np.int64)
    for i in range(n):
        b1 = big
        j1 = -1
        b2 = big
        c = 0
        for j in range(m):
            d = np.int64(0)
            for k in range(w):
                d += np.int64(_popcount64(a[i, k] ^ b[j, k]))
            if d < b1:
                b2 = b1
                b1 = d
                j1 = j
            elif d < b2:
                b2 = d
            if d <= max_d:
                c += 1
                if d < col_best[j]:
                    col_best[j] = d
                    col_row[j] = i
        best[i] = b1
        best_j[i] = j1
        second[i] = b2
        count[i] = c
    r32 = np.float32(ratio)
    n_out = 0
    for i in range(n):
        c = count[i]
        if c == 0:
            continue
        if c >= 2 and not (np.float64(best[i]) < ratio * np.float64(second[i])):
            continue
        if second_in_row and m > 1 and not (np.float32(best[i]) < r32 * np.float32(second[i])):
            continue
        j = best_j[i]
        if col_row[j] != i:
            continue
        out_i[n_out] = i
        out_j[n_out] = j
        n_out += 1
    return n_out


@jit
def window_pairs_kernel(
    px: np.ndarray,
    pred: np.ndarray,
    order: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    r: float,
    rows_known: bool,
    out_i: np.ndarray,
    out_j: np.ndarray,
) -> int:  # pragma: no cover - compiled
    """Pairs (i, j) with |px[i, 0] − pred[j, 0]| ≤ r, (``rows_known``) |px[i, 2] − pred[j, 2]| ≤ r
    and |(px[i, 0] − px[i, 1]) − (pred[j, 0] − pred[j, 1])| ≤ r, in float64 exactly as numpy
    evaluates those masks; written in row-major order (i, then j ascending) to ``out_i``/``out_j``.

    ``order`` sorts ``pred`` by column, and ``order[lo[i]:hi[i]]`` must hold every j whose column
    can pass for measurement i (a superset: the exact test is applied here). The outputs hold at
    least Σ(hi − lo) entries; returns the count.
    """
    n = 0
    for i in range(px.shape[0]):
        x = px[i, 0]
        y = px[i, 2]
        dm = px[i, 0] - px[i, 1]
        start = n
        for p in range(lo[i], hi[i]):
            j = order[p]
            if not abs(x - pred[j, 0]) <= r:
                continue
            if rows_known and not abs(y - pred[j, 2]) <= r:
                continue
            if not abs(dm - (pred[j, 0] - pred[j, 1])) <= r:
                continue
            # insertion in ascending j (a window holds a handful)
            q = n
            while q > start and out_j[q - 1] > j:
                out_j[q] = out_j[q - 1]
                q -= 1
            out_j[q] = j
            out_i[n] = i
            n += 1
    return n
