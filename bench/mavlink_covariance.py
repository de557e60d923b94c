#!/usr/bin/env python3
"""docs/mavlink.md §8's worked example: one real replayed frame, from the covariance robotd reports
to the observation noise ArduPilot's EKF3 and PX4's EKF2 fuse it with.

1. Replays SOURCE with the default configuration through ``robotd.tools.replay.replay`` (exactly what
   ``robotd replay SOURCE --out DIR/T.txt`` runs; it writes ``DIR/T.txt`` and ``DIR/T.cov.txt``)
   and takes one frame (``--frame``, default the last). Its ``T.cov.txt`` row is read back and
   must equal the step's reported covariance.
2. Sends that pose, with the quality the daemon would give it, through robotd's MAVLink driver to
   a pymavlink peer on loopback UDP (drivers.mavlink_mock) and prints the ODOMETRY it received.
3. Applies each autopilot's arithmetic to the received message, with the parameters' defaults
   (``--viso-pos-m-nse`` … to change them):

   - ArduPilot (GCS_MAVLINK::handle_odometry, AP_VisualOdom_MAV / _IntelT265 for VISO_TYPE 1, 2,
     3, NavEKF3): posErr = ∛(c0² + c6² + c11²), angErr = ∛(c15² + c18² + c20²) from the variances
     on the diagonal; clamped to [VISO_POS_M_NSE, 100] and [VISO_YAW_M_NSE, 1.5]; EKF3 fuses the
     horizontal position with σ = clamp(posErr, 0.01, 10) and the ExtNav yaw with
     σ = max(angErr, 0.05);
   - PX4 (mavlink_receiver, EKF2.cpp UpdateExtVisionSample, ev_pos_control / ev_yaw_control):
     the diagonal only (c0, c6, c11; c15, c18, c20); with EKF2_EV_NOISE_MD = 0 each variance
     floored at EKF2_EVP_NOISE² (position) or EKF2_EVA_NOISE² (angles), with 1 the parameters
     alone.

Prints Markdown (or one JSON object with --json). The figures in docs/mavlink.md come from

    python bench/mavlink_covariance.py            # kitti-seq1 beside the repository, last frame
    python bench/mavlink_covariance.py --source kitti://DIR --frame 25 --json
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from robotd.config import load_config  # noqa: E402
from robotd.core.msgs import PoseEstimate, StepResult  # noqa: E402
from robotd.formats.autopilot import DIAG_INDEX, CovarianceFloors, position_sigma_m, upper21_to_cov6  # noqa: E402
from robotd.outputs import pose_quality  # noqa: E402
from robotd.research.evaluate import cov_path_for, read_pose_cov  # noqa: E402

DEFAULT_DATA = Path(os.environ.get("ROBOTD_SHARED_DATA", REPO.parent / "shared" / "data"))
AXES = ("x", "y", "z", "roll", "pitch", "yaw")


def replay_frame(source: str, frame: int, out_dir: Path) -> tuple[StepResult, int, dict[str, Any]]:
    """Replay ``source`` (default configuration, T.txt / T.cov.txt in ``out_dir``) -> (the frame's
    step result, its quality, what the replay wrote)."""
    from robotd.tools.replay import replay

    cfg = load_config(None)
    results: list[StepResult] = []
    traj = out_dir / "T.txt"
    summary = replay(cfg, source, out_traj=str(traj), progress=False, on_step=results.append)
    if not -len(results) <= frame < len(results):
        raise SystemExit(f"--frame {frame}: the replay has {len(results)} frames")
    k = frame % len(results)
    res = results[k]
    t_s, covs = read_pose_cov(cov_path_for(traj))
    # the file holds 9 significant digits of the step's covariance
    if not (abs(t_s[k] - res.t_ns / 1e9) < 1e-6 and np.allclose(covs[k], res.pose.cov, rtol=1e-8, atol=1e-15)):
        raise SystemExit(f"{cov_path_for(traj)} row {k} differs from the step's reported covariance")
    qs = [pose_quality(r, cfg.frontend.min_inliers, cfg.mavlink.quality_good_sigma_m) for r in results]
    wrote = {"trajectory": str(traj), "covariance": str(cov_path_for(traj)), "frame": k, "frames": len(results)}
    wrote["truth_nees_pos_in_band_frac"] = summary.get("truth_nees_pos_in_band_frac")
    wrote["quality_over_run"] = {"min": min(qs), "median": float(np.median(qs)), "max": max(qs)}
    sig = [position_sigma_m(r.pose.cov) for r in results]
    wrote["position_sigma_m_over_run"] = {"first": sig[0], "median": float(np.median(sig)), "last": sig[-1]}
    return res, qs[k], wrote


def send_and_receive(pose: PoseEstimate, quality: int) -> Any:
    """The pose through robotd's MAVLink driver to a pymavlink peer on loopback UDP -> its ODOMETRY."""
    from drivers import open_vehicle
    from drivers.mavlink_mock import MockAutopilot

    with MockAutopilot(sysid=1) as ap:
        with open_vehicle(ap.url) as link:
            autopilot = link.autopilot
            if autopilot is None:
                raise SystemExit(f"{ap.url}: the link has no autopilot role")
            t_end = time.monotonic() + 5.0
            while not getattr(link, "link_up", False) and time.monotonic() < t_end:
                time.sleep(0.01)
            autopilot.send_pose(pose, quality, 0)
            while not ap.messages("ODOMETRY") and time.monotonic() < t_end:
                time.sleep(0.01)
        odo = ap.messages("ODOMETRY")
    if not odo:
        raise SystemExit("no ODOMETRY arrived on the loopback link within 5 s")
    return odo[0].msg


def ardupilot(c: list[float], viso_pos_m_nse: float, viso_yaw_m_nse: float) -> dict[str, float]:
    """What ArduPilot (4.1+, VISO_TYPE 1/2/3, EKF3) makes of ODOMETRY.pose_covariance ``c``."""
    pos_err = math.cbrt(c[0] ** 2 + c[6] ** 2 + c[11] ** 2)
    ang_err = math.cbrt(c[15] ** 2 + c[18] ** 2 + c[20] ** 2)
    pos_used = min(max(pos_err, viso_pos_m_nse), 100.0)
    ang_used = min(max(ang_err, viso_yaw_m_nse), 1.5)
    return {
        "posErr": pos_err,
        "angErr": ang_err,
        "posErr_after_VISO_POS_M_NSE": pos_used,
        "angErr_after_VISO_YAW_M_NSE": ang_used,
        "ekf3_pos_sigma_m": min(max(pos_used, 0.01), 10.0),  # NavEKF3: R = sq(constrain(posErr, 0.01, 10))
        "ekf3_yaw_sigma_rad": max(ang_used, 0.05),  # NavEKF3 ExtNav yaw: R = sq(max(yawAngErr, 0.05))
    }


def px4(c: list[float], evp_noise: float, eva_noise: float, noise_md: int) -> dict[str, float]:
    """What PX4's EKF2 (1.14+) makes of ODOMETRY.pose_covariance ``c`` (frame LOCAL_FRD)."""
    var = [c[i] for i in DIAG_INDEX]
    if noise_md == 0:
        pos = [max(v, evp_noise**2) for v in var[:3]]
        ang = [max(v, eva_noise**2) for v in var[3:]]
    else:
        pos, ang = [evp_noise**2] * 3, [eva_noise**2] * 3
    return {
        "ekf2_pos_sigma_m_x": math.sqrt(pos[0]),
        "ekf2_pos_sigma_m_y": math.sqrt(pos[1]),
        "ekf2_pos_sigma_m_z": math.sqrt(pos[2]),
        "ekf2_yaw_sigma_rad": math.sqrt(ang[2]),
    }


def report(
    res: StepResult, quality: int, wrote: dict[str, Any], o: Any, ap: dict[str, float], p4: dict[str, dict[str, float]]
) -> dict[str, Any]:
    pose = res.pose
    received = upper21_to_cov6(list(o.pose_covariance))
    floors = CovarianceFloors()  # the driver's defaults (floor_pos_m2, floor_ang_rad2)
    expected = pose.cov.copy()
    raised = [AXES[i] for i in range(6) if expected[i, i] < floors.diag()[i]]
    np.fill_diagonal(expected, np.maximum(np.diag(expected), floors.diag()))
    return {
        **wrote,
        "t_s": res.t_ns / 1e9,
        "xyz_m": [float(v) for v in pose.xyz_W_m],
        "rpy_rad": [float(v) for v in pose.rpy_rad],
        "reported_cov": pose.cov.tolist(),
        "reported_sigma": {a: math.sqrt(max(float(pose.cov[i, i]), 0.0)) for i, a in enumerate(AXES)},
        "position_sigma_m": position_sigma_m(pose.cov),
        "identified": int(res.counts.get("identified", 0)),
        "neff": float(pose.neff),
        "n_particles": int(pose.n_particles),
        "consistency": dict(res.consistency),
        "quality": quality,
        "odometry": {
            "time_usec": int(o.time_usec),
            "frame_id": int(o.frame_id),
            "child_frame_id": int(o.child_frame_id),
            "xyz": [float(o.x), float(o.y), float(o.z)],
            "q": [float(v) for v in o.q],
            "pose_covariance": [float(v) for v in o.pose_covariance],
            "velocity_covariance_0": float(o.velocity_covariance[0]),
            "quality": int(o.quality),
            "reset_counter": int(o.reset_counter),
            "estimator_type": int(o.estimator_type),
        },
        "received_equals_reported": bool(np.allclose(received, expected, rtol=1e-6, atol=1e-12)),
        "raised_by_floor": raised,
        "ardupilot": ap,
        "px4": p4,
    }


def markdown(r: dict[str, Any], args: argparse.Namespace) -> str:
    C = np.array(r["reported_cov"])
    s, o = r["reported_sigma"], r["odometry"]
    lines = [
        f"frame {r['frame']} of {r['frames']} (t = {r['t_s']:.1f} s), pose x y z = "
        + " ".join(f"{v:.3f}" for v in r["xyz_m"])
        + " m, roll pitch yaw = "
        + " ".join(f"{math.degrees(v):.2f}" for v in r["rpy_rad"])
        + "°",
        "",
        "Reported covariance (the T.cov.txt row; x y z [m], roll pitch yaw [rad]):",
        "",
        "```",
        *("  ".join(f"{v:+.3e}" for v in row) for row in C),
        "```",
        "",
        "σ: "
        + ", ".join(f"{a} {s[a]:.3g}" + (" m" if a in "xyz" else f" rad ({math.degrees(s[a]):.2f}°)") for a in AXES)
        + f"; position σ (√trace) {r['position_sigma_m']:.3f} m",
        "",
        f"quality {r['quality']}: inliers {r['identified']}, N_eff {r['neff']:.1f} of {r['n_particles']}, "
        f"consistency {r['consistency'].get('state')} (NIS ratio {r['consistency'].get('nis_ratio')})",
        "",
        "ODOMETRY as received (pymavlink, loopback UDP):",
        "",
        "| field | value |",
        "|---|---|",
        f"| time_usec | {o['time_usec']} |",
        f"| frame_id, child_frame_id | {o['frame_id']}, {o['child_frame_id']} |",
        "| x, y, z | " + ", ".join(f"{v:.4f}" for v in o["xyz"]) + " |",
        "| q (w, x, y, z) | " + ", ".join(f"{v:.5f}" for v in o["q"]) + " |",
        "| pose_covariance[0, 6, 11] (x, y, z) | "
        + ", ".join(f"{o['pose_covariance'][i]:.4g}" for i in (0, 6, 11))
        + " |",
        "| pose_covariance[15, 18, 20] (roll, pitch, yaw) | "
        + ", ".join(f"{o['pose_covariance'][i]:.4g}" for i in (15, 18, 20))
        + " |",
        "| pose_covariance[1] (x·y) | " + f"{o['pose_covariance'][1]:.4g} |",
        f"| velocity_covariance[0] | {o['velocity_covariance_0']} |",
        f"| quality, reset_counter, estimator_type | {o['quality']}, {o['reset_counter']}, {o['estimator_type']} |",
        "",
        f"received 6×6 equals the reported one (float32): {r['received_equals_reported']}"
        + (f" (floor raised: {', '.join(r['raised_by_floor'])})" if r["raised_by_floor"] else " (no floor reached)"),
        "",
        "over the whole run: quality min / median / max "
        + " / ".join(f"{r['quality_over_run'][k]:g}" for k in ("min", "median", "max"))
        + "; position σ first / median / last "
        + " / ".join(f"{r['position_sigma_m_over_run'][k]:.3f}" for k in ("first", "median", "last"))
        + " m",
        "",
        f"ArduPilot (VISO_POS_M_NSE {args.viso_pos_m_nse}, VISO_YAW_M_NSE {args.viso_yaw_m_nse}):",
        "",
    ]
    a = r["ardupilot"]
    lines += [
        f"- posErr = ∛(c0² + c6² + c11²) = {a['posErr']:.4f} → after the floor {a['posErr_after_VISO_POS_M_NSE']:.4f}"
        f" → EKF3 horizontal position σ {a['ekf3_pos_sigma_m']:.4f} m (robotd's σx, σy: {s['x']:.4f}, {s['y']:.4f} m)",
        f"- angErr = ∛(c15² + c18² + c20²) = {a['angErr']:.3g} → after the floor {a['angErr_after_VISO_YAW_M_NSE']:.4f}"
        f" → EKF3 yaw σ {a['ekf3_yaw_sigma_rad']:.4f} rad (robotd's σyaw: {s['yaw']:.4g} rad)",
        "",
        f"PX4 (EKF2_EVP_NOISE {args.evp_noise}, EKF2_EVA_NOISE {args.eva_noise}):",
        "",
    ]
    for md, p in r["px4"].items():
        lines.append(
            f"- EKF2_EV_NOISE_MD = {md}: position σ x y z = "
            + ", ".join(f"{p[k]:.4f}" for k in ("ekf2_pos_sigma_m_x", "ekf2_pos_sigma_m_y", "ekf2_pos_sigma_m_z"))
            + f" m, yaw σ {p['ekf2_yaw_sigma_rad']:.4f} rad"
        )
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--source", default=f"kitti://{DEFAULT_DATA / 'kitti-seq1'}")
    ap.add_argument("--frame", type=int, default=-1, help="frame index (negative: from the end)")
    ap.add_argument("--out", default="", help="directory for T.txt / T.cov.txt (default: a temporary one)")
    ap.add_argument("--viso-pos-m-nse", type=float, default=0.2)
    ap.add_argument("--viso-yaw-m-nse", type=float, default=0.2)
    ap.add_argument("--evp-noise", type=float, default=0.1)
    ap.add_argument("--eva-noise", type=float, default=0.1)
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    for name in ("viso_pos_m_nse", "viso_yaw_m_nse", "evp_noise", "eva_noise"):
        v = getattr(a, name)
        if not (math.isfinite(v) and v > 0):
            raise SystemExit(f"--{name.replace('_', '-')}: expected a number > 0, got {v}")
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(a.out) if a.out else Path(tmp)
        if not out.is_dir():
            raise SystemExit(f"--out {out}: not a directory")
        res, q, wrote = replay_frame(a.source, a.frame, out)
        if not a.out:
            wrote = {**wrote, "trajectory": "(temporary)", "covariance": "(temporary)"}
    o = send_and_receive(res.pose, q)
    c = list(o.pose_covariance)
    r = report(
        res,
        q,
        wrote,
        o,
        ardupilot(c, a.viso_pos_m_nse, a.viso_yaw_m_nse),
        {str(md): px4(c, a.evp_noise, a.eva_noise, md) for md in (0, 1)},
    )
    print(json.dumps(r) if a.json else markdown(r, a))


if __name__ == "__main__":
    main()
