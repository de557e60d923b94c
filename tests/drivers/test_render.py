"""The sim:// renderer's geometry: textures land where the pinhole model says, depth is exact,
nearer surfaces occlude farther ones, and the rendered yard is a usable stereo scene."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from drivers._render import ViewRenderer, clip_polygon_z
from drivers.sim import SimParams, SimRig
from drivers.simworld import build_world, make_surface
from robotd.core.geometry import euler_to_R, se3
from robotd.core.stereo import project, triangulate
from tests.support.tolerances import FLOAT32_ARITH_TOL, ROUNDOFF_ATOL

F, PX, PY, B, W, H = 430.0, 319.5, 199.5, 0.0755, 640, 400
BACKGROUND = 100
# centroid of a blurred blob vs its analytic projection; bilinear resampling keeps it far below this
CENTROID_TOL_PX = 0.1
STEREO_ROW_TOL_PX = 0.5  # median |y_L - y_R| of matches (task requirement)
DEPTH_REL_TOL = 0.02  # median |X_triangulated - X_zbuffer| / X_zbuffer (task requirement)
REPROJ_TOL_PX = 0.3  # median frame-to-frame reprojection error through the truth (measured ≈ 0.13)
# the buffer holds 1/Z = a x + b y + c evaluated in float32 at x ≤ 640, y ≤ 400, whose terms partly
# cancel: ten times FLOAT32_ARITH_TOL, relative
INV_DEPTH_RTOL = 10 * FLOAT32_ARITH_TOL


def _blob_texture(size: int, centre: tuple[float, float], sigma: float) -> np.ndarray:
    """(size, size) texture: flat background with one Gaussian blob at texel ``centre`` (s, t)."""
    t, s = np.mgrid[0:size, 0:size].astype(float)
    blob = np.exp(-((s - centre[0]) ** 2 + (t - centre[1]) ** 2) / (2 * sigma**2))
    return np.clip(BACKGROUND + 150 * blob, 0, 255).astype(np.uint8)


def _rig_poses(T_world_robot: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    T_rl = se3(np.array([[0.0, 0, 1], [1, 0, 0], [0, 1, 0]]), np.array([0.0, -B / 2, 0]))
    T_rr = se3(np.array([[0.0, 0, 1], [1, 0, 0], [0, 1, 0]]), np.array([0.0, B / 2, 0]))
    return T_world_robot @ T_rl, T_world_robot @ T_rr


def _centroid(img: np.ndarray, iz: np.ndarray) -> np.ndarray:
    """Intensity-weighted centroid (x, y) of the blob; the sky (1/Z = 0) is left out."""
    w = np.where(iz > 0, np.clip(img.astype(float) - BACKGROUND - 5, 0, None), 0.0)
    ys, xs = np.mgrid[0 : img.shape[0], 0 : img.shape[1]]
    return np.array([np.sum(w * xs), np.sum(w * ys)]) / np.sum(w)


@pytest.mark.parametrize(
    "rpy, plane_tilt",
    [((0.0, 0.0, 0.0), 0.0), ((0.05, -0.03, 0.4), 0.5), ((-0.04, 0.06, -1.1), -0.7)],
)
def test_marker_lands_at_its_analytic_projection_in_both_images(rpy: tuple[float, float, float], plane_tilt: float):
    # a 6 m square wall about 3 m ahead of the robot, turned by plane_tilt about the vertical
    T_world_robot = se3(euler_to_R(np.array(rpy)), np.array([1.0, -0.5, 0.2]))
    size, texel = 1200, 0.005
    centre_tex = (617.3, 571.8)  # off the texel grid on purpose
    tex = _blob_texture(size, centre_tex, sigma=4.0)
    Rp = euler_to_R(np.array([0.0, 0.0, plane_tilt]))
    a = Rp @ np.array([0.0, size * texel, 0.0])  # columns run right (+y)
    b = np.array([0.0, 0.0, size * texel])  # rows run down (+z)
    centre_robot = np.array([3.0, 0.0, 0.0])
    corner_robot = centre_robot - a / 2 - b / 2
    R, t = T_world_robot[:3, :3], T_world_robot[:3, 3]
    surf = make_surface("marker", R @ corner_robot + t, R @ a, R @ b, R @ (-(Rp @ np.array([1.0, 0, 0]))), tex)
    rend = ViewRenderer((surf,), F, PX, PY, W, H)
    T_wl, T_wr = _rig_poses(T_world_robot)
    left, iz_l = rend.render(T_wl)
    right, iz_r = rend.render(T_wr)

    blob_W = surf.origin_W + centre_tex[0] * surf.u_W + centre_tex[1] * surf.v_W
    blob_R = R.T @ (blob_W - t)
    xl, xr, y = project(blob_R[None], F, PX, PY, B)
    assert np.allclose(_centroid(left, iz_l), [xl[0], y[0]], atol=CENTROID_TOL_PX)
    assert np.allclose(_centroid(right, iz_r), [xr[0], y[0]], atol=CENTROID_TOL_PX)


def test_depth_buffer_is_the_exact_ray_plane_depth():
    T_world_robot = se3(euler_to_R(np.array([0.02, 0.04, 0.3])), np.array([0.5, 0.2, -0.1]))
    tex = _blob_texture(64, (30.0, 30.0), 3.0)
    n_R = euler_to_R(np.array([0.0, 0.2, 0.5])) @ np.array([-1.0, 0.0, 0.0])
    # plane through (4, 0, 0) in the robot frame with normal n_R (towards the robot), 20 m wide
    e1 = np.cross(n_R, [0.0, 0.0, 1.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n_R, e1)
    p0 = np.array([4.0, 0.0, 0.0]) - 10 * e1 - 10 * e2
    R, t = T_world_robot[:3, :3], T_world_robot[:3, 3]
    surf = make_surface("plane", R @ p0 + t, R @ (20 * e1), R @ (20 * e2), R @ n_R, tex)
    rend = ViewRenderer((surf,), F, PX, PY, W, H)
    T_wl, _ = _rig_poses(T_world_robot)
    _, iz = rend.render(T_wl)
    assert np.all(iz > 0), "the plane fills the view"
    # analytic: left-camera ray through pixel (x, y) hits n·(X - q) = 0
    R_cw = T_wl[:3, :3].T
    n_c = R_cw @ (R @ n_R)
    q_c = R_cw @ (R @ np.array([4.0, 0.0, 0.0]) + t - T_wl[:3, 3])
    ys, xs = np.mgrid[0:H, 0:W]
    rays = np.stack([(xs - PX) / F, (ys - PY) / F, np.ones_like(xs, dtype=float)], -1)
    Z = (n_c @ q_c) / (rays @ n_c)
    assert np.max(np.abs(1.0 / iz - Z) / Z) < INV_DEPTH_RTOL


def test_nearer_surface_occludes_and_owns_the_depth_buffer():
    far = make_surface(
        "far", np.array([5.0, -5, -5]), np.array([0.0, 10, 0]), np.array([0.0, 0, 10]), np.array([-1.0, 0, 0]),
        np.full((100, 100), 200, np.uint8),
    )  # fmt: skip
    near = make_surface(
        "near", np.array([2.0, -0.3, -0.3]), np.array([0.0, 0.6, 0]), np.array([0.0, 0, 0.6]),
        np.array([-1.0, 0, 0]), np.full((60, 60), 30, np.uint8),
    )  # fmt: skip
    # draw order must not matter: the depth test decides
    for surfaces in ((far, near), (near, far)):
        rend = ViewRenderer(surfaces, F, PX, PY, W, H)
        img, iz = rend.render(_rig_poses(np.eye(4))[0])
        xl, _, y = project(np.array([[2.0, 0.0, 0.0], [5.0, 1.5, 1.5]]), F, PX, PY, B)
        c_near = (round(y[0]), round(xl[0]))
        c_far = (round(y[1]), round(xl[1]))
        assert img[c_near] == 30 and iz[c_near] == pytest.approx(1 / 2.0, rel=FLOAT32_ARITH_TOL)
        assert img[c_far] == 200 and iz[c_far] == pytest.approx(1 / 5.0, rel=FLOAT32_ARITH_TOL)


def test_a_coverage_mask_shows_what_lies_behind_where_the_surface_is_not():
    """A surface with ``alpha`` (a tree crown's outline) is drawn, and owns the depth, only where
    its coverage is set: elsewhere the farther wall shows through, in the image and the depth."""
    far = make_surface(
        "far", np.array([8.0, -8, -8]), np.array([0.0, 16, 0]), np.array([0.0, 0, 16]), np.array([-1.0, 0, 0]),
        np.full((100, 100), 200, np.uint8),
    )  # fmt: skip
    alpha = np.zeros((80, 80), np.uint8)
    alpha[:, :40] = 255  # the left half of the near square is there
    near = make_surface(
        "near", np.array([3.0, -1.0, -1.0]), np.array([0.0, 2.0, 0]), np.array([0.0, 0, 2.0]),
        np.array([-1.0, 0, 0]), np.full((80, 80), 30, np.uint8), alpha,
    )  # fmt: skip
    img, iz = ViewRenderer((far, near), F, PX, PY, W, H).render(_rig_poses(np.eye(4))[0])
    xl, _, y = project(np.array([[3.0, -0.5, 0.0], [3.0, 0.5, 0.0]]), F, PX, PY, B)
    there = (round(y[0]), round(xl[0]))
    not_there = (round(y[1]), round(xl[1]))
    assert img[there] == 30 and iz[there] == pytest.approx(1 / 3.0, rel=FLOAT32_ARITH_TOL)
    assert img[not_there] == 200 and iz[not_there] == pytest.approx(1 / 8.0, rel=FLOAT32_ARITH_TOL)
    with pytest.raises(ValueError, match="alpha"):
        make_surface("bad", np.zeros(3), np.eye(3)[1], np.eye(3)[2], -np.eye(3)[0], np.zeros((4, 4), np.uint8), alpha)


def test_back_faces_are_culled():
    wall = make_surface(
        "w", np.array([5.0, -5, -5]), np.array([0.0, 10, 0]), np.array([0.0, 0, 10]), np.array([1.0, 0, 0]),
        np.full((10, 10), 10, np.uint8),
    )  # fmt: skip
    img, iz = ViewRenderer((wall,), F, PX, PY, W, H).render(_rig_poses(np.eye(4))[0])
    assert np.all(iz == 0) and img.min() > 100  # only sky


def test_clip_polygon_keeps_only_the_slab_and_leaves_inside_polygons_alone():
    quad = np.array([[-1.0, 0, -2], [1.0, 0, -2], [1.0, 0, 6], [-1.0, 0, 6]])
    clipped = clip_polygon_z(quad, 0.5, 4.0)
    assert clipped[:, 2].min() == pytest.approx(0.5) and clipped[:, 2].max() == pytest.approx(4.0)
    assert len(clipped) == 4
    inside = np.array([[-1.0, 0, 1], [1.0, 0, 1], [1.0, 0, 2]])
    assert np.array_equal(clip_polygon_z(inside, 0.5, 4.0), inside)
    assert len(clip_polygon_z(quad + np.array([0.0, 0, 20]), 0.5, 4.0)) == 0


# --------------------------------------------------------------------------------------------
# The yard


@pytest.fixture(scope="module")
def rig() -> SimRig:
    return SimRig(build_world(1), SimParams(realtime=0))


def test_truth_starts_at_identity_and_the_ground_is_at_camera_height(rig: SimRig):
    frame, depth = rig.render(0, 0)
    assert frame.truth_T_world_robot is not None
    assert np.allclose(frame.truth_T_world_robot, np.eye(4), atol=ROUNDOFF_ATOL)
    # bottom-centre pixel sees the ground (if no box is in the way): Z = h f / (y - p_y)
    y = H - 1
    assert depth[y, W // 2] == pytest.approx(0.4 * F / (y - PY), rel=1e-3)


def test_same_seed_renders_identical_images_and_another_seed_does_not(rig: SimRig):
    other = SimRig(build_world(1), SimParams(realtime=0))
    a, _ = rig.render(37, 123)
    b, _ = other.render(37, 123)
    assert np.array_equal(a.left, b.left) and np.array_equal(a.right, b.right)
    c, _ = SimRig(build_world(2), SimParams(realtime=0, seed=2)).render(37, 123)
    assert np.mean(np.abs(a.left.astype(int) - c.left.astype(int))) > 10


def test_sensor_noise_differs_per_frame_and_has_the_configured_sigma():
    world = build_world(1, speed_mps=0.0)  # a parked rover: consecutive frames differ by noise only
    noisy = SimRig(world, SimParams(realtime=0, speed=0.0, img_noise=3.0))
    clean = SimRig(world, SimParams(realtime=0, speed=0.0, img_noise=0.0))
    f1, _ = noisy.render(1, 0)
    f2, _ = noisy.render(2, 0)
    ref, _ = clean.render(1, 0)
    diff = f1.left.astype(float) - ref.left
    mid = (ref.left > 20) & (ref.left < 235)  # away from saturation
    assert np.std(diff[mid]) == pytest.approx(3.0, rel=0.1)
    assert not np.array_equal(f1.left, f2.left)


def _match(det: cv2.Feature2D, norm: int, left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    kl, dl = det.detectAndCompute(left, None)
    kr, dr = det.detectAndCompute(right, None)
    matches = cv2.BFMatcher(norm, crossCheck=True).match(dl, dr)
    pl = np.array([kl[m.queryIdx].pt for m in matches])
    pr = np.array([kr[m.trainIdx].pt for m in matches])
    return pl, pr


@pytest.mark.parametrize("k", [0, 140, 420])
def test_stereo_matches_are_row_aligned_and_triangulate_to_the_depth_buffer(rig: SimRig, k: int):
    frame, depth = rig.render(k, 0)
    m = rig.model
    for det, norm in ((cv2.ORB_create(1500), cv2.NORM_HAMMING), (cv2.SIFT_create(1500), cv2.NORM_L2)):
        pl, pr = _match(det, norm, frame.left, frame.right)
        dy = pl[:, 1] - pr[:, 1]
        d = pl[:, 0] - pr[:, 0]
        # plausible matches only: a loose row band and the disparity range the front end uses
        ok = (np.abs(dy) < 3) & (d >= 5) & (d <= m.fb / 0.3)
        assert ok.sum() >= 50
        assert np.median(np.abs(dy[ok])) < STEREO_ROW_TOL_PX
    # depth against the z-buffer with SIFT (sub-pixel keypoints; ORB's are integer FAST corners)
    xyz = triangulate(pl[ok, 0], pr[ok, 0], 0.5 * (pl[ok, 1] + pr[ok, 1]), m.f_px, m.px, m.py, m.baseline_m)
    zbuf = depth[np.rint(pl[ok, 1]).astype(int), np.rint(pl[ok, 0]).astype(int)]
    finite = np.isfinite(zbuf)
    rel = np.abs(xyz[finite, 0] - zbuf[finite]) / zbuf[finite]
    assert np.median(rel) < DEPTH_REL_TOL


def test_enough_orb_features_on_most_frames(rig: SimRig):
    orb = cv2.ORB_create(nfeatures=1000)
    ks = np.linspace(0, 28.5 * 30, 12, endpoint=False).astype(int)  # around the whole loop
    counts = np.array([len(orb.detect(rig.render(int(k), 0)[0].left, None)) for k in ks])
    assert np.mean(counts >= 300) >= 0.8, counts


@pytest.mark.parametrize("k0", [30, 300, 600])
def test_truth_poses_agree_with_the_motion_the_images_show(rig: SimRig, k0: int):
    """A feature of frame k0, lifted with the z-buffer and moved by the truth's relative pose,
    reprojects onto its SIFT match in frame k0 + 6 (0.2 s later): truth and images agree."""
    from robotd.core.geometry import se3_inverse

    m = rig.model
    f0, depth0 = rig.render(k0, 0)
    f1, _ = rig.render(k0 + 6, 0)
    sift = cv2.SIFT_create(1500)
    ka, da = sift.detectAndCompute(f0.left, None)
    kb, db = sift.detectAndCompute(f1.left, None)
    mt = cv2.BFMatcher(cv2.NORM_L2, crossCheck=True).match(da, db)
    pa = np.array([ka[x.queryIdx].pt for x in mt])
    pb = np.array([kb[x.trainIdx].pt for x in mt])
    Z = depth0[np.rint(pa[:, 1]).astype(int), np.rint(pa[:, 0]).astype(int)]
    ok = np.isfinite(Z)
    pa, pb, Z = pa[ok], pb[ok], Z[ok]
    xyz_C0 = np.stack([(pa[:, 0] - m.px) / m.f_px * Z, (pa[:, 1] - m.py) / m.f_px * Z, Z], 1)
    xyz_R0 = xyz_C0 @ rig.T_robot_left[:3, :3].T + rig.T_robot_left[:3, 3]
    assert f0.truth_T_world_robot is not None and f1.truth_T_world_robot is not None
    T_10 = se3_inverse(f1.truth_T_world_robot) @ f0.truth_T_world_robot
    assert np.linalg.norm(T_10[:3, 3]) > 0.15  # the rover did move
    xl, _, y = project(xyz_R0 @ T_10[:3, :3].T + T_10[:3, 3], m.f_px, m.px, m.py, m.baseline_m)
    err = np.hypot(xl - pb[:, 0], y - pb[:, 1])
    assert len(err) >= 200
    assert np.median(err) < REPROJ_TOL_PX
