#!/usr/bin/env python3
"""Filter consistency study (docs/math.md §11 NEES, §12 simulation world, 2D and 3D loops).

Runs EKF SLAM and FastSLAM 2.0 on the same simulated 2D loops under three measurement-noise models
(robotd.research.landmark_sim ``noise_model``):

- ``stereo``: §12's recipe, pixel noise then triangulation, Q from the noisy pixels (the default
  and what a real front end delivers);
- ``gaussian``: z ~ N(z_true, Q(z_true)), the stereo ellipsoid without its bias;
- ``isotropic``: z ~ N(z_true, σ²I), σ = 5 cm.

then on 3D loops (terrain with roll and pitch, landmark heights) of the same lengths with
``stereo`` noise only (``--noise3d``), and on a long 3D loop (``--long3d``, FastSLAM 2.0 only: the
EKF's O(M²) update would take hours there). It reports, per (dim, noise, path length, filter,
particles, option): ATE / batch bound (mean, max), the ANEES over the runs against its two-sided
95 % band, and the fraction of single steps whose NEES lies in the single-run 95 % interval. The
NEES is over the filter's pose state: (x, y, yaw) in 2D (n = 3), all six of (x, y, z, roll,
pitch, yaw) in 3D (n = 6), each row with the band of its n. ``--options`` adds FastSLAM 2.0 variants given as
SlamParams overrides, e.g. ``fs2_weights=sequential``, plus two study-only keys: ``q_scale`` and
``m_scale`` multiply the measurement (Q) and motion (M) covariances the filter is given (docs/math.md
§11's inflation remedy; the simulated noise is unchanged). The JSON also holds each case's mean
NEES in each tenth of the run (``nees_tenths``), printed as a second table.

    python bench/consistency.py [--seeds 6] [--lengths 12,40] [--particles 50]
        [--noise stereo,gaussian,isotropic] [--dims 2,3] [--noise3d stereo] [--long3d 120]
        [--options ""] [--json]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.stats import chi2

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from robotd.research.evaluate import anees_band
from robotd.research.experiments import make_scenario, run_filter
from robotd.research.landmark_sim import SimConfig, SimRun

STUDY_KEYS = ("q_scale", "m_scale", "covariance")  # option keys not passed to SlamParams


def _bar(total: int, unit: str, desc: str) -> Any:
    """The benchmark's progress on stderr (robotd.tools.progress); cleared at the end, so the table or the
    JSON object on stdout is all that stays."""
    from robotd.tools.progress import progress_bar

    return progress_bar(total, unit, desc, leave=False, mininterval=0.5)


def inflated(run: SimRun, q_scale: float, m_scale: float) -> SimRun:
    """The run with every observation covariance × ``q_scale`` and motion covariance × ``m_scale``."""
    if q_scale == 1.0 and m_scale == 1.0:
        return run
    steps = []
    for st in run.steps:
        obs = dataclasses.replace(st.observations, cov_R=st.observations.cov_R * q_scale)
        mot = None if st.motion is None else dataclasses.replace(st.motion, cov=st.motion.cov * m_scale)
        steps.append(dataclasses.replace(st, observations=obs, motion=mot))
    return dataclasses.replace(run, steps=steps)


def _parse_options(spec: str) -> list[dict[str, Any]]:
    """ "" -> [{}]; "a=b;c=d,e=f" -> [{}, {a: b}, {c: d, e: f}] (numbers parsed)."""
    out: list[dict[str, Any]] = [{}]
    for group in filter(None, spec.split(";")):
        d: dict[str, Any] = {}
        for kv in group.split(","):
            k, v = kv.split("=", 1)
            try:
                d[k] = float(v) if "." in v else int(v)
            except ValueError:
                d[k] = {"true": True, "false": False}.get(v.lower(), v)
        out.append(d)
    return out


@dataclass(frozen=True)
class World:
    """One simulated world of the study: dimension, noise model, loop length, whether the EKF runs."""

    dim: int
    noise: str
    path_m: float
    ekf: bool = True


def worlds(dims: list[int], lengths: list[float], noises: list[str], noises3d: list[str], long3d: float) -> list[World]:
    """The study's worlds in table order: 2D (every noise × length), 3D (``noises3d`` × length), the
    long 3D loop (``long3d`` m, 0 for none; FastSLAM only)."""
    out = []
    if 2 in dims:
        out += [World(2, n, L) for n in noises for L in lengths]
    if 3 in dims:
        out += [World(3, n, L) for n in noises3d for L in lengths]
        if long3d > 0:
            out += [World(3, n, long3d, ekf=False) for n in noises3d]
    return out


def run(seeds: int, ws: list[World], particles: list[int], options: str) -> list[dict]:
    results: list[dict] = []
    n_opt = len(particles) * len(_parse_options(options))
    n_cases = sum(int(w.ekf) + n_opt for w in ws)
    # the bar counts filter runs (seeds per case) and moves after each case, outside its "seconds"
    with _bar(n_cases * seeds, "run", "consistency") as bar:
        for w in ws:
            _run_world(results, bar, seeds, w, particles, options)
    return results


def _run_world(results: list[dict], bar: Any, seeds: int, w: World, particles: list[int], options: str) -> None:
    noise, L = w.noise, w.path_m
    # the NEES is over the filter's pose state: (x, y, yaw) in 2D, all six in 3D (run_filter)
    n_state = 3 if w.dim == 2 else 6
    lo1, hi1 = chi2.ppf(0.025, n_state), chi2.ppf(0.975, n_state)
    cfg = SimConfig(dim=w.dim, trajectory="loop", path_length_m=L, landmark_density_per_m2=0.5, noise_model=noise)
    scs = [make_scenario(cfg, s) for s in range(seeds)]
    cases: list[tuple[str, int, dict[str, Any]]] = [("ekf", 0, {})] if w.ekf else []
    cases += [("fastslam2", n, o) for n in particles for o in _parse_options(options)]
    for filt, n, opt in cases:
        bar.set_postfix_str(f"{w.dim}D {noise} {L:g} m {filt} {n or ''}".rstrip())
        t0 = time.perf_counter()
        if opt.get("measurement") == "pixel" and noise != "stereo":
            # the pixel model needs noise made in the pixels; gaussian / isotropic noise is
            # added to the 3-D point, so its rows would measure a model mismatch, not the filter
            bar.update(seeds)
            continue
        slam_opt = {k: v for k, v in opt.items() if k not in STUDY_KEYS}
        if slam_opt.get("measurement") == "pixel":
            # robotd's default model: the rig's pixels with the simulator's pixel noise
            slam_opt["stereo_intrinsics"] = (cfg.f_px, cfg.px, cfg.py, cfg.baseline_m)
            slam_opt["pixel_sigma_px"] = (cfg.sigma_px, cfg.sigma_px / np.sqrt(2.0))
        try:
            qs, ms = float(opt.get("q_scale", 1.0)), float(opt.get("m_scale", 1.0))
        except (TypeError, ValueError):
            raise SystemExit(f"--options: q_scale and m_scale must be numbers, got {opt}") from None
        if not (qs > 0 and ms > 0 and np.isfinite(qs) and np.isfinite(ms)):
            raise SystemExit(f"--options: q_scale and m_scale must be finite and > 0, got {qs}, {ms}")
        runs = [
            run_filter(
                inflated(sc.run, qs, ms),
                filt,
                s,
                n_particles=max(n, 1),
                batch_ate=sc.batch_ate,
                overrides=slam_opt,
                covariance=str(opt.get("covariance", "consistent")),
            )
            for s, sc in enumerate(scs)
        ]
        ratio = np.array([r.ate_ratio for r in runs])
        E = np.concatenate([r.nees for r in runs])
        lo, hi = anees_band(n_state, seeds)
        anees = float(np.mean([np.mean(r.nees) for r in runs]))
        results.append(
            {
                "dim": w.dim,
                "noise": noise,
                "path_m": L,
                "filter": filt,
                "particles": n,
                "option": ",".join(f"{k}={v}" for k, v in opt.items()) or "-",
                "batch_ate_m": float(np.mean([sc.batch_ate for sc in scs])),
                "ate_ratio_mean": float(ratio.mean()),
                "ate_ratio_max": float(ratio.max()),
                "nees_dim": n_state,
                "anees": anees,
                "anees_band": [lo, hi],
                "in_band": bool(lo <= anees <= hi),
                "steps_in_interval": float(np.mean((E > lo1) & (E < hi1))),
                "resamples_mean": float(np.mean([r.n_resamples for r in runs])),
                "nees_tenths": [
                    float(np.mean(part)) for part in np.array_split(np.mean([r.nees for r in runs], 0), 10)
                ],
                "seconds": time.perf_counter() - t0,
            }
        )
        bar.write(f"  {results[-1]}", file=sys.stderr)  # above the bar (plain line when it is off)
        bar.update(seeds)


def table(results: list[dict], seeds: int) -> str:
    lines = [
        f"Loops, 0.5 landmarks/m², {seeds} seeds; ANEES = mean over runs of the per-run mean NEES over the "
        "pose state (2D: x, y, yaw, n = 3; 3D: x, y, z, roll, pitch, yaw, n = 6; band: two-sided 95 %); "
        "steps = fraction of single-step NEES in the single-run 95 % interval of χ²(n)",
        "",
        "| dim | noise | path m | filter | N | option | batch ATE m | ATE/batch | max | ANEES | band | in band "
        "| steps |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        lo, hi = r["anees_band"]
        lines.append(
            f"| {r.get('dim', 2)}D | {r['noise']} | {r['path_m']:g} | {r['filter']} | {r['particles'] or '-'} "
            f"| {r['option']} "
            f"| {r['batch_ate_m']:.3f} | {r['ate_ratio_mean']:.2f} | {r['ate_ratio_max']:.2f} "
            f"| {r['anees']:.3g} | {lo:.2f}–{hi:.2f} | {'yes' if r['in_band'] else 'no'} "
            f"| {r['steps_in_interval']:.2f} |"
        )
    lines += ["", "Mean NEES over the runs in each tenth of the run, and resamplings per run", ""]
    lines += [
        "| dim | noise | path m | filter | N | option | NEES by tenth | resamples |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        tenths = " ".join(f"{v:.3g}" for v in r["nees_tenths"])
        lines.append(
            f"| {r.get('dim', 2)}D | {r['noise']} | {r['path_m']:g} | {r['filter']} | {r['particles'] or '-'} "
            f"| {r['option']} | {tenths} | {r['resamples_mean']:.0f} |"
        )
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=6)
    ap.add_argument("--lengths", default="12,40")
    ap.add_argument("--particles", default="50")
    ap.add_argument("--noise", default="stereo,gaussian,isotropic", help="2D noise models")
    ap.add_argument("--dims", default="2,3", help="2, 3 or 2,3")
    ap.add_argument("--noise3d", default="stereo", help="3D noise models")
    ap.add_argument("--long3d", type=float, default=120.0, help="the long 3D loop [m] (FastSLAM only); 0: none")
    ap.add_argument(
        "--options",
        default="measurement=pixel;covariance=filter;measurement=pixel,covariance=filter",
        help='FastSLAM variants: "k=v,k=v;k=v" (SlamParams overrides, plus q_scale, m_scale and covariance = '
        "consistent | filter, the reported covariance; measurement=pixel is robotd's default model)",
    )
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    try:
        dims = [int(x) for x in a.dims.split(",")]
        lengths = [float(x) for x in a.lengths.split(",")]
        particles = [int(x) for x in a.particles.split(",")]
    except ValueError as exc:
        raise SystemExit(f"--dims/--lengths/--particles: expected comma-separated numbers ({exc})") from None
    if not dims or any(d not in (2, 3) for d in dims):
        raise SystemExit(f"--dims: expected 2, 3 or 2,3, got {a.dims!r}")
    if not (a.long3d >= 0 and np.isfinite(a.long3d)):
        raise SystemExit(f"--long3d: expected a length >= 0 [m], got {a.long3d}")
    ws = worlds(dims, lengths, a.noise.split(","), a.noise3d.split(","), a.long3d)
    res = run(a.seeds, ws, particles, a.options)
    if a.json:
        print(json.dumps({"seeds": a.seeds, "results": res}))
    else:
        print(table(res, a.seeds))


if __name__ == "__main__":
    main()
