"""numba kernels for the FastSLAM hot path (Cartesian measurements, 2D and 3D).

``fastslam_step_numba`` has the signature and the effects of
:func:`robotd.slam.fastslam.fastslam_step` for the Cartesian models (algorithms.md §7.1, §7.2)
and agrees with it and with :mod:`robotd.slam._reference` to 1e-9 given the same ``eps``. Each
particle is one iteration of a ``prange`` loop; inside it the §9/§10 formulas are written out
with 2×2/3×3 closed-form inverses and a hand-written Cholesky factor, so there are no per-call
numpy dispatch costs. Compiled with ``cache=True`` (first call compiles for a few seconds, later
processes load the cache; ``NUMBA_CACHE_DIR`` must be writable by the service).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from robotd.slam._store import LandmarkStore

_TWO_PI = 2.0 * math.pi
_LOG_2PI = math.log(2.0 * math.pi)
# Fast-math without the no-NaN/no-inf assumptions: fused multiply-adds and reassociation let LLVM
# vectorise the small fixed-size products (~10-15 % faster); results still agree with the
# reference to ~1e-14.
_FM = {"contract", "reassoc", "arcp", "nsz"}


@nb.njit(cache=True, fastmath=_FM)
def _wrap(a: float) -> float:
    w = a - _TWO_PI * math.floor((a + math.pi) / _TWO_PI)
    if w == -math.pi:
        w = math.pi
    return w


@nb.njit(cache=True, fastmath=_FM)
def _mm_into(A, B, C, n: int, k: int, m: int) -> None:  # type: ignore[no-untyped-def]
    """C = A @ B for (n, k) @ (k, m); sizes are passed so that they are compile-time constants."""
    for i in range(n):
        for j in range(m):
            acc = 0.0
            for t in range(k):
                acc += A[i, t] * B[t, j]
            C[i, j] = acc


@nb.njit(cache=True, fastmath=_FM)
def _mmT_into(A, B, C, n: int, k: int, m: int) -> None:  # type: ignore[no-untyped-def]
    """C = A @ B.T for (n, k) @ (m, k)^T."""
    for i in range(n):
        for j in range(m):
            acc = 0.0
            for t in range(k):
                acc += A[i, t] * B[j, t]
            C[i, j] = acc


@nb.njit(cache=True, fastmath=_FM)
def _inv_det_into(A, inv, n: int) -> float:  # type: ignore[no-untyped-def]
    """Closed-form inverse (into ``inv``) and determinant of a 2×2 or 3×3 matrix (formulas of _linalg)."""
    if n == 2:
        d = A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0]
        inv[0, 0] = A[1, 1] / d
        inv[0, 1] = -A[0, 1] / d
        inv[1, 0] = -A[1, 0] / d
        inv[1, 1] = A[0, 0] / d
        return d
    c00 = A[1, 1] * A[2, 2] - A[1, 2] * A[2, 1]
    c01 = A[1, 2] * A[2, 0] - A[1, 0] * A[2, 2]
    c02 = A[1, 0] * A[2, 1] - A[1, 1] * A[2, 0]
    c10 = A[0, 2] * A[2, 1] - A[0, 1] * A[2, 2]
    c11 = A[0, 0] * A[2, 2] - A[0, 2] * A[2, 0]
    c12 = A[0, 1] * A[2, 0] - A[0, 0] * A[2, 1]
    c20 = A[0, 1] * A[1, 2] - A[0, 2] * A[1, 1]
    c21 = A[0, 2] * A[1, 0] - A[0, 0] * A[1, 2]
    c22 = A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0]
    d = A[0, 0] * c00 + A[0, 1] * c01 + A[0, 2] * c02
    inv[0, 0] = c00 / d
    inv[0, 1] = c10 / d
    inv[0, 2] = c20 / d
    inv[1, 0] = c01 / d
    inv[1, 1] = c11 / d
    inv[1, 2] = c21 / d
    inv[2, 0] = c02 / d
    inv[2, 1] = c12 / d
    inv[2, 2] = c22 / d
    return d


@nb.njit(cache=True, fastmath=_FM)
def _rot_into(x, R, D, dm: int) -> None:  # type: ignore[no-untyped-def]
    """R(x's angles) into R; 3D: ∂R/∂(roll, pitch, yaw) into D[0..2] (algorithms.md §1.3, expanded ZYX).

    2D: R is the 2×2 R2(ψ) and D[0] its derivative.
    """
    if dm == 2:
        c, s = math.cos(x[2]), math.sin(x[2])
        R[0, 0], R[0, 1], R[1, 0], R[1, 1] = c, -s, s, c
        D[0, 0, 0], D[0, 0, 1], D[0, 1, 0], D[0, 1, 1] = -s, -c, c, -s
        return
    cr, sr = math.cos(x[3]), math.sin(x[3])
    cp, sp = math.cos(x[4]), math.sin(x[4])
    cy, sy = math.cos(x[5]), math.sin(x[5])
    R[0, 0], R[0, 1], R[0, 2] = cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr
    R[1, 0], R[1, 1], R[1, 2] = sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr
    R[2, 0], R[2, 1], R[2, 2] = -sp, cp * sr, cp * cr
    # ∂R/∂roll = Rz Ry Rx'
    D[0, 0, 0], D[0, 0, 1], D[0, 0, 2] = 0.0, cy * sp * cr + sy * sr, -cy * sp * sr + sy * cr
    D[0, 1, 0], D[0, 1, 1], D[0, 1, 2] = 0.0, sy * sp * cr - cy * sr, -sy * sp * sr - cy * cr
    D[0, 2, 0], D[0, 2, 1], D[0, 2, 2] = 0.0, cp * cr, -cp * sr
    # ∂R/∂pitch = Rz Ry' Rx
    D[1, 0, 0], D[1, 0, 1], D[1, 0, 2] = -cy * sp, cy * cp * sr, cy * cp * cr
    D[1, 1, 0], D[1, 1, 1], D[1, 1, 2] = -sy * sp, sy * cp * sr, sy * cp * cr
    D[1, 2, 0], D[1, 2, 1], D[1, 2, 2] = -cp, -sp * sr, -sp * cr
    # ∂R/∂yaw = Rz' Ry Rx
    D[2, 0, 0], D[2, 0, 1], D[2, 0, 2] = -sy * cp, -sy * sp * sr - cy * cr, -sy * sp * cr + cy * sr
    D[2, 1, 0], D[2, 1, 1], D[2, 1, 2] = cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr
    D[2, 2, 0], D[2, 2, 1], D[2, 2, 2] = 0.0, 0.0, 0.0


@nb.njit(cache=True, fastmath=_FM)
def _meas_into(x, m, want_hx: bool, R, D, d, z, Hx, Hm, dm: int) -> None:  # type: ignore[no-untyped-def]
    """Cartesian h(x, m) (§7.1 in 3D, §7.2 in 2D) into z, H_x (if wanted), H_m = R^T.

    R, D must hold R(x) and its derivatives (``_rot_into``): poses that do not change between
    observations compute them once.
    """
    for i in range(dm):
        d[i] = m[i] - x[i]
    for i in range(dm):
        acc = 0.0
        for j in range(dm):
            acc += R[j, i] * d[j]
            Hm[i, j] = R[j, i]
        z[i] = acc
    if want_hx:
        for i in range(dm):
            for j in range(dm):
                Hx[i, j] = -R[j, i]
        na = 1 if dm == 2 else 3
        for a in range(na):
            for i in range(dm):
                acc = 0.0
                for j in range(dm):
                    acc += D[a, j, i] * d[j]
                Hx[i, dm + a] = acc


@nb.njit(cache=True, fastmath=_FM)
def _logpdf(nu, Sinv, det: float, n: int) -> float:  # type: ignore[no-untyped-def]
    maha = 0.0
    for i in range(n):
        for j in range(n):
            maha += nu[i] * Sinv[i, j] * nu[j]
    return -0.5 * (maha + math.log(det) + n * _LOG_2PI)


@nb.njit(cache=True, fastmath=_FM)
def _cholesky_into(A, L, n: int) -> bool:  # type: ignore[no-untyped-def]
    """Lower Cholesky factor into L; False when A is not positive definite."""
    for i in range(n):
        for j in range(n):
            L[i, j] = 0.0
    for j in range(n):
        s = A[j, j]
        for t in range(j):
            s -= L[j, t] * L[j, t]
        if s <= 0.0:
            return False
        L[j, j] = math.sqrt(s)
        for i in range(j + 1, n):
            s = A[i, j]
            for t in range(j):
                s -= L[i, t] * L[j, t]
            L[i, j] = s / L[j, j]
    return True


@nb.njit(cache=True, fastmath=_FM)
def _particle(  # type: ignore[no-untyped-def]
    k,
    version,
    pose,
    S,
    pool_mean,
    pool_cov,
    table,
    bs,
    slots_old,
    z_old,
    Q_old,
    slots_new,
    z_new,
    Q_new,
    eps,
    floor,
    out_pose,
    dlogw,
    dx: int,
    dm: int,
) -> None:
    """The whole FastSLAM step of particle k (§9, §10). dx, dm are compile-time constants."""
    a0 = 2 if dx == 3 else 3
    n_old = slots_old.shape[0]
    # per-particle scratch, allocated once per particle (never per observation)
    R = np.empty((dm, dm))
    D = np.empty((3, dm, dm))
    d = np.empty(dm)
    z = np.empty(dm)
    nu = np.empty(dm)
    Hx = np.empty((dm, dx))
    Hm = np.empty((dm, dm))
    A = np.empty((dm, dm))
    B = np.empty((dm, dm))
    Psi = np.empty((dm, dm))
    Pinv = np.empty((dm, dm))
    K = np.empty((dm, dm))
    HxS = np.empty((dm, dx))
    RtS = np.empty((dm, dx))
    Kx = np.empty((dx, dm))
    SHt = np.empty((dx, dm))
    Lc = np.empty((dx, dx))
    Sx = np.empty((dx, dx))
    x = np.empty(dx)
    mu = np.empty(dx)
    for i in range(dx):
        x[i] = pose[k, i]
    w = 0.0
    if version == 2:
        # importance weight at the prior x̂ with the landmarks before the update (§10).
        # H_x = [-R^T | H_a] and x̂, S are fixed here, so H_x S = -R^T S[:dm] + H_a S[dm:] with R^T S[:dm]
        # computed once per particle.
        _rot_into(x, R, D, dm)
        for a in range(dm):
            for t in range(dx):
                acc = 0.0
                for c in range(dm):
                    acc += R[c, a] * S[k, c, t]
                RtS[a, t] = acc
        for j in range(n_old):
            s = slots_old[j]
            _meas_into(x, pool_mean[table[k, s // bs], s % bs], True, R, D, d, z, Hx, Hm, dm)
            for a in range(dm):
                for t in range(dx):
                    acc = -RtS[a, t]
                    for c in range(dm, dx):
                        acc += Hx[a, c] * S[k, c, t]
                    HxS[a, t] = acc
            _mmT_into(HxS, Hx, Psi, dm, dx, dm)
            _mm_into(Hm, pool_cov[table[k, s // bs], s % bs], A, dm, dm, dm)
            _mmT_into(A, Hm, B, dm, dm, dm)
            for a in range(dm):
                nu[a] = z_old[j, a] - z[a]
                for b in range(dm):
                    Psi[a, b] += B[a, b] + Q_old[j, a, b]
            det = _inv_det_into(Psi, Pinv, dm)
            w += _logpdf(nu, Pinv, det, dm)
        # proposal, one observation after another (Kalman form)
        for i in range(dx):
            mu[i] = x[i]
            for t in range(dx):
                Sx[i, t] = S[k, i, t]
        for j in range(n_old):
            s = slots_old[j]
            _rot_into(mu, R, D, dm)
            _meas_into(mu, pool_mean[table[k, s // bs], s % bs], True, R, D, d, z, Hx, Hm, dm)
            _mmT_into(Sx, Hx, SHt, dx, dx, dm)  # Σx Hx^T
            _mm_into(Hx, SHt, Psi, dm, dx, dm)
            _mm_into(Hm, pool_cov[table[k, s // bs], s % bs], A, dm, dm, dm)
            _mmT_into(A, Hm, B, dm, dm, dm)
            for a in range(dm):
                nu[a] = z_old[j, a] - z[a]
                for b in range(dm):
                    Psi[a, b] += B[a, b] + Q_old[j, a, b]
            _inv_det_into(Psi, Pinv, dm)
            _mm_into(SHt, Pinv, Kx, dx, dm, dm)
            for i in range(dx):
                acc = 0.0
                for t in range(dm):
                    acc += Kx[i, t] * nu[t]
                mu[i] += acc
            for i in range(a0, dx):
                mu[i] = _wrap(mu[i])
            # Σx ← (I - Kx Hx) Σx = Σx - Kx (Σx Hx^T)^T, symmetric: fill the upper triangle and mirror
            for i in range(dx):
                for t in range(i, dx):
                    acc = 0.0
                    for c in range(dm):
                        acc += Kx[i, c] * SHt[t, c]
                    v = Sx[i, t] - acc
                    Sx[i, t] = v
                    Sx[t, i] = v
        if not _cholesky_into(Sx, Lc, dx):
            ev, V = np.linalg.eigh(Sx)
            for i in range(dx):
                for t in range(dx):
                    Lc[i, t] = V[i, t] * math.sqrt(max(ev[t], 0.0))
        for i in range(dx):
            acc = 0.0
            for t in range(dx):
                acc += Lc[i, t] * eps[k, t]
            x[i] = mu[i] + acc
        for i in range(a0, dx):
            x[i] = _wrap(x[i])
    # landmark EKFs at the sampled pose (§9 step 2), Joseph form
    _rot_into(x, R, D, dm)
    for j in range(n_old):
        s = slots_old[j]
        C = pool_cov[table[k, s // bs], s % bs]
        _meas_into(x, pool_mean[table[k, s // bs], s % bs], False, R, D, d, z, Hx, Hm, dm)
        _mm_into(Hm, C, A, dm, dm, dm)  # A = H C
        _mmT_into(A, Hm, Psi, dm, dm, dm)
        for a in range(dm):
            nu[a] = z_old[j, a] - z[a]
            for b in range(dm):
                Psi[a, b] += Q_old[j, a, b]
        det = _inv_det_into(Psi, Pinv, dm)
        # K = C H^T Ψ^{-1} = A^T Ψ^{-1}
        for a in range(dm):
            for b in range(dm):
                acc = 0.0
                for t in range(dm):
                    acc += A[t, a] * Pinv[t, b]
                K[a, b] = acc
        for a in range(dm):
            acc = 0.0
            for b in range(dm):
                acc += K[a, b] * nu[b]
            pool_mean[table[k, s // bs], s % bs, a] += acc
        # B = I - K H; C' = B C B^T + K Q K^T, symmetrised
        _mm_into(K, Hm, B, dm, dm, dm)
        for a in range(dm):
            for b in range(dm):
                B[a, b] = (1.0 if a == b else 0.0) - B[a, b]
        _mm_into(B, C, A, dm, dm, dm)
        _mmT_into(A, B, Psi, dm, dm, dm)
        _mm_into(K, Q_old[j], A, dm, dm, dm)
        _mmT_into(A, K, B, dm, dm, dm)
        for a in range(dm):
            for b in range(a, dm):
                v = 0.5 * (Psi[a, b] + B[a, b] + Psi[b, a] + B[b, a])
                C[a, b] = v
                C[b, a] = v
        if version == 1:
            w += _logpdf(nu, Pinv, det, dm)
    # new landmarks (§9 step 3): μ = p + R z, Σ = R Q R^T (R(x) is still in R)
    if slots_new.shape[0] > 0:
        for j in range(slots_new.shape[0]):
            s = slots_new[j]
            for i in range(dm):
                acc = x[i]
                for t in range(dm):
                    acc += R[i, t] * z_new[j, t]
                pool_mean[table[k, s // bs], s % bs, i] = acc
            _mm_into(R, Q_new[j], A, dm, dm, dm)
            _mmT_into(A, R, B, dm, dm, dm)
            for i in range(dm):
                for t in range(dm):
                    pool_cov[table[k, s // bs], s % bs, i, t] = 0.5 * (B[i, t] + B[t, i]) + (floor if i == t else 0.0)
    for i in range(dx):
        out_pose[k, i] = x[i]
    dlogw[k] = w


@nb.njit(cache=True, fastmath=_FM)
def _particle3(  # type: ignore[no-untyped-def]
    k,
    version,
    pose,
    S,
    pool_mean,
    pool_cov,
    table,
    bs,
    slots_old,
    z_old,
    Q_old,
    slots_new,
    z_new,
    Q_new,
    eps,
    floor,
    out_pose,
    dlogw,
):
    _particle(
        k,
        version,
        pose,
        S,
        pool_mean,
        pool_cov,
        table,
        bs,
        slots_old,
        z_old,
        Q_old,
        slots_new,
        z_new,
        Q_new,
        eps,
        floor,
        out_pose,
        dlogw,
        6,
        3,
    )


@nb.njit(cache=True, fastmath=_FM)
def _particle2(  # type: ignore[no-untyped-def]
    k,
    version,
    pose,
    S,
    pool_mean,
    pool_cov,
    table,
    bs,
    slots_old,
    z_old,
    Q_old,
    slots_new,
    z_new,
    Q_new,
    eps,
    floor,
    out_pose,
    dlogw,
):
    _particle(
        k,
        version,
        pose,
        S,
        pool_mean,
        pool_cov,
        table,
        bs,
        slots_old,
        z_old,
        Q_old,
        slots_new,
        z_new,
        Q_new,
        eps,
        floor,
        out_pose,
        dlogw,
        3,
        2,
    )


@nb.njit(cache=True, parallel=True, fastmath=_FM)
def _step3(  # type: ignore[no-untyped-def]
    version,
    pose,
    S,
    pool_mean,
    pool_cov,
    table,
    bs,
    slots_old,
    z_old,
    Q_old,
    slots_new,
    z_new,
    Q_new,
    eps,
    floor,
    out_pose,
    dlogw,
):
    for k in nb.prange(pose.shape[0]):
        _particle3(
            k,
            version,
            pose,
            S,
            pool_mean,
            pool_cov,
            table,
            bs,
            slots_old,
            z_old,
            Q_old,
            slots_new,
            z_new,
            Q_new,
            eps,
            floor,
            out_pose,
            dlogw,
        )


@nb.njit(cache=True, parallel=True, fastmath=_FM)
def _step2(  # type: ignore[no-untyped-def]
    version,
    pose,
    S,
    pool_mean,
    pool_cov,
    table,
    bs,
    slots_old,
    z_old,
    Q_old,
    slots_new,
    z_new,
    Q_new,
    eps,
    floor,
    out_pose,
    dlogw,
):
    for k in nb.prange(pose.shape[0]):
        _particle2(
            k,
            version,
            pose,
            S,
            pool_mean,
            pool_cov,
            table,
            bs,
            slots_old,
            z_old,
            Q_old,
            slots_new,
            z_new,
            Q_new,
            eps,
            floor,
            out_pose,
            dlogw,
        )


def _run(
    version: int,
    pose: np.ndarray,
    S: np.ndarray | None,
    pool_mean: np.ndarray,
    pool_cov: np.ndarray,
    table: np.ndarray,
    bs: int,
    slots_old: np.ndarray,
    z_old: np.ndarray,
    Q_old: np.ndarray,
    slots_new: np.ndarray,
    z_new: np.ndarray,
    Q_new: np.ndarray,
    eps: np.ndarray | None,
    floor: float,
) -> tuple[np.ndarray, np.ndarray]:
    P, dx = pose.shape
    out_pose = np.empty_like(pose)
    dlogw = np.zeros(P)
    S_ = S if S is not None else np.zeros((P, dx, dx))
    eps_ = eps if eps is not None else np.zeros((P, dx))
    (_step3 if dx == 6 else _step2)(
        int(version),
        np.ascontiguousarray(pose, dtype=np.float64),
        np.ascontiguousarray(S_, dtype=np.float64),
        pool_mean,
        pool_cov,
        np.ascontiguousarray(table, dtype=np.int64),
        int(bs),
        np.ascontiguousarray(slots_old, dtype=np.int64),
        np.ascontiguousarray(z_old, dtype=np.float64),
        np.ascontiguousarray(Q_old, dtype=np.float64),
        np.ascontiguousarray(slots_new, dtype=np.int64),
        np.ascontiguousarray(z_new, dtype=np.float64),
        np.ascontiguousarray(Q_new, dtype=np.float64),
        np.ascontiguousarray(eps_, dtype=np.float64),
        float(floor),
        out_pose,
        dlogw,
    )
    return out_pose, dlogw


def fastslam_step_numba(
    version: int,
    pose: np.ndarray,
    S: np.ndarray | None,
    lm_mean: np.ndarray,
    lm_cov: np.ndarray,
    slots_old: np.ndarray,
    z_old: np.ndarray,
    Q_old: np.ndarray,
    slots_new: np.ndarray,
    z_new: np.ndarray,
    Q_new: np.ndarray,
    eps: np.ndarray | None,
    floor: float,
) -> tuple[np.ndarray, np.ndarray]:
    """numba ``fastslam_step`` on dense arrays lm_mean (P, cap, dm), lm_cov (P, cap, dm, dm), in place.

    Dense storage is block storage with one block of ``cap`` slots per particle.
    """
    P, cap = lm_mean.shape[:2]
    table = np.arange(P, dtype=np.int64)[:, None]
    return _run(
        version, pose, S, lm_mean, lm_cov, table, cap, slots_old, z_old, Q_old, slots_new, z_new, Q_new, eps, floor
    )


def fastslam_step_numba_store(
    version: int,
    pose: np.ndarray,
    S: np.ndarray | None,
    store: LandmarkStore,
    slots_old: np.ndarray,
    z_old: np.ndarray,
    Q_old: np.ndarray,
    slots_new: np.ndarray,
    z_new: np.ndarray,
    Q_new: np.ndarray,
    eps: np.ndarray | None,
    floor: float,
) -> tuple[np.ndarray, np.ndarray]:
    """The same step directly in a copy-on-write :class:`LandmarkStore` (no gather/scatter copies).

    The blocks written this step are made private first, then the kernel reads and writes the pool
    through the particles' block tables.
    """
    store.make_writable(np.concatenate([slots_old, slots_new]))
    return _run(
        version,
        pose,
        S,
        store.pool_mean,
        store.pool_cov,
        store.table,
        store.B,
        slots_old,
        z_old,
        Q_old,
        slots_new,
        z_new,
        Q_new,
        eps,
        floor,
    )


def warmup() -> None:
    """Compile (first run) or load from the cache (later runs) both kernel variants on tiny inputs."""
    for dx, dm in ((6, 3), (3, 2)):
        P, n = 2, 2
        pose = np.zeros((P, dx))
        S = np.tile(np.eye(dx) * 1e-4, (P, 1, 1))
        mean = np.ones((P, n, dm))
        cov = np.tile(np.eye(dm), (P, n, 1, 1))
        z = np.ones((1, dm))
        Q = np.eye(dm)[None]
        for version in (1, 2):
            fastslam_step_numba(
                version, pose, S, mean, cov, np.array([0]), z, Q, np.array([1]), z, Q, np.zeros((P, dx)), 0.0
            )
