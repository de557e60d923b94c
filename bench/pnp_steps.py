"""The front end's frame-to-frame motion (stereo PnP) against the simulator's truth, by step size.

For each ``sim://`` URL the frames run through ``Frontend.process`` (no filter, no motion prior:
the PnP alone) and every frame-to-frame increment is compared with the truth's relative pose:
the step ratio |t_est| / |t_true| (median and interquartile range), the translation and rotation
NEES of the increment under its own covariance (medians; χ²(3)'s median is 2.37, so below it the
covariance is cautious) and the median yaw error. A ratio below 1 is a motion measured short
(docs/frontend.md "Short steps in open terrain"). Prints a Markdown table, or one JSON object
with --json.

    python bench/pnp_steps.py [--seconds 6] [--detector orb] [--json] [URL ...]
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

import numpy as np

from drivers import open_camera
from robotd.config import load_config
from robotd.config.params import frontend_params_from_config
from robotd.core.geometry import so3_exp, so3_log
from robotd.frontend.frontend import Frontend

# a car's metre a frame, 10 cm a frame two ways, a rover's 3.3 cm in open country and in the yard
DEFAULT_URLS = (
    "sim://?world=open_terrain&speed=5&fps=5&seed=2",
    "sim://?world=open_terrain&speed=3&fps=30&seed=2",
    "sim://?world=open_terrain&speed=1&fps=10&seed=2",
    "sim://?world=open_terrain&speed=1&fps=30&seed=2",
    "sim://?world=yard&speed=1&fps=30",
    "sim://?world=yard&speed=0.3&fps=30",
)


def steps(url: str, seconds: float, detector: str) -> dict[str, Any]:
    """One URL's increments against the truth, summarised."""
    cfg = load_config(None, {"frontend": {"detector": detector}})
    sep = "&" if "?" in url else "?"
    ratio, nees_t, nees_r, yaw_deg, step_m = [], [], [], [], []
    with open_camera(f"{url}{sep}realtime=0&odometry=0&duration={seconds:g}") as cam:
        fe = Frontend(cam.rectified_model(), frontend_params_from_config(cfg), np.random.default_rng(1))
        prev_T = None
        for frame in cam.frames():
            res = fe.process(frame.left, frame.right, frame.t_ns)
            T = frame.truth_T_world_robot
            inc = res.motion
            if inc is not None and prev_T is not None and T is not None:
                D = np.linalg.inv(prev_T) @ T
                e_r = so3_log(D[:3, :3].T @ so3_exp(np.asarray(inc.drot_R_rad)))
                e_t = np.asarray(inc.dp_R_m) - D[:3, 3]
                C = np.asarray(inc.cov, dtype=float)
                true_step = float(np.linalg.norm(D[:3, 3]))
                if true_step > 1e-4:
                    ratio.append(float(np.linalg.norm(inc.dp_R_m)) / true_step)
                    step_m.append(true_step)
                nees_t.append(float(e_t @ np.linalg.solve(C[:3, :3], e_t)))
                nees_r.append(float(e_r @ np.linalg.solve(C[3:, 3:], e_r)))
                yaw_deg.append(float(np.degrees(abs(e_r[2]))))
            prev_T = T
    if not ratio:
        raise SystemExit(f"{url}: no frame-to-frame motion measured (too short a run?)")
    q1, med, q3 = np.percentile(ratio, [25, 50, 75])
    return {
        "url": url,
        "detector": detector,
        "increments": len(ratio),
        "step_m": float(np.median(step_m)),
        "step_ratio": float(med),
        "step_ratio_iqr": [float(q1), float(q3)],
        "nees_t_median": float(np.median(nees_t)),
        "nees_rot_median": float(np.median(nees_r)),
        "yaw_err_deg_median": float(np.median(yaw_deg)),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("urls", nargs="*", help="sim:// URLs (default: six paces and places)")
    ap.add_argument("--seconds", type=float, default=6.0, help="simulated seconds per URL")
    ap.add_argument("--detector", default="orb", choices=("orb", "sift", "surf"))
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    if not a.seconds > 0:
        ap.error(f"--seconds: expected a positive duration, got {a.seconds}")
    rows = [steps(u, a.seconds, a.detector) for u in (a.urls or DEFAULT_URLS)]
    if a.json:
        print(json.dumps({"rows": rows}))
        return 0
    print("| source | detector | increments | step | step ratio (IQR) | translation NEES | rotation NEES | yaw error |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        lo, hi = r["step_ratio_iqr"]
        print(
            f"| {r['url']} | {r['detector']} | {r['increments']} | {100 * r['step_m']:.1f} cm | "
            f"{r['step_ratio']:.3f} ({lo:.2f}–{hi:.2f}) | {r['nees_t_median']:.2f} | {r['nees_rot_median']:.2f} | "
            f"{r['yaw_err_deg_median']:.4f}° |"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
