"""The stereo PnP's second, wider gate (robotd.frontend.frontend.PNP_WIDE_GATE): a frame blurred
beyond what its exposure allows for still gives the images' motion."""

from __future__ import annotations

import numpy as np

import robotd.frontend.frontend as ff
from robotd.config import load_config
from robotd.config.params import frontend_params_from_config
from robotd.core.geometry import so3_exp, so3_log
from robotd.core.stereo import RectifiedStereo, triangulate
from robotd.frontend.frontend import Frontend, _PrevFrame
from robotd.frontend.pnp import project_stereo
from robotd.frontend.stereo_match import StereoMatches

RIG = RectifiedStereo(458.0, 376.0, 240.0, 0.11, 752, 480)  # EuRoC's rig


def _matches(z: np.ndarray, desc: np.ndarray) -> StereoMatches:
    n = z.shape[0]
    xyz = triangulate(z[:, 0], z[:, 1], z[:, 2], RIG.f_px, RIG.px, RIG.py, RIG.baseline_m)
    return StereoMatches(
        z[:, 0], z[:, 1], z[:, 2], xyz, np.tile(np.eye(3) * 1e-4, (n, 1, 1)), desc,
        np.arange(n), np.arange(n), np.zeros(n), np.zeros(n, bool), binary=True,
    )  # fmt: skip


def _blurred_pair(seed: int, blur_px: float, n: int = 20) -> tuple[Frontend, StereoMatches, np.ndarray]:
    """A sharp previous frame of ``n`` points 2-8 m away spread over the image, and the current
    one after a 4° turn, each corner found anywhere within ``blur_px`` of where it is, each its
    own way (a shake's turn about the optical axis streaks every point in its own direction), the
    same in both images (both cameras expose together)."""
    rng = np.random.default_rng(seed)
    u = rng.uniform(60, 690, n)
    v = rng.uniform(40, 440, n)
    depth = rng.uniform(2.0, 8.0, n)
    P = np.c_[depth, (u - RIG.px) * depth / RIG.f_px, (v - RIG.py) * depth / RIG.f_px]  # robot frame: x ahead
    w = np.radians([0.0, 2.0, 3.5])  # pitch and yaw between the frames
    R, t = so3_exp(w), np.array([0.02, 0.01, 0.0])
    z_prev = project_stereo(P, RIG)
    z_cur = project_stereo((P - t) @ R, RIG)
    r, a = blur_px * np.sqrt(rng.uniform(0.0, 1.0, n)), rng.uniform(0.0, 2 * np.pi, n)
    z_cur[:, 0] += r * np.cos(a)
    z_cur[:, 1] += r * np.cos(a)
    z_cur[:, 2] += r * np.sin(a)
    desc = rng.integers(0, 256, (n, 32), dtype=np.uint8)
    fe = Frontend(RIG, frontend_params_from_config(load_config(None, {})), rng=np.random.default_rng(0))
    fe._prev = _PrevFrame(0, _matches(z_prev, desc), np.arange(n))  # the previous frame, as commit leaves it
    return fe, _matches(z_cur, desc), w


def test_a_frame_blurred_beyond_the_gate_gives_its_motion_at_the_wider_gate(monkeypatch) -> None:
    """Blur of up to 6 px leaves about a ninth of 20 matches inside the PnP's 2 px gate, fewer than
    its 8: the first attempt finds nothing, the second at 3× the gate finds the turn (within 1°:
    one corner's blur is up to 0.75° of view);
    with no second gate (PNP_WIDE_GATE 1) the frame has no motion. Sharp, the first attempt does
    it and the second gate is never tried."""
    for seed in range(3):
        fe, cur, w = _blurred_pair(seed, 6.0)
        vm = fe.visual_motion(cur, 50_000_000)
        assert vm.increment is not None and vm.counts["motion_wide_gate"] == 1
        assert np.degrees(np.linalg.norm(so3_log(so3_exp(vm.increment.drot_R_rad).T @ so3_exp(w)))) < 1.0
    sharp, cur, _ = _blurred_pair(0, 0.0)
    vm = sharp.visual_motion(cur, 50_000_000)
    assert vm.increment is not None and "motion_wide_gate" not in vm.counts
    monkeypatch.setattr(ff, "PNP_WIDE_GATE", 1.0)
    fe, cur, _ = _blurred_pair(0, 6.0)
    assert fe.visual_motion(cur, 50_000_000).increment is None


def test_a_frame_blurred_beyond_the_wider_gate_too_gives_none() -> None:
    """Far beyond three times the gate as well (up to 40 px): no motion, and the count says the
    second gate failed. A gate the known blur had already widened past 3× the sharp one (8 px)
    is not tried again: the second gate is for blur nothing allowed for."""
    fe, cur, _ = _blurred_pair(0, 40.0)
    vm = fe.visual_motion(cur, 50_000_000)
    assert vm.increment is None and vm.counts["motion_wide_gate"] == 0
    fe, cur, _ = _blurred_pair(0, 40.0)
    vm = fe.visual_motion(cur, 50_000_000, inlier_px=8.0)
    assert vm.increment is None and "motion_wide_gate" not in vm.counts
