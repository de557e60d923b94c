"""Throughput of ``robotd replay-many``: recordings per minute on 1 and 2 local workers (and on a local
Ray instance with ``--ray``), against replaying them one by one with ``robotd replay``.

The recordings are robotd recordings (MCAP) of simulated drives, written by the recording writer
into a temporary folder first (``--recordings N`` of ``--frames F`` frames at ``--size WxH``, 10 Hz,
seeds 1..N). Every mode runs in fresh processes, as a person would run it: "one by one" is N
``robotd replay REC --quiet`` commands in a row (each pays Python's start, the imports and the numba
cache load), the others one ``robotd replay-many`` command into an empty results folder. All modes
must write the same trajectories (checked: the benchmark fails otherwise).

    python bench/replay_many.py [--recordings 8] [--frames 100] [--size 320x200] [--ray] [--json]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def make_recordings(folder: Path, n: int, frames: int, size: str) -> list[Path]:
    import drivers
    from robotd.formats.record import SessionWriter, record_session

    w, h = size.split("x")
    out = []
    for seed in range(1, n + 1):
        url = f"sim://yard?duration={frames / 10 + 1:g}&realtime=0&width={w}&height={h}&fps=10&seed={seed}"
        path = folder / f"drive-{seed:02d}.mcap"
        with drivers.open_camera(url) as cam, drivers.open_vehicle(url) as veh:
            with SessionWriter(path, cam.rectified_model(), {"source": url, "seed": seed}) as wr:
                record_session(cam, veh, wr, duration_s=0, max_frames=frames)
        out.append(path)
    return out


def _robotd(*args: str) -> subprocess.CompletedProcess[str]:
    proc = subprocess.run(
        [sys.executable, "-m", "robotd", *args], cwd=REPO, capture_output=True, text=True, timeout=3600
    )
    if proc.returncode != 0:
        raise SystemExit(f"robotd {' '.join(args[:2])} failed ({proc.returncode}): {proc.stderr[-2000:]}")
    return proc


def one_by_one(recs: list[Path], folder: Path) -> tuple[float, dict[str, str]]:
    t0 = time.perf_counter()
    hashes = {}
    for k, rec in enumerate(recs):
        out = folder / f"single-{k}.txt"
        _robotd("replay", str(rec), "--out", str(out), "--quiet", "--log-level", "WARNING")
        hashes[str(rec)] = hashlib.sha256(out.read_bytes()).hexdigest()
    return time.perf_counter() - t0, hashes


def replay_many(recs: list[Path], out: Path, *engine: str) -> tuple[float, dict[str, str], dict[str, Any]]:
    t0 = time.perf_counter()
    proc = _robotd("replay-many", *map(str, recs), "--out", str(out), "--quiet", "--json", *engine)
    wall = time.perf_counter() - t0
    doc = json.loads(proc.stdout.strip().splitlines()[-1])
    return wall, {r["url"]: r["trajectory_sha256"] for r in doc["rows"]}, doc


def _host() -> str:
    model = ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{model or platform.processor() or platform.machine()}, {os.cpu_count()} CPUs"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--recordings", type=int, default=8)
    ap.add_argument("--frames", type=int, default=100, help="frames per recording (10 Hz)")
    ap.add_argument("--size", default="320x200", help="image size WxH")
    ap.add_argument("--ray", action="store_true", help="also on a local Ray instance (2 CPUs)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    load0 = os.getloadavg()
    with tempfile.TemporaryDirectory(prefix="robotd-bench-replay-many-") as tmp:
        folder = Path(tmp)
        t0 = time.perf_counter()
        recs = make_recordings(folder, args.recordings, args.frames, args.size)
        t_rec = time.perf_counter() - t0
        modes: list[dict[str, Any]] = []
        wall, ref = one_by_one(recs, folder)
        modes.append({"mode": "one by one (robotd replay, in a row)", "wall_s": wall})
        runs: list[tuple[str, tuple[str, ...]]] = [
            ("replay-many --workers 1", ("--workers", "1")),
            ("replay-many --workers 2", ("--workers", "2")),
        ]
        if args.ray:
            runs.append(("replay-many --ray local (2 CPUs)", ("--ray", "local", "--workers", "2")))
        for k, (name, extra) in enumerate(runs):
            wall, hashes, _ = replay_many(recs, folder / f"out-{k}", *extra)
            if hashes != ref:
                raise SystemExit(f"{name}: trajectories differ from the single replays'")
            modes.append({"mode": name, "wall_s": wall})
    base = modes[0]["wall_s"]
    for m in modes:
        m["recordings_per_min"] = 60.0 * args.recordings / m["wall_s"]
        m["speedup"] = base / m["wall_s"]
    out = {
        "benchmark": "replay_many",
        "host": _host(),
        "load_before": load0,
        "load_after": os.getloadavg(),
        "recordings": args.recordings,
        "frames_per_recording": args.frames,
        "size": args.size,
        "recording_s": t_rec,
        "modes": modes,
        "identical_trajectories": True,
    }
    if args.json:
        print(json.dumps(out))
        return 0
    print(
        f"replay-many throughput: {args.recordings} recordings of {args.frames} frames ({args.size}, sim yard), "
        f"{out['host']}, load {load0[0]:.1f} before, {out['load_after'][0]:.1f} after\n"
    )
    print("| mode | wall s | recordings / min | speed-up vs one by one |")
    print("|---|---|---|---|")
    for m in modes:
        print(f"| {m['mode']} | {m['wall_s']:.1f} | {m['recordings_per_min']:.1f} | {m['speedup']:.2f}× |")
    print("\nevery mode wrote the same trajectories, byte for byte")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
