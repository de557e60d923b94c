"""Geometry: round trips on seeded random poses, batch vs one-at-a-time, Jacobians vs central differences."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from robotd.core import geometry as g
from tests.support.tolerances import (
    ANGLE_FROM_COSINE_FLOOR_RAD,
    CENTRAL_DIFF_ATOL,
    CONDITIONED_ATOL,
    ROUNDOFF_ATOL,
    ULP_ATOL,
)

# 10000 explicit Euler steps of the Euler-angle rate: a first-order error O(|w|²/n) ≈ 5e-6
EULER_INTEGRATION_ATOL = 1e-4

angles = st.floats(-np.pi, np.pi, allow_nan=False)
small = st.floats(-1.4, 1.4, allow_nan=False)  # pitch away from ±90°
coords = st.floats(-100, 100, allow_nan=False)


@settings(max_examples=200, deadline=None)
@given(roll=angles, pitch=small, yaw=angles)
def test_euler_round_trip(roll: float, pitch: float, yaw: float) -> None:
    rpy = np.array([roll, pitch, yaw])
    R = g.euler_to_R(rpy)
    assert np.allclose(R @ R.T, np.eye(3), atol=ROUNDOFF_ATOL)
    assert np.linalg.det(R) == pytest.approx(1.0)
    back = g.R_to_euler(R)
    assert np.allclose(g.wrap_angle(back - rpy), 0.0, atol=CONDITIONED_ATOL)


@settings(max_examples=200, deadline=None)
@given(roll=angles, pitch=angles, yaw=angles)
def test_quaternion_round_trip(roll: float, pitch: float, yaw: float) -> None:
    R = g.euler_to_R(np.array([roll, pitch, yaw]))
    q = g.R_to_quat(R)
    assert np.linalg.norm(q) == pytest.approx(1.0) and q[0] >= 0
    assert np.allclose(g.quat_to_R(q), R, atol=ROUNDOFF_ATOL)


def test_quaternion_conventions() -> None:
    assert np.allclose(g.R_to_quat(np.eye(3)), [1, 0, 0, 0])
    # 90° yaw (a right turn in FRD) is a rotation about +z
    q = g.euler_to_quat(np.array([0.0, 0.0, np.pi / 2]))
    assert np.allclose(q, [np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)])
    # 180° rotations (w = 0) survive the round trip
    for axis in np.eye(3):
        R = g.so3_exp(axis * np.pi)
        assert np.allclose(g.quat_to_R(g.R_to_quat(R)), R, atol=ROUNDOFF_ATOL)


def test_quat_multiply_matches_matrix_product(rng: np.random.Generator) -> None:
    a, b = rng.normal(size=(2, 50, 4))
    a /= np.linalg.norm(a, axis=-1, keepdims=True)
    b /= np.linalg.norm(b, axis=-1, keepdims=True)
    assert np.allclose(g.quat_to_R(g.quat_multiply(a, b)), g.quat_to_R(a) @ g.quat_to_R(b), atol=ROUNDOFF_ATOL)


def test_so3_exp_log_round_trip(rng: np.random.Generator) -> None:
    w = rng.normal(size=(200, 3))
    w *= (rng.uniform(0, np.pi - 1e-3, 200) / np.linalg.norm(w, axis=1))[:, None]
    assert np.allclose(g.so3_log(g.so3_exp(w)), w, atol=CONDITIONED_ATOL)
    assert np.allclose(g.rotation_angle(g.so3_exp(w)), np.linalg.norm(w, axis=1), atol=CONDITIONED_ATOL)
    # near π and tiny angles
    # near π the log's arccos cannot resolve the last ~1e-8 rad (cos(π − 1e-9) rounds to −1, so the
    # angle comes back as π: 1e-9 off, which passed a 1e-9 atol only through allclose's rtol term)
    for v, tol in (
        (np.array([np.pi - 1e-9, 0, 0]), ANGLE_FROM_COSINE_FLOOR_RAD),
        (np.array([1e-12, 0, 0]), CONDITIONED_ATOL),
        (np.zeros(3), CONDITIONED_ATOL),
    ):
        assert np.allclose(g.so3_exp(g.so3_log(g.so3_exp(v))), g.so3_exp(v), atol=tol)


def random_pose6(rng: np.random.Generator, n: int) -> np.ndarray:
    return np.c_[
        rng.uniform(-10, 10, (n, 3)),
        rng.uniform(-np.pi, np.pi, n),
        rng.uniform(-1.4, 1.4, n),
        rng.uniform(-np.pi, np.pi, n),
    ]


def test_se3_inverse_and_compose_round_trip(rng: np.random.Generator) -> None:
    T = g.pose6_to_T(random_pose6(rng, 100))
    assert np.allclose(g.se3_compose(T, g.se3_inverse(T)), np.eye(4), atol=ROUNDOFF_ATOL)
    assert np.allclose(g.se3_inverse(T), np.linalg.inv(T), atol=ROUNDOFF_ATOL)
    x = random_pose6(rng, 100)
    assert np.allclose(g.pose6_to_T(g.T_to_pose6(g.pose6_to_T(x))), g.pose6_to_T(x), atol=ROUNDOFF_ATOL)
    y = random_pose6(rng, 100)
    # composition goes through Euler angles (conditioned by 1/cos(pitch) near ±90°): CONDITIONED_ATOL, 1e-10
    # before; measured 3.6e-15
    assert np.allclose(g.pose6_to_T(g.pose6_compose(x, g.pose6_inverse(x))), np.eye(4), atol=CONDITIONED_ATOL)
    assert np.allclose(g.pose6_to_T(g.pose6_compose(x, y)), g.pose6_to_T(x) @ g.pose6_to_T(y), atol=CONDITIONED_ATOL)


def test_batch_transform_points_matches_one_at_a_time(rng: np.random.Generator) -> None:
    T = g.pose6_to_T(random_pose6(rng, 20))
    p = rng.normal(size=(20, 3))
    batch = g.transform_points(T, p)
    for i in range(20):
        ref = (T[i] @ np.r_[p[i], 1.0])[:3]
        assert np.allclose(batch[i], ref, atol=ROUNDOFF_ATOL)
    one = g.transform_points(T[0], p)
    assert np.allclose(one, p @ T[0, :3, :3].T + T[0, :3, 3])


@settings(max_examples=200, deadline=None)
@given(x=coords, y=coords, yaw=angles, bx=coords, by=coords, byaw=angles)
def test_se2_round_trips(x: float, y: float, yaw: float, bx: float, by: float, byaw: float) -> None:
    a = np.array([x, y, yaw])
    b = np.array([bx, by, byaw])
    ident = g.pose2_compose(a, g.pose2_inverse(a))
    assert np.allclose(ident[:2], 0.0, atol=CONDITIONED_ATOL) and abs(g.wrap_angle(ident[2])) < CONDITIONED_ATOL
    ab = g.pose2_compose(a, b)
    assert np.allclose(g.pose2_to_T(ab), g.pose2_to_T(a) @ g.pose2_to_T(b), atol=CONDITIONED_ATOL)
    assert np.allclose(g.T_to_pose2(g.pose2_to_T(a))[:2], a[:2])


def test_wrap_angle_interval() -> None:
    a = np.linspace(-20, 20, 10001)
    w = g.wrap_angle(a)
    assert np.all(w > -np.pi) and np.all(w <= np.pi)
    assert np.allclose(np.sin(w), np.sin(a)) and np.allclose(np.cos(w), np.cos(a))
    assert g.wrap_angle(np.pi) == pytest.approx(np.pi) and g.wrap_angle(-np.pi) == pytest.approx(np.pi)


# ---------------------------------------------------------------- Jacobians vs central differences


def test_rotation_derivatives(rng: np.random.Generator) -> None:
    for rpy in random_pose6(rng, 10)[:, 3:]:
        analytic = g.euler_to_R_derivatives(rpy)
        numeric = g.numerical_jacobian(lambda e: g.euler_to_R(e).ravel(), rpy)
        for i in range(3):
            assert np.allclose(analytic[i].ravel(), numeric[:, i], atol=CENTRAL_DIFF_ATOL)


def test_euler_rate_jacobian(rng: np.random.Generator) -> None:
    for rpy, w in zip(random_pose6(rng, 10)[:, 3:], rng.normal(size=(10, 3))):
        numeric = g.numerical_jacobian(lambda e: g.euler_rate_matrix(e) @ w, rpy)
        assert np.allclose(g.euler_rate_jacobian(rpy, w), numeric, atol=CENTRAL_DIFF_ATOL)


def test_euler_rate_matrix_maps_body_rates() -> None:
    # integrate a constant body rate with E and compare with the exact rotation
    rpy0 = np.array([0.1, -0.2, 0.3])
    w = np.array([0.05, -0.1, 0.2])
    rpy = rpy0.copy()
    n = 10000
    for _ in range(n):
        rpy = rpy + g.euler_rate_matrix(rpy) @ w / n
    assert np.allclose(g.euler_to_R(rpy), g.euler_to_R(rpy0) @ g.so3_exp(w), atol=EULER_INTEGRATION_ATOL)


def test_pose2_compose_jacobians(rng: np.random.Generator) -> None:
    for _ in range(10):
        a = np.r_[rng.normal(size=2), rng.uniform(-3, 3)]
        b = np.r_[rng.normal(size=2), rng.uniform(-3, 3)]
        Ja, Jb = g.pose2_compose_jacobians(a, b)
        wrap = np.array([False, False, True])
        assert np.allclose(
            Ja, g.numerical_jacobian(lambda x: g.pose2_compose(x, b), a, wrap=wrap), atol=CENTRAL_DIFF_ATOL
        )
        assert np.allclose(
            Jb, g.numerical_jacobian(lambda x: g.pose2_compose(a, x), b, wrap=wrap), atol=CENTRAL_DIFF_ATOL
        )


def test_drot2() -> None:
    for yaw in np.linspace(-3, 3, 7):
        num = g.numerical_jacobian(lambda e: g.rot2(e[0]).ravel(), np.array([yaw]))
        assert np.allclose(g.drot2(yaw).ravel(), num[:, 0], atol=CENTRAL_DIFF_ATOL)


# ---------------------------------------------------------------- frames and alignment


def test_optical_to_robot_axes() -> None:
    # a point straight ahead of the camera is forward in FRD; right is right; down is down
    assert np.allclose(g.optical_to_robot_points(np.array([[0.0, 0.0, 5.0]])), [[5, 0, 0]])
    assert np.allclose(g.optical_to_robot_points(np.array([[1.0, 2.0, 0.0]])), [[0, 1, 2]])
    # a camera that moved forward along its optical axis moved forward in FRD
    T_cam = g.se3(np.eye(3), np.array([0.0, 0.0, 2.0]))
    assert np.allclose(g.T_optical_to_robot(T_cam)[:3, 3], [2, 0, 0])
    # a camera that turned right (about its y axis, down) turned right in FRD (positive yaw)
    T_cam = g.se3(g.rot_y(0.3), np.zeros(3))
    assert np.allclose(g.R_to_euler(g.T_optical_to_robot(T_cam)[:3, :3]), [0, 0, 0.3])


@pytest.mark.parametrize("dim", [2, 3])
def test_umeyama_recovers_similarity_exactly(dim: int, rng: np.random.Generator) -> None:
    a = rng.normal(size=(30, dim)) * 5
    if dim == 3:
        R = g.so3_exp(rng.normal(size=3))
    else:
        R = g.rot2(rng.uniform(-3, 3))
    s, t = 1.07, rng.normal(size=dim)
    b = s * a @ R.T + t
    s2, R2, t2 = g.umeyama(a, b)
    assert (
        s2 == pytest.approx(s, abs=CONDITIONED_ATOL)
        and np.allclose(R2, R, atol=CONDITIONED_ATOL)
        and np.allclose(t2, t, atol=CONDITIONED_ATOL)
    )
    sb, Rb, tb = g.umeyama_batch(np.stack([a[:3], a[3:6]]), np.stack([b[:3], b[3:6]]))
    assert (
        np.allclose(sb, s)
        and np.allclose(Rb, R[None], atol=CONDITIONED_ATOL)
        and np.allclose(tb, t[None], atol=CONDITIONED_ATOL)
    )
    _, Rr, _ = g.umeyama(a, a @ R.T + t, with_scale=False)
    assert np.allclose(Rr, R, atol=CONDITIONED_ATOL)


def test_umeyama_never_returns_a_reflection(rng: np.random.Generator) -> None:
    a = rng.normal(size=(10, 3))
    b = a * np.array([1, 1, -1])  # a mirror image: the best proper rotation, never det -1
    _, R, _ = g.umeyama(a, b)
    assert np.linalg.det(R) == pytest.approx(1.0)


def test_euler_to_R_is_the_product_of_elementary_rotations():
    # the closed form must equal Rz(yaw) Ry(pitch) Rx(roll) for any batch shape
    rng = np.random.default_rng(7)
    for shape in [(3,), (50, 3), (4, 6, 3)]:
        rpy = rng.uniform(-4.0, 4.0, shape)
        ref = g.rot_z(rpy[..., 2]) @ g.rot_y(rpy[..., 1]) @ g.rot_x(rpy[..., 0])
        np.testing.assert_allclose(g.euler_to_R(rpy), ref, rtol=0, atol=ULP_ATOL)
