"""Analytic Jacobians of the SLAM models against central differences (docs/math.md §6, §7)."""

from __future__ import annotations

import numpy as np
import pytest

from robotd.core.errors import EstimatorError
from robotd.core.geometry import euler_to_R, numerical_jacobian, rot2, so3_exp
from robotd.core.stereo import project, triangulation_jacobian
from robotd.slam import models as md
from tests.support.tolerances import CENTRAL_DIFF_ATOL, ROUNDOFF_ATOL, ULP_ATOL

# ω = 1e-3 rad/s off the straight-line limit, central differences at h = 1e-5: the limit form and the
# exact model differ by O(ω·dt) = 5e-4
STRAIGHT_LINE_LIMIT_ATOL = 1e-3
# ω = 2e-6 rad/s against ω = 0 over dt = 0.1 s: the heading differs by ω·dt = 2e-7
STRAIGHT_LINE_CONTINUITY_ATOL = 1e-6


def _wrap_rows(dz: int, rows: tuple[int, ...]) -> np.ndarray:
    w = np.zeros(dz, bool)
    w[list(rows)] = True
    return w


@pytest.mark.parametrize("w", [0.7, -0.3, 1e-9, 0.0])
def test_velocity2d_jacobians(w: float) -> None:
    x = np.array([1.0, -2.0, 0.4])
    u = np.array([1.3, w])
    dt = 0.5
    _, G, V = md.velocity2d(x[None], u[None], dt)
    wrap = np.array([False, False, True])
    Gn = numerical_jacobian(lambda xx: md.velocity2d(xx[None], u[None], dt)[0][0], x, wrap=wrap)
    np.testing.assert_allclose(G[0], Gn, atol=CENTRAL_DIFF_ATOL)
    if abs(w) > 1e-4:  # the straight-line branch switches inside the difference stencil near 0
        Vn = numerical_jacobian(lambda uu: md.velocity2d(x[None], uu[None], dt)[0][0], u, wrap=wrap)
        np.testing.assert_allclose(V[0], Vn, atol=CENTRAL_DIFF_ATOL)
    else:
        # compare the limit form with the exact model evaluated just off the switch
        Vn = numerical_jacobian(lambda uu: md.velocity2d(x[None], uu[None], dt)[0][0], np.array([1.3, 1e-3]), eps=1e-5)
        np.testing.assert_allclose(V[0], Vn, atol=STRAIGHT_LINE_LIMIT_ATOL)


def test_velocity2d_straight_line_continuity() -> None:
    x = np.array([[0.5, 0.2, -1.0]])
    a = md.velocity2d(x, np.array([[2.0, 0.0]]), 0.1)[0]
    b = md.velocity2d(x, np.array([[2.0, 2e-6]]), 0.1)[0]
    np.testing.assert_allclose(a, b, atol=STRAIGHT_LINE_CONTINUITY_ATOL)


def test_odometry2d_jacobians() -> None:
    x = np.array([1.0, -2.0, 2.9])
    u = np.array([0.3, -0.05, 0.2])
    _, G, V = md.odometry2d(x[None], u[None])
    wrap = np.array([False, False, True])
    np.testing.assert_allclose(
        G[0], numerical_jacobian(lambda a: md.odometry2d(a[None], u[None])[0][0], x, wrap=wrap), atol=CENTRAL_DIFF_ATOL
    )
    np.testing.assert_allclose(
        V[0], numerical_jacobian(lambda a: md.odometry2d(x[None], a[None])[0][0], u, wrap=wrap), atol=CENTRAL_DIFF_ATOL
    )


def test_motion3d_jacobians() -> None:
    x = np.array([1.0, -2.0, 0.3, 0.1, -0.2, 2.5])
    u = np.array([0.4, 0.05, -0.02, 0.03, -0.02, 0.1])
    _, G, V = md.motion3d(x[None], u[None])
    wrap = np.array([False] * 3 + [True] * 3)
    Gn = numerical_jacobian(lambda a: md.motion3d(a[None], u[None])[0][0], x, wrap=wrap)
    Vn = numerical_jacobian(lambda a: md.motion3d(x[None], a[None])[0][0], u, wrap=wrap)
    np.testing.assert_allclose(G[0], Gn, atol=CENTRAL_DIFF_ATOL)
    np.testing.assert_allclose(V[0], Vn, atol=CENTRAL_DIFF_ATOL)


def test_motion3d_rejects_pitch_singularity() -> None:
    from robotd.core.errors import EstimatorError

    x = np.array([[0.0, 0.0, 0.0, 0.0, np.pi / 2, 0.0]])
    with pytest.raises(EstimatorError, match="pitch"):
        md.motion3d(x, np.zeros((1, 6)))


@pytest.mark.parametrize("w", [0.03, 0.56])
def test_motion3d_turning_keeps_the_tilt(w: float) -> None:
    """A turn about the body's own vertical leaves the tilt of that vertical unchanged. The
    first-order η + E ω it replaced grew a tilt by √(1 + w²) per increment (15 % at the 0.56 rad a
    frame of 5 m/s round the sim yard at 5 fps: from 1° to 90° in about 33 frames of turning)."""
    x = np.array([[0.0, 0.0, 0.0, np.radians(3.0), np.radians(4.0), 0.3]])
    u = np.array([[1.0, 0.0, 0.0, 0.0, 0.0, w]])

    def tilt(pose: np.ndarray) -> float:
        return float(np.degrees(np.arccos(euler_to_R(pose[0, 3:6])[2, 2])))

    t0 = tilt(x)
    for _ in range(60):
        x = md.motion3d(x, u)[0]
    assert abs(tilt(x) - t0) < 1e-9
    np.testing.assert_allclose(
        euler_to_R(x[0, 3:6]),
        euler_to_R(np.array([np.radians(3.0), np.radians(4.0), 0.3])) @ so3_exp([0, 0, 60 * w]),
        atol=ROUNDOFF_ATOL,
    )


CASES = [
    (
        md.CARTESIAN_3D,
        np.array([1.0, -2.0, 0.3, 0.1, -0.2, 2.5]),
        np.array([4.0, 1.0, -0.5]),
        np.array([2.0, 0.5, 0.3]),
    ),
    (md.CARTESIAN_2D, np.array([1.0, -2.0, 2.9]), np.array([4.0, 1.0]), np.array([2.0, 0.5])),
    (md.RANGE_BEARING_2D, np.array([1.0, -2.0, 2.9]), np.array([4.0, 1.0]), np.array([3.0, 0.7])),
]


@pytest.mark.parametrize(("model", "x", "m", "z"), CASES, ids=[c[0].name for c in CASES])
def test_measurement_jacobians(model: md.MeasurementModel, x: np.ndarray, m: np.ndarray, z: np.ndarray) -> None:
    wrap = _wrap_rows(model.dz, model.angle_rows)
    _, Hx, Hm = model.h(x[None], m[None])
    Hxn = numerical_jacobian(lambda a: model.h(a[None], m[None])[0][0], x, wrap=wrap)
    Hmn = numerical_jacobian(lambda a: model.h(x[None], a[None])[0][0], m, wrap=wrap)
    np.testing.assert_allclose(Hx[0], Hxn, atol=CENTRAL_DIFF_ATOL)
    np.testing.assert_allclose(Hm[0], Hmn, atol=CENTRAL_DIFF_ATOL)
    # inverse model: its Jacobians, and the round trip h(x, inverse(x, z)) = z
    mi, Jx, Jz = model.inverse(x[None], z[None])
    Jxn = numerical_jacobian(lambda a: model.inverse(a[None], z[None])[0][0], x)
    Jzn = numerical_jacobian(lambda a: model.inverse(x[None], a[None])[0][0], z)
    np.testing.assert_allclose(Jx[0], Jxn, atol=CENTRAL_DIFF_ATOL)
    np.testing.assert_allclose(Jz[0], Jzn, atol=CENTRAL_DIFF_ATOL)
    np.testing.assert_allclose(model.h(x[None], mi)[0][0], z, atol=ROUNDOFF_ATOL)


def test_batch_matches_single() -> None:
    rng = np.random.default_rng(3)
    x = np.concatenate([rng.normal(size=(5, 3)), rng.uniform(-0.5, 0.5, (5, 3))], 1)
    m = rng.normal(size=(5, 3)) * 4
    zb, Hxb, Hmb = md.meas3d(x, m)
    for k in range(5):
        z1, Hx1, Hm1 = md.meas3d(x[k : k + 1], m[k : k + 1])
        np.testing.assert_allclose(zb[k], z1[0], atol=ULP_ATOL)
        np.testing.assert_allclose(Hxb[k], Hx1[0], atol=ULP_ATOL)
        np.testing.assert_allclose(Hmb[k], Hm1[0], atol=ULP_ATOL)


def test_range_bearing_innovation_wraps() -> None:
    nu = md.RANGE_BEARING_2D.innovation(np.array([1.0, 3.1]), np.array([1.0, -3.1]))
    assert abs(nu[1] - (6.2 - 2 * np.pi)) < ROUNDOFF_ATOL


def test_noise_models_grow_with_motion() -> None:
    a = (0.002, 0.05, 0.02, 0.035, 0.05, 0.001)
    M0 = md.odometry2d_noise(np.zeros(3), a)
    M1 = md.odometry2d_noise(np.array([1.0, 0.0, 0.5]), a)
    np.testing.assert_allclose(np.diag(M0), [0.002**2, 0.002**2, 0.001**2])
    np.testing.assert_allclose(np.diag(M1), [0.052**2, 0.022**2, (0.035 + 0.025 + 0.001) ** 2])
    M, g = md.velocity2d_noise(1.0, 0.5, 0.1, (0.1, 0.2, 0.3, 0.4, 0.5, 0.6))
    np.testing.assert_allclose(np.diag(M), [0.1 + 0.05, 0.3 + 0.1])
    assert g == pytest.approx((0.5 + 0.15) * 0.01)


def test_closed_form_rotations_match_geometry() -> None:
    from robotd.core.geometry import euler_to_R, euler_to_R_derivatives

    eta = np.random.default_rng(4).uniform(-3, 3, (20, 3))
    eta[:, 1] /= 2.5
    R, Rr, Rp, Ry = md._rot3_all(eta)
    # two separately written closed forms (the sin/cos products associated differently): 10 ULP_ATOL
    np.testing.assert_allclose(R, euler_to_R(eta), atol=10 * ULP_ATOL)
    for a, b in zip((Rr, Rp, Ry), euler_to_R_derivatives(eta)):
        np.testing.assert_allclose(a, b, atol=10 * ULP_ATOL)


# --------------------------------------------------------------------------------------------
# Stereo pixel model

RIG = (718.0, 607.0, 185.0, 0.54)  # f, p_x, p_y [px], baseline [m] (KITTI-like)
# Pixel values are O(10³) px and their derivatives up to f/X ≈ 360 px/m: central differences'
# round-off EPS·|f|/h grows with the magnitude, ~100× that of the O(10) functions
# CENTRAL_DIFF_ATOL is sized for (measured ≤ 1.2e-7); a wrong term is ≥ 1 px/m
PIXEL_DIFF_ATOL = 100 * CENTRAL_DIFF_ATOL


def _pixel_case(dim: int, seed: int) -> tuple[md.MeasurementModel, np.ndarray, np.ndarray, np.ndarray]:
    """A random pose (3D: roll, pitch within ±0.5 rad; yaw anywhere) and a landmark 2–30 m in front."""
    rng = np.random.default_rng(seed)
    if dim == 3:
        x = np.r_[rng.normal(0, 5, 3), rng.uniform(-0.5, 0.5, 2), rng.uniform(-np.pi, np.pi)]
        R = euler_to_R(x[3:])
    else:
        x = np.r_[rng.normal(0, 5, 2), rng.uniform(-np.pi, np.pi)]
        R = rot2(x[2])
    X = rng.uniform(2.0, 30.0)
    q = np.array([X, rng.uniform(-0.5, 0.5) * X, rng.uniform(-0.3, 0.3) * X])[:dim]
    return md.stereo_pixel_model(dim, *RIG), x, x[:dim] + R @ q, q


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("dim", [2, 3])
def test_pixel_measurement_jacobians(dim: int, seed: int) -> None:
    model, x, m, _ = _pixel_case(dim, seed)
    z, Hx, Hm = model.h(x[None], m[None])
    np.testing.assert_allclose(
        Hx[0], numerical_jacobian(lambda a: model.h(a[None], m[None])[0][0], x), atol=PIXEL_DIFF_ATOL
    )
    np.testing.assert_allclose(
        Hm[0], numerical_jacobian(lambda a: model.h(x[None], a[None])[0][0], m), atol=PIXEL_DIFF_ATOL
    )
    mi, Jx, Jz = model.inverse(x[None], z)
    Jxn = numerical_jacobian(lambda a: model.inverse(a[None], z)[0][0], x)
    Jzn = numerical_jacobian(lambda a: model.inverse(x[None], a[None])[0][0], z[0])
    np.testing.assert_allclose(Jx[0], Jxn, atol=CENTRAL_DIFF_ATOL)
    np.testing.assert_allclose(Jz[0], Jzn, atol=CENTRAL_DIFF_ATOL)
    # the inverse model inverts h: landmarks and pixels round-trip
    np.testing.assert_allclose(mi[0], m, atol=ROUNDOFF_ATOL * np.abs(m).max())
    np.testing.assert_allclose(model.h(x[None], mi)[0][0], z[0], atol=ROUNDOFF_ATOL * np.abs(z).max())


@pytest.mark.parametrize("dim", [2, 3])
def test_pixel_model_is_the_rigs_projection(dim: int) -> None:
    """h is robotd.core.stereo.project of R(η)ᵀ(m − p) (2D: its columns); the inverse's J_z is R times the
    triangulation Jacobian of robotd.core.stereo at the pixels."""
    model, x, m, q = _pixel_case(dim, 7)
    q3 = np.r_[q, 0.0][:3]
    uv = np.stack(project(q3[None], *RIG), -1)[0]
    z = model.h(x[None], m[None])[0][0]
    np.testing.assert_allclose(z, uv[:dim], atol=ROUNDOFF_ATOL * 1e3)
    _, _, Jz = model.inverse(x[None], z[None])
    Jt = triangulation_jacobian(uv[:1], uv[1:2], uv[2:3], *RIG)[0][:dim, :dim]
    R = euler_to_R(x[3:]) if dim == 3 else rot2(x[2])
    np.testing.assert_allclose(Jz[0], R @ Jt, atol=ROUNDOFF_ATOL)


@pytest.mark.parametrize("dim", [2, 3])
def test_pixel_model_stays_finite_behind_the_rig(dim: int) -> None:
    """A landmark that a (wrong) pose puts at or behind the rig gives finite pixels and Jacobians
    (the depth is clamped to PIXEL_MIN_DEPTH_M), so a bad particle cannot poison the filter."""
    model = md.stereo_pixel_model(dim, *RIG)
    x = np.zeros((3, 3 if dim == 2 else 6))
    m = np.array([[0.0, 1.0, 0.5], [-2.0, 0.3, 0.1], [1e-9, 0.0, 0.0]])[:, :dim]
    z, Hx, Hm = model.h(x, m)
    assert np.all(np.isfinite(z)) and np.all(np.isfinite(Hx)) and np.all(np.isfinite(Hm))
    with pytest.raises(EstimatorError, match="baseline_m > 0"):
        md.stereo_pixel_model(dim, 700.0, 300.0, 200.0, 0.0)
