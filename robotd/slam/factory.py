"""Build a SLAM filter from its parameters: ``make_estimator`` (EKF / FastSLAM 1.0 / 2.0, 2D / 3D),
and ``warmup`` of the numba kernels the filters use."""

from __future__ import annotations

import numpy as np

from robotd.choices import MEASUREMENTS
from robotd.slam.ekf import EkfSlam
from robotd.slam.estimator import Estimator
from robotd.slam.fastslam import FastSlam
from robotd.slam.params import SlamParams, VisibleFn, fov_visibility


def make_estimator(
    params: SlamParams | None = None,
    rng: np.random.Generator | None = None,
    visible: VisibleFn | None = None,
) -> Estimator:
    """Build the filter ``params.filter`` in ``params.dim`` dimensions.

    Args:
        params: tuning; ``SlamParams()`` when None.
        rng: the injected generator (FastSLAM draws from it); a fixed seed 0 when None.
        visible: field-of-view test for landmark pruning, (M, dim) robot-frame points -> (M,)
            bool; defaults to :func:`fov_visibility` built from the params.
    """
    params = params or SlamParams()
    rng = rng if rng is not None else np.random.default_rng(0)
    if visible is None:
        visible = fov_visibility(params)
    if params.filter == "ekf":
        return EkfSlam(params, visible)
    return FastSlam(params, rng, visible, version=2 if params.filter == "fastslam2" else 1)


def warmup(models: tuple[str, ...] = MEASUREMENTS) -> float | None:
    """Compile or load the numba FastSLAM kernels now, for the measurement ``models`` (each one
    compiles on its own); returns the seconds it took, None without numba.

    Call it at daemon start-up (after NUMBA_CACHE_DIR is set) so that the first frame is not
    delayed: compiling takes ~11–16 s on a 2-core machine, loading the cache ~1–2 s.
    """
    import time

    try:
        from robotd.slam._kernels import warmup
    except ImportError:
        return None
    t0 = time.perf_counter()
    warmup(tuple(models))
    return time.perf_counter() - t0
