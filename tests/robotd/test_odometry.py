"""Odometry integration to frame times (robotd.odometry): exact on a constant twist, refuses gaps."""

from __future__ import annotations

import numpy as np
import pytest

from robotd.geometry import so3_exp, so3_log
from robotd.msgs import Odometry
from robotd.odometry import OdometryIntegrator
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
