#!/usr/bin/env python3
"""Where the map sits relative to the pose that sees it: signed depth error by depth band.

Runs FastSLAM 2.0 (pixel model, 50 particles, robotd's defaults otherwise) on the landmark
simulator's loops with stereo noise, and after each frame compares every landmark the frame
observed with the truth *in the robot frame* (estimated landmark minus estimated pose, against
true landmark minus true pose), so the pose's own drift cancels and what is left is the map's
error as the filter uses it. Rows split new landmarks (the frame created them) from re-observed
ones, by true depth, beside the mean error of the frame's own triangulated depth
("measured"). A negative mean is a map that is too near: the rover then under-travels.

The simulator, like the front end, keeps a point only when its measured disparity is at least
``d_min_px``, so a landmark coming into range is first seen when its noise made it look nearer
(docs/slam.md, "Where it falls short").

    python bench/landmark_bias.py [--length 40] [--seeds 1,2] [--dim 2] [--json]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from robotd.research.landmark_sim import SimConfig, simulate
from robotd.slam.factory import make_estimator
from robotd.slam.params import SlamParams

BANDS = ((0.0, 2.5), (2.5, 5.0), (5.0, 7.0))


def robot_frame(xyz: np.ndarray, pose_xyz: np.ndarray, yaw: float) -> np.ndarray:
    """Points (N, 3) in the frame of a pose, yaw only (the 2D loops; the 3D ones tilt a little)."""
    c, s = np.cos(yaw), np.sin(yaw)
    d = xyz - pose_xyz
    return np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]], axis=1)


def study(length_m: float, seed: int, dim: int) -> dict[str, list[dict[str, float]]]:
    cfg = SimConfig(dim=dim, trajectory="loop", path_length_m=length_m, landmark_density_per_m2=0.5)
    run = simulate(cfg, np.random.default_rng(seed))
    params = SlamParams(
        filter="fastslam2",
        dim=dim,
        n_particles=50,
        n_particles_min=1,
        prune_enabled=False,
        motion_cov_source="message",
        measurement="pixel",
        stereo_intrinsics=(cfg.f_px, cfg.px, cfg.py, cfg.baseline_m),
        pixel_sigma_px=(cfg.sigma_px, cfg.sigma_px / np.sqrt(2.0)),
    )
    est = make_estimator(params, np.random.default_rng([seed, 7919]))
    rows: dict[str, list[np.ndarray]] = {"new": [], "re-observed": []}
    for k, step in enumerate(run.steps):
        if step.motion is not None:
            est.predict(step.motion)
        est.update(step.observations)
        pose, lm, obs = est.estimate(), est.landmarks(), step.observations
        order = np.argsort(lm.ids)
        pos = np.minimum(np.searchsorted(lm.ids[order], obs.ids), max(lm.n - 1, 0))
        found = lm.ids[order[pos]] == obs.ids
        j, ids, new = order[pos[found]], obs.ids[found], obs.is_new[found]
        est_r = robot_frame(lm.xyz_W_m[j], pose.xyz_W_m, float(pose.rpy_rad[2]))
        t = run.poses_W[k]
        true_r = robot_frame(run.landmarks_W[ids], t[:3], float(t[5]))
        meas = obs.xyz_R_m[found, 0] - true_r[:, 0]  # the frame's own triangulated depth, against truth
        err = np.column_stack([est_r[:, 0] - true_r[:, 0], true_r[:, 0], meas])
        rows["new"].append(err[new])
        rows["re-observed"].append(err[~new])
    out: dict[str, list[dict[str, float]]] = {}
    for kind, parts in rows.items():
        a = np.concatenate(parts) if parts else np.zeros((0, 3))
        out[kind] = []
        for lo, hi in BANDS:
            m = (a[:, 1] >= lo) & (a[:, 1] < hi)
            if m.any():
                e, z = a[m, 0], a[m, 1]
                out[kind].append(
                    {
                        "depth_from_m": lo,
                        "depth_to_m": hi,
                        "n": int(m.sum()),
                        "mean_m": float(e.mean()),
                        "mean_rel": float(np.mean(e / z)),
                        "sd_m": float(e.std()),
                        "measured_mean_m": float(a[m, 2].mean()),
                    }
                )
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--length", type=float, default=40.0, help="loop length [m]")
    ap.add_argument("--seeds", default="1,2")
    ap.add_argument("--dim", type=int, default=2, choices=(2, 3))
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    res = {int(s): study(a.length, int(s), a.dim) for s in a.seeds.split(",")}
    if a.json:
        print(json.dumps({"length_m": a.length, "dim": a.dim, "seeds": res}, indent=1))
        return 0
    print(
        f"{a.dim}D loop {a.length:.0f} m, FastSLAM 2.0 pixel model, depth error in the robot frame (estimate - truth)"
    )
    print(
        f"{'seed':>4} {'landmarks':>11} {'depth m':>9} {'n':>6} {'mean m':>8} {'mean %':>7} {'sd m':>6} "
        f"{'measured m':>10}"
    )
    for seed, r in res.items():
        for kind, bands in r.items():
            for b in bands:
                print(
                    f"{seed:>4} {kind:>11} {b['depth_from_m']:>4.1f}-{b['depth_to_m']:<4.1f} {b['n']:>6} "
                    f"{b['mean_m']:>+8.3f} {100 * b['mean_rel']:>+7.2f} {b['sd_m']:>6.3f} "
                    f"{b['measured_mean_m']:>+10.3f}"
                )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
