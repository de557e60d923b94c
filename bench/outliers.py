"""Outlier detectors under injected mismatches (docs/math.md §12.3, simulated part).

For each mismatch rate and seed, one frame of putative correspondences from
``robotd.research.synthetic_pairs.simulate_pairs`` (OAK-D rig, stereo-consistent noise, half of the
mismatches to a landmark 0.25–1 m from the true one) goes through each detector:

- similarity_mahalanobis: the thesis's detector (§5.1–§5.3), χ²₃,0.99 = 11.345;
- similarity_euclidean: the same with |e| < 0.2 m;
- fundamental: normalised 8-point F, Sampson ≤ 3.84 px² (§5.4), on the same pairs' pixels.

recall = fraction of injected mismatches rejected; false_rejection = fraction of correct pairs
rejected; ms = mean time per call. Prints a Markdown table, or one JSON object with --json.

    python bench/outliers.py [--seeds 20] [--n 40] [--json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from robotd.core.outliers import OutlierParams, ransac_fundamental, ransac_similarity
from robotd.research.synthetic_pairs import simulate_pairs

RATES = (0.0, 0.05, 0.1, 0.2, 0.3, 0.4, 0.5)
DETECTORS = ("similarity_mahalanobis", "similarity_euclidean", "fundamental")


def _bar(total: int, unit: str, desc: str) -> Any:
    """The benchmark's progress on stderr (robotd.tools.progress); cleared at the end, so the table or the
    JSON object on stdout is all that stays."""
    from robotd.tools.progress import progress_bar

    return progress_bar(total, unit, desc, leave=False, mininterval=0.5)


def run(seeds: int, n: int, rates: tuple[float, ...], tick: Callable[[], None] = lambda: None) -> list[dict]:
    """``tick()`` after each (rate, seed) frame, outside the timed detector calls."""
    results = []
    for rate in rates:
        acc: dict[str, dict[str, list[float]]] = {
            d: {"tp": [], "bad": [], "fr": [], "good": [], "ms": []} for d in DETECTORS
        }
        for seed in range(seeds):
            data = simulate_pairs(np.random.default_rng(seed), n=n, mismatch_rate=rate)
            for det in DETECTORS:
                rng = np.random.default_rng(1000 + seed)
                t0 = time.perf_counter()
                if det == "fundamental":
                    res = ransac_fundamental(data.x1, data.x2, OutlierParams(method=det), rng)
                else:
                    res = ransac_similarity(data.a, data.b, data.A, data.B, OutlierParams(method=det), rng)
                ms = (time.perf_counter() - t0) * 1e3
                rejected = ~res.inliers
                a = acc[det]
                a["tp"].append(float(np.sum(rejected & data.is_mismatch)))
                a["bad"].append(float(np.sum(data.is_mismatch)))
                a["fr"].append(float(np.sum(rejected & ~data.is_mismatch)))
                a["good"].append(float(np.sum(~data.is_mismatch)))
                a["ms"].append(ms)
            tick()
        for det in DETECTORS:
            a = acc[det]
            bad, good = sum(a["bad"]), sum(a["good"])
            results.append(
                {
                    "detector": det,
                    "mismatch_rate": rate,
                    "recall": (sum(a["tp"]) / bad) if bad else None,
                    "false_rejection": sum(a["fr"]) / good if good else None,
                    "ms": float(np.mean(a["ms"])),
                    "ms_p95": float(np.percentile(a["ms"], 95)),
                }
            )
    return results


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--n", type=int, default=40, help="putative correspondences per frame")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    with _bar(len(RATES) * args.seeds, "frame", "outliers") as bar:
        results = run(args.seeds, args.n, RATES, lambda: bar.update(1))
    wall = time.perf_counter() - t0
    if args.json:
        out = {
            "benchmark": "outliers",
            "seeds": args.seeds,
            "n_pairs": args.n,
            "rig": "OAK-D 640x400 f=430 b=0.0755, depth 0.5-5 m, sigma 0.5 px",
            "near_mismatch_fraction": 0.5,
            "wall_s": wall,
            "results": results,
        }
        json.dump(out, sys.stdout)
        sys.stdout.write("\n")
        return 0

    def fmt(v: float | None) -> str:
        return "—" if v is None else f"{v:.3f}"

    print(f"Outlier detectors, {args.seeds} seeds × {args.n} pairs per rate (OAK-D sim, σ 0.5 px)\n")
    print("| detector | mismatch rate | recall | false rejection | ms (mean) | ms (p95) |")
    print("|---|---|---|---|---|---|")
    for r in results:
        print(
            f"| {r['detector']} | {r['mismatch_rate']:.2f} | {fmt(r['recall'])} | {fmt(r['false_rejection'])} "
            f"| {r['ms']:.2f} | {r['ms_p95']:.2f} |"
        )
    print(f"\nwall time {wall:.1f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
