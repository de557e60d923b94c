#!/usr/bin/env python3
"""Soak: the real daemon on ``sim://`` for an hour, watched from outside (issue 15, not in CI).

Starts ``robotd run`` as a subprocess (this checkout, like the tests do) on the simulated rover,
whose 28.5 m loop it drives again and again (a lap every ≈ 28 s at 1 m/s), with Zenoh on a free
loopback port and the map saved in a temporary state directory. Every ``--every`` seconds it
samples, from outside the process, the resident set size (``VmRSS`` in /proc/PID/status), the
open file descriptors (entries of /proc/PID/fd) and the threads, and from the daemon's own
``robotd/<id>/health`` topic (a real Zenoh subscriber) the landmark count, the health state, the
frame rate, the budget rung and the error against the simulator's truth. At the end it stops the
daemon with SIGTERM (it saves its map) and prints a table of the samples and a summary:

- RSS growth over the last 30 minutes (or the last half of a shorter run): the goal is < 5 %;
- the landmark count over the same window (its growth and its slope: a plateau once the rover
  revisits its loop), and the largest;
- the open descriptors (first, last, largest: they must not grow).

    python bench/soak.py [--minutes 60] [--every 30] [--fps 10] [--json] [--keep DIR]

One hour of a loaded 2-core machine: run it by hand (``nohup python bench/soak.py --json >
soak.json &``), not in CI. Figures: docs/reliability.md ("Soak").
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
ROBOT_ID = "soak"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _proc_status(pid: int) -> dict[str, int]:
    """VmRSS [kB] and Threads of a live process from /proc/PID/status ({} once it has gone)."""
    out: dict[str, int] = {}
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            key, _, val = line.partition(":")
            if key in ("VmRSS", "Threads"):
                out[key] = int(val.split()[0])
    except (OSError, ValueError, IndexError):
        return {}
    return out


def _open_fds(pid: int) -> int | None:
    try:
        return len(os.listdir(f"/proc/{pid}/fd"))
    except OSError:
        return None


class HealthWatch:
    """The latest health document of robot ``ROBOT_ID`` over a Zenoh client session on loopback."""

    def __init__(self, port: int) -> None:
        import zenoh

        conf = zenoh.Config()
        conf.insert_json5("mode", '"client"')
        conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
        conf.insert_json5("scouting/multicast/enabled", "false")
        self._zenoh = zenoh
        self._conf = conf
        self._session: Any = None
        self._sub: Any = None
        self._lock = threading.Lock()
        self.latest: dict[str, Any] | None = None
        self.count = 0

    def _on_health(self, sample: Any) -> None:
        try:
            doc = json.loads(sample.payload.to_bytes())
        except ValueError:
            return
        with self._lock:
            self.latest = doc
            self.count += 1

    def connect(self) -> bool:
        """Open the session once the daemon listens (a client cannot connect before)."""
        if self._session is not None:
            return True
        try:
            self._session = self._zenoh.open(self._conf)
        except Exception:  # zenoh raises its own ZError when nobody listens yet
            return False
        self._sub = self._session.declare_subscriber(f"robotd/{ROBOT_ID}/health", self._on_health)
        return True

    def snapshot(self) -> dict[str, Any] | None:
        with self._lock:
            return None if self.latest is None else dict(self.latest)

    def close(self) -> None:
        if self._sub is not None:
            self._sub.undeclare()
        if self._session is not None:
            self._session.close()


def _config(tmp: Path, port: int, fps: float, world: str) -> Path:
    cfg = tmp / "robotd.toml"
    url = f"sim://?world={world}&fps={fps:g}"
    cfg.write_text(
        f"""
[robot]
id = "{ROBOT_ID}"
[camera]
url = "{url}"
[vehicle]
url = "{url}"
[zenoh]
listen = ["tcp/127.0.0.1:{port}"]
[persistence]
state_dir = "{tmp / "state"}"
"""
    )
    return cfg


def _sample(pid: int, t0: float, health: HealthWatch) -> dict[str, Any]:
    st = _proc_status(pid)
    h = health.snapshot() or {}
    return {
        "t_s": round(time.monotonic() - t0, 1),
        "rss_mb": round(st["VmRSS"] / 1024.0, 1) if "VmRSS" in st else None,
        "fds": _open_fds(pid),
        "threads": st.get("Threads"),
        "landmarks": h.get("landmarks"),
        "state": h.get("state"),
        "fps": None,  # from the frames processed since the previous sample
        "budget": (h.get("budget") or {}).get("level"),
        "error_m": h.get("error_vs_truth_m"),
        "frames": h.get("frames_processed"),
    }


def _add(samples: list[dict[str, Any]], s: dict[str, Any]) -> None:
    """Append sample ``s`` with its frame rate since the previous sample."""
    if samples and s["frames"] is not None and samples[-1]["frames"] is not None:
        dt = max(s["t_s"] - samples[-1]["t_s"], 1e-3)
        s["fps"] = round((s["frames"] - samples[-1]["frames"]) / dt, 2)
    samples.append(s)


def _window(samples: list[dict[str, Any]], minutes: float) -> list[dict[str, Any]]:
    """The samples of the last ``minutes`` of the run (the last half when the run is shorter)."""
    if not samples:
        return []
    end = samples[-1]["t_s"]
    span = min(minutes * 60.0, end / 2.0)
    return [s for s in samples if s["t_s"] >= end - span]


def _growth(win: list[dict[str, Any]], key: str) -> dict[str, float | None]:
    vals = [(s["t_s"], s[key]) for s in win if s.get(key) is not None]
    if len(vals) < 2:
        return {"first": None, "last": None, "growth_pct": None, "slope_per_min": None}
    t = np.array([v[0] for v in vals]) / 60.0
    y = np.array([float(v[1]) for v in vals])
    slope = float(np.polyfit(t, y, 1)[0]) if np.ptp(t) > 0 else 0.0
    first, last = y[0], y[-1]
    return {
        "first": float(first),
        "last": float(last),
        "growth_pct": float(100.0 * (last - first) / first) if first else None,
        "slope_per_min": slope,
    }


def summarise(samples: list[dict[str, Any]], window_min: float = 30.0) -> dict[str, Any]:
    """The soak's figures: growth of RSS, landmarks and descriptors over the last ``window_min``."""
    win = _window(samples, window_min)
    rss = _growth(win, "rss_mb")
    lms = _growth(win, "landmarks")
    fds = [s["fds"] for s in samples if s.get("fds") is not None]
    lm_all = [s["landmarks"] for s in samples if s.get("landmarks") is not None]
    errs = [s["error_m"] for s in win if s.get("error_m") is not None]
    return {
        "window_s": (win[-1]["t_s"] - win[0]["t_s"]) if win else 0.0,
        "rss_mb": rss,
        "rss_goal_met": rss["growth_pct"] is not None and rss["growth_pct"] < 5.0,
        "landmarks": {**lms, "max": max(lm_all) if lm_all else None},
        "fds": {"first": fds[0] if fds else None, "last": fds[-1] if fds else None, "max": max(fds) if fds else None},
        "error_m_window": {"median": float(np.median(errs)), "max": float(np.max(errs))} if errs else None,
        "states_window": sorted({str(s.get("state")) for s in win}),
    }


def _row(s: dict[str, Any]) -> str:
    def f(v: Any, fmt: str) -> str:
        return "" if v is None else format(v, fmt)

    return (
        f"| {s['t_s']:.0f} | {f(s['rss_mb'], '.1f')} | {f(s['fds'], 'd')} | {f(s['threads'], 'd')} | "
        f"{f(s['landmarks'], 'd')} | {s['state'] or ''} | {f(s['fps'], '.1f')} | {f(s['budget'], 'd')} | "
        f"{f(s['error_m'], '.3f')} |"
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--minutes", type=float, default=60.0, help="how long the daemon runs (default 60)")
    ap.add_argument("--every", type=float, default=30.0, help="seconds between samples (default 30)")
    ap.add_argument("--fps", type=float, default=10.0, help="the simulated camera's rate (default 10)")
    ap.add_argument("--world", default="yard", help="sim:// world (default yard: the loop)")
    ap.add_argument("--window", type=float, default=30.0, help="minutes at the end the growth is taken over")
    ap.add_argument("--keep", type=Path, default=None, help="keep the config, log and map in this folder")
    ap.add_argument("--json", action="store_true", help="print one JSON object instead of the table")
    a = ap.parse_args(argv)
    if a.minutes <= 0 or a.every <= 0:
        ap.error("--minutes and --every must be > 0")
    tmp_ctx = tempfile.TemporaryDirectory(prefix="robotd-soak-") if a.keep is None else None
    tmp = Path(tmp_ctx.name) if tmp_ctx is not None else a.keep
    tmp.mkdir(parents=True, exist_ok=True)
    port = _free_port()
    cfg = _config(tmp, port, a.fps, a.world)
    log = (tmp / "robotd.log").open("w")
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    duration = a.minutes * 60.0
    proc = subprocess.Popen(
        [sys.executable, "-m", "robotd", "run", "--config", str(cfg), "--duration", f"{duration + 30:.0f}"],
        cwd=str(tmp),
        env=env,
        stdout=log,
        stderr=subprocess.STDOUT,
    )
    health = HealthWatch(port)
    samples: list[dict[str, Any]] = []
    t0 = time.monotonic()
    print(
        f"soak: robotd pid {proc.pid}, {a.minutes:g} min, sample every {a.every:g} s, log {tmp / 'robotd.log'}",
        file=sys.stderr,
        flush=True,
    )
    try:
        next_t = t0
        while time.monotonic() - t0 < duration and proc.poll() is None:
            if not health.connect() or health.count == 0:  # start-up (numba kernels) is not sampled
                time.sleep(0.5)
                continue
            now = time.monotonic()
            if now >= next_t:
                _add(samples, _sample(proc.pid, t0, health))
                print(_row(samples[-1]), file=sys.stderr, flush=True)
                next_t = next_t + a.every if next_t + a.every > now else now + a.every
            time.sleep(min(0.5, max(0.0, next_t - time.monotonic())))
        if proc.poll() is None:
            _add(samples, _sample(proc.pid, t0, health))
    finally:
        health.close()
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
        try:
            code = proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            proc.kill()
            code = proc.wait()
        log.close()
    tail = (tmp / "robotd.log").read_text(errors="replace").splitlines()[-3:]
    out = {
        "minutes": a.minutes,
        "fps": a.fps,
        "world": a.world,
        "exit_code": code,
        "health_docs": health.count,
        "summary": summarise(samples, a.window),
        "samples": samples,
        "log_tail": tail,
    }
    if tmp_ctx is not None:
        tmp_ctx.cleanup()
    if a.json:
        print(json.dumps(out, indent=1))
        return 0 if code == 0 else 1
    print("| t [s] | RSS [MB] | fds | threads | landmarks | state | fps | budget | error [m] |")
    print("|---|---|---|---|---|---|---|---|---|")
    for s in samples:
        print(_row(s))
    sm = out["summary"]
    print()
    print(f"exit code {code}; over the last {sm['window_s'] / 60:.1f} min:")
    r, lm, fd = sm["rss_mb"], sm["landmarks"], sm["fds"]
    print(
        f"- RSS {r['first']} -> {r['last']} MB: {r['growth_pct']:+.2f} % (goal < 5 %: "
        f"{'met' if sm['rss_goal_met'] else 'NOT met'}), {r['slope_per_min']:+.3f} MB/min"
        if r["growth_pct"] is not None
        else "- RSS: too few samples"
    )
    if lm["growth_pct"] is not None:
        print(
            f"- landmarks {lm['first']:.0f} -> {lm['last']:.0f} ({lm['growth_pct']:+.1f} %, "
            f"{lm['slope_per_min']:+.1f}/min), largest {lm['max']}"
        )
    print(f"- open descriptors: first {fd['first']}, last {fd['last']}, largest {fd['max']}")
    if sm["error_m_window"]:
        print(
            f"- error against the truth: median {sm['error_m_window']['median']:.3f} m, "
            f"largest {sm['error_m_window']['max']:.3f} m"
        )
    return 0 if code == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
