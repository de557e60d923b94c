"""Per-step latency of the SLAM filters (3D): FastSLAM 2.0 / 1.0 over particles × map size ×
observations, EKF SLAM against map size, resampling copy cost and memory per particle.

    python bench/fastslam.py            # full grid, Markdown tables
    python bench/fastslam.py --quick    # reduced grid, < 1 min
    python bench/fastslam.py --json     # exactly one JSON object on stdout
    python bench/fastslam.py --measurement pixel   # the filters with the stereo pixel model

A step is ``predict(inc)`` + ``update(obs)`` (including resampling when N_eff falls below N/2)
on a stationary robot re-observing ``observations`` landmarks of a map of ``map_size`` landmarks
that every particle already holds. The observed landmarks are drawn from a window of 2·observations
consecutive ids (landmarks seen together were mostly created together, which is what the
copy-on-write landmark blocks exploit); one extra row draws them from the whole map instead.
Landmark pruning is off except in the ``pruning on`` rows (the daemon's default: one visibility
pass over the best particle's whole map per frame; pruned ids are no longer observed there).
FastSLAM rows run the numba kernel with ``numba_threads`` threads (the target figure is one thread;
robotd has no other FastSLAM step since issue 28); the kernels are compiled (or loaded from cache)
before timing. With ``--measurement pixel`` the observations carry
the landmarks' pixels in a rectified pair (OAK-D-like rig, 0.5 px noise) and the filters use the
stereo pixel model (slam.measurement = "pixel").
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from functools import partial
from typing import Any

# One BLAS thread: the EKF's n×n updates are small dgemm calls, and OpenBLAS's worker threads
# spinning against the numba threads on a shared 2-core machine made them ~15× slower. The daemon
# should do the same (OPENBLAS_NUM_THREADS=1 in the service environment).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_WAIT_POLICY", "passive")  # as robotd.tools.cli: OpenMP workers sleep, not spin

import numpy as np

from robotd.core.geometry import euler_to_R
from robotd.core.msgs import MotionIncrement, Observations
from robotd.core.stereo import project, triangulate
from robotd.slam.ekf import EkfSlam
from robotd.slam.factory import estimator_kind, make_estimator
from robotd.slam.fastslam import FastSlam
from robotd.slam.params import SlamParams

SIGMA_Z = 0.03  # measurement noise [m]
SIGMA_PX = 0.5  # pixel noise of the pixel-model rows [px]
RIG = (432.0, 320.0, 200.0, 0.075)  # f [px], p_x, p_y [px], baseline [m]: an OAK-D at 640×400


def _bar(total: int, unit: str, desc: str) -> Any:
    """The benchmark's progress on stderr (robotd.tools.progress); cleared at the end, so the table or the
    JSON object on stdout is all that stays."""
    from robotd.tools.progress import progress_bar

    return progress_bar(total, unit, desc, leave=False, mininterval=0.5)


def _world(M: int, rng: np.random.Generator) -> np.ndarray:
    L = rng.uniform(-5.0, 5.0, (M, 3))
    L[:, 0] = np.abs(L[:, 0]) + 1.0  # in front of the robot
    return L


def _measure(q: np.ndarray, rng: np.random.Generator, pixel: bool) -> tuple[np.ndarray, np.ndarray | None]:
    """Noisy measurements of robot-frame points q (N, 3): (points, None), or with ``pixel`` the
    triangulated noisy pixels and the pixels (N, 3)."""
    if not pixel:
        return q + rng.normal(0.0, SIGMA_Z, q.shape), None
    uv = np.stack(project(q, *RIG), -1) + rng.normal(0.0, SIGMA_PX, q.shape)
    uv[:, 1] = np.minimum(uv[:, 1], uv[:, 0] - 0.5)  # a positive disparity, as the front end guarantees
    return triangulate(uv[:, 0], uv[:, 1], uv[:, 2], RIG[0], RIG[1], RIG[2], RIG[3]), uv


def _populate(est: FastSlam | EkfSlam, L: np.ndarray, rng: np.random.Generator, pixel: bool = False) -> np.ndarray:
    """Put all landmarks in the map; returns their ids."""
    ids = np.arange(L.shape[0], dtype=np.int64)
    z, uv = _measure(L, rng, pixel)
    cov = np.tile(np.eye(3) * SIGMA_Z**2, (L.shape[0], 1, 1))
    est.update(Observations(0, z, cov, ids, np.ones(L.shape[0], bool), uv))
    return ids


def _obs(
    L: np.ndarray,
    ids: np.ndarray,
    n: int,
    t: int,
    x: np.ndarray,
    rng: np.random.Generator,
    spread: bool = False,
    pixel: bool = False,
) -> Observations:
    if spread or ids.size <= 2 * n:
        sel = rng.choice(ids.size, size=min(n, ids.size), replace=False)
    else:
        start = int(rng.integers(0, ids.size - 2 * n))
        sel = start + rng.choice(2 * n, size=n, replace=False)
    R = euler_to_R(x[3:])
    z, uv = _measure((L[sel] - x[:3]) @ R, rng, pixel)
    cov = np.tile(np.eye(3) * SIGMA_Z**2, (sel.size, 1, 1))
    return Observations(t, z, cov, ids[sel], np.zeros(sel.size, bool), uv)


def _threads_used(threads: int) -> int:
    """numba threads a row really ran with (NUMBA_NUM_THREADS caps the request)."""
    try:
        import numba

        return min(threads, int(getattr(numba.config, "NUMBA_NUM_THREADS", 1)))
    except ImportError:
        return 0


def time_filter(
    filt: str,
    P: int,
    M: int,
    N: int,
    budget_s: float,
    threads: int,
    seed: int = 0,
    spread: bool = False,
    block: int = 64,
    prune: bool = False,
    measurement: str = "cartesian",
) -> dict[str, Any]:
    rng = np.random.default_rng(seed)
    pixel = measurement == "pixel"
    params = SlamParams(
        filter=filt,
        dim=3,
        n_particles=max(P, 1),
        numba_threads=threads,
        prune_enabled=prune,
        landmark_block_size=block,
        measurement=measurement,
        stereo_intrinsics=RIG,
        pixel_sigma_px=(SIGMA_PX, SIGMA_PX),
    )
    est = make_estimator(params, np.random.default_rng(seed + 1))
    assert isinstance(est, FastSlam | EkfSlam)
    L = _world(M, rng)
    ids = _populate(est, L, rng, pixel)
    x = np.zeros(6)
    inc = MotionIncrement(0, 1, np.zeros(3), np.zeros(3), np.diag([1e-4] * 3 + [1e-5] * 3))
    times: list[float] = []
    n_obs: list[int] = []
    n_res = 0
    t_end = time.perf_counter() + budget_s
    k = 0
    while k < 3 or (time.perf_counter() < t_end and k < 200) or len(times) < 5:
        obs = _obs(L, ids, N, k + 1, x, rng, spread, pixel)
        if prune:  # the existence counters delete landmarks the robot should see but does not: skip those
            obs = obs.subset(np.isin(obs.ids, est.book.slot_id[est.book.active_slots()]))
        t0 = time.perf_counter()
        est.predict(inc)
        rep = est.update(obs)
        dt = time.perf_counter() - t0
        if k >= 2:  # the first steps include numba dispatch/cache loading
            times.append(dt)
            n_obs.append(int(obs.ids.size))
            n_res += int(rep.resampled)
        k += 1
    a = np.asarray(times) * 1e3
    return {
        "filter": filt,
        "measurement": measurement,
        "dim": 3,
        "particles": P if estimator_kind(filt).particles is not None else 0,
        "map_size": M,
        "observations": N,
        "observations_mean": round(float(np.mean(n_obs)), 1),  # < N only where pruning deleted some
        "median_ms": round(float(np.median(a)), 3),
        "p99_ms": round(float(np.percentile(a, 99)), 3),
        # on a shared machine the fastest step approximates the uncontended cost
        "min_ms": round(float(np.min(a)), 3),
        "path": f"numba{_threads_used(threads)}" if isinstance(est, FastSlam) else "numpy",
        "steps": len(times),
        "resampled_frac": round(n_res / len(times), 3),
        "block": block,
        "obs_spread": spread,
        "prune": prune,
        "landmark_bytes_per_particle": int(est.store.nbytes() // max(P, 1)) if isinstance(est, FastSlam) else 0,
    }


def time_resample_copy(P: int, M: int, reps: int = 5) -> dict[str, Any]:
    """Resampling cost: copying every particle's landmark arrays vs the copy-on-write store.

    Weights are drawn so that N_eff ≈ 0.44 P (just below the default threshold P/2), a typical
    resampling. "dense" gathers all P × M Gaussians into a preallocated second buffer (the cheapest
    resampling with per-particle arrays); "cow" is the store's table gather plus the copy on write
    of the blocks that the next frame writes (100 landmarks from a window of 200 consecutive slots).
    """
    from robotd.slam.resampling import effective_sample_size, low_variance_indices

    copier: Any = None
    try:  # the block copier FastSLAM's numba path uses
        from robotd.slam._kernels import copy_blocks

        copier = copy_blocks
    except ImportError:
        pass

    rng = np.random.default_rng(0)
    est = make_estimator(SlamParams(filter="fastslam2", dim=3, n_particles=P, prune_enabled=False), rng)
    assert isinstance(est, FastSlam)
    _populate(est, _world(M, rng), rng)
    # give every particle its own copy of every block first (the state after many updates)
    est.store.make_writable(np.arange(M))
    # dense per-particle arrays and a preallocated (already touched) target: the best a dense store can do
    dm_, dc_ = est.store.dense(M)
    bm_, bc_ = np.empty_like(dm_), np.empty_like(dc_)
    bm_[:] = 0.0
    bc_[:] = 0.0
    dense_t, select_t, write_t, neffs = [], [], [], []
    for _ in range(reps):
        w = rng.random(P) ** 3
        w /= w.sum()
        neffs.append(effective_sample_size(w))
        idx = low_variance_indices(w, float(rng.random()))
        t0 = time.perf_counter()
        np.take(dm_, idx, axis=0, out=bm_, mode="clip")
        np.take(dc_, idx, axis=0, out=bc_, mode="clip")
        dense_t.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        est._select(idx)
        select_t.append(time.perf_counter() - t0)
        n_obs = min(100, M)
        start = int(rng.integers(0, max(M - 2 * n_obs, 0) + 1))
        slots = start + rng.choice(min(2 * n_obs, M), size=n_obs, replace=False)
        t0 = time.perf_counter()
        est.store.make_writable(slots, copier)
        write_t.append(time.perf_counter() - t0)
    per_particle = M * (3 + 9) * 8
    return {
        "particles": P,
        "map_size": M,
        "dense_copy_ms": round(float(np.median(dense_t)) * 1e3, 3),
        "cow_select_ms": round(float(np.median(select_t)) * 1e3, 3),
        "cow_write_ms": round(float(np.median(write_t)) * 1e3, 3),
        "neff_over_P": round(float(np.mean(neffs)) / P, 2),
        "dense_bytes_per_particle": per_particle,
        "cow_bytes_per_particle": int(est.store.nbytes() // P),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="reduced grid, < 1 min")
    ap.add_argument("--json", action="store_true", help="print exactly one JSON object")
    ap.add_argument("--budget", type=float, default=None, help="seconds of timing per cell")
    ap.add_argument(
        "--target-repeats", type=int, default=5, help="extra timings of the target cell, for its spread (default 5)"
    )
    ap.add_argument(
        "--measurement",
        choices=("cartesian", "pixel"),
        default="cartesian",
        help="the filters' measurement model (slam.measurement; default cartesian)",
    )
    args = ap.parse_args(argv)
    tf = partial(time_filter, measurement=args.measurement)
    load_start = round(os.getloadavg()[0], 2)

    if args.quick:
        Ps, Ms, Ns, ekf_M = [10, 100], [100, 1000], [20, 100], [100, 300]
        budget = args.budget or 0.5
    else:
        Ps, Ms, Ns, ekf_M = [10, 100, 1000], [100, 1000, 10000], [20, 100], [100, 300, 1000]
        budget = args.budget or 1.5

    # the bar counts cells (one time_filter or time_resample_copy call each) and moves between
    # them, never inside a timed step
    n_grid = 2 * len(Ps) * len(Ms) * len(Ns)
    total = 2 + n_grid + 2 + len(Ms[1:]) + len(ekf_M) + len(Ps) * len(Ms) + max(0, args.target_repeats)
    bar = _bar(total, "cell", "fastslam")

    def note(r: dict[str, Any]) -> None:
        bar.write(f"# {r}", file=sys.stderr)  # above the bar (plain line when it is off)
        bar.update(1)

    with bar:
        # compile / load the numba kernels once before any timing
        bar.set_postfix_str("numba warm-up")
        tf("fastslam2", 4, 10, 5, 0.0, 1)
        bar.update(1)
        tf("fastslam1", 4, 10, 5, 0.0, 1)
        bar.update(1)

        results: list[dict[str, Any]] = []
        for filt in ("fastslam2", "fastslam1"):
            for P in Ps:
                for M in Ms:
                    for N in Ns:
                        bar.set_postfix_str(f"{filt} P={P} M={M} N={N}")
                        results.append(tf(filt, P, M, N, budget, 1))
                        note(results[-1])
        # the target cell with 2 threads, and with observations spread over the map
        bar.set_postfix_str("target cell variants")
        results.append(tf("fastslam2", 100, 1000, 100, budget, 2))
        note(results[-1])
        results.append(tf("fastslam2", 100, 1000, 100, budget, 1, spread=True))
        note(results[-1])
        # the daemon's default: landmark pruning on (one O(M) visibility pass over the best particle's map)
        for M in Ms[1:]:
            bar.set_postfix_str(f"pruning M={M}")
            results.append(tf("fastslam2", 100, M, 100, budget, 1, prune=True))
            note(results[-1])
        for M in ekf_M:
            bar.set_postfix_str(f"ekf M={M}")
            results.append(tf("ekf", 0, M, 20, budget, 0))
            note(results[-1])
        copies = []
        for P in Ps:
            for M in Ms:
                bar.set_postfix_str(f"resample copy P={P} M={M}")
                copies.append(time_resample_copy(P, M))
                bar.update(1)

        target = next(
            r
            for r in results
            if r["filter"] == "fastslam2"
            and r["particles"] == 100
            and r["map_size"] == 1000
            and r["observations"] == 100
            and r["path"] == "numba1"
            and not r["obs_spread"]
            and not r["prune"]
        )
        # the target cell again, several times: on a shared machine one cell's median is noisy
        repeats = []
        for i in range(max(0, args.target_repeats)):
            bar.set_postfix_str(f"target repeat {i + 1}")
            repeats.append(tf("fastslam2", 100, 1000, 100, budget, 1, seed=1 + i)["median_ms"])
            bar.update(1)
    medians = [target["median_ms"], *repeats]
    conditions = {
        "machine": platform.machine(),
        "cpus": os.cpu_count(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "note": "shared 2-core machine with other jobs running; figures are pessimistic",
        "load_avg_1min_start": load_start,
        "load_avg_1min_end": round(os.getloadavg()[0], 2),
        "openblas_threads": os.environ.get("OPENBLAS_NUM_THREADS"),
        "numba_threads_env": os.environ.get("NUMBA_NUM_THREADS"),
        "cpu_affinity": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
        "quick": bool(args.quick),
        "budget_s_per_cell": budget,
        "measurement": args.measurement,
    }
    mom = round(float(np.median(medians)), 3)
    out = {
        "benchmark": "fastslam",
        "conditions": conditions,
        "results": results,
        "resample_copy": copies,
        "target": {
            "cell": f"fastslam2 3D P=100 M=1000 N=100 numba1 {args.measurement}",
            "median_ms": target["median_ms"],
            "min_ms": target["min_ms"],
            "goal_ms": 5.0,
            # medians of the grid's run and of --target-repeats reruns (seeds 1…n)
            "run_medians_ms": medians,
            "median_of_medians_ms": mom,
            "spread_ms": round(max(medians) - min(medians), 3),
            "met": mom <= 5.0,
        },
    }
    if args.json:
        print(json.dumps(out))
        return 0
    print("## Per-step latency (predict + update), 3D\n")
    print(
        "| filter | path | particles | map size | observations | obs spread | pruning | median ms | p99 ms | min ms "
        "| resampled |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in results:
        kept = "" if r["observations_mean"] == r["observations"] else f" ({r['observations_mean']:.0f})"
        print(
            f"| {r['filter']} | {r['path']} | {r['particles']} | {r['map_size']} | {r['observations']}{kept} | "
            f"{'map' if r['obs_spread'] else 'window'} | {'on' if r['prune'] else 'off'} | {r['median_ms']:.2f} | "
            f"{r['p99_ms']:.2f} | "
            f"{r['min_ms']:.2f} | {r['resampled_frac']:.2f} |"
        )
    print("\n## Resampling: dense copy of all maps vs copy-on-write blocks (table gather + next frame's writes)\n")
    print(
        "| particles | map size | dense copy ms | CoW select ms | CoW writes ms | N_eff/P "
        "| dense B/particle | CoW B/particle |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for c in copies:
        print(
            f"| {c['particles']} | {c['map_size']} | {c['dense_copy_ms']:.2f} | {c['cow_select_ms']:.2f} | "
            f"{c['cow_write_ms']:.2f} | {c['neff_over_P']} | {c['dense_bytes_per_particle']} | "
            f"{c['cow_bytes_per_particle']} |"
        )
    print(
        "\nTarget (FastSLAM 2.0, 3D, 100 particles, 100 obs, 1000 landmarks, 1 thread): "
        f"median {target['median_ms']:.2f} ms, fastest step {target['min_ms']:.2f} ms (goal 5 ms); "
        f"medians over {len(medians)} runs {min(medians):.2f}–{max(medians):.2f} ms, "
        f"median {mom:.2f} ms: goal {'met' if mom <= 5.0 else 'NOT met'}"
    )
    print(f"Conditions: {conditions}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
