"""Rectified stereo: triangulation (thesis eq. 3.2.14) and its first-order covariance.

Points are returned in the robot frame (algorithms.md §1.2, §2.2): origin at the baseline centre,
X forward (depth), Y right along the baseline, Z down. All functions are vectorised over N points.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, slots=True)
class RectifiedStereo:
    """A rectified rig is described by f, p_x, p_y, b and the image size (algorithms.md §2.1).

    This is what the front end needs; how it was obtained (calibration, OAK factory data,
    dataset files) is the business of the calibration code.
    """

    f_px: float
    px: float
    py: float
    baseline_m: float
    width: int
    height: int

    @property
    def fb(self) -> float:
        """f·b [px·m]: depth X = fb / d."""
        return self.f_px * self.baseline_m

    def disparity_bounds(self, depth_min_m: float = 0.3, d_min_px: float = 5.0) -> tuple[float, float]:
        """(d_min, d_max) from the configured near limit and disparity floor (algorithms.md §2.2)."""
        return d_min_px, self.fb / depth_min_m


def triangulate(xl: np.ndarray, xr: np.ndarray, y: np.ndarray, f: float, px: float, py: float, b: float) -> np.ndarray:
    """Rectified correspondences -> (N, 3) points in the robot frame (eq. 3.2.14).

    ``xl``, ``xr``: (N,) columns in the left/right rectified image; ``y``: (N,) common row
    (use the mean of both rows); ``f``, ``px``, ``py`` [px]; ``b`` baseline [m]. Disparity
    ``d = xl - xr`` must be positive (callers enforce the disparity bounds).
    """
    xl = np.asarray(xl, dtype=float)
    xr = np.asarray(xr, dtype=float)
    y = np.asarray(y, dtype=float)
    d = xl - xr
    X = f * b / d
    Y = (xl - px) * b / d - b / 2.0
    Z = (y - py) * b / d
    return np.stack([X, Y, Z], -1)


def triangulation_jacobian(
    xl: np.ndarray, xr: np.ndarray, y: np.ndarray, f: float, px: float, py: float, b: float
) -> np.ndarray:
    """∂(X, Y, Z)/∂(x_L, x_R, y), (N, 3, 3) (algorithms.md §3.1)."""
    xl = np.asarray(xl, dtype=float)
    xr = np.asarray(xr, dtype=float)
    y = np.asarray(y, dtype=float)
    d = xl - xr
    k = b / d**2
    z = np.zeros_like(d)
    J = np.stack(
        [
            np.stack([-f * np.ones_like(d), f * np.ones_like(d), z], -1),
            np.stack([px - xr, xl - px, z], -1),
            np.stack([py - y, y - py, d], -1),
        ],
        -2,
    )
    return J * k[:, None, None]


def triangulation_covariance(
    xl: np.ndarray,
    xr: np.ndarray,
    y: np.ndarray,
    f: float,
    px: float,
    py: float,
    b: float,
    sigma_x_px: float = 0.5,
    sigma_y_px: float = 0.5 / np.sqrt(2.0),
    inflation: float = 1.0,
) -> np.ndarray:
    """First-order covariance Q = J Σ_px J^T of each triangulated point, (N, 3, 3) [m²].

    Σ_px = diag(σx², σx², σy²) for (x_L, x_R, y) (algorithms.md §3.1); ``inflation`` multiplies Q
    (§3.3, default 1).
    """
    J = triangulation_jacobian(xl, xr, y, f, px, py, b)
    s = np.array([sigma_x_px**2, sigma_x_px**2, sigma_y_px**2])
    Q = np.einsum("nij,j,nkj->nik", J, s, J)
    return inflation * 0.5 * (Q + np.swapaxes(Q, -1, -2))


def covariance_from_points(
    xyz_R: np.ndarray, f: float, b: float, sigma_x_px: float = 0.5, sigma_y_px: float = 0.5 / np.sqrt(2.0)
) -> np.ndarray:
    """Closed form of the same covariance from the triangulated points (algorithms.md §3.2).

    Q = X²/(f²b²) (2σx² z zᵀ + diag(0, σx² b²/2, σy² b²)), (N, 3, 3). Used by simulators that
    produce points directly; agrees with :func:`triangulation_covariance`.
    """
    z = np.asarray(xyz_R, dtype=float)
    X = z[:, 0]
    k = (X**2 / (f * f * b * b))[:, None, None]
    Q = 2.0 * sigma_x_px**2 * np.einsum("ni,nj->nij", z, z)
    Q[:, 1, 1] += 0.5 * sigma_x_px**2 * b * b
    Q[:, 2, 2] += sigma_y_px**2 * b * b
    return k * Q


def project(xyz_R: np.ndarray, f: float, px: float, py: float, b: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Inverse of :func:`triangulate`: robot-frame points (N, 3) -> (xl, xr, y) pixel coordinates."""
    z = np.asarray(xyz_R, dtype=float)
    X, Y, Z = z[:, 0], z[:, 1], z[:, 2]
    xl = px + f * (Y + b / 2.0) / X
    xr = px + f * (Y - b / 2.0) / X
    y = py + f * Z / X
    return xl, xr, y
