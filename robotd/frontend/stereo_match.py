"""Stereo matching on rectified images (docs/math.md §4.1–§4.2) and triangulation (§2.2, §3.1).

Candidates for a left feature are the right features that satisfy every stereo constraint:
row |y_L − y_R| ≤ ε_y, disparity d_min ≤ x_L − x_R ≤ d_max = fb / X_min, and (SURF) the same
Laplacian sign. The ratio test runs among those candidates only; a lone candidate must instead
pass an absolute descriptor-distance limit. Then the cross-check keeps mutual best matches.

Candidate generation uses row bucketing: right features sorted by row, a binary search per left
feature gives the band of rows within ε_y, so only O(N·band) pairs are ever scored (≈ 1.5 % of
the L×R pairs on KITTI). The per-pair loops (candidate pairs, ratio and cross-check, the
sub-pixel refinement below) are numba kernels (``_stereo_kernels``); the tests hold them to
readable numpy twins (``*_numpy`` in tests/support/reference_frontend.py) and to brute force
(candidate pairs).

Sub-pixel disparity. ORB keypoints on pyramid level k are quantised to 1.2^k px, far coarser than
the 0.5 px σ_x the covariance model assumes (§3.1); SIFT/SURF positions are sub-pixel but the
left and right keypoints are localised independently. So the disparity is re-measured directly
from the images: a zero-mean SSD cost of a (2h+1)² patch around the left keypoint against the
right image at integer disparities d₀−r … d₀+r along the same row, and a parabola through the
minimum and its two neighbours, δ = (c₋ − c₊) / (2(c₋ − 2c₀ + c₊)) (parabola fits suit SSD costs;
Shimizu & Okutomi 2001). Zero-mean removes the KITTI cameras' gain difference. A minimum on the
border of the search window means the photometry disagrees with the descriptor match by ≥ r px:
such matches are dropped (``refine_reject_edge``), which also removes many stereo mismatches.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np

from robotd.core.errors import ConfigError, InputError
from robotd.core.stereo import (
    RectifiedStereo,
    debias_points,
    gate_selection_shift,
    triangulate,
    triangulation_covariance,
)
from robotd.frontend import _stereo_kernels as _k
from robotd.frontend.features import Features

logger = logging.getLogger(__name__)


# --------------------------------------------------------------------------------------------
# Descriptor distances (shared with association.py)


def normalise_descriptors(desc: np.ndarray, binary: bool) -> np.ndarray:
    """Float descriptors scaled to unit L2 norm (so one absolute limit fits SIFT and SURF); binary as is."""
    if binary:
        return np.ascontiguousarray(desc, dtype=np.uint8)
    d = np.asarray(desc, dtype=np.float32)
    n = np.linalg.norm(d, axis=1, keepdims=True)
    return d / np.maximum(n, 1e-12)


def pair_distances(a: np.ndarray, b: np.ndarray, binary: bool) -> np.ndarray:
    """Row-wise distances between (P, D) descriptor arrays: Hamming bits or Euclidean (unit-normalised)."""
    if binary:
        return np.bitwise_count(np.bitwise_xor(a, b)).sum(axis=1, dtype=np.int32).astype(np.float32)
    diff = a - b
    return np.sqrt(np.einsum("pd,pd->p", diff, diff))


def distance_matrix(a: np.ndarray, b: np.ndarray, binary: bool, chunk_bytes: int = 1 << 24) -> np.ndarray:
    """(N, M) distances between normalised descriptor sets ``a`` (N, D) and ``b`` (M, D)."""
    n, m = a.shape[0], b.shape[0]
    if n == 0 or m == 0:
        return np.zeros((n, m), np.float32)
    if binary:
        out = np.empty((n, m), np.float32)
        a = np.ascontiguousarray(a)
        b = np.ascontiguousarray(b)
        if a.shape[1] % 8 == 0:
            # popcount on 64-bit words: 8× fewer elements than on bytes
            a = a.view(np.uint64)
            b = b.view(np.uint64)
        # one (chunk, M) XOR + popcount per descriptor word, accumulated in uint16: ≈ 6–10× faster
        # than a popcount over a (chunk, M, words) buffer reduced along its short last axis;
        # chunked so each (chunk, M) temporary stays near chunk_bytes (16 MB) for large maps
        chunk = max(1, chunk_bytes // max(1, 8 * m))
        for s in range(0, n, chunk):
            aa = a[s : s + chunk]
            acc = np.bitwise_count(aa[:, None, 0] ^ b[None, :, 0]).astype(np.uint16)
            for w in range(1, a.shape[1]):
                acc += np.bitwise_count(aa[:, None, w] ^ b[None, :, w])
            out[s : s + chunk] = acc
        return out
    # |a − b|² = |a|² + |b|² − 2 a·b; both unit norm
    g = a @ b.T
    return np.sqrt(np.maximum(2.0 - 2.0 * g, 0.0)).astype(np.float32)


def ratio_and_cross_check(
    i: np.ndarray,
    j: np.ndarray,
    dist: np.ndarray,
    n_j: int,
    ratio: float,
    max_single: float,
    cross_check: bool = True,
) -> tuple[np.ndarray, dict[str, int]]:
    """Select mutual best matches from sparse candidate pairs (docs/math.md §4.1–§4.2).

    ``i``, ``j``: (P,) indices of candidate pairs; ``dist``: (P,) their descriptor distances.
    For each i the best pair is kept if dist < ratio · second-best distance, or, when it is the
    only candidate, if dist ≤ ``max_single``. Then the cross-check keeps (i, j) only if i is also
    j's nearest candidate. Returns the indices (into the pair arrays) of accepted pairs and counts.
    Ties: the earliest pair wins. (numba kernel; numpy twin: ``ratio_and_cross_check_numpy`` in
    tests/support/reference_frontend.py.)
    """
    p = int(np.shape(i)[0])
    stats = {"pairs": p, "ratio_rejected": 0, "single_rejected": 0, "cross_rejected": 0}
    if p == 0:
        return np.zeros(0, np.int64), stats
    # contiguous int64 / float32|float64: one compiled signature each (np.nonzero returns strided views)
    i = np.ascontiguousarray(i, dtype=np.int64)
    j = np.ascontiguousarray(j, dtype=np.int64)
    # the kernel indexes without bounds checks: refuse what numpy would have raised on
    if j.shape != (p,) or np.shape(dist) != (p,) or i.shape != (p,):
        raise InputError(
            f"ratio_and_cross_check: expected i, j, dist of one length, got {i.shape}, {j.shape}, {np.shape(dist)}"
        )
    if j.min() < 0 or j.max() >= n_j:
        raise InputError(f"ratio_and_cross_check: expected 0 <= j < n_j = {n_j}, got j in [{j.min()}, {j.max()}]")
    dist = np.ascontiguousarray(dist, dtype=np.float32 if np.asarray(dist).dtype == np.float32 else np.float64)
    # every caller passes pairs grouped by i (row-major); only an unsorted i is sorted
    if np.any(i[1:] < i[:-1]):
        order = np.argsort(i, kind="stable")
        i_s, d_s = i[order], dist[order]
    else:
        order, i_s, d_s = np.arange(p), i, dist
    out = np.empty(p, np.int64)
    counts = np.zeros(3, np.int64)
    n = _k.ratio_cross_kernel(
        i_s, d_s, order, j, dist, int(n_j), float(ratio), dist.dtype.type(max_single), bool(cross_check), out, counts
    )
    stats["ratio_rejected"], stats["single_rejected"], stats["cross_rejected"] = (int(c) for c in counts)
    return out[:n], stats


# --------------------------------------------------------------------------------------------
# Parameters and result


@dataclass(frozen=True, slots=True)
class StereoMatchParams:
    """Stereo matching configuration (config key ``frontend.stereo``; defaults of docs/math.md §5.5).

    row_tol_px: ε_y of the row constraint. d_min_px, depth_min_m: disparity bounds (d_max = fb/X_min).
    ratio: τ_r; None picks 0.8 for float descriptors (SIFT, SURF) and 0.75 for binary (ORB).
    max_single_float / max_single_binary: absolute distance limit when one candidate survives
      (unit-normalised Euclidean; Hamming bits).
    use_laplacian: SURF's Laplacian-sign constraint (ignored where the sign is 0/unknown).
    max_scale_ratio / max_angle_deg: optional size and orientation constraints (None: off).
    cross_check: mutual best matches only.
    refine: "patch" (ZSSD + parabola along the row, see module doc) or "keypoint" (use x_R as given).
    patch_half_px, search_px: patch half-size h and search radius r of the refinement.
    refine_reject_edge: drop matches whose SSD minimum lies at ±r (descriptor and photometry disagree).
    sigma_x_px, sigma_y_px, cov_inflation: pixel noise of §3.1 and the §3.3 inflation.
    debias_depth: remove the second-order triangulation bias (robotd.core.stereo.debias_points) for
      the pixel model's σ_d² = 2σ_x². Off by default: real and rendered matches' disparity noise is
      0.07–0.10 px, not 0.71, so it puts far points 1–3 % too near
      (docs/frontend.md "Aligned pixels, no depth debias").
    debias_limits: correct the disparities of matches near the gate's limits for the selection the
      gate makes (robotd.core.stereo.gate_selection_shift): a point near the far limit is kept only when
      its noise made it look nearer, so it comes out too near (docs/frontend.md).
    """

    row_tol_px: float = 2.0
    d_min_px: float = 2.0
    depth_min_m: float = 0.3
    ratio: float | None = None
    max_single_float: float = 0.45
    max_single_binary: float = 60.0
    use_laplacian: bool = True
    max_scale_ratio: float | None = None
    max_angle_deg: float | None = None
    cross_check: bool = True
    refine: str = "patch"
    patch_half_px: int = 3
    search_px: int = 2
    refine_reject_edge: bool = True
    sigma_x_px: float = 0.5
    sigma_y_px: float = 0.5 / np.sqrt(2.0)
    cov_inflation: float = 1.0
    debias_depth: bool = False
    debias_limits: bool = False

    def __post_init__(self) -> None:
        if self.row_tol_px < 0 or self.d_min_px <= 0 or self.depth_min_m <= 0:
            raise ConfigError(
                "frontend.stereo: expected row_tol_px >= 0, d_min_px > 0, depth_min_m > 0, got "
                f"{self.row_tol_px}, {self.d_min_px}, {self.depth_min_m}"
            )
        if self.ratio is not None and not 0.0 < self.ratio <= 1.0:
            raise ConfigError(f"frontend.stereo.ratio: expected in (0, 1], got {self.ratio}")
        if self.refine not in ("patch", "keypoint"):
            raise ConfigError(f"frontend.stereo.refine: expected 'patch' or 'keypoint', got {self.refine!r}")
        if self.patch_half_px < 1 or self.search_px < 1:
            raise ConfigError(
                f"frontend.stereo.patch_half_px/search_px: expected >= 1, got {self.patch_half_px}, {self.search_px}"
            )


@dataclass(frozen=True, slots=True, eq=False)
class StereoMatches:
    """Triangulated stereo measurements of one frame.

    xl, xr, y: (N,) [px] left column, right column, row (rectified image); xyz_R: (N, 3) [m] points
    in the robot frame (FRD, baseline centre; eq. 3.2.14); cov_R: (N, 3, 3) [m²] first-order
    covariance (§3.1); desc: (N, D) left descriptors (normalised as in :func:`normalise_descriptors`);
    left_idx / right_idx: (N,) indices into the left / right Features; dist: (N,) descriptor
    distance of the stereo match; refined: (N,) True where the sub-pixel patch refinement applied.
    sigma_d: (N,) [px] the refinement's own precision of each disparity (:func:`refine_disparity`;
    inf where it did not apply), or None when no refinement ran.
    """

    xl: np.ndarray
    xr: np.ndarray
    y: np.ndarray
    xyz_R: np.ndarray
    cov_R: np.ndarray
    desc: np.ndarray
    left_idx: np.ndarray
    right_idx: np.ndarray
    dist: np.ndarray
    refined: np.ndarray
    binary: bool = False
    stats: dict[str, int] = field(default_factory=dict)
    sigma_d: np.ndarray | None = None

    @property
    def n(self) -> int:
        return int(self.xl.shape[0])

    def subset(self, idx: np.ndarray) -> StereoMatches:
        """The measurements at ``idx`` (indices or boolean mask)."""
        return StereoMatches(
            self.xl[idx],
            self.xr[idx],
            self.y[idx],
            self.xyz_R[idx],
            self.cov_R[idx],
            self.desc[idx],
            self.left_idx[idx],
            self.right_idx[idx],
            self.dist[idx],
            self.refined[idx],
            self.binary,
            dict(self.stats),
            None if self.sigma_d is None else self.sigma_d[idx],
        )

    @staticmethod
    def empty(dim: int, binary: bool) -> StereoMatches:
        z = np.zeros(0)
        zi = np.zeros(0, np.int64)
        return StereoMatches(
            z,
            z.copy(),
            z.copy(),
            np.zeros((0, 3)),
            np.zeros((0, 3, 3)),
            np.zeros((0, dim), np.uint8 if binary else np.float32),
            zi,
            zi.copy(),
            np.zeros(0, np.float32),
            np.zeros(0, bool),
            binary,
            {},
        )


# --------------------------------------------------------------------------------------------
# Matching


def candidate_pairs(
    left: Features, right: Features, rig: RectifiedStereo, params: StereoMatchParams
) -> tuple[np.ndarray, np.ndarray]:
    """All (i, j) left/right index pairs that satisfy the §4.2 constraints, as two (P,) arrays."""
    if left.n == 0 or right.n == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    d_min, d_max = rig.disparity_bounds(params.depth_min_m, params.d_min_px)
    yl = left.xy[:, 1].astype(np.float64)
    yr = right.xy[:, 1].astype(np.float64)
    order_r = np.argsort(yr, kind="stable")
    yr_s = yr[order_r]
    lo = np.searchsorted(yr_s, yl - params.row_tol_px, side="left")
    hi = np.searchsorted(yr_s, yl + params.row_tol_px, side="right")
    total = int((hi - lo).sum())
    if total == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    # (a Laplacian sign of 0 means unknown: ORB and SIFT give none, and the test would pass every pair)
    use_lap = bool(params.use_laplacian and np.any(left.laplacian) and np.any(right.laplacian))
    out_i = np.empty(total, np.int64)
    out_j = np.empty(total, np.int64)
    n = _k.candidate_pairs_kernel(
        np.ascontiguousarray(left.xy[:, 0]),
        np.ascontiguousarray(right.xy[:, 0]),
        np.ascontiguousarray(left.laplacian, dtype=np.int8),
        np.ascontiguousarray(right.laplacian, dtype=np.int8),
        use_lap,
        order_r.astype(np.int64, copy=False),
        lo.astype(np.int64, copy=False),
        hi.astype(np.int64, copy=False),
        float(d_min),
        float(d_max),
        out_i,
        out_j,
    )
    i, j = out_i[:n], out_j[:n]
    if params.max_scale_ratio is None and params.max_angle_deg is None:
        return i, j
    ok = np.ones(n, bool)
    if params.max_scale_ratio is not None:
        r = left.size[i] / np.maximum(right.size[j], 1e-6)
        ok &= (r <= params.max_scale_ratio) & (r >= 1.0 / params.max_scale_ratio)
    if params.max_angle_deg is not None:
        ai, aj = left.angle[i], right.angle[j]
        da = np.abs((ai - aj + 180.0) % 360.0 - 180.0)
        ok &= (ai < 0) | (aj < 0) | (da <= params.max_angle_deg)
    return i[ok], j[ok]


def mutual_matches(
    a: np.ndarray, b: np.ndarray, binary: bool, max_dist: float, ratio: float, second_in_row: bool
) -> tuple[np.ndarray, np.ndarray]:
    """Mutual best descriptor matches (i, j) between normalised sets ``a`` (N, D) and ``b`` (M, D),
    every element of one set against every one of the other (frame-to-frame motion, the disparity
    offset's anchor pairs).

    The candidates are the pairs within ``max_dist``; among them :func:`ratio_and_cross_check`
    (ratio ``ratio``, a lone candidate kept) picks each i's best and keeps it when it is also its
    j's nearest candidate. With ``second_in_row`` (and M > 1) a best must also be below ``ratio`` ×
    the second-smallest distance of its whole row, candidate or not, which rejects a lone candidate
    with a near rival just outside ``max_dist``. Returns (ic, jc) int64 in ascending i.

    Binary descriptors whose width is a multiple of 8 bytes (ORB's 32) go through one numba pass
    (``_stereo_kernels.mutual_binary_kernel``) that never forms the (N, M) distance matrix: at 700
    ORB features against 700 it is ≈ 5× faster than the matrix, its threshold mask and its row
    partition. Float descriptors (one matrix product) and other widths take that numpy path; both
    give the same pairs (numpy twin: ``mutual_matches_numpy`` in tests/support/reference_frontend.py).
    """
    if np.ndim(a) != 2 or np.ndim(b) != 2 or np.shape(a)[1] != np.shape(b)[1]:
        raise InputError(
            f"mutual_matches: expected (N, D) and (M, D) descriptors of one width, got {np.shape(a)}, {np.shape(b)}"
        )
    n, m = int(np.shape(a)[0]), int(np.shape(b)[0])
    if n == 0 or m == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    if binary and a.shape[1] % 8 == 0:
        aw = np.ascontiguousarray(a, dtype=np.uint8).view(np.uint64)
        bw = np.ascontiguousarray(b, dtype=np.uint8).view(np.uint64)
        out_i = np.empty(n, np.int64)
        out_j = np.empty(n, np.int64)
        limit = int(min(math.floor(max_dist), 1 << 30))  # integer distances: d ≤ max_dist ⇔ d ≤ ⌊max_dist⌋
        k = _k.mutual_binary_kernel(aw, bw, limit, float(ratio), bool(second_in_row), out_i, out_j)
        return out_i[:k], out_j[:k]
    return mutual_matches_matrix(a, b, binary, max_dist, ratio, second_in_row)


def mutual_matches_matrix(
    a: np.ndarray, b: np.ndarray, binary: bool, max_dist: float, ratio: float, second_in_row: bool
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`mutual_matches` through the whole (N, M) distance matrix: its path for float
    descriptors and binary widths that are not whole 64-bit words, and the path binary descriptors
    took before the kernel (``bench/matching.py`` times the two)."""
    m = int(np.shape(b)[0])
    if np.shape(a)[0] == 0 or m == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    D = distance_matrix(a, b, binary)
    ii, jj = np.nonzero(D <= max_dist)
    sel, _ = ratio_and_cross_check(ii, jj, D[ii, jj], m, ratio, max_dist, True)
    ic, jc = ii[sel].astype(np.int64), jj[sel].astype(np.int64)
    if second_in_row and m > 1:
        second = np.partition(D, 1, axis=1)[:, 1]
        ok = D[ic, jc] < ratio * second[ic]
        ic, jc = ic[ok], jc[ok]
    return ic, jc


def window_pairs(
    px: np.ndarray, predicted: np.ndarray, r: float, rows_known: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """Guided identification's candidate pairs: (i, j) with measurement i's left column, row (when
    ``rows_known``) and disparity all within ``r`` [px] of landmark j's predicted ones.

    ``px`` (N, 3), ``predicted`` (K, 3): pixels (x_l, x_r, y), float64. Returns (ii, jj) int64 in
    row-major order (i, then j ascending), the order ``np.nonzero`` gives the three (N, K) masks.
    The predictions are sorted by column once and each measurement visits only its column window
    (numba kernel ``_stereo_kernels.window_pairs_kernel``; numpy twin: ``window_pairs_numpy`` in
    tests/support/reference_frontend.py, the masks this replaced).
    """
    px = np.ascontiguousarray(px, dtype=np.float64)
    predicted = np.ascontiguousarray(predicted, dtype=np.float64)
    if px.ndim != 2 or px.shape[1] != 3 or predicted.ndim != 2 or predicted.shape[1] != 3:
        raise InputError(f"window_pairs: expected (N, 3) and (K, 3) pixels, got {px.shape}, {predicted.shape}")
    empty = np.zeros(0, np.int64)
    if px.shape[0] == 0 or predicted.shape[0] == 0 or not r >= 0:
        return empty, empty
    order = np.argsort(predicted[:, 0], kind="stable")
    cols = predicted[order, 0]
    # a window a little wider than r (the kernel applies the exact test): every column that can pass
    pad = r + 1e-6 * (1.0 + r + np.abs(px[:, 0]))
    lo = np.searchsorted(cols, px[:, 0] - pad, "left").astype(np.int64)
    hi = np.searchsorted(cols, px[:, 0] + pad, "right").astype(np.int64)
    hi = np.maximum(hi, lo)
    total = int(np.sum(hi - lo))
    if total == 0:
        return empty, empty
    out_i = np.empty(total, np.int64)
    out_j = np.empty(total, np.int64)
    n = _k.window_pairs_kernel(px, predicted, order, lo, hi, float(r), bool(rows_known), out_i, out_j)
    return out_i[:n], out_j[:n]


def refine_disparity(
    left_img: np.ndarray,
    right_img: np.ndarray,
    xl: np.ndarray,
    yl: np.ndarray,
    d0: np.ndarray,
    half: int = 3,
    search: int = 2,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Sub-pixel disparity by ZSSD patch cost and a parabola fit along the row (module doc).

    ``xl``, ``yl``: (N,) [px] left keypoints; ``d0``: (N,) [px] initial disparities. Returns
    (d (N,) refined disparity at the left keypoint, ok (N,) refinement applied, edge (N,) minimum
    on the search border, sigma (N,) [px] the fit's own precision, from the cost's curvature
    against its minimum). Where ``ok`` is False, ``d`` is ``d0`` and ``sigma`` inf. The cost is measured at the
    integer column rint(xl); the caller keeps the keypoint's sub-pixel column and assumes the
    disparity is constant over that < 0.5 px offset. (numba kernel; numpy twin:
    ``refine_disparity_numpy`` in tests/support/reference_frontend.py.)
    """
    n = np.shape(xl)[0]
    if np.shape(yl) != (n,) or np.shape(d0) != (n,) or np.shape(left_img) != np.shape(right_img):
        raise InputError(
            f"refine_disparity: expected xl, yl, d0 of one length and images of one size, got "
            f"{np.shape(xl)}, {np.shape(yl)}, {np.shape(d0)}, {np.shape(left_img)}, {np.shape(right_img)}"
        )
    d_out = np.array(d0, dtype=np.float64)
    ok = np.zeros(n, bool)
    edge = np.zeros(n, bool)
    sigma = np.full(n, np.inf)
    if n == 0:
        return d_out, ok, edge, sigma
    _k.refine_kernel(
        np.ascontiguousarray(left_img, dtype=np.uint8),
        np.ascontiguousarray(right_img, dtype=np.uint8),
        np.rint(xl).astype(np.int64),
        np.rint(yl).astype(np.int64),
        np.rint(d0).astype(np.int64),
        int(half),
        int(search),
        d_out,
        ok,
        edge,
        sigma,
    )
    return d_out, ok, edge, sigma


def warmup() -> None:
    """Compile or load the matcher's numba kernels now (tiny inputs, the daemon's dtypes). The
    daemon calls it at start-up so that its first frame is not delayed."""
    img = np.zeros((16, 32), np.uint8)
    x = np.array([20.0], np.float32)
    lap = np.zeros(1, np.int8)
    zero, one = np.zeros(1, np.int64), np.ones(1, np.int64)
    out_i, out_j = np.empty(1, np.int64), np.empty(1, np.int64)
    _k.candidate_pairs_kernel(x, x - 5.0, lap, lap, False, zero, zero, one, 1.0, 100.0, out_i, out_j)
    d = np.zeros(1, np.float32)
    _k.ratio_cross_kernel(zero, d, zero, zero, d, 1, 0.8, np.float32(60.0), True, out_i, np.zeros(3, np.int64))
    c = np.full(1, 8, np.int64)
    _k.refine_kernel(
        img, img, np.full(1, 16, np.int64), c, c, 3, 2, np.zeros(1), np.zeros(1, bool), np.zeros(1, bool), np.zeros(1)
    )
    words = np.zeros((1, 4), np.uint64)
    _k.mutual_binary_kernel(words, words, 60, 0.75, True, out_i, out_j)
    pix = np.zeros((1, 3))
    _k.window_pairs_kernel(pix, pix, zero, zero, one, 15.0, True, out_i, out_j)


def match_stereo(
    left: Features,
    right: Features,
    rig: RectifiedStereo,
    params: StereoMatchParams | None = None,
    left_img: np.ndarray | None = None,
    right_img: np.ndarray | None = None,
    disparity_offset_px: float = 0.0,
) -> StereoMatches:
    """Match rectified left/right features and triangulate them (docs/math.md §2.2, §3.1, §4.2).

    ``left``/``right``: Features of the rectified images (one detector); ``left_img``/``right_img``:
    (H, W) uint8 rectified images, needed for ``refine="patch"`` (without them the keypoint
    positions are used). ``disparity_offset_px``: the rig's estimated constant disparity error δ̂,
    taken off every disparity before the limits and the triangulation (x_r ← x_r + δ̂;
    robotd.frontend.disparity_bias). Returns :class:`StereoMatches` in the robot frame.
    """
    params = params or StereoMatchParams()
    if left.binary != right.binary or (left.n and right.n and left.desc.shape[1] != right.desc.shape[1]):
        raise InputError(
            f"match_stereo: expected features of one detector, got binary={left.binary}/{right.binary}, "
            f"dims {left.desc.shape[1:]}/{right.desc.shape[1:]}"
        )
    binary = left.binary
    dim = left.desc.shape[1] if left.desc.ndim == 2 else (32 if binary else 64)
    i, j = candidate_pairs(left, right, rig, params)
    dl = normalise_descriptors(left.desc, binary)
    dr = normalise_descriptors(right.desc, binary)
    if i.size == 0:
        out = StereoMatches.empty(dim, binary)
        out.stats.update({"pairs": 0})
        return out
    dist = pair_distances(dl[i], dr[j], binary)
    ratio = params.ratio if params.ratio is not None else (0.75 if binary else 0.8)
    max_single = params.max_single_binary if binary else params.max_single_float
    sel, stats = ratio_and_cross_check(i, j, dist, right.n, ratio, max_single, params.cross_check)
    i, j, dist = i[sel], j[sel], dist[sel]
    xl = left.xy[i, 0].astype(np.float64)
    yl = left.xy[i, 1].astype(np.float64)
    xr = right.xy[j, 0].astype(np.float64)
    yr = right.xy[j, 1].astype(np.float64)
    y = 0.5 * (yl + yr)
    refined = np.zeros(i.size, bool)
    sigma_d: np.ndarray | None = None
    n_edge = 0
    if params.refine == "patch" and left_img is not None and right_img is not None and i.size:
        d, refined, edge, sigma_d = refine_disparity(
            left_img, right_img, xl, yl, xl - xr, params.patch_half_px, params.search_px
        )
        xr = np.where(refined, xl - d, xr)
        # the refined match lies on the left keypoint's row (the images are rectified)
        y = np.where(refined, yl, y)
        keep = ~edge if params.refine_reject_edge else np.ones(i.size, bool)
        n_edge = int(np.sum(edge))
    else:
        keep = np.ones(i.size, bool)
    if disparity_offset_px:
        xr = xr + disparity_offset_px
    if disparity_offset_px or (params.refine == "patch" and left_img is not None and right_img is not None):
        d_min, d_max = rig.disparity_bounds(params.depth_min_m, params.d_min_px)
        keep &= (xl - xr >= d_min) & (xl - xr <= d_max)
        i, j, dist, xl, xr, y, refined = i[keep], j[keep], dist[keep], xl[keep], xr[keep], y[keep], refined[keep]
        sigma_d = None if sigma_d is None else sigma_d[keep]
    stats["refine_edge"] = n_edge
    stats["matches"] = int(i.size)
    f, px, py, b = rig.f_px, rig.px, rig.py, rig.baseline_m
    if params.debias_limits and i.size:
        d_lo, d_hi = rig.disparity_bounds(params.depth_min_m, params.d_min_px)
        shift = gate_selection_shift(xl - xr, d_lo, d_hi, np.sqrt(2.0) * params.sigma_x_px)
        # both columns move by half, so the point stays on its ray through the baseline's centre
        xl, xr = xl - 0.5 * shift, xr + 0.5 * shift
    xyz = triangulate(xl, xr, y, f, px, py, b)
    if params.debias_depth:
        xyz = debias_points(xyz, xl - xr, params.sigma_x_px)
    cov = triangulation_covariance(xl, xr, y, f, px, py, b, params.sigma_x_px, params.sigma_y_px, params.cov_inflation)
    logger.debug(
        "stereo: %d left, %d right, %d candidate pairs, %d ratio-, %d single-, %d cross-, %d refine-rejected, "
        "%d matches",
        left.n,
        right.n,
        stats["pairs"],
        stats["ratio_rejected"],
        stats["single_rejected"],
        stats["cross_rejected"],
        n_edge,
        i.size,
    )
    return StereoMatches(
        xl, xr, y, xyz, cov, dl[i], i.astype(np.int64), j.astype(np.int64), dist, refined, binary, stats, sigma_d
    )
