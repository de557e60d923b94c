#!/usr/bin/env python3
"""What each rung of the latency budget costs in accuracy, and what it saves in time (issue 25).

The daemon's latency budget (robotd/daemon/budget.py) steps down a ladder when frames take longer
than the frame period: fewer features (halving down to ``budget.min_features``), then fewer
particles (down to ``budget.min_particles``), then one frame in k. This bench runs every rung of
the default configuration's ladder as a fixed setting through ``robotd.tools.replay.replay`` on the
shared KITTI folders and on ``sim://``: the features and particles of the rung, and for a
skipping rung the source replayed with ``stride=k`` (what processing one frame in k leaves the
filter). Per rung and source: ATE, drift, lost frames and the step's median time; then the rungs
ordered by ATE lost per millisecond saved against L0, averaged over the sources (the order a
budget should take them in).

    python bench/budget_accuracy.py [--json] [--folders kitti-seq1,kitti-raw-0009] [--sim URL] [--quick]

Step times are only comparable run to run on an otherwise idle machine (the bench runs one replay
at a time and says the load average).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from pathlib import Path
from typing import Any

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_WAIT_POLICY", "passive")

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from robotd.config import Config, load_config  # noqa: E402
from robotd.daemon.budget import LatencyBudget  # noqa: E402
from robotd.tools.replay import replay  # noqa: E402

DEFAULT_DATA = Path(os.environ.get("ROBOTD_SHARED_DATA", REPO.parent / "shared" / "data"))
SIM_DEFAULT = "sim://?duration=10&realtime=0&odometry=0"


def ladder(cfg: Config) -> list[tuple[int, int, int]]:
    """(features, particles, one frame in k) of every rung of the daemon's ladder, L0 first."""
    b = LatencyBudget(
        33.3,
        cfg.frontend.max_features,
        cfg.slam.n_particles,
        min(cfg.budget.min_features, cfg.frontend.max_features),
        min(cfg.budget.min_particles, cfg.slam.n_particles),
    )
    out = []
    for level in range(b.max_level + 1):
        b.level = level
        s = b.state
        out.append((s.max_features, s.n_particles, s.skip_every))
    return out


def with_stride(source: str, k: int) -> str:
    if k == 1:
        return source
    if source.startswith("sim://"):
        # the simulated camera at 1/k of its rate: the frames a 1-in-k budget leaves
        fps = 30.0 / k
        return source + ("&" if "?" in source else "?") + f"fps={fps:g}"
    return source + ("&" if "?" in source else "?") + f"stride={k}"


def run_rung(source: str, features: int, particles: int, k: int) -> dict[str, Any]:
    cfg = load_config(None, {"frontend": {"max_features": features}, "slam": {"n_particles": particles}})
    s = replay(cfg, with_stride(source, k), progress=False)
    return {
        "ate_m": s.get("truth_ate_rmse_m"),
        "drift_pct": s.get("truth_drift_pct"),
        "lost": s.get("lost_frames"),
        "frames": s.get("frames"),
        # per processed frame; a 1-in-k rung spends it on every k-th frame only
        "step_ms_p50": s.get("step_ms_p50"),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--folders", default="kitti-seq1,kitti-raw-0009", help="folders under ../shared/data")
    ap.add_argument("--sim", action="append", default=None, help=f"sim:// URL(s) (default {SIM_DEFAULT})")
    ap.add_argument("--quick", action="store_true", help="L0, the last feature rung, the last particle rung, 1 in 2")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    cfg = load_config(None, {})
    rungs = ladder(cfg)
    levels = list(range(len(rungs)))
    if args.quick:
        last_f = max(i for i, r in enumerate(rungs) if r[1] == rungs[0][1] and r[2] == 1)
        last_p = max(i for i, r in enumerate(rungs) if r[2] == 1)
        levels = sorted({0, last_f, last_p, last_p + 1})
    sources = [f"kitti://{DEFAULT_DATA / f}" for f in args.folders.split(",") if (DEFAULT_DATA / f).is_dir()]
    sources += args.sim or [SIM_DEFAULT]
    rows: list[dict[str, Any]] = []
    for src in sources:
        for level in levels:
            f, p, k = rungs[level]
            print(f"{src}: L{level} ({f} features, {p} particles, 1 in {k})", file=sys.stderr, flush=True)
            r = run_rung(src, f, p, k)
            rows.append({"source": src, "level": level, "features": f, "particles": p, "skip": k, **r})
    # per rung: ATE lost against L0 per ms saved (per frame period: a 1-in-k rung saves (k-1)/k of L0's
    # step on average and spends its own on one frame in k), averaged over the sources
    order = []
    for level in levels:
        if level == 0:
            continue
        costs = []
        for src in sources:
            base = next(r for r in rows if r["source"] == src and r["level"] == 0)
            here = next(r for r in rows if r["source"] == src and r["level"] == level)
            if base["ate_m"] is None or here["ate_m"] is None:
                continue
            saved = base["step_ms_p50"] - here["step_ms_p50"] / here["skip"]
            lost = here["ate_m"] - base["ate_m"]
            costs.append((lost, saved))
        if costs:
            lost = sum(c[0] for c in costs) / len(costs)
            saved = sum(c[1] for c in costs) / len(costs)
            order.append(
                {
                    "level": level,
                    "ate_lost_m": lost,
                    "ms_saved": saved,
                    "mm_per_ms": 1e3 * lost / saved if saved > 0 else math.inf,
                }
            )
    order.sort(key=lambda o: o["mm_per_ms"])
    info = {"load1": os.getloadavg()[0], "cpus": os.cpu_count()}
    if args.json:
        print(json.dumps({"machine": info, "rungs": rows, "order": order}))
        return 0
    print(f"Budget rungs as fixed settings, one replay at a time ({info['cpus']} CPUs, load {info['load1']:.2f})\n")
    print("| source | rung | features | particles | 1 in k | frames | lost | ATE m | drift % | step p50 ms |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        name = r["source"].split("/")[-1] if r["source"].startswith("kitti") else r["source"]
        ate = "n/a" if r["ate_m"] is None else f"{r['ate_m']:.3f}"
        drift = "n/a" if r["drift_pct"] is None else f"{r['drift_pct']:.2f}"
        print(
            f"| {name} | L{r['level']} | {r['features']} | {r['particles']} | {r['skip']} | {r['frames']} | "
            f"{r['lost']} | {ate} | {drift} | {r['step_ms_p50']:.1f} |"
        )
    print("\nRungs by ATE lost per millisecond saved a frame period (mean over the sources; cheapest first)\n")
    print("| rung | ATE lost mm | ms saved | mm per ms |")
    print("|---|---|---|---|")
    for o in order:
        print(f"| L{o['level']} | {1e3 * o['ate_lost_m']:+.1f} | {o['ms_saved']:.1f} | {o['mm_per_ms']:+.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
