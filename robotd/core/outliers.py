"""Outlier detection for landmark correspondences: RANSAC (docs/math.md §5).

A stage of its own, usable with any detector and any filter: it sees only the matched landmark
sets, never the filter's pose.

- ``similarity_mahalanobis`` (the thesis's detector, default): 3-point samples, the similarity
  transform b = sRa + t by Umeyama's closed form (§5.1), consensus by the squared Mahalanobis
  distance d² = eᵀ(B + s²RARᵀ)⁻¹e ≤ χ²_{3,α} (§5.2).
- ``similarity_euclidean``: the same loop with the standard consensus |e| < τ (baseline).
- ``fundamental``: normalised 8-point fundamental matrix with rank-2 projection and the Sampson
  distance ≤ 3.84σ² (Hartley 1997; Hartley & Zisserman 2003 ch. 11), on the left-image positions
  at t−1 and t (§5.4; baseline).
- ``none``: accept every correspondence.

2-D filters call the similarity variants with (N, 2) points: Umeyama holds in any dimension,
samples have 2 pairs and the thresholds are χ²₂ (§5.1).

All RANSAC variants share one loop (§5.3): distinct random samples from an injected
``np.random.Generator``, degenerate samples skipped, hypotheses scored in batches (one call
for a batch of hypotheses × all pairs, 3×3 systems solved in closed form; a numba kernel in
``_outlier_kernels`` for the Mahalanobis consensus), best = most inliers
with ties to the smaller Σd² (each new best locally optimised by a weighted re-fit on its
inliers), the adaptive budget K = ⌈log(1−p)/log(1−w^m)⌉ with a cap, one
re-fit on the inliers and one re-classification, and "accept none" below ``min_inliers``.
"""

from __future__ import annotations

import functools
import logging
import math
import time
from dataclasses import dataclass

import numpy as np
from scipy.special import chdtri  # chi2 quantiles; scipy.stats costs 1 s of start-up

from robotd.core._outlier_kernels import gn_fit, gn_weights, similarity_d2_kernel
from robotd.core.choices import OUTLIER_METHODS
from robotd.core.errors import ConfigError, InputError
from robotd.core.geometry import umeyama, umeyama_batch

logger = logging.getLogger("robotd.outliers")  # its name before the layer packages: users filter by it

# Gauss–Newton stops when its step (|δt| in m, δθ in rad, δσ) falls below this: 0.1 µm is far
# below any stereo noise, and the iteration converges about 1000× per step, so one more step
# would change the fit by ≈ 1e-10 only
GN_STEP_TOL = 1e-7


@dataclass(frozen=True, slots=True)
class OutlierParams:
    """Outlier-stage configuration (config key ``frontend.outliers``; defaults of docs/math.md §5.5).

    method: one of ``OUTLIER_METHODS``.
    confidence: χ² level 1−α of the Mahalanobis test (0.99 → 11.345 in 3-D, 9.210 in 2-D).
    p_success: p of the iteration budget; max_iterations: cap (similarity); f_max_iterations: cap (F).
    max_scale_dev: ε_s, reject hypotheses with |s−1| above it. min_sample_area_m2: degenerate-sample
      limit (3-D: triangle area in either set; 2-D: squared separation of the two points, so 0.01 m²
      means 0.1 m).
    min_inliers: fewer inliers → accept no correspondence this frame.
    euclidean_tau_m: τ of the Euclidean baseline. sampson_sigma_px, sampson_chi2: the F-matrix test
      d_S² ≤ sampson_chi2 · σ².
    score: "count" (inliers, ties by smaller Σd²) or "msac" (Σ min(d², χ²), Torr & Zisserman 2000).
    batch: hypotheses scored per numpy call.
    local_optimisation: re-fit each new best hypothesis on its inliers (LO-RANSAC) before scoring
      it against the budget, repeated while it improves (at most lo_steps times); the final
      re-fit is Mahalanobis-weighted too (Umeyama for the Euclidean measure).
    lo_gn_iterations: Gauss–Newton steps of each LO re-fit (from the sample's hypothesis the step
      is ≈ 1e-5 m after two, far below the stereo noise); the final re-fit takes up to 5.
    """

    method: str = "similarity_mahalanobis"
    confidence: float = 0.99
    p_success: float = 0.99
    max_iterations: int = 500
    f_max_iterations: int = 2000
    max_scale_dev: float = 0.1
    min_sample_area_m2: float = 0.01
    min_inliers: int = 6
    euclidean_tau_m: float = 0.2
    sampson_sigma_px: float = 1.0
    sampson_chi2: float = 3.84
    score: str = "count"
    batch: int = 32
    local_optimisation: bool = True
    lo_steps: int = 4
    lo_gn_iterations: int = 2

    def __post_init__(self) -> None:
        if self.method not in OUTLIER_METHODS:
            raise ConfigError(f"frontend.outliers.method: expected one of {OUTLIER_METHODS}, got {self.method!r}")
        if self.score not in ("count", "msac"):
            raise ConfigError(f"frontend.outliers.score: expected 'count' or 'msac', got {self.score!r}")
        for key in ("confidence", "p_success"):
            v = getattr(self, key)
            if not 0.0 < v < 1.0:
                raise ConfigError(f"frontend.outliers.{key}: expected in (0, 1), got {v}")
        if self.max_iterations < 1 or self.f_max_iterations < 1 or self.batch < 1 or self.lo_gn_iterations < 1:
            raise ConfigError(
                "frontend.outliers: expected max_iterations, f_max_iterations, batch, lo_gn_iterations >= 1, got "
                f"{self.max_iterations}, {self.f_max_iterations}, {self.batch}, {self.lo_gn_iterations}"
            )

    def chi2_threshold(self, dof: int) -> float:
        """χ²_{dof, confidence}: 11.345 for (3, 0.99), 9.210 for (2, 0.99)."""
        return _chi2_ppf(self.confidence, dof)


@functools.lru_cache(maxsize=64)
def _chi2_ppf(p: float, dof: int) -> float:
    # scipy's ppf costs ≈ 0.2 ms per call, and RANSAC runs once or twice per frame
    return float(chdtri(dof, 1.0 - p))


@dataclass(frozen=True, slots=True, eq=False)
class OutlierResult:
    """What the outlier stage decided for N putative correspondences.

    inliers: (N,) bool, all False when ``accepted`` is False (fewer than min_inliers).
    s, R, t: the similarity b = s R a + t fitted on the inliers (R (d, d), t (d,)); None for F/none.
    F: (3, 3) fundamental matrix x2ᵀ F x1 = 0 (pixels) for the F baseline, else None.
    d2: (N,) final squared distance of each pair (Mahalanobis, Euclidean [m²] or Sampson [px²]).
    iterations: hypotheses drawn; degenerate / scale_rejected: samples skipped for those reasons.
    """

    method: str
    inliers: np.ndarray
    accepted: bool
    n_input: int
    n_inliers: int
    iterations: int
    degenerate: int
    scale_rejected: int
    ms: float
    threshold: float
    d2: np.ndarray
    s: float | None = None
    R: np.ndarray | None = None
    t: np.ndarray | None = None
    F: np.ndarray | None = None

    @property
    def n_rejected(self) -> int:
        return self.n_input - self.n_inliers

    def T_b_a(self) -> np.ndarray | None:
        """The fitted similarity as a (d+1, d+1) matrix [sR t; 0 1] mapping a-points to b-points."""
        if self.R is None or self.t is None or self.s is None:
            return None
        d = self.R.shape[0]
        T = np.eye(d + 1)
        T[:d, :d] = self.s * self.R
        T[:d, d] = self.t
        return T


# --------------------------------------------------------------------------------------------
# Small helpers


def sample_indices(rng: np.random.Generator, n: int, m: int, k: int) -> np.ndarray:
    """(k, m) samples of m distinct indices from range(n), uniformly (vectorised).

    Draw r_q from range(n − q) and step it over the already chosen indices (in increasing order),
    which yields each m-subset with equal probability without rejection.
    """
    out = np.empty((k, m), np.int64)
    chosen = np.empty((k, 0), np.int64)
    for q in range(m):
        r = rng.integers(0, n - q, size=k)
        srt = np.sort(chosen, axis=1)
        for c in range(q):
            r = r + (r >= srt[:, c])
        out[:, q] = r
        chosen = out[:, : q + 1]
    return out


def iteration_budget(w: float, m: int, p: float, cap: int) -> int:
    """K = ⌈log(1−p) / log(1−w^m)⌉ (docs/math.md §5.3), within [1, cap]."""
    if w <= 0.0:
        return cap
    wm = w**m
    if wm >= 1.0:
        return 1
    return int(min(cap, max(1, math.ceil(math.log(1.0 - p) / math.log(1.0 - wm)))))


def mahalanobis_sq(e: np.ndarray, C: np.ndarray) -> np.ndarray:
    """eᵀC⁻¹e for stacks: e (..., d), C (..., d, d), d = 2 or 3, by the closed-form inverse.

    Non-positive-definite C (det ≤ 0) gives +inf, so such a pair is never an inlier.
    """
    d = e.shape[-1]
    if d == 3:
        a, b, c = C[..., 0, 0], C[..., 0, 1], C[..., 0, 2]
        dd, ee, f = C[..., 1, 1], C[..., 1, 2], C[..., 2, 2]
        # adjugate of the symmetric matrix [[a b c] [b dd ee] [c ee f]]
        A00 = dd * f - ee * ee
        A01 = c * ee - b * f
        A02 = b * ee - c * dd
        A11 = a * f - c * c
        A12 = b * c - a * ee
        A22 = a * dd - b * b
        det = a * A00 + b * A01 + c * A02
        x, y, z = e[..., 0], e[..., 1], e[..., 2]
        q = A00 * x * x + A11 * y * y + A22 * z * z + 2.0 * (A01 * x * y + A02 * x * z + A12 * y * z)
    elif d == 2:
        a, b, c = C[..., 0, 0], C[..., 0, 1], C[..., 1, 1]
        det = a * c - b * b
        x, y = e[..., 0], e[..., 1]
        q = c * x * x - 2.0 * b * x * y + a * y * y
    else:
        raise InputError(f"mahalanobis_sq: expected dimension 2 or 3, got {d}")
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.where(det > 0, q / np.where(det > 0, det, 1.0), np.inf)
    return out


def _sample_degenerate(P: np.ndarray, min_area: float) -> np.ndarray:
    """(K,) True where a sample of points P (K, m, d) is degenerate (§5.1)."""
    if P.shape[2] == 3:
        cr = np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0])
        return 0.5 * np.linalg.norm(cr, axis=1) < min_area
    # 2-D: two points closer than sqrt(min_area)
    dv = P[:, 1] - P[:, 0]
    return np.einsum("ki,ki->k", dv, dv) < min_area


def similarity_residuals(s: np.ndarray, R: np.ndarray, t: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """e = b − (s R a + t) for K hypotheses and N pairs: s (K,), R (K, d, d), t (K, d) -> (K, N, d)."""
    return b[None] - (s[:, None, None] * np.einsum("kij,nj->kni", R, a) + t[:, None, :])


def similarity_d2(
    s: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    a: np.ndarray,
    b: np.ndarray,
    A: np.ndarray | None,
    B: np.ndarray | None,
    euclidean: bool = False,
) -> np.ndarray:
    """Squared consensus distance (K, N) of every pair under every hypothesis (§5.2).

    Mahalanobis: d² = eᵀ C⁻¹ e with C_i = B_i + s² R A_i Rᵀ (A: (N, d, d) covariance of a in its
    frame, B: (N, d, d) of b); a C that is not positive definite gives +inf. Euclidean: d² = |e|².
    (Mahalanobis: numba kernel; numpy twin: ``similarity_d2_numpy`` in tests/support/reference_outliers.py.)
    """
    if euclidean:
        e = similarity_residuals(s, R, t, a, b)
        return np.einsum("kni,kni->kn", e, e)
    s = np.ascontiguousarray(s, dtype=np.float64)
    R = np.ascontiguousarray(R, dtype=np.float64)
    t = np.ascontiguousarray(t, dtype=np.float64)
    a = np.ascontiguousarray(a, dtype=np.float64)
    b = np.ascontiguousarray(b, dtype=np.float64)
    none = np.zeros((1, 1, 1))
    A_ = none if A is None else np.ascontiguousarray(A, dtype=np.float64)
    B_ = none if B is None else np.ascontiguousarray(B, dtype=np.float64)
    # the kernel indexes without bounds checks: refuse what numpy would have raised on
    k, (n, d) = s.shape[0], a.shape
    if (
        d not in (2, 3)
        or b.shape != (n, d)
        or R.shape != (k, d, d)
        or t.shape != (k, d)
        or (A is not None and A_.shape != (n, d, d))
        or (B is not None and B_.shape != (n, d, d))
    ):
        raise InputError(
            f"similarity_d2: expected s (K,), R (K, d, d), t (K, d), a, b (N, d), A, B (N, d, d) with d = 2 or 3, "
            f"got {s.shape}, {R.shape}, {t.shape}, {a.shape}, {b.shape}, {None if A is None else A_.shape}, "
            f"{None if B is None else B_.shape}"
        )
    out = np.empty((s.shape[0], a.shape[0]))
    similarity_d2_kernel(s, R, t, a, b, A_, B_, A is not None, B is not None, out)
    return out


def warmup() -> None:
    """Compile or load the consensus and re-fit kernels now (the daemon calls it at start-up)."""
    z = np.zeros((1, 3))
    similarity_d2(np.ones(1), np.eye(3)[None], z, z, z, np.eye(3)[None], np.eye(3)[None])
    a = np.eye(3)
    C = np.broadcast_to(np.eye(3), (3, 3, 3)).copy()
    fit_similarity_mahalanobis(a, a, C, C, 1.0, np.eye(3), np.zeros(3), iterations=1)


# --------------------------------------------------------------------------------------------
# Shared pieces of the RANSAC loops


def _best_of_batch(d2: np.ndarray, thr: float, mode: str) -> tuple[int, int, float]:
    """Index of the best hypothesis in a batch, its inlier count and its cost (lower is better)."""
    inl = d2 <= thr
    cnt = inl.sum(axis=1)
    if mode == "msac":
        cost = np.minimum(d2, thr).sum(axis=1)
        k = int(np.argmin(cost))
        return k, int(cnt[k]), float(cost[k])
    ssum = np.where(inl, d2, 0.0).sum(axis=1)
    k = int(np.lexsort((ssum, -cnt))[0])
    return k, int(cnt[k]), float(ssum[k])


def _better(cnt: int, cost: float, best_cnt: int, best_cost: float, mode: str) -> bool:
    if mode == "msac":
        return cost < best_cost
    return cnt > best_cnt or (cnt == best_cnt and cost < best_cost)


# --------------------------------------------------------------------------------------------
# Mahalanobis-weighted similarity fit (re-fit on inliers)


def _fit_covariance(H: np.ndarray) -> np.ndarray:
    """The fit's covariance: the inverse Gauss–Newton information, symmetrised; inf when singular.

    Also used by the numpy twin of the fit (tests/support/reference_outliers.py), so that both
    compute it alike.
    """
    try:
        cov = np.linalg.inv(H)
    except np.linalg.LinAlgError:
        cov = np.full(H.shape, np.inf)
    return 0.5 * (cov + cov.T)


def fit_similarity_mahalanobis(
    a: np.ndarray,
    b: np.ndarray,
    A: np.ndarray | None,
    B: np.ndarray | None,
    s0: float,
    R0: np.ndarray,
    t0: np.ndarray,
    with_scale: bool = True,
    iterations: int = 5,
) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
    """(s, R, t) minimising Σ eᵢᵀ Cᵢ⁻¹ eᵢ, eᵢ = bᵢ − (s R aᵢ + t), by Gauss–Newton from (s0, R0, t0).

    Cᵢ = Bᵢ + s0² R0 Aᵢ R0ᵀ (§5.2) is held at the start value. Unweighted least squares (Umeyama)
    is dominated by the far points, whose depth error grows with X² (§3.2); this weighting is what
    makes the re-fit on inliers improve the hypothesis; a pair whose Cᵢ is not positive definite
    is left out. Perturbation: t + δt, exp(δθ) R, s·e^{δσ}.
    ``a``, ``b``: (N, d), d = 2 or 3; ``A``, ``B``: (N, d, d) or None. Returns (s, R, t, cov) with
    cov the inverse Gauss–Newton information over (δt, δθ[, δσ]). (numba kernels; numpy twin:
    ``fit_similarity_mahalanobis_numpy`` in tests/support/reference_outliers.py.)
    """
    n, d = a.shape
    # the kernels index without bounds checks: refuse what numpy would have raised on
    for name, M, shape in (("b", b, (n, d)), ("A", A, (n, d, d)), ("B", B, (n, d, d)), ("R0", R0, (d, d))):
        if M is not None and np.shape(M) != shape:
            raise InputError(f"fit_similarity_mahalanobis: expected {name} of shape {shape}, got {np.shape(M)}")
    if d not in (2, 3) or np.shape(t0) != (d,):
        raise InputError(
            f"fit_similarity_mahalanobis: expected d = 2 or 3 and t0 ({d},), got a {a.shape}, t0 {np.shape(t0)}"
        )
    if A is not None or B is not None:
        none = np.zeros((1, 1, 1))
        W = np.empty((n, d, d))
        gn_weights(
            none if A is None else np.ascontiguousarray(A, dtype=np.float64),
            none if B is None else np.ascontiguousarray(B, dtype=np.float64),
            float(s0),
            np.ascontiguousarray(R0, dtype=np.float64),
            A is not None,
            B is not None,
            W,
        )
    else:
        W = np.broadcast_to(np.eye(d), (n, d, d))
    k_rot = 3 if d == 3 else 1
    npar = d + k_rot + (1 if with_scale else 0)
    H = np.eye(npar)
    # the Gauss–Newton loop in one numba call (_outlier_kernels.gn_fit): H = Σ Jᵢᵀ Wᵢ Jᵢ and
    # g = Σ Jᵢᵀ Wᵢ eᵢ with ∂e/∂δt = −I, ∂e/∂δθ = −∂(exp(δθ) v)/∂δθ = [v]× for v = sRa in 3-D,
    # (v_y, −v_x) in 2-D, ∂e/∂δσ = −v; δ = −H⁻¹g until |δ| < GN_STEP_TOL
    s, R, t = gn_fit(
        np.ascontiguousarray(a, dtype=np.float64),
        np.ascontiguousarray(b, dtype=np.float64),
        np.ascontiguousarray(W, dtype=np.float64),
        float(s0),
        np.ascontiguousarray(R0, dtype=np.float64),
        np.ascontiguousarray(t0, dtype=np.float64),
        bool(with_scale),
        int(iterations),
        GN_STEP_TOL,
        H,
    )
    return s, R, t, _fit_covariance(H)


def _refit(
    a: np.ndarray,
    b: np.ndarray,
    A: np.ndarray | None,
    B: np.ndarray | None,
    model: tuple[float, np.ndarray, np.ndarray],
    inl: np.ndarray,
    euclidean: bool,
    iterations: int = 5,
) -> tuple[float, np.ndarray, np.ndarray]:
    """Re-fit a similarity on the inliers: Umeyama for the Euclidean measure, else Mahalanobis-weighted."""
    if euclidean:
        return umeyama(a[inl], b[inl])
    s, R, t, _ = fit_similarity_mahalanobis(
        a[inl],
        b[inl],
        None if A is None else A[inl],
        None if B is None else B[inl],
        model[0],
        model[1],
        model[2],
        iterations=iterations,
    )
    return s, R, t


# --------------------------------------------------------------------------------------------
# Similarity RANSAC (§5.1–§5.3)


def ransac_similarity(
    a: np.ndarray,
    b: np.ndarray,
    A: np.ndarray | None = None,
    B: np.ndarray | None = None,
    params: OutlierParams | None = None,
    rng: np.random.Generator | None = None,
    euclidean: bool | None = None,
) -> OutlierResult:
    """RANSAC over putative pairs (a_i, b_i) with the similarity model b = s R a + t.

    ``a``: (N, d) map landmarks (world frame, or the robot frame at t−1), ``A``: (N, d, d) their
    covariances; ``b``: (N, d) measured landmarks (robot frame), ``B``: (N, d, d) their covariances
    (§3); d = 3, or 2 for the planar filters. ``euclidean`` defaults to params.method. The
    returned (s, R, t) maps a into b: with a in the world frame it is T_robot_world (scaled).
    """
    params = params or OutlierParams()
    if rng is None:
        raise InputError("ransac_similarity: expected an injected np.random.Generator (rng), got None")
    t0 = time.perf_counter()
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    if a.ndim != 2 or a.shape != b.shape or a.shape[1] not in (2, 3):
        raise InputError(f"ransac_similarity: expected a, b of one shape (N, 2|3), got {a.shape} and {b.shape}")
    n, dim = a.shape
    for name, M in (("A", A), ("B", B)):
        if M is not None and M.shape != (n, dim, dim):
            raise InputError(f"ransac_similarity: expected {name} of shape {(n, dim, dim)}, got {M.shape}")
    if euclidean is None:
        euclidean = params.method == "similarity_euclidean"
    method = "similarity_euclidean" if euclidean else "similarity_mahalanobis"
    if not euclidean and A is None and B is None:
        raise InputError("ransac_similarity: the Mahalanobis consensus needs covariances A and/or B, got neither")
    thr = params.euclidean_tau_m**2 if euclidean else params.chi2_threshold(dim)
    m = dim  # minimal sample: 3 pairs in 3-D, 2 in 2-D
    empty = np.zeros(n, bool)
    if n < max(m, params.min_inliers):
        ms = (time.perf_counter() - t0) * 1e3
        logger.debug("outliers[%s]: %d pairs < %d, none accepted", method, n, max(m, params.min_inliers))
        return OutlierResult(method, empty, False, n, 0, 0, 0, 0, ms, thr, np.full(n, np.inf))

    best_cnt, best_cost = -1, math.inf
    best_model: tuple[float, np.ndarray, np.ndarray] | None = None
    K, it, n_degen, n_scale = params.max_iterations, 0, 0, 0
    while it < K:
        kb = min(params.batch, K - it)
        idx = sample_indices(rng, n, m, kb)
        it += kb
        Pa, Pb = a[idx], b[idx]  # (kb, m, d)
        degen = _sample_degenerate(Pa, params.min_sample_area_m2) | _sample_degenerate(Pb, params.min_sample_area_m2)
        n_degen += int(degen.sum())
        if np.all(degen):
            continue
        s, R, t = umeyama_batch(Pa[~degen], Pb[~degen])
        ok = np.abs(s - 1.0) <= params.max_scale_dev
        n_scale += int(np.sum(~ok))
        if not np.any(ok):
            continue
        s, R, t = s[ok], R[ok], t[ok]
        d2 = similarity_d2(s, R, t, a, b, A, B, euclidean)
        k, cnt, cost = _best_of_batch(d2, thr, params.score)
        if _better(cnt, cost, best_cnt, best_cost, params.score):
            model = (float(s[k]), R[k], t[k])
            if params.local_optimisation and cnt > m:
                # LO-RANSAC (Chum et al. 2003): a 3-point hypothesis from noisy stereo points is
                # imprecise; re-fitting it on its own inliers recovers most of the consensus
                inl_k = d2[k] <= thr
                for _ in range(params.lo_steps):
                    lo = _refit(a, b, A, B, model, inl_k, euclidean, params.lo_gn_iterations)
                    d2_lo = similarity_d2(np.array([lo[0]]), lo[1][None], lo[2][None], a, b, A, B, euclidean)
                    _, cnt_lo, cost_lo = _best_of_batch(d2_lo, thr, params.score)
                    if abs(lo[0] - 1.0) > params.max_scale_dev or not _better(cnt_lo, cost_lo, cnt, cost, params.score):
                        break
                    model, cnt, cost, inl_k = lo, cnt_lo, cost_lo, d2_lo[0] <= thr
            best_cnt, best_cost, best_model = cnt, cost, model
            K = min(K, iteration_budget(best_cnt / n, m, params.p_success, params.max_iterations))

    if best_model is None:
        ms = (time.perf_counter() - t0) * 1e3
        logger.debug(
            "outliers[%s]: no valid hypothesis in %d iterations (%d degenerate, %d scale-rejected)",
            method,
            it,
            n_degen,
            n_scale,
        )
        return OutlierResult(method, empty, False, n, 0, it, n_degen, n_scale, ms, thr, np.full(n, np.inf))

    s0, R0, t0v = best_model
    d2 = similarity_d2(np.array([s0]), R0[None], t0v[None], a, b, A, B, euclidean)[0]
    inl = d2 <= thr
    # one re-fit on all inliers and one re-classification (§5.3, step 5); keep the sample's
    # hypothesis if the re-fit is worse (it can be, since least squares is not the consensus score)
    if inl.sum() >= m + 1:
        s1, R1, t1 = _refit(a, b, A, B, (s0, R0, t0v), inl, euclidean)
        if abs(s1 - 1.0) <= params.max_scale_dev:
            d2_1 = similarity_d2(np.array([s1]), R1[None], t1[None], a, b, A, B, euclidean)[0]
            inl1 = d2_1 <= thr
            if inl1.sum() >= inl.sum():
                s0, R0, t0v, d2, inl = s1, R1, t1, d2_1, inl1
    n_in = int(inl.sum())
    accepted = n_in >= params.min_inliers
    if not accepted:
        inl = empty
    ms = (time.perf_counter() - t0) * 1e3
    logger.debug(
        "outliers[%s]: %d pairs, %d inliers, %d rejected, %d iterations (%d degenerate, %d scale-rejected), "
        "thr %.3f, s %.4f, %.2f ms%s",
        method,
        n,
        n_in if accepted else 0,
        n - (n_in if accepted else 0),
        it,
        n_degen,
        n_scale,
        thr,
        s0,
        ms,
        "" if accepted else f" (< {params.min_inliers} inliers: none accepted)",
    )
    return OutlierResult(
        method, inl, accepted, n, n_in if accepted else 0, it, n_degen, n_scale, ms, thr, d2, s0, R0, t0v
    )


# --------------------------------------------------------------------------------------------
# Fundamental-matrix RANSAC baseline (§5.4)


def fundamental_8point(x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Normalised 8-point F with rank-2 projection, batched: x1, x2 (K, n, 2), n ≥ 8 -> F (K, 3, 3).

    x2ᵀ F x1 = 0 (eq. 3.2.2). Each sample is normalised on its own points (Hartley 1997); F is
    scaled to unit Frobenius norm.
    """
    x1 = np.asarray(x1, dtype=float)
    x2 = np.asarray(x2, dtype=float)
    k, n, _ = x1.shape
    c1, c2 = x1.mean(1, keepdims=True), x2.mean(1, keepdims=True)
    s1 = math.sqrt(2.0) / np.maximum(np.mean(np.linalg.norm(x1 - c1, axis=2), axis=1), 1e-12)
    s2 = math.sqrt(2.0) / np.maximum(np.mean(np.linalg.norm(x2 - c2, axis=2), axis=1), 1e-12)
    u1 = (x1 - c1) * s1[:, None, None]
    u2 = (x2 - c2) * s2[:, None, None]
    X, Y = u1[..., 0], u1[..., 1]
    Xp, Yp = u2[..., 0], u2[..., 1]
    one = np.ones_like(X)
    M = np.stack([Xp * X, Xp * Y, Xp, Yp * X, Yp * Y, Yp, X, Y, one], axis=-1)  # (K, n, 9)
    # null vector of M: the right singular vector of the smallest singular value; for n = 8 pad
    # with a zero row so the SVD returns the full 9×9 basis
    if n < 9:
        M = np.concatenate([M, np.zeros((k, 9 - n, 9))], axis=1)
    _, _, Vt = np.linalg.svd(M)
    Fn = Vt[:, -1, :].reshape(k, 3, 3)
    U, S, Vt2 = np.linalg.svd(Fn)
    S[:, 2] = 0.0
    Fn = np.einsum("kij,kj,kjl->kil", U, S, Vt2)
    T1 = np.zeros((k, 3, 3))
    T1[:, 0, 0] = T1[:, 1, 1] = s1
    T1[:, 0, 2] = -s1 * c1[:, 0, 0]
    T1[:, 1, 2] = -s1 * c1[:, 0, 1]
    T1[:, 2, 2] = 1.0
    T2 = np.zeros((k, 3, 3))
    T2[:, 0, 0] = T2[:, 1, 1] = s2
    T2[:, 0, 2] = -s2 * c2[:, 0, 0]
    T2[:, 1, 2] = -s2 * c2[:, 0, 1]
    T2[:, 2, 2] = 1.0
    F = np.einsum("kji,kjl,klm->kim", T2, Fn, T1)  # T2ᵀ F̂ T1
    return F / np.maximum(np.linalg.norm(F, axis=(1, 2), keepdims=True), 1e-300)


def sampson_sq(F: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Sampson distance² (K, N) [px²] of pairs x1, x2 (N, 2) under K matrices F (K, 3, 3) (§5.4)."""
    h1 = np.c_[x1, np.ones(x1.shape[0])]
    h2 = np.c_[x2, np.ones(x2.shape[0])]
    Fx1 = np.einsum("kij,nj->kni", F, h1)
    Ftx2 = np.einsum("kji,nj->kni", F, h2)
    num = np.einsum("ni,kni->kn", h2, Fx1) ** 2
    den = Fx1[..., 0] ** 2 + Fx1[..., 1] ** 2 + Ftx2[..., 0] ** 2 + Ftx2[..., 1] ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(den > 0, num / np.where(den > 0, den, 1.0), np.inf)


def ransac_fundamental(
    x1: np.ndarray,
    x2: np.ndarray,
    params: OutlierParams | None = None,
    rng: np.random.Generator | None = None,
) -> OutlierResult:
    """Fundamental-matrix RANSAC on left-image positions at t−1 (``x1``) and t (``x2``), (N, 2) [px]."""
    params = params or OutlierParams(method="fundamental")
    if rng is None:
        raise InputError("ransac_fundamental: expected an injected np.random.Generator (rng), got None")
    t0 = time.perf_counter()
    x1 = np.asarray(x1, dtype=float)
    x2 = np.asarray(x2, dtype=float)
    if x1.ndim != 2 or x1.shape != x2.shape or x1.shape[1] != 2:
        raise InputError(f"ransac_fundamental: expected x1, x2 of one shape (N, 2), got {x1.shape} and {x2.shape}")
    n = x1.shape[0]
    m = 8
    thr = params.sampson_chi2 * params.sampson_sigma_px**2
    empty = np.zeros(n, bool)
    if n < max(m, params.min_inliers):
        ms = (time.perf_counter() - t0) * 1e3
        logger.debug("outliers[fundamental]: %d pairs < %d, none accepted", n, max(m, params.min_inliers))
        return OutlierResult("fundamental", empty, False, n, 0, 0, 0, 0, ms, thr, np.full(n, np.inf))
    best_cnt, best_cost = -1, math.inf
    best_F: np.ndarray | None = None
    K, it = params.f_max_iterations, 0
    while it < K:
        kb = min(params.batch, K - it)
        idx = sample_indices(rng, n, m, kb)
        it += kb
        F = fundamental_8point(x1[idx], x2[idx])
        d2 = sampson_sq(F, x1, x2)
        k, cnt, cost = _best_of_batch(d2, thr, params.score)
        if _better(cnt, cost, best_cnt, best_cost, params.score):
            best_cnt, best_cost, best_F = cnt, cost, F[k]
            K = min(K, iteration_budget(best_cnt / n, m, params.p_success, params.f_max_iterations))
    assert best_F is not None
    d2 = sampson_sq(best_F[None], x1, x2)[0]
    inl = d2 <= thr
    if inl.sum() >= m:
        F1 = fundamental_8point(x1[inl][None], x2[inl][None])[0]
        d2_1 = sampson_sq(F1[None], x1, x2)[0]
        inl1 = d2_1 <= thr
        if inl1.sum() >= inl.sum():
            best_F, d2, inl = F1, d2_1, inl1
    n_in = int(inl.sum())
    accepted = n_in >= max(params.min_inliers, m)
    if not accepted:
        inl = empty
    ms = (time.perf_counter() - t0) * 1e3
    logger.debug(
        "outliers[fundamental]: %d pairs, %d inliers, %d rejected, %d iterations, thr %.2f px², %.2f ms",
        n,
        n_in if accepted else 0,
        n - (n_in if accepted else 0),
        it,
        thr,
        ms,
    )
    return OutlierResult("fundamental", inl, accepted, n, n_in if accepted else 0, it, 0, 0, ms, thr, d2, F=best_F)


# --------------------------------------------------------------------------------------------
# Dispatcher


def detect_outliers(
    params: OutlierParams,
    rng: np.random.Generator,
    a: np.ndarray | None = None,
    b: np.ndarray | None = None,
    A: np.ndarray | None = None,
    B: np.ndarray | None = None,
    x1: np.ndarray | None = None,
    x2: np.ndarray | None = None,
) -> OutlierResult:
    """Run the detector named by ``params.method`` on whichever inputs it needs.

    Similarity variants use a, b (N, d) and A, B (N, d, d); ``fundamental`` uses x1, x2 (N, 2)
    left-image pixels at t−1 and t; ``none`` accepts every pair (N from whichever input is given).
    """
    if params.method == "fundamental":
        if x1 is None or x2 is None:
            raise InputError("detect_outliers[fundamental]: expected x1 and x2 (N, 2) pixel positions, got None")
        return ransac_fundamental(x1, x2, params, rng)
    if params.method == "none":
        ref = a if a is not None else x1
        if ref is None:
            raise InputError("detect_outliers[none]: expected a or x1 to count the pairs, got neither")
        n = int(np.asarray(ref).shape[0])
        return OutlierResult("none", np.ones(n, bool), True, n, n, 0, 0, 0, 0.0, math.inf, np.zeros(n))
    if a is None or b is None:
        raise InputError(f"detect_outliers[{params.method}]: expected a and b (N, d) landmark sets, got None")
    return ransac_similarity(a, b, A, B, params, rng)
