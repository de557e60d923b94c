"""What every vehicle link must hand on, however hostile its input: finite odometry that the
plausibility gate either refuses (counted) or accepts within its limits."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from robotd.core.msgs import Odometry
from robotd.pipeline.odometry import OdometryGate


def assert_finite_and_gated(samples: Sequence[Odometry]) -> None:
    for s in samples:  # Odometry refuses non-finite values at construction
        assert np.all(np.isfinite(s.vel_R_mps)) and np.all(np.isfinite(s.rate_R_radps))
    gate = OdometryGate()
    accepted = [s for s in samples if gate.accept(s)]
    assert gate.accepted + sum(gate.rejected.values()) == len(samples)
    for s in accepted:
        assert np.linalg.norm(s.vel_R_mps) <= gate.limits.max_speed_mps
        assert np.linalg.norm(s.rate_R_radps) <= gate.limits.max_rate_radps
