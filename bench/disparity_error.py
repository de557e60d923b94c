"""How robotd's stereo disparity is wrong, against the exact disparity of the rendered world (issue 26).

Renders frames of a ``sim://`` source (default: the open-terrain world at car pace), runs the
front end's own detector and stereo matcher (robotd.frontend.Frontend with the default
configuration, or ``--config FILE``) on each pair, and compares each match's measured disparity
x_L − x_R with the true one at the left keypoint, f·b / Z, Z from the renderer's depth buffer
(inverse depth interpolated bilinearly at the sub-pixel keypoint; the rectified pair is exact, so
every error is the matcher's). Matches are binned by true disparity; per bin: the count, the
mean, standard deviation and median of (measured − true) [px] over the matches within ±``--gross``
px, the share of gross errors beyond it, and the same split into matches whose (2h+1)² patch of
the sub-pixel refinement lies on one plane ("one depth": inverse depth within 2 % of a plane) and
those whose patch straddles a depth edge ("edge": a tree crown against the hills or the sky, a
post against the field) or touches the sky.

The far limit ``frontend.disparity_min_px`` (5 px by default) is lowered to ``--d-min`` (0.5 px)
so the far bins are measured too; the table marks which bins the default front end keeps.
``--refine keypoint`` measures the keypoints' own disparity (no patch refinement).

    python bench/disparity_error.py [--url URL] [--frames N] [--step K] [--d-min 0.5]
        [--refine patch|keypoint] [--config FILE] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from drivers import open_camera
from robotd.config import load_config
from robotd.config.params import frontend_params_from_config
from robotd.frontend.frontend import Frontend

DEFAULT_URL = "sim://?world=open_terrain&speed=5&fps=5&realtime=0"
BINS = ((0.0, 3.0), (3.0, 5.0), (5.0, 10.0), (10.0, 20.0), (20.0, np.inf))
EDGE_REL = 0.02  # inverse depth off a plane by more than this (relative) over the patch: an edge


def true_disparity(depth: np.ndarray, x: np.ndarray, y: np.ndarray, fb: float) -> np.ndarray:
    """f·b / Z at sub-pixel (x, y): inverse depth interpolated bilinearly (it is affine in the pixel
    on a plane); NaN where a neighbour is sky."""
    h, w = depth.shape
    iz = np.where(np.isfinite(depth), 1.0 / depth, np.nan)
    x0 = np.clip(np.floor(x).astype(int), 0, w - 2)
    y0 = np.clip(np.floor(y).astype(int), 0, h - 2)
    ax, ay = x - x0, y - y0
    v = (
        iz[y0, x0] * (1 - ax) * (1 - ay)
        + iz[y0, x0 + 1] * ax * (1 - ay)
        + iz[y0 + 1, x0] * (1 - ax) * ay
        + iz[y0 + 1, x0 + 1] * ax * ay
    )
    return fb * v  # type: ignore[no-any-return]


def patch_on_one_surface(depth: np.ndarray, x: np.ndarray, y: np.ndarray, half: int) -> np.ndarray:
    """(N,) True where the (2·half+1)² patch at (rint x, rint y) lies on one plane: no sky, and
    its inverse depth (affine in the pixel on a plane) fits a plane to within ``EDGE_REL`` of its
    centre's. False at a depth edge (a crown against the hills or the sky, a post against the
    field) and for patches that leave the image."""
    h, w = depth.shape
    n = 2 * half + 1
    dy, dx = np.mgrid[-half : half + 1, -half : half + 1]
    A = np.stack([dx.ravel(), dy.ravel(), np.ones(n * n)], 1)
    proj = A @ np.linalg.pinv(A)  # (n², n²): the plane fit
    iz = np.where(np.isfinite(depth), 1.0 / depth, np.nan)
    c, r = np.rint(x).astype(int), np.rint(y).astype(int)
    out = np.zeros(len(x), bool)
    inside = (c >= half) & (c < w - half) & (r >= half) & (r < h - half)
    for i in np.flatnonzero(inside):
        p = iz[r[i] - half : r[i] + half + 1, c[i] - half : c[i] + half + 1].ravel()
        if np.all(np.isfinite(p)):
            out[i] = float(np.max(np.abs(p - proj @ p))) <= EDGE_REL * float(p[n * n // 2])
    return out


def _stats(err: np.ndarray, gross: float) -> dict[str, Any]:
    """Count, and over the errors within ±gross: mean, its standard error, std and median; and the
    share beyond."""
    good = np.abs(err) <= gross
    e = err[good]
    return {
        "n": int(err.size),
        "mean_px": float(e.mean()) if e.size else None,
        "sem_px": float(e.std(ddof=1) / np.sqrt(e.size)) if e.size > 1 else None,
        "std_px": float(e.std(ddof=1)) if e.size > 1 else None,
        "median_px": float(np.median(e)) if e.size else None,
        "gross_frac": float(1.0 - good.mean()) if err.size else None,
    }


def run(url: str, frames: int, step: int, d_min: float, refine: str, config: str | None, gross: float) -> dict:
    cfg = load_config(config, {"frontend": {"disparity_min_px": d_min}})
    default_d_min = load_config(config, {}).frontend.disparity_min_px
    params = frontend_params_from_config(cfg)
    params = replace(params, stereo=replace(params.stereo, refine=refine))
    rows: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    t0 = time.perf_counter()
    with open_camera(url) as cam:
        rig = cam.rectified_model()
        fe = Frontend(rig, params)
        half = params.stereo.patch_half_px
        for k in range(0, frames * step, step):
            frame, depth = cam.render(k)  # type: ignore[attr-defined]
            feats = fe.detect(frame.left, frame.right)
            m = fe.match_stereo(feats, frame.left, frame.right)
            d_true = true_disparity(depth, m.xl, m.y, rig.fb)
            ok = np.isfinite(d_true)
            one = patch_on_one_surface(depth, m.xl, m.y, half)
            rows.append(((m.xl - m.xr)[ok], d_true[ok], one[ok]))
    d_meas = np.concatenate([r[0] for r in rows])
    d_true = np.concatenate([r[1] for r in rows])
    one = np.concatenate([r[2] for r in rows])
    err = d_meas - d_true
    table = []
    for lo, hi in BINS:
        sel = (d_true >= lo) & (d_true < hi)
        table.append(
            {
                "bin_px": [lo, None if np.isinf(hi) else hi],
                "kept_by_default": bool(lo >= default_d_min),
                "all": _stats(err[sel], gross),
                "one_depth": _stats(err[sel & one], gross),
                "edge": _stats(err[sel & ~one], gross),
            }
        )
    return {
        "url": url,
        "frames": frames,
        "step": step,
        "width": rig.width,
        "height": rig.height,
        "f_px": rig.f_px,
        "baseline_m": rig.baseline_m,
        "fb_px_m": rig.fb,
        "detector": cfg.frontend.detector,
        "refine": refine,
        "d_min_px": d_min,
        "default_d_min_px": default_d_min,
        "gross_px": gross,
        "matches": int(err.size),
        "seconds": round(time.perf_counter() - t0, 1),
        "loadavg_1min": os.getloadavg()[0],
        "bins": table,
    }


def _f(v: float | None, fmt: str = "+.3f") -> str:
    return "–" if v is None else format(v, fmt)


def print_table(res: dict) -> None:
    print(
        f"{res['url']}: {res['frames']} frames (every {res['step']}), {res['width']}×{res['height']}, "
        f"f = {res['f_px']:.1f} px, b = {res['baseline_m']} m (fb = {res['fb_px_m']:.1f} px·m), "
        f"{res['detector']}, refine = {res['refine']}, d ≥ {res['d_min_px']} px "
        f"(the default keeps d ≥ {res['default_d_min_px']}), {res['matches']} matches\n"
    )
    print(
        f"measured − true disparity [px] over |error| ≤ {res['gross_px']:g} px (± its standard error); gross: beyond\n"
    )
    head = ["true d [px]", "depth [m]", "kept", "n", "mean", "std", "median", "gross"]
    head += ["one depth: n", "mean", "std", "edge: n", "mean", "std"]
    print("| " + " | ".join(head) + " |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    fb = res["fb_px_m"]
    for b in res["bins"]:
        lo, hi = b["bin_px"]
        depth = f"{fb / hi if hi is not None else 0:.0f}–{'∞' if lo == 0 else f'{fb / lo:.0f}'}"
        label = f"{lo:g}–{hi:g}" if hi is not None else f"> {lo:g}"
        a, o, e = b["all"], b["one_depth"], b["edge"]
        cells = [label, depth, "yes" if b["kept_by_default"] else "no", str(a["n"])]
        cells += [f"{_f(a['mean_px'])} ± {_f(a['sem_px'], '.3f')}", _f(a["std_px"], ".2f"), _f(a["median_px"])]
        cells += [_f(a["gross_frac"], ".3f"), str(o["n"]), f"{_f(o['mean_px'])} ± {_f(o['sem_px'], '.3f')}"]
        cells += [_f(o["std_px"], ".2f"), str(e["n"]), f"{_f(e['mean_px'])} ± {_f(e['sem_px'], '.3f')}"]
        cells += [_f(e["std_px"], ".2f")]
        print("| " + " | ".join(cells) + " |")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--url", default=DEFAULT_URL, help=f"a sim:// source (default {DEFAULT_URL})")
    ap.add_argument("--frames", type=int, default=12, help="frames to measure")
    ap.add_argument("--step", type=int, default=10, help="frame index step between them")
    ap.add_argument("--d-min", type=float, default=0.5, help="the matcher's smallest disparity [px]")
    ap.add_argument("--refine", choices=("patch", "keypoint"), default="patch")
    ap.add_argument("--gross", type=float, default=2.0, help="errors beyond this [px] count as gross")
    ap.add_argument("--config", default=None, help="TOML file as robotd replay --config")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    if not args.url.startswith("sim://"):
        ap.error("--url: a sim:// source (its renderer gives the true depth)")
    res = run(args.url, args.frames, args.step, args.d_min, args.refine, args.config, args.gross)
    if args.json:
        print(json.dumps(res))
    else:
        print_table(res)
    return 0


if __name__ == "__main__":
    sys.exit(main())
