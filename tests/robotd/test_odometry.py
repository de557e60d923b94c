"""Odometry integration to frame times (robotd.odometry): exact on a constant twist, refuses gaps."""

from __future__ import annotations

import numpy as np
import pytest

from robotd.geometry import so3_exp, so3_log
from robotd.msgs import Odometry
from robotd.odometry import OdometryGate, OdometryIntegrator
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
    from robotd.config_params import odometry_limits_from_config

    lim = odometry_limits_from_config(load_config(None, {"vehicle": {"max_speed_mps": 3.0}}))
    assert lim.max_speed_mps == 3.0
    gate = OdometryGate(lim)
    assert gate.check(Odometry(0, np.array([3.5, 0.0, 0.0]), np.zeros(3))) == "speed"
