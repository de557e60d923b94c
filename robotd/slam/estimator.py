"""The estimator interface of robotd: the ``Estimator`` Protocol every SLAM filter implements,
and ``Persistent``, the one a filter whose map can be saved and resumed implements besides.

The pipeline only sees these interfaces: it builds a filter with
:func:`robotd.slam.factory.make_estimator` and then calls ``predict(inc)`` once per motion
increment and ``update(obs)`` once per frame; it saves and loads the map through
:func:`persistent`. Planar filters (``dim == 2``) also offer ``predict_velocity(v, w, dt)``
(§6.1) and ``update_range_bearing(ids, r, beta, R_rb, is_new)`` (§7.2), see
:class:`PlanarEstimator`. What a filter is (a particle set or not, ...) it declares at its
registration in :mod:`robotd.slam.factory`, not here.
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import numpy as np

from robotd.core.errors import PersistenceError
from robotd.core.msgs import LandmarkMap, MotionIncrement, Observations, PoseEstimate, UpdateReport


@runtime_checkable
class Estimator(Protocol):
    """A SLAM filter with known correspondences (docs/math.md §8–§10)."""

    name: str  # its registered name (robotd.slam.factory), the value of slam.filter
    dim: int  # 2 | 3

    def predict(self, inc: MotionIncrement) -> None:
        """Propagate the pose by one motion increment (§6.2 in 2D, §6.3 in 3D)."""
        ...

    def update(self, obs: Observations) -> UpdateReport:
        """Fuse one frame of identified (``~is_new``) and new (``is_new``) landmark measurements."""
        ...

    def update_gravity(
        self, g_R: np.ndarray, g_W: np.ndarray, sigma_rad: float, reopen: bool = False
    ) -> tuple[bool, float]:
        """3D: fuse a measured direction of gravity in the robot frame (world direction ``g_W``);
        returns (fused, its normalised innovation squared); a gated measurement changes nothing.
        ``reopen``: widen roll and pitch by the innovation and fuse without the gate."""
        ...

    def estimate(self) -> PoseEstimate:
        """Current pose: EKF mean/marginal; FastSLAM weighted (circular) mean and particle covariance."""
        ...

    def landmarks(self) -> LandmarkMap:
        """Landmark map: EKF marginals, or the highest-weight particle's landmarks (2D: z = 0)."""
        ...

    def landmark_ids(self) -> np.ndarray:
        """(M,) int64 global ids of the landmarks currently in the map."""
        ...

    def set_particles(self, n: int) -> int:
        """Change the particle count (clamped to [n_particles_min, ∞)); returns the new count. Without
        particles (robotd.slam.factory.EstimatorKind): a no-op."""
        ...

    def reset_pose(self, x: np.ndarray, cov: np.ndarray | None = None) -> None:
        """Relocalisation: put the pose at ``x`` (dx,) with covariance ``cov``; the map is kept."""
        ...

    def hold_landmarks(self, below_id: int) -> None:
        """Landmarks with ids below ``below_id`` are never deleted for being missed (0: none held):
        a loaded map while the pose is not yet found in it (robotd/pipeline/relocalise.py)."""
        ...

    def spread_kept(self) -> float:
        """The share (0–1) of the pose spread the filter had after its previous update that it
        still carries after the last one (a particle filter: its particles' ancestors' spread
        under the new weights, against under the old); 0 for a filter without particles, or
        after the particles were drawn again. The previous frame's reported covariance holds that
        part already (robotd.slam.uncertainty.AnchoredCovariance.step)."""
        ...


@runtime_checkable
class Persistent(Protocol):
    """A filter whose state can be saved and resumed (``Pipeline.state_dict``, which the map file saves)."""

    def state_dict(self) -> dict[str, np.ndarray | float | int]:
        """Everything needed to resume: numpy arrays and scalars only."""
        ...

    def check_state_dict(self, state: Any) -> dict[str, Any]:
        """Check a saved state whole without touching the filter (PersistenceError naming the key;
        MapMismatchError for another filter or dimension); ``["ids"]``: its landmark ids (M,)."""
        ...

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore from ``state_dict()``; raises PersistenceError on a foreign or corrupt state."""
        ...

    def restore(self, checked: dict[str, Any]) -> None:
        """Restore from what ``check_state_dict`` returned (cannot fail)."""
        ...


def persistent(est: Estimator) -> Persistent:
    """``est`` as a :class:`Persistent`; PersistenceError when it cannot be saved or loaded."""
    if not isinstance(est, Persistent):
        raise PersistenceError(f"the {est.name!r} filter cannot be saved or loaded (it is not Persistent)")
    return est


@runtime_checkable
class PlanarEstimator(Estimator, Protocol):
    """2D filters also take velocity controls and range–bearing measurements."""

    def predict_velocity(self, v: float, w: float, dt: float, t_ns: int | None = None) -> None:
        """Velocity-model predict (§6.1): v [m/s], w [rad/s] (positive turns X towards Y), dt [s]."""
        ...

    def update_range_bearing(
        self,
        ids: np.ndarray,
        r: np.ndarray,
        beta: np.ndarray,
        R_rb: np.ndarray,
        is_new: np.ndarray | None = None,
        t_ns: int | None = None,
    ) -> UpdateReport:
        """Range–bearing update (§7.2): ids (N,), r (N,) [m], beta (N,) [rad], R_rb (N, 2, 2) or (2, 2)."""
        ...
