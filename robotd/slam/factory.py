"""The estimators robotd can run, each registered once with what it declares about itself, and
``make_estimator`` that builds the one ``slam.filter`` names; ``warmup`` of the numba kernels the
filters use.

A registration (:func:`register`) is the only place a filter's name means anything: the
configuration offers the registered names (``slam.filter``), and every decision that depends on
the filter reads its declared :class:`EstimatorKind` (:func:`estimator_kind`) instead of
comparing names:

- ``particles`` (a :class:`ParticleCost`, or None): the filter holds a particle set, so
  ``slam.n_particles`` sizes it and is bounded by its cost (robotd.config.bounds), and the latency
  budget may trade particles for time (the daemon calls ``set_particles``);
- ``anchored_covariance``: the filter's own pose covariance is only the last fix, so the reported
  covariance anchors new landmarks at it (robotd.slam.uncertainty.ReportedCovariance).

This module imports nothing heavy at load (the configuration imports it to validate
``slam.filter`` and size the bounds); the filters are imported when one is built.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING

from robotd.core.choices import MEASUREMENTS
from robotd.core.errors import ConfigError

if TYPE_CHECKING:
    import numpy as np

    from robotd.slam.estimator import Estimator
    from robotd.slam.params import SlamParams, VisibleFn


@dataclass(frozen=True)
class ParticleCost:
    """What one particle costs, for the bounds on ``slam.n_particles`` (robotd.config.bounds)."""

    # µs of one step per particle and observation, on one core of the reference machine
    step_us_per_obs: float
    # one particle's copy of one landmark (mean and covariance), by dimension (2, 3)
    landmark_bytes: Mapping[int, int]


@dataclass(frozen=True)
class EstimatorKind:
    """What an estimator declares about itself at its registration (see the module docstring)."""

    particles: ParticleCost | None  # None: no particle set (set_particles is a no-op)
    anchored_covariance: bool  # the reported covariance anchors landmarks at the pose covariance


# (params, the injected generator, the field-of-view test) -> the filter
Builder = Callable[["SlamParams", "np.random.Generator", "VisibleFn"], "Estimator"]


@dataclass(frozen=True)
class Registration:
    name: str  # the value of slam.filter that selects it
    kind: EstimatorKind
    build: Builder


# name -> registration, in registration order (the configuration's choices read it live)
ESTIMATORS: dict[str, Registration] = {}


def register(name: str, kind: EstimatorKind, build: Builder) -> Registration:
    """Make ``name`` a value of ``slam.filter`` that builds ``build(params, rng, visible)``."""
    if name in ESTIMATORS:
        raise ValueError(f"estimator {name!r} is registered already")
    ESTIMATORS[name] = reg = Registration(name, kind, build)
    return reg


def unregister(name: str) -> None:
    """Remove a registration (tests that register a fake estimator)."""
    del ESTIMATORS[name]


def registration(name: str) -> Registration:
    """The registration of ``name``; ConfigError naming ``slam.filter`` when there is none."""
    try:
        return ESTIMATORS[name]
    except (KeyError, TypeError):
        raise ConfigError(
            f"slam.filter: {name!r} is not a registered estimator (registered in robotd.slam.factory: "
            f"{' | '.join(ESTIMATORS)})"
        ) from None


def estimator_kind(name: str) -> EstimatorKind:
    """What the estimator registered as ``name`` declared (ConfigError when none is)."""
    return registration(name).kind


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
    import numpy as np

    from robotd.slam.params import SlamParams, fov_visibility

    params = params or SlamParams()
    reg = registration(params.filter)
    rng = rng if rng is not None else np.random.default_rng(0)
    if visible is None:
        visible = fov_visibility(params)
    return reg.build(params, rng, visible)


def _ekf(params: SlamParams, rng: np.random.Generator, visible: VisibleFn) -> Estimator:
    from robotd.slam.ekf import EkfSlam

    return EkfSlam(params, visible)


def _fastslam(version: int) -> Builder:
    def build(params: SlamParams, rng: np.random.Generator, visible: VisibleFn) -> Estimator:
        from robotd.slam.fastslam import FastSlam

        return FastSlam(params, rng, visible, version=version)

    return build


# FastSLAM's copy-on-write store holds, per particle and landmark, the mean and covariance in
# float64: 2-D 2 + 4 = 6 values (48 B), 3-D 3 + 9 = 12 (96 B); bench/fastslam.py measured it.
# Step cost: docs/benchmarks.md, 1000 particles × 100 observations took 27.1 ms (2.0) and
# 15.6 ms (1.0) on one core.
_FASTSLAM_LANDMARK_BYTES = {2: 6 * 8, 3: 12 * 8}
register("ekf", EstimatorKind(particles=None, anchored_covariance=False), _ekf)
register(
    "fastslam1",
    EstimatorKind(ParticleCost(0.156, _FASTSLAM_LANDMARK_BYTES), anchored_covariance=True),
    _fastslam(1),
)
register(
    "fastslam2",
    EstimatorKind(ParticleCost(0.271, _FASTSLAM_LANDMARK_BYTES), anchored_covariance=True),
    _fastslam(2),
)


def warmup(models: tuple[str, ...] = MEASUREMENTS, dims: tuple[int, ...] = (2, 3)) -> float | None:
    """Compile or load the numba FastSLAM kernels now, for the measurement ``models`` and the
    dimensions ``dims`` (each pair compiles on its own); returns the seconds it took, None without
    numba.

    Call it at daemon start-up (after NUMBA_CACHE_DIR is set) so that the first frame is not
    delayed: compiling takes ~11–16 s on a 2-core machine, loading the cache ~1–2 s.
    """
    import time

    try:
        from robotd.slam._kernels import warmup
    except ImportError:
        return None
    t0 = time.perf_counter()
    warmup(tuple(models), tuple(dims))
    return time.perf_counter() - t0
