"""FastSLAM pruning's whole-map view: the Jacobian-free robot-frame transform equals the measurement model."""

from __future__ import annotations

import numpy as np
import pytest

from robotd.core.msgs import Observations
from robotd.slam import models as md
from robotd.slam.factory import make_estimator
from robotd.slam.fastslam import FastSlam
from robotd.slam.params import SlamParams
from tests.support.tolerances import ROUNDOFF_ATOL


@pytest.mark.parametrize("dim", [2, 3])
def test_best_view_equals_cartesian_h_at_best_particle(dim: int) -> None:
    rng = np.random.default_rng(4)
    est = make_estimator(SlamParams(filter="fastslam2", dim=dim, n_particles=6), np.random.default_rng(0))
    assert isinstance(est, FastSlam)
    n = 40
    z = rng.uniform(-4, 4, (n, 3))
    est.update(Observations(0, z, np.tile(np.eye(3) * 1e-3, (n, 1, 1)), np.arange(n), np.ones(n, bool)))
    # particles at distinct, strongly rotated poses; the best one is not particle 0
    est.pose[:, :dim] = rng.normal(0, 2, (6, dim))
    est.pose[:, -1] = rng.uniform(-np.pi, np.pi, 6)
    if dim == 3:
        est.pose[:, 3:5] = rng.uniform(-0.8, 0.8, (6, 2))
    est.best = 4
    slots = est.book.active_slots()[::3]
    model = md.CARTESIAN_3D if dim == 3 else md.CARTESIAN_2D
    m = est.store.gather_particle(4, slots)[0]
    ref = model.h(np.repeat(est.pose[4][None], slots.size, 0), m)[0]
    np.testing.assert_allclose(est._best_view(slots), ref, atol=ROUNDOFF_ATOL, rtol=0)
    np.testing.assert_array_equal(est.store.particle_means(4, slots), m)
