"""Odometry integration to frame times (robotd.pipeline.odometry): exact on a constant twist, refuses gaps."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from robotd.core.errors import InputError
from robotd.core.geometry import so3_exp, so3_log
from robotd.core.msgs import Odometry
from robotd.pipeline.odometry import OdometryGate, OdometryIntegrator
from tests.support.tolerances import CONDITIONED_ATOL

# the translation is integrated over 100 segments of 10 ms, each with the rotation at its midpoint
# (second order; measured 9.7e-7 m against the closed form)
MIDPOINT_INTEGRATION_ATOL = 1e-4


def _feed(integ: OdometryIntegrator, v: np.ndarray, w: np.ndarray, t0: int, t1: int, hz: int = 100) -> None:
    for t in range(t0, t1 + 1, int(1e9 / hz)):
        integ.add(Odometry(t, v, w))


def test_integration_of_constant_twist_is_exact() -> None:
    integ = OdometryIntegrator()
    v, w = np.array([1.0, 0.1, 0.0]), np.array([0.0, 0.0, 0.5])
    _feed(integ, v, w, 0, 2_000_000_000)
    inc = integ.integrate(200_000_000, 1_200_000_000)
    assert inc is not None
    # exact SE(3) exponential of the constant twist over 1 s, from the closed form of a planar arc
    th = 0.5
    R = so3_exp(np.array([0, 0, th]))
    V = np.array([[np.sin(th) / th, -(1 - np.cos(th)) / th, 0], [(1 - np.cos(th)) / th, np.sin(th) / th, 0], [0, 0, 1]])
    assert np.allclose(inc.dp_R_m, V @ v, atol=MIDPOINT_INTEGRATION_ATOL)
    assert np.allclose(inc.drot_R_rad, so3_log(R), atol=CONDITIONED_ATOL)
    assert inc.dt_s == pytest.approx(1.0)


def test_integration_refuses_gaps_and_uncovered_intervals() -> None:
    integ = OdometryIntegrator(max_gap_s=0.2)
    assert integ.integrate(0, 10) is None  # nothing yet
    _feed(integ, np.ones(3), np.zeros(3), 0, 1_000_000_000)
    _feed(integ, np.ones(3), np.zeros(3), 2_000_000_000, 3_000_000_000)  # 1 s hole
    assert integ.integrate(100_000_000, 900_000_000) is not None
    assert integ.integrate(800_000_000, 2_200_000_000) is None  # spans the hole
    assert integ.integrate(2_900_000_000, 4_000_000_000) is None  # runs past the data
    assert integ.gaps == 2
    integ.add(Odometry(5, np.zeros(3), np.zeros(3)))  # late sample: dropped, counted
    assert integ.out_of_order == 1


# ---------------------------------------------------------------------------------------------
# plausibility gates: what no vehicle can do is refused, counted, and never integrated


def _stream(n: int = 200, hz: int = 50, v: float = 1.0, w: float = 0.2) -> list[Odometry]:
    return [Odometry(k * int(1e9 / hz), np.array([v, 0.0, 0.0]), np.array([0.0, 0.0, w])) for k in range(n)]


def _increment(samples: list[Odometry], gate: OdometryGate | None = None):
    integ = OdometryIntegrator()
    for s in samples:
        if gate is None or gate.accept(s):
            integ.add(s)
    return integ.integrate(0, samples[-1].t_ns)


def test_the_simulated_rovers_own_odometry_passes_the_gates() -> None:
    import drivers

    with drivers.open_vehicle("sim://?realtime=0") as veh:
        it = veh.odometry(timeout_s=0.1)
        samples = [next(it) for _ in range(3000)]  # 60 s of its noisy 50 Hz odometry
    gate = OdometryGate()
    assert all(gate.accept(s) for s in samples) and gate.stats()["accepted"] == 3000


@pytest.mark.parametrize(
    ("bad", "reason"),
    [
        (Odometry(2_010_000_000, np.array([2.1e6, 0.0, 0.0]), np.zeros(3)), "speed"),  # ticks 0 -> 2^31-1 in 10 ms
        (Odometry(2_010_000_000, np.array([3e38, -3e38, 0.0]), np.zeros(3)), "speed"),  # a corrupt float field
        (Odometry(2_010_000_000, np.array([4.0, 0.0, 0.0]), np.array([0.0, 0.0, 0.2])), "acceleration"),  # +3 m/s
        (Odometry(2_010_000_000, np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 40.0])), "rate"),
        (Odometry(1_000_000_000, np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 0.2])), "clock"),  # backwards
    ],
    ids=["tick-jump", "float-garbage", "acceleration", "rate", "clock-backwards"],
)
def test_an_implausible_sample_is_refused_counted_and_never_integrated(bad: Odometry, reason: str) -> None:
    clean = _stream()
    gate = OdometryGate()
    dirty = [*clean[:101], bad, *clean[101:]]  # inserted after t = 2.0 s
    inc = _increment(dirty, gate)
    ref = _increment(clean)
    assert gate.rejected[reason] == 1 and sum(gate.rejected.values()) == 1
    assert inc is not None and ref is not None
    np.testing.assert_allclose(inc.dp_R_m, ref.dp_R_m, atol=CONDITIONED_ATOL)
    np.testing.assert_allclose(inc.drot_R_rad, ref.drot_R_rad, atol=CONDITIONED_ATOL)


def test_a_sample_from_the_future_is_refused_live_but_not_in_a_replay() -> None:
    late = Odometry(10_000_000_000, np.array([1.0, 0.0, 0.0]), np.zeros(3))
    assert OdometryGate().check(late, now_ns=5_000_000_000) == "clock"  # 5 s ahead of the host clock
    assert OdometryGate().check(late, now_ns=None) is None


def test_acceleration_is_judged_over_a_floor_interval() -> None:
    # two samples 1 ms apart differ by their noise, not a physical acceleration
    gate = OdometryGate()
    assert gate.accept(Odometry(0, np.array([1.0, 0.0, 0.0]), np.zeros(3)))
    assert gate.accept(Odometry(1_000_000, np.array([1.3, 0.0, 0.0]), np.zeros(3)))  # 0.3 m/s / 20 ms = 15 m/s²


def test_the_limits_come_from_the_config() -> None:
    from robotd.config import load_config
    from robotd.config.params import odometry_limits_from_config

    lim = odometry_limits_from_config(load_config(None, {"vehicle": {"max_speed_mps": 3.0}}))
    assert lim.max_speed_mps == 3.0
    gate = OdometryGate(lim)
    assert gate.check(Odometry(0, np.array([3.5, 0.0, 0.0]), np.zeros(3))) == "speed"


# --------------------------------------------------------------------------------------------
# samples that state their noise (Odometry.cov) give the increment its covariance


def _noisy_increment(rng: np.random.Generator | None, S: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Four 10 Hz samples of a car turning and pitching, integrated over [0, 0.3] s, each sample
    perturbed by N(0, S) when ``rng`` is given: (dp, R, stated cov)."""
    integ = OdometryIntegrator()
    v, w = np.array([10.0, 0.5, -0.2]), np.array([0.3, -0.2, 0.6])
    for t in (-30_000_000, 70_000_000, 170_000_000, 270_000_000):
        e = rng.multivariate_normal(np.zeros(6), S) if rng is not None else np.zeros(6)
        integ.add(Odometry(t, v + e[:3], w + e[3:], cov=S))
    inc = integ.integrate(0, 300_000_000)
    assert inc is not None
    return inc.dp_R_m, so3_exp(inc.drot_R_rad), inc.cov


def test_stated_sample_noise_becomes_the_increments_covariance() -> None:
    """Monte Carlo: the spread of (dp, φ) over noisy runs, φ = log(R̃ Rᵀ) the rotation error in the
    frame at t0, matches the first-order covariance the integrator states."""
    S = np.diag([0.06**2] * 3 + [0.05**2] * 3)
    dp0, R0, P = _noisy_increment(None, S)
    rng = np.random.default_rng(11)
    K = 3000
    E = np.empty((K, 6))
    for k in range(K):
        dp, R, _ = _noisy_increment(rng, S)
        E[k] = np.r_[dp - dp0, so3_log(R @ R0.T)]
    # the rotation error moves the translation: a sizeable cross term, which the check must see
    assert np.abs(P[:3, 3:]).max() > 0.3 * np.sqrt(P[0, 0] * P[3, 3])
    L = np.linalg.cholesky(P)
    W = np.linalg.solve(L, E.T).T  # whitened by the stated covariance: identity covariance expected
    C = W.T @ W / K
    # sampling error of a unit variance/covariance over K runs: sqrt(2/K) = 0.026; 5 sigma
    assert np.abs(C - np.eye(6)).max() < 5 * np.sqrt(2 / K), np.round(C, 3)


def test_samples_without_stated_noise_leave_the_covariance_to_the_model() -> None:
    integ = OdometryIntegrator()
    S = np.eye(6) * 1e-4
    integ.add(Odometry(0, np.ones(3), np.zeros(3), cov=S))
    integ.add(Odometry(50_000_000, np.ones(3), np.zeros(3)))  # this one states nothing
    inc = integ.integrate(10_000_000, 90_000_000)
    assert inc is not None and not np.any(inc.cov)
    inc = integ.integrate(0, 40_000_000)  # only the stated sample holds here
    # σ_v² Δt² (the rate noise adds 0.08 % through the rotation of v during the segment)
    assert inc is not None and inc.cov[0, 0] == pytest.approx(1e-4 * 0.04**2, rel=1e-2)


def test_odometry_cov_is_validated_at_the_border() -> None:
    from robotd.core.errors import InputError

    with pytest.raises(InputError, match=r"Odometry\.cov: expected shape \(6, 6\)"):
        Odometry(0, np.zeros(3), np.zeros(3), cov=np.eye(3))
    bad = np.eye(6)
    bad[0, 1] = 1.0
    with pytest.raises(InputError, match="Odometry.cov: expected a symmetric matrix"):
        Odometry(0, np.zeros(3), np.zeros(3), cov=bad)


def test_dead_reckoning_of_a_constant_turn_follows_the_arc() -> None:
    from robotd.core.errors import InputError
    from robotd.pipeline.odometry import dead_reckon

    v, w = np.array([2.0, 0.0, 0.0]), np.array([0.0, 0.0, 0.4])  # yaw rate > 0 turns right in FRD
    samples = [Odometry(int(t), v, w) for t in np.arange(0, 5_000_000_001, 10_000_000)]
    t = np.arange(0, 5_000_000_001, 250_000_000)
    T = dead_reckon(samples, t)
    th = 0.4 * t / 1e9
    r = 2.0 / 0.4
    np.testing.assert_allclose(T[:, 0, 3], r * np.sin(th), atol=MIDPOINT_INTEGRATION_ATOL)
    np.testing.assert_allclose(T[:, 1, 3], r * (1 - np.cos(th)), atol=MIDPOINT_INTEGRATION_ATOL)
    np.testing.assert_allclose(np.arctan2(T[:, 1, 0], T[:, 0, 0]), np.angle(np.exp(1j * th)), atol=CONDITIONED_ATOL)
    with pytest.raises(InputError, match="no odometry covers"):
        dead_reckon(samples, [0, 6_000_000_000])


def test_values_near_float32s_limit_are_refused_without_an_overflow_warning() -> None:
    # a link's float32 fields may carry 3e38: its square overflows float32, and the gate (and the
    # gravity check) must refuse it quietly rather than print a RuntimeWarning per sample
    big = np.array([3.0e38, 3.0e38, 0.0], dtype=np.float32)
    gate = OdometryGate()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert not gate.accept(Odometry(10**9, big, np.zeros(3)))
        assert not gate.accept(Odometry(2 * 10**9, np.zeros(3), big))
        with pytest.raises(InputError, match="gravity_R: expected a direction"):
            Odometry(3 * 10**9, np.zeros(3), np.zeros(3), gravity_R=big)
    assert gate.rejected["speed"] == 1 and gate.rejected["rate"] == 1
