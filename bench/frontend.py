"""Front end on real KITTI frames: SIFT, SURF and ORB at full and OAK-D resolution (docs/math.md §12.6).

For each detector and resolution the 51-frame sequence runs through ``Frontend.process`` with the
previous frame as the identification reference (no filter). Reported per frame: features (left),
stereo matches, identified landmarks (outlier-stage inliers), inlier ratio (inliers / putative map
matches), milliseconds per stage (median, p95), and the frame-to-frame motion against the
ground-truth relative poses: median |t_est − t_gt| / |t_gt| and rotation error.

The 640×400 variant scales the rectified pair uniformly by 640/1226 (so f, p_x, p_y scale by the
same factor and the rig keeps one f) and pads it with black rows to 400 lines, i.e. the OAK-D's
pixel count with KITTI's geometry. Prints a Markdown table, or one JSON object with --json.

    python bench/frontend.py [--data ../shared/data/kitti-seq1] [--frames 51] [--json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from robotd.core.geometry import R_ROBOT_OPTICAL, se3, se3_inverse
from robotd.core.stereo import RectifiedStereo
from robotd.frontend.detectors import DetectorParams, surf_available
from robotd.frontend.frontend import Frontend, FrontendParams

STAGES = ("detect", "stereo", "identify", "outliers", "motion", "total")


def _bar(total: int, unit: str, desc: str) -> Any:
    """The benchmark's progress on stderr (robotd.tools.progress); cleared at the end, so the table or the
    JSON object on stdout is all that stays."""
    from robotd.tools.progress import progress_bar

    return progress_bar(total, unit, desc, leave=False, mininterval=0.5)


def load_kitti(root: Path) -> tuple[RectifiedStereo, np.ndarray, list[Path], list[Path]]:
    """Rig (calib.txt P0/P1), robot-frame ground truth T_R0_Rk (N, 4, 4) and the image paths."""
    rows = []
    for line in (root / "calib.txt").read_text().splitlines():
        vals = line.split(":", 1)[-1].split()
        if len(vals) == 12:
            rows.append(np.array(vals, dtype=float).reshape(3, 4))
    if len(rows) < 2:
        raise SystemExit(f"{root / 'calib.txt'}: expected P0 and P1 rows of 12 numbers, got {len(rows)} rows")
    P0, P1 = rows[0], rows[1]
    b = -P1[0, 3] / P1[0, 0]
    left = sorted((root / "image_l").glob("*.png"))
    right = sorted((root / "image_r").glob("*.png"))
    h, w = cv2.imread(str(left[0]), cv2.IMREAD_GRAYSCALE).shape
    rig = RectifiedStereo(P0[0, 0], P0[0, 2], P0[1, 2], b, w, h)
    poses = np.loadtxt(root / "poses.txt").reshape(-1, 3, 4)
    T = np.tile(np.eye(4), (poses.shape[0], 1, 1))
    T[:, :3, :] = poses
    # left optical frame -> robot frame (baseline centre, FRD): T_R0_Rk = T_R_C T_C0_Ck T_C_R
    T_C_R = se3(R_ROBOT_OPTICAL.T, np.array([b / 2.0, 0.0, 0.0]))
    return rig, se3_inverse(T_C_R) @ se3_inverse(T[0]) @ T @ T_C_R, left, right


def scaled(rig: RectifiedStereo, width: int, height: int) -> tuple[RectifiedStereo, float, int]:
    """Uniform scale to ``width`` and vertical padding to ``height``: (rig, scale, top padding)."""
    s = width / rig.width
    h_scaled = round(rig.height * s)
    if h_scaled > height:
        raise SystemExit(f"cannot fit {rig.width}×{rig.height} into {width}×{height} by uniform scaling")
    top = (height - h_scaled) // 2
    # pixel centres at integers: x' = s (x + 0.5) − 0.5
    px = s * (rig.px + 0.5) - 0.5
    py = s * (rig.py + 0.5) - 0.5 + top
    return RectifiedStereo(rig.f_px * s, px, py, rig.baseline_m, width, height), s, top


def prepare(img: np.ndarray, s: float, top: int, width: int, height: int) -> np.ndarray:
    if s == 1.0:
        return img
    small = cv2.resize(img, (width, round(img.shape[0] * s)), interpolation=cv2.INTER_AREA)
    out = np.zeros((height, width), np.uint8)
    out[top : top + small.shape[0]] = small
    return out


def run_one(
    name: str,
    rig0: RectifiedStereo,
    T_gt: np.ndarray,
    left: list[Path],
    right: list[Path],
    n_frames: int,
    size: tuple[int, int] | None,
    seed: int,
    tick: Callable[[], None] = lambda: None,
) -> dict:
    """One detector at one resolution over the sequence; ``tick()`` after each frame (outside
    ``Frontend.process``, whose stage times are the figures)."""
    if size is None:
        rig, s, top = rig0, 1.0, 0
        label = f"{rig0.width}x{rig0.height}"
    else:
        rig, s, top = scaled(rig0, *size)
        label = f"{size[0]}x{size[1]}"
    # the per-frame cap is the detector default (1000); SURF's Hessian threshold is its default
    fe = Frontend(rig, FrontendParams(detector=DetectorParams(name=name)), np.random.default_rng(seed))
    feats, stereo, ident, ratio, t_err, r_err = [], [], [], [], [], []
    ms: dict[str, list[float]] = {k: [] for k in STAGES}
    for k in range(min(n_frames, len(left))):
        L = prepare(cv2.imread(str(left[k]), cv2.IMREAD_GRAYSCALE), s, top, rig.width, rig.height)
        R = prepare(cv2.imread(str(right[k]), cv2.IMREAD_GRAYSCALE), s, top, rig.width, rig.height)
        r = fe.process(L, R, k * 100_000_000)
        tick()
        feats.append(r.counts["features_left"])
        stereo.append(r.counts["stereo_matches"])
        for st in STAGES:
            ms[st].append(r.timings_ms.get(st, 0.0))
        if k == 0:
            continue
        ident.append(r.counts["inliers"])
        if r.counts["map_matches"]:
            ratio.append(r.counts["inliers"] / r.counts["map_matches"])
        gt = se3_inverse(T_gt[k - 1]) @ T_gt[k]
        if r.T_prev_curr is None:
            t_err.append(np.inf)  # lost: counts as a failure in the median
            r_err.append(np.inf)
            continue
        t_err.append(float(np.linalg.norm(r.T_prev_curr[:3, 3] - gt[:3, 3]) / np.linalg.norm(gt[:3, 3])))
        dR = r.T_prev_curr[:3, :3] @ gt[:3, :3].T
        r_err.append(float(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1)))))
    te = np.array(t_err)
    return {
        "detector": name,
        "resolution": label,
        "frames": len(feats),
        "features_per_frame": float(np.mean(feats)),
        "stereo_matches": float(np.mean(stereo)),
        "identified_landmarks": float(np.mean(ident)) if ident else 0.0,
        "inlier_ratio": float(np.mean(ratio)) if ratio else 0.0,
        "ms": {st: {"median": float(np.median(v)), "p95": float(np.percentile(v, 95))} for st, v in ms.items()},
        "median_rel_translation_error": float(np.median(te)) if te.size else None,
        "p95_rel_translation_error": float(np.percentile(te, 95)) if te.size else None,
        "median_rotation_error_deg": float(np.median(r_err)) if r_err else None,
        "motion_failures": int(np.sum(~np.isfinite(te))),
    }


def main(argv: list[str] | None = None) -> int:
    default = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "kitti-seq1"
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=default, help="KITTI folder (calib.txt, poses.txt, image_l, image_r)")
    ap.add_argument("--frames", type=int, default=51)
    ap.add_argument("--detectors", default="sift,surf,orb")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    if not (args.data / "calib.txt").exists():
        print(
            f"KITTI data not found at {args.data} (expected calib.txt, poses.txt, image_l/, image_r/)", file=sys.stderr
        )
        return 2
    rig, T_gt, left, right = load_kitti(args.data)
    names = [n.strip() for n in args.detectors.split(",") if n.strip()]
    skipped = []
    if "surf" in names and not surf_available():
        names.remove("surf")
        skipped.append("surf (robotd.frontend.surf not importable)")
    t0 = time.perf_counter()
    results = []
    n_frames = min(args.frames, len(left))
    with _bar(len(names) * 2 * n_frames, "frame", "frontend") as bar:
        for name in names:
            for size in (None, (640, 400)):
                bar.set_postfix_str(f"{name} {'full' if size is None else f'{size[0]}x{size[1]}'}")
                results.append(
                    run_one(name, rig, T_gt, left, right, args.frames, size, args.seed, lambda: bar.update(1))
                )
    wall = time.perf_counter() - t0
    full = f"{rig.width}x{rig.height}"
    summary = {r["detector"]: r["median_rel_translation_error"] for r in results if r["resolution"] == full}
    if args.json:
        out = {
            "benchmark": "frontend",
            "data": str(args.data),
            "frames": args.frames,
            "seed": args.seed,
            "conditions": "frame-to-frame reference (no filter map), default FrontendParams, max 1000 features",
            "skipped": skipped,
            "wall_s": wall,
            "median_rel_translation_error": summary,
            "results": results,
        }
        json.dump(out, sys.stdout)
        sys.stdout.write("\n")
        return 0
    print(f"Front end on {args.data.name}, {args.frames} frames (frame-to-frame reference)\n")
    print(
        "| detector | resolution | features | stereo matches | identified | inlier ratio | detect ms (med/p95) "
        "| stereo ms | identify ms | outliers ms | motion ms | total ms | median rel. t error | median rot. error ° |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in results:
        m = r["ms"]
        cells = " | ".join(f"{m[s]['median']:.1f} / {m[s]['p95']:.1f}" for s in STAGES)
        print(
            f"| {r['detector']} | {r['resolution']} | {r['features_per_frame']:.0f} | {r['stereo_matches']:.0f} "
            f"| {r['identified_landmarks']:.0f} | {r['inlier_ratio']:.2f} | {cells} "
            f"| {r['median_rel_translation_error']:.4f} | {r['median_rotation_error_deg']:.3f} |"
        )
    if skipped:
        print(f"\nskipped: {', '.join(skipped)}")
    print(f"\nwall time {wall:.1f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
