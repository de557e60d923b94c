"""The numba FastSLAM kernel (robotd/slam/_kernels.py): world-frame formulas at large angles, motion update,
threads, CoW copies, the dimension and model dispatch."""

from __future__ import annotations

import numpy as np
import pytest

from robotd.core.errors import EstimatorError, InputError
from robotd.core.msgs import MotionIncrement
from robotd.slam import models as md
from robotd.slam._store import LandmarkStore
from robotd.slam.factory import make_estimator
from robotd.slam.fastslam import FastSlam
from robotd.slam.params import SlamParams
from tests.support.reference_fastslam import fastslam_step_reference
from tests.support.tolerances import KERNEL_TWIN_ATOL, ROUNDOFF_ATOL, ULP_ATOL

nb = pytest.importorskip("numba")
K = pytest.importorskip("robotd.slam._kernels")


def _spd(rng: np.random.Generator, shape: tuple[int, ...], n: int, scale: float, floor: float) -> np.ndarray:
    A = rng.normal(0, scale, (*shape, n, n))
    return A @ np.swapaxes(A, -1, -2) + floor * np.eye(n)


def _problem(dim: int, seed: int, P: int = 9, n_old: int = 12, n_new: int = 4):
    """Poses with yaw anywhere and (3D) large roll and pitch (±0.9 rad), so every angle derivative matters."""
    rng = np.random.default_rng(seed)
    dx = 3 if dim == 2 else 6
    pose = np.zeros((P, dx))
    pose[:, :dim] = rng.normal(0, 1.0, (P, dim))
    if dim == 3:
        pose[:, 3:5] = rng.uniform(-0.9, 0.9, (P, 2))
    pose[:, -1] = rng.uniform(-np.pi, np.pi, P)
    cap = n_old + n_new + 2
    lm_mean = rng.uniform(-6, 6, (P, cap, dim))
    lm_cov = _spd(rng, (P, cap), dim, 0.1, 0.01)
    perm = rng.permutation(cap)
    so, sn = perm[:n_old], perm[n_old : n_old + n_new]
    # measurements from particle 0's view of its landmarks plus noise (other particles see innovations)
    model = md.CARTESIAN_3D if dim == 3 else md.CARTESIAN_2D
    x0 = np.repeat(pose[:1], n_old + n_new, 0)
    z = model.h(x0, lm_mean[0, np.r_[so, sn]])[0] + rng.normal(0, 0.05, (n_old + n_new, dim))
    Q = _spd(rng, (n_old + n_new,), dim, 0.05, 0.002)
    S = _spd(rng, (P,), dx, 0.05, 1e-4)
    eps = rng.standard_normal((P, dx))
    return pose, S, lm_mean, lm_cov, so, sn, z[:n_old], Q[:n_old], z[n_old:], Q[n_old:], eps


@pytest.mark.parametrize("version", [1, 2])
@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("seed", [3, 4])
def test_world_frame_kernel_matches_reference_at_large_angles(version: int, dim: int, seed: int) -> None:
    pose, S, lm_mean, lm_cov, so, sn, zo, Qo, zn, Qn, eps = _problem(dim, seed)
    model = md.CARTESIAN_3D if dim == 3 else md.CARTESIAN_2D
    a_mean, a_cov = lm_mean.copy(), lm_cov.copy()
    b_mean, b_cov = lm_mean.copy(), lm_cov.copy()
    pa, wa = K.fastslam_step(version, pose, S, a_mean, a_cov, so, zo, Qo, sn, zn, Qn, eps, model, 1e-12)
    pb, wb = fastslam_step_reference(version, pose, S, b_mean, b_cov, so, zo, Qo, sn, zn, Qn, eps, model, 1e-12)
    for name, a, b in (("pose", pa, pb), ("dlogw", wa, wb), ("mean", a_mean, b_mean), ("cov", a_cov, b_cov)):
        np.testing.assert_allclose(a, b, atol=KERNEL_TWIN_ATOL, rtol=0, err_msg=name)
    # the weights are informative (not a degenerate constant) and the covariances stay symmetric
    assert np.ptp(wa) > 1.0
    np.testing.assert_array_equal(a_cov, np.swapaxes(a_cov, -1, -2))


@pytest.mark.parametrize("dim", [2, 3])
def test_kernel_result_independent_of_chunking(dim: int, monkeypatch: pytest.MonkeyPatch) -> None:
    # The parallel kernel splits the particles into one contiguous chunk per thread
    # (get_num_threads() chunks); the result must not depend on the split. The chunk count is
    # forced here, so the property is checked on a one-core machine too (the chunks then run one
    # after the other); with two cores the two-chunk case also runs on two threads.
    pose, S, lm_mean, lm_cov, so, sn, zo, Qo, zn, Qn, eps = _problem(dim, 5, P=23)
    model = md.CARTESIAN_3D if dim == 3 else md.CARTESIAN_2D
    out = []
    for chunks in (1, 2, 3, 7):
        monkeypatch.setattr(K.nb, "get_num_threads", lambda c=chunks: c)
        m, c = lm_mean.copy(), lm_cov.copy()
        p, w = K.fastslam_step(2, pose, S, m, c, so, zo, Qo, sn, zn, Qn, eps, model, 1e-12)
        out.append((p, w, m, c))
    for other in out[1:]:
        for a, b in zip(out[0], other):
            np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("per_particle", [False, True])
def test_predict3_matches_motion3d(per_particle: bool) -> None:
    rng = np.random.default_rng(8)
    P = 17
    pose = np.c_[rng.normal(0, 2, (P, 3)), rng.uniform(-1.2, 1.2, (P, 2)), rng.uniform(-np.pi, np.pi, P)]
    u = rng.normal(0, 0.2, (P, 6)) if per_particle else rng.normal(0, 0.2, 6)
    M = _spd(rng, (), 6, 0.01, 1e-6)
    extra = rng.uniform(1e-8, 1e-6, 6)
    x, S, bad = K.predict3_numba(pose, u, M, extra, True, md.COS_PITCH_MIN)
    xr, _, V = md.motion3d(pose, np.broadcast_to(u, (P, 6)))
    Sr = V @ M @ np.swapaxes(V, -1, -2) + np.diag(extra)
    assert bad == -1 and S is not None
    np.testing.assert_allclose(x, xr, atol=ROUNDOFF_ATOL, rtol=0)
    np.testing.assert_allclose(S, Sr, atol=ROUNDOFF_ATOL, rtol=0)
    np.testing.assert_array_equal(S, np.swapaxes(S, -1, -2))


def test_fastslam_numba_predict_rejects_pitch_singularity_and_keeps_state() -> None:
    est = make_estimator(SlamParams(filter="fastslam2", dim=3, n_particles=5), np.random.default_rng(0))
    assert isinstance(est, FastSlam)
    est.pose[:, 4] = np.pi / 2
    before = est.pose.copy()
    inc = MotionIncrement(0, 1, np.array([0.1, 0.0, 0.0]), np.zeros(3), np.eye(6) * 1e-4)
    with pytest.raises(EstimatorError, match="pitch 90.000 deg"):
        est.predict(inc)
    np.testing.assert_array_equal(est.pose, before)
    assert est.pending_S is None


def test_numba_block_copies_match_numpy_store() -> None:
    rng = np.random.default_rng(2)
    P, n, block = 8, 40, 4
    m, c = rng.normal(size=(P, n, 3)), rng.normal(size=(P, n, 3, 3))
    stores = [LandmarkStore.from_dense(m, c, block) for _ in range(2)]
    for _ in range(20):
        idx = np.sort(rng.integers(0, P, P))
        slots = rng.choice(n, size=7, replace=False)
        for st, copier in zip(stores, (None, K.copy_blocks)):
            st.select(idx)
            st.make_writable(slots, copier)
            b = st.table[:, slots // block]
            st.pool_mean[b, slots % block] += 1.0  # write through the now private blocks
        assert stores[0].n_copied_blocks == stores[1].n_copied_blocks
    for a, b in zip(stores[0].dense(n), stores[1].dense(n)):
        np.testing.assert_array_equal(a, b)


def test_angle_addition_matches_trig_on_both_branches() -> None:
    rng = np.random.default_rng(6)
    for a in rng.uniform(-np.pi, np.pi, 20):
        for delta in (0.0, 1e-9, -3e-4, 0.0499, -0.0501, 0.7, -2.5):
            c, s = K._turn(np.cos(a), np.sin(a), delta)
            assert abs(c - np.cos(a + delta)) < ULP_ATOL and abs(s - np.sin(a + delta)) < ULP_ATOL, (a, delta)


def test_pixel_kernel_refuses_a_noise_it_does_not_model() -> None:
    """The pixel kernel takes the pixel model's constant noise diag(σx², σx², σy²) (it is folded into
    closed forms); any other Q is refused in one line rather than silently misread."""
    model = md.stereo_pixel_model(3, 718.0, 607.0, 185.0, 0.54)
    pose, S, lm_mean, lm_cov, so, sn, zo, _, zn, _, eps = _problem(3, 3)
    zo = model.h(np.zeros((so.size, 6)), np.abs(lm_mean[0, so]) + np.array([3.0, 0.0, 0.0]))[0]
    Q = np.tile(np.diag([0.25, 0.25, 0.125]), (so.size, 1, 1))
    Q[2, 0, 1] = Q[2, 1, 0] = 0.01
    with pytest.raises(InputError, match=r"diag\(σx², σx², σy²\)"):
        K.fastslam_step(2, pose, S, lm_mean, lm_cov, so, zo, Q, sn[:0], zn[:0], Q[:0], eps, model, 0.0)


def test_kernel_refuses_a_model_it_has_no_formulas_for() -> None:
    pose, S, lm_mean, lm_cov, so, sn, zo, Qo, zn, Qn, eps = _problem(2, 3)
    other = md.MeasurementModel("bearing_only2d", 3, 2, 2, md.range_bearing, md.range_bearing_inverse, (1,))
    with pytest.raises(InputError, match="no formulas for the measurement model 'bearing_only2d'"):
        K.fastslam_step(2, pose, S, lm_mean, lm_cov, so, zo, Qo, sn, zn, Qn, eps, other, 0.0)
    with pytest.raises(InputError, match=r"expected poses \(P, 6\)"):
        K.fastslam_step(2, pose, S, lm_mean, lm_cov, so, zo, Qo, sn, zn, Qn, eps, md.CARTESIAN_3D, 0.0)


def test_one_algorithm_compiled_per_dimension_and_model() -> None:
    """One per-particle function, specialised by numba per (measurement model, dimension): the
    dimension and the model are types (the markers Dim2/Dim3, rig None / pixel tuple /
    RangeBearing), resolved while compiling, not branches in the loop."""
    assert not hasattr(K, "_particle2") and not hasattr(K, "_particle3")
    for model in (md.CARTESIAN_2D, md.CARTESIAN_3D, md.RANGE_BEARING_2D):
        pose, S, lm_mean, lm_cov, so, sn, zo, Qo, zn, Qn, eps = _problem(model.dm, 4)
        if model is md.RANGE_BEARING_2D:
            zo = md.range_bearing(np.repeat(pose[:1], so.size, 0), lm_mean[0, so])[0]
            zn = md.range_bearing(np.repeat(pose[:1], sn.size, 0), lm_mean[0, sn])[0]
        K.fastslam_step(2, pose, S, lm_mean, lm_cov, so, zo, Qo, sn, zn, Qn, eps, model, 1e-12)
    compiled = {(str(sig[-3]), str(sig[-2])) for sig in K._step.signatures}
    assert {("none", "Dim2()"), ("none", "Dim3()"), ("RangeBearing()", "Dim2()")} <= compiled, compiled
