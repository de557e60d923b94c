#!/usr/bin/env python3
"""Daemon benchmark: capture-to-publish latency on the simulated rover, at nominal rate and at 2× overload.

Runs the real daemon in-process (camera, vehicle, SLAM and publisher threads, the latency budget,
a real Zenoh session on loopback) on ``sim://`` for each detector, once with the camera at the
nominal rate and once at twice that rate with the deadline kept at the nominal frame period (the
camera then delivers twice what the pipeline may spend time on: the budget must degrade and the
drop-oldest queue must keep latency bounded). The first ``--warmup`` seconds (numba compilation,
map initialisation) are excluded from the latency figures.

    python bench/daemon.py [--seconds 20] [--fps 30] [--detectors orb,sift] [--json]
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import socket
import sys
import threading
import time
from pathlib import Path

# as the robotd command does (robotd.tools.cli), before numpy loads: one BLAS thread (the daemon also
# limits it at startup, but OpenBLAS honours a limit set before loading more reliably)
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_WAIT_POLICY", "passive")  # as robotd.tools.cli: OpenMP workers sleep, not spin

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from robotd.config import load_config
from robotd.daemon import Daemon
from robotd.daemon.health import rss_mb


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _overrides(pairs: list[str]) -> dict[str, dict[str, object]]:
    """["slam.numba_threads=1", ...] -> {"slam": {"numba_threads": 1}} (robotd.config.parse_overrides)."""
    from robotd.config import parse_overrides
    from robotd.core.errors import ConfigError

    try:
        return parse_overrides(pairs)
    except ConfigError as exc:
        raise SystemExit(str(exc)) from exc


_PROBE = """
import sys, time
t_end = time.perf_counter() + float(sys.argv[1])
out = []
while time.perf_counter() < t_end:
    t0 = time.perf_counter()
    x = 0
    for i in range(40000):
        x += i * i
    out.append((time.perf_counter() - t0) * 1e3)
print(" ".join(f"{v:.4f}" for v in out))
"""


def host_jitter(seconds: float = 3.0, workers: int = 2) -> dict[str, float]:
    """How steady this machine's CPUs are right now: ``workers`` processes (default: one per core of
    a 2-core machine) run the same fixed pure-Python work unit back to back for ``seconds``; the
    unit's time p50 / p99 [ms] over all of them, and p99 / p50. On a quiet machine the ratio is
    ≈ 1.1; on a shared VM whose neighbours are busy it reaches 1.5–1.8, and every stage of the
    pipeline slows by as much at the same moments."""
    import subprocess

    procs = [
        subprocess.Popen([sys.executable, "-c", _PROBE, str(seconds)], stdout=subprocess.PIPE, text=True)
        for _ in range(workers)
    ]
    times = np.concatenate([np.array(p.communicate()[0].split(), float) for p in procs])
    if times.size == 0:  # a probe process failed: say nothing rather than a made-up figure
        print("# host_jitter: the probe processes returned no timings", file=sys.stderr)
        return {"p50_ms": float("nan"), "p99_ms": float("nan"), "p99_over_p50": float("nan")}
    p50, p99 = (float(v) for v in np.percentile(times, [50, 99]))
    return {"p50_ms": round(p50, 3), "p99_ms": round(p99, 3), "p99_over_p50": round(p99 / p50, 3)}


def thread_cpu_s() -> dict[int, tuple[str, float]]:
    """CPU seconds (user + system) of each of this process's threads, by native id (Linux /proc)."""
    tick = os.sysconf("SC_CLK_TCK")
    out: dict[int, tuple[str, float]] = {}
    for task in Path("/proc/self/task").iterdir():
        try:
            stat = (task / "stat").read_text()
        except OSError:
            continue  # the thread ended
        comm = stat[stat.index("(") + 1 : stat.rindex(")")]
        fields = stat[stat.rindex(")") + 2 :].split()
        out[int(task.name)] = (comm, (int(fields[11]) + int(fields[12])) / tick)
    return out


def _cpu_by_thread(before: dict[int, tuple[str, float]], after: dict[int, tuple[str, float]]) -> dict[str, float]:
    """CPU seconds spent between two samples, grouped by Python thread name (others by OS name)."""
    names = {t.native_id: t.name for t in threading.enumerate() if t.native_id is not None}
    names.update(_seen_threads)
    out: dict[str, float] = {}
    for tid, (comm, cpu) in after.items():
        used = cpu - before.get(tid, (comm, 0.0))[1]
        if tid == os.getpid():
            key = "main"
        else:
            key = names.get(tid, comm)
        out[key] = out.get(key, 0.0) + used
    return out


_seen_threads: dict[int, str] = {}


def run_once(
    detector: str,
    fps: float,
    deadline_ms: float,
    seconds: float,
    warmup_s: float,
    particles: int,
    fixed: bool = False,
    extra: dict[str, dict[str, object]] | None = None,
    prerender: bool = True,
) -> dict:
    tmp = Path(os.environ.get("TMPDIR", "/tmp")) / f"robotd-bench-{os.getpid()}"
    budget: dict[str, float] = {"deadline_ms": deadline_ms}
    if fixed:
        # floors at the full settings: the budget may only skip frames (the full-settings cost)
        budget.update(min_features=load_config(None, {}).frontend.max_features, min_particles=particles)
    # prerendered: the whole drive rendered before the clock starts, so the camera thread costs
    # what a real driver's hand-off costs and the renderer's own cost is reported apart
    url = f"sim://?fps={fps:g}&duration={seconds + 5:g}&prerender=1" if prerender else f"sim://?fps={fps:g}"
    tree: dict[str, dict[str, object]] = {
        "camera": {"url": url},
        "vehicle": {"url": url},
        "frontend": {"detector": detector},
        "slam": {"n_particles": particles},
        "budget": budget,
        "zenoh": {"listen": [f"tcp/127.0.0.1:{_free_port()}"]},
        "persistence": {"state_dir": str(tmp), "save_period_s": 0.0},
        "log": {"status_period_s": 5.0},
    }
    for section, kv in (extra or {}).items():
        tree.setdefault(section, {}).update(kv)
    cfg = load_config(None, tree)
    # the run's clock starts at its first step, not at start-up: loading the kernels and
    # prerendering (9 s on a slow VM) came before it, and were counted in the warm-up and in the
    # main thread's CPU when it did; the bench stops the daemon itself ``seconds`` after the first
    # step (the duration only guards against a hang)
    d = Daemon(cfg, duration_s=seconds + 300.0, environ={})
    d.stats.max_latency_window = 10**7
    rss: dict[str, float] = {}
    marks: dict[str, int] = {}
    first_step: dict[str, float] = {}

    def wait_first_step() -> None:
        while d.stats.steps == 0 and not d.stop_event.is_set():
            time.sleep(0.01)
        first_step.setdefault("t", time.monotonic())

    def sample() -> None:
        # RSS once the warm-up is over (caches built, numba compiled), and again at the end
        wait_first_step()
        time.sleep(warmup_s)
        rss["start"] = rss_mb()
        marks["latencies"] = len(d.stats.latencies_ms)
        marks["frames_in"] = d.stats.frames_in
        marks["processed"] = d.stats.steps
        marks["dropped"] = d.frame_q.dropped
        marks["skipped"] = d.budget.skipped if d.budget else 0

    threads_cpu: dict[str, dict[int, tuple[str, float]]] = {}

    def sample_cpu() -> None:
        wait_first_step()
        time.sleep(warmup_s)
        marks["cpu_s"] = time.process_time()
        marks["load1"] = os.getloadavg()[0]
        threads_cpu["start"] = thread_cpu_s()
        _seen_threads.update({t.native_id: t.name for t in threading.enumerate() if t.native_id is not None})
        # the daemon's threads end with the run: sample them just before it stops
        time.sleep(max(0.0, seconds - warmup_s - 0.5))
        _seen_threads.update({t.native_id: t.name for t in threading.enumerate() if t.native_id is not None})
        threads_cpu["end"] = thread_cpu_s()
        time.sleep(0.5)
        d.stop_reason = "duration reached"
        d.stop_event.set()

    th = threading.Thread(target=sample, daemon=True)
    th.start()
    th_cpu = threading.Thread(target=sample_cpu, daemon=True)
    th_cpu.start()
    t0 = time.monotonic()
    d.run()
    wall = time.monotonic() - first_step.get("t", t0)
    th.join(1)
    th_cpu.join(1)
    rss["end"] = rss_mb()
    cpu_s = time.process_time() - marks.get("cpu_s", 0.0)
    cam_stats = d.camera.stats() if d.camera is not None else {}
    lat = np.asarray(d.stats.latencies_ms[marks.get("latencies", 0) :])
    b = d.budget
    by_thread = _cpu_by_thread(threads_cpu.get("start", {}), threads_cpu.get("end", {}))
    processed = d.stats.steps - marks.get("processed", 0)
    # the last 300 frames' stage times (wall clock, as the budget sees them)
    stages = {k: {"p50": round(v["p50"], 2), "p99": round(v["p99"], 2)} for k, v in d.timer.percentiles().items()}
    return {
        "detector": detector,
        "fps": fps,
        "particles": particles,
        "fixed_settings": fixed,
        "deadline_ms": round(deadline_ms, 3),
        "seconds": round(wall - warmup_s, 2),
        "latency_p50_ms": float(np.percentile(lat, 50)) if lat.size else None,
        "latency_p99_ms": float(np.percentile(lat, 99)) if lat.size else None,
        "latency_max_ms": float(lat.max()) if lat.size else None,
        "frames_in": d.stats.frames_in - marks.get("frames_in", 0),
        "processed": processed,
        "dropped": d.frame_q.dropped - marks.get("dropped", 0),
        "skipped": (b.skipped if b else 0) - marks.get("skipped", 0),
        "budget_level_end": b.state.level if b else None,
        "max_features_end": b.state.max_features if b else None,
        "particles_end": b.state.n_particles if b else None,
        "deadline_misses": b.deadline_misses if b else None,
        "rss_mb_start": round(rss.get("start", float("nan")), 1),
        "rss_mb_end": round(rss["end"], 1),
        "error_vs_truth_m": None if not np.isfinite(d.stats.last_error_m) else round(d.stats.last_error_m, 3),
        # the frames processed on each rung of the budget (L0 = full settings), warm-up included
        "frames_at_level": list(b.frames_at_level) if b else [],
        "l0_pct": round(100.0 * b.frames_at_level[0] / max(1, sum(b.frames_at_level)), 1) if b else None,
        "prerendered": prerender,
        # the renderer's own cost per frame: before the run when prerendered, else in the camera thread
        "render_ms_per_frame": round(
            float(cam_stats.get("prerender_ms_per_frame") or cam_stats.get("render_ms_p50") or 0), 2
        ),
        # the whole process (camera rendering, SLAM, publishing) after the warm-up, per processed frame
        "cpu_ms_per_frame": round(1e3 * cpu_s / processed, 2) if processed else None,
        # the machine is shared: the 1-minute load average at the end of the warm-up and at the end
        "load1_start": round(marks.get("load1", float("nan")), 2),
        "load1_end": round(os.getloadavg()[0], 2),
        "stage_ms": stages,
        # CPU per processed frame of each thread (sampled from the warm-up to 0.5 s before the end)
        "cpu_ms_per_frame_by_thread": {
            k: round(1e3 * v / processed, 2) for k, v in sorted(by_thread.items(), key=lambda kv: -kv[1]) if v > 0
        }
        if processed
        else {},
    }


def _summary(results: list[dict], deadline_ms: float) -> list[dict]:
    """Per (detector, case): the p99 over repeated runs (median, range) and how many runs kept
    their p99 within the deadline: one 20 s run holds only ≈ 6 frames above its p99, so one run
    says little about a tail that follows the host."""
    groups: dict[tuple[str, str], list[float]] = {}
    for r in results:
        if r["latency_p99_ms"] is not None:
            groups.setdefault((r["detector"], r["case"]), []).append(float(r["latency_p99_ms"]))
    return [
        {
            "detector": det,
            "case": case,
            "runs": len(v),
            "p99_median_ms": float(np.median(v)),
            "p99_min_ms": min(v),
            "p99_max_ms": max(v),
            "runs_within_deadline": sum(x < deadline_ms for x in v),
        }
        for (det, case), v in groups.items()
    ]


def _cell(col: str, v: object) -> str:
    if isinstance(v, float):
        return f"{v:.2f}" if col.startswith("host_") else f"{v:.1f}"
    return str(v)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--seconds", type=float, default=20.0, help="run length per case from its first step, warm-up included"
    )
    ap.add_argument("--warmup", type=float, default=4.0)
    ap.add_argument("--fps", type=float, default=30.0, help="nominal camera rate")
    ap.add_argument("--particles", type=int, default=100)
    ap.add_argument("--detectors", default="orb,sift")
    ap.add_argument("--cases", default="nominal,overload", help="nominal, overload (2x camera rate), or both")
    ap.add_argument(
        "--fixed", action="store_true", help="keep features and particles at full settings (the budget may only skip)"
    )
    ap.add_argument(
        "--set", action="append", default=[], metavar="SECTION.KEY=VALUE", help="config override (repeatable)"
    )
    ap.add_argument("--repeat", type=int, default=1, help="run each case this many times")
    ap.add_argument(
        "--probe-seconds",
        type=float,
        default=2.0,
        help="host CPU steadiness probe before and after each case (see host_jitter; 0 = off)",
    )
    ap.add_argument(
        "--live-render",
        action="store_true",
        help="render the simulated camera live in its thread (default: every frame rendered before the run)",
    )
    ap.add_argument(
        "--cpus",
        default="",
        help="pin the process to these CPUs, e.g. 0 (a rover-class single core; as taskset -c 0)",
    )
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    if args.cpus:
        os.sched_setaffinity(0, {int(c) for c in args.cpus.split(",")})
    extra = _overrides(args.set)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    results = []
    nominal_deadline = 1000.0 / args.fps
    cases = [c.strip() for c in args.cases.split(",")]
    plan = [
        (det, label, fps, rep)
        for det in args.detectors.split(",")
        for label, fps in (("nominal", args.fps), ("overload 2x", 2 * args.fps))
        if label.split()[0] in cases
        for rep in range(max(1, args.repeat))
    ]
    # progress: one line per run on stderr before it starts (only when stderr is a terminal; the
    # runs' timing is untouched: nothing runs beside the daemon)
    show = sys.stderr.isatty()
    per_run_s = args.seconds + (2 * args.probe_seconds if args.probe_seconds > 0 else 0.0)
    t_start = time.monotonic()
    for i, (det, label, fps, rep) in enumerate(plan):
        if show:
            elapsed = time.monotonic() - t_start
            # the runs so far say how long one takes (start-up included); before the first, the nominal length
            est = elapsed / i if i else per_run_s
            again = f" (repeat {rep + 1}/{max(1, args.repeat)})" if args.repeat > 1 else ""
            print(
                f"[{i + 1}/{len(plan)}] {det} {label}{again}: ~{est:.0f} s; elapsed {elapsed:.0f} s, "
                f"about {est * (len(plan) - i):.0f} s left",
                file=sys.stderr,
                flush=True,
            )
        before = host_jitter(args.probe_seconds) if args.probe_seconds > 0 else None
        r = run_once(
            det,
            fps,
            nominal_deadline,
            args.seconds,
            args.warmup,
            args.particles,
            args.fixed,
            extra,
            not args.live_render,
        )
        after = host_jitter(args.probe_seconds) if args.probe_seconds > 0 else None
        r["case"] = label
        if r.get("latency_p50_ms") is None:
            print(f"# {det} {label}: the daemon processed no frame (its error is above)", file=sys.stderr)
            return 1
        # the host's p99/p50 on two busy cores just before and after the case (≈ 1.1 quiet)
        r["host_jitter_before"] = before["p99_over_p50"] if before else None
        r["host_jitter_after"] = after["p99_over_p50"] if after else None
        results.append(r)
        print(
            f"# {det} {label}: p50 {r['latency_p50_ms']:.1f} p99 {r['latency_p99_ms']:.1f} ms, level "
            f"{r['budget_level_end']}, host jitter {r['host_jitter_before']} / {r['host_jitter_after']}",
            file=sys.stderr,
        )
    if show:
        print(f"done: {len(plan)} runs in {time.monotonic() - t_start:.0f} s", file=sys.stderr, flush=True)
    machine = {"cpus": os.cpu_count(), "pinned_to": sorted(os.sched_getaffinity(0)), "python": sys.version.split()[0]}
    summary = _summary(results, nominal_deadline)
    if args.json:
        print(json.dumps({"machine": machine, "results": results, "summary": summary}))
        return 0
    print(
        f"Daemon on sim:// (640×400), {args.particles} particles, deadline {nominal_deadline:.1f} ms, "
        f"{args.seconds:g} s per case ({args.warmup:g} s warm-up excluded), {os.cpu_count()} CPUs"
        f"{' (pinned to CPU ' + args.cpus + ')' if args.cpus else ''}, camera "
        f"{'rendered live' if args.live_render else 'prerendered'}\n"
    )
    cols = [
        "detector",
        "case",
        "fps",
        "latency_p50_ms",
        "latency_p99_ms",
        "processed",
        "dropped",
        "skipped",
        "budget_level_end",
        "l0_pct",
        "max_features_end",
        "particles_end",
        "rss_mb_start",
        "rss_mb_end",
        "error_vs_truth_m",
        "cpu_ms_per_frame",
        "render_ms_per_frame",
        "load1_start",
        "load1_end",
        "host_jitter_before",
        "host_jitter_after",
    ]
    print("| " + " | ".join(cols) + " |")
    print("|" + "---|" * len(cols))
    for r in results:
        cells = [_cell(c, r[c]) for c in cols]
        print("| " + " | ".join(cells) + " |")
    names = sorted({k for r in results for k in r["stage_ms"]})
    print("\nStage wall times p50 / p99 [ms] (last 300 frames of each case)\n")
    print("| detector | case | " + " | ".join(names) + " |")
    print("|---|---|" + "---|" * len(names))
    for r in results:
        st = r["stage_ms"]
        cells = [f"{st[k]['p50']:.1f} / {st[k]['p99']:.1f}" if k in st else "-" for k in names]
        print(f"| {r['detector']} | {r['case']} | " + " | ".join(cells) + " |")
    if any(g["runs"] > 1 for g in summary):
        print("\nRepeated runs: p99 over the runs of each case\n")
        print("| detector | case | runs | p99 median ms | p99 min–max ms | runs with p99 < deadline |")
        print("|---|---|---|---|---|---|")
        for g in summary:
            print(
                f"| {g['detector']} | {g['case']} | {g['runs']} | {g['p99_median_ms']:.1f} "
                f"| {g['p99_min_ms']:.1f}–{g['p99_max_ms']:.1f} | {g['runs_within_deadline']} |"
            )
    print("\nCPU per processed frame by thread [ms] (after the warm-up)\n")
    for r in results:
        parts = ", ".join(f"{k} {v:.1f}" for k, v in r["cpu_ms_per_frame_by_thread"].items() if v >= 0.05)
        print(f"- {r['detector']} {r['case']}: {parts}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
