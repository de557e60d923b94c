#!/usr/bin/env python3
"""The autopilot in the loop: ArduPilot's SITL Rover drives a waypoint mission on robotd's poses.

    python bench/sitl.py                         # every scenario, a Markdown table
    python bench/sitl.py --scenarios main --json
    python bench/sitl.py --quick                 # 0.6 laps (17 m) per scenario

Each scenario is one mission in the closed loop of robotd/research/sitl.py (docs/sitl.md):
ArduPilot's SITL with the project's ground-vehicle physics (drivers/rover_physics.py), robotd in
its own process on ``sim://yard?follow=…`` (the yard rendered from the physics's pose), GPS off,
EKF3 on robotd's ODOMETRY, a mission of waypoints along the yard's loop in AUTO. Figures come
from the SITL's DataFlash log (EKF position against the physics's truth, VISP, AHRS texts) and
robotd's health topic (budget rungs, reset counters, frames without odometry).

Scenarios:

- ``main``: robotd's odometry from the simulated rover's wheels and gyro, robotd the heading
  source (EK3_SRC1_YAW 6, VISO_TYPE 1);
- ``restart``: the same, robotd stopped and started again from its saved map halfway, while the
  rover drives;
- ``restart_hold``: the same, the rover holding still while robotd restarts;
- ``restart_new_ground``: the restart a quarter of the way in, the rover facing ground its map
  does not hold yet: the relocalising window cannot find the map, and the pose comes from the
  autopilot's motion across the restart (robotd/daemon/handover.py);
- ``restart_new_ground_wheels``: the same, EKF3 fusing the rover's wheel encoders beside robotd;
- ``mavlink``: robotd's odometry from the autopilot's own link (simulated wheel encoders'
  WHEEL_DISTANCE, ATTITUDE);
- ``compass``: the compass is the heading source (EK3_SRC1_YAW 1, VISO_TYPE 2), the yard turned
  30° from north: pre-arm must pass with no manual step.

Skips with a message (exit 0) when the SITL binary is absent. Exit 1 when a scenario misses its
criteria (issue 24's evidence), each named in the ``failed`` column.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from robotd.research.sitl import LoopOptions, LoopResult, SitlError, find_sitl, run_loop  # noqa: E402

# wheel encoders on the simulated rover, and EKF3 fusing their velocity beside ExternalNav's
# (source set 2's VELXY, with EK3_SRC_OPTIONS bit 0: fuse every velocity source of the sets)
WHEELS_IN_EKF3: dict[str, float] = {
    "WENC_TYPE": 10,
    "WENC2_TYPE": 10,
    "WENC_POS_Y": -0.15,
    "WENC2_POS_Y": 0.15,
    "WENC_RADIUS": 0.05,
    "WENC2_RADIUS": 0.05,
    "EK3_SRC2_VELXY": 7,
    "EK3_SRC_OPTIONS": 1,
}

SCENARIOS: dict[str, LoopOptions] = {
    "main": LoopOptions(),
    "restart": LoopOptions(restart_at=0.5),
    "restart_hold": LoopOptions(restart_at=0.5, hold_for_restart=True),
    # a quarter in: the first lap not done, the rover comes up facing ground the map does not hold
    "restart_new_ground": LoopOptions(restart_at=0.25),
    # the same with the rover's wheel encoders fused by EKF3 beside robotd (docs/mavlink.md §9):
    # the autopilot then dead-reckons through robotd's downtime on its wheels, not its IMU alone
    "restart_new_ground_wheels": LoopOptions(restart_at=0.25, extra_params=tuple(WHEELS_IN_EKF3.items())),
    "mavlink": LoopOptions(vehicle="mavlink"),
    "compass": LoopOptions(yaw_source="compass", yaw0_deg=30.0),
}

EKF_RMS_MAX_M = 0.2
XTRACK_MAX_M = 0.5
L0_MIN = 0.9


def judge(name: str, r: LoopResult, quick: bool) -> list[str]:
    """The criteria the scenario misses (issue 24's evidence), empty when it meets them all."""
    f = r.figures
    rb = r.robotd
    failed: list[str] = []
    if not r.completed:
        failed.append(f"not completed: {r.reason}")
        return failed
    if not quick and (r.waypoints < 4 or r.mission_length_m < 60.0):
        failed.append(f"mission {r.waypoints} waypoints, {r.mission_length_m:.0f} m (≥ 4 and ≥ 60 m)")
    if f.get("dcm_fallbacks", 0):
        failed.append(f"AHRS fell back to DCM {f['dcm_fallbacks']}×")
    if f.get("stopped_aiding", 0):
        failed.append("EKF3 stopped aiding")
    if not f.get("ekf_error_rms_m", math.inf) <= EKF_RMS_MAX_M:
        failed.append(f"EKF error RMS {f.get('ekf_error_rms_m', math.nan):.3f} m (≤ {EKF_RMS_MAX_M})")
    if not f.get("cross_track_max_m", math.inf) <= XTRACK_MAX_M:
        failed.append(f"cross-track max {f.get('cross_track_max_m', math.nan):.2f} m (≤ {XTRACK_MAX_M})")
    counters = rb.get("reset_counters") or []
    # the counter changes only where robotd means it to: a new run's first pose, and a bump at a
    # deliberate event (a relocalisation in the loaded map, the handover's pose, a map load);
    # never at a jump, a gap or a stall the autopilot would have to absorb
    deliberate = {"relocalisation", "map_load"}
    accidental = [f"{c}: {why}" for c, why in rb.get("reset_bumps") or [] if why not in deliberate]
    if accidental or (not name.startswith("restart") and len(counters) > 1):
        failed.append(f"reset_counter changed {len(counters) - 1}× ({counters}; {', '.join(accidental) or 'no bump'})")
    if not rb.get("l0_fraction", 0.0) >= L0_MIN:
        failed.append(f"budget L0 {100 * rb.get('l0_fraction', 0.0):.0f} % of frames (≥ {100 * L0_MIN:.0f} %)")
    if name == "mavlink" and rb.get("frames_without_odometry"):
        failed.append(f"{rb['frames_without_odometry']} frames without odometry")
    if name == "compass" and not r.armed:
        failed.append("did not arm")
    return failed


def row(name: str, r: LoopResult, failed: list[str]) -> dict[str, Any]:
    f, rb = r.figures, r.robotd
    return {
        "scenario": name,
        "completed": r.completed,
        "waypoints": r.waypoints,
        "mission_m": round(r.mission_length_m, 1),
        "driven_m": round(r.driven_m, 1),
        "mission_s": round(r.mission_s, 1),
        "ekf_rms_m": f.get("ekf_error_rms_m"),
        "ekf_max_m": f.get("ekf_error_max_m"),
        "xtrack_max_m": f.get("cross_track_max_m"),
        "xtrack_rms_m": f.get("cross_track_rms_m"),
        "reset_counters": rb.get("reset_counters"),
        "reset_bumps": rb.get("reset_bumps"),
        "visp_ignored": f.get("visp_ignored"),
        "visp_max_gap_s": f.get("visp_max_gap_s"),
        "dcm_fallbacks": f.get("dcm_fallbacks"),
        "l0_fraction": rb.get("l0_fraction"),
        "frames_at_level": rb.get("frames_at_level"),
        "frames_without_odometry": rb.get("frames_without_odometry"),
        "restart_gap_s": f.get("restart_gap_s"),
        "prearm_failures": r.prearm_failures,
        "failed": failed,
    }


def _fmt(v: Any, digits: int = 3) -> str:
    if isinstance(v, float):
        return "n/a" if math.isnan(v) else f"{v:.{digits}f}"
    return "n/a" if v is None else str(v)


def table(rows: list[dict[str, Any]]) -> str:
    head = (
        "| scenario | done | mission | EKF vs truth RMS / max m | cross-track max m | reset counters | "
        "L0 % | frames w/o odometry | failed |"
    )
    out = [head, "|" + "---|" * 9]
    for r in rows:
        l0 = r["l0_fraction"]
        out.append(
            f"| {r['scenario']} | {'yes' if r['completed'] else 'no'} | {r['waypoints']} wp, {r['mission_m']} m "
            f"({r['driven_m']} m driven, {r['mission_s']} s) | {_fmt(r['ekf_rms_m'])} / {_fmt(r['ekf_max_m'])} | "
            f"{_fmt(r['xtrack_max_m'], 2)} | {r['reset_counters']} | "
            f"{'n/a' if l0 is None or (isinstance(l0, float) and math.isnan(l0)) else f'{100 * l0:.0f}'} | "
            f"{_fmt(r['frames_without_odometry'])} | {'; '.join(r['failed']) or '—'} |"
        )
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--scenarios", default=",".join(SCENARIOS), help=f"comma-separated, of {', '.join(SCENARIOS)}")
    ap.add_argument("--json", action="store_true", help="one JSON object on stdout")
    ap.add_argument("--quick", action="store_true", help="0.6 laps (17 m) per scenario; the 60 m criterion is off")
    ap.add_argument("--fps", type=float, default=None, help="camera rate [Hz] (default 30)")
    ap.add_argument("--speedup", type=float, default=None, help="SITL's --speedup (default 1)")
    ap.add_argument("--laps", type=float, default=None, help="laps of the yard's 28.5 m loop (default 2.2)")
    ap.add_argument(
        "--keep",
        metavar="DIR",
        help="keep each run's files (SITL log, robotd log) under DIR/<scenario> (DIR/<scenario>-2 … when taken)",
    )
    ap.add_argument("-v", "--verbose", action="store_true", help="log the loop's progress and the SITL's texts")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, format="%(asctime)s %(message)s")
    names = [n.strip() for n in args.scenarios.split(",") if n.strip()]
    unknown = [n for n in names if n not in SCENARIOS]
    if unknown:
        ap.error(f"unknown scenario(s) {', '.join(unknown)}; known: {', '.join(SCENARIOS)}")
    if find_sitl() is None:
        msg = "ArduPilot SITL (ardurover) not found beside the repository or in $ROBOTD_ARDUPILOT_SITL: skipped"
        print(json.dumps({"skipped": msg}) if args.json else msg)
        return 0
    rows: list[dict[str, Any]] = []
    for name in names:
        opts = SCENARIOS[name]
        over: dict[str, Any] = {}
        if args.quick:
            over["laps"] = 0.6
        for key in ("fps", "speedup", "laps"):
            if getattr(args, key) is not None:
                over[key] = getattr(args, key)
        if args.keep:
            # a directory of its own per run: a state directory left by an earlier run of the same
            # scenario would be resumed by this one's robotd (its map, its reset counter)
            workdir, k = Path(args.keep) / name, 1
            while workdir.exists():
                k += 1
                workdir = Path(args.keep) / f"{name}-{k}"
            over["workdir"] = str(workdir)
        opts = replace(opts, **over)
        print(f"{name}: running ({opts.laps} laps at {opts.speed_mps} m/s, camera {opts.fps:g} Hz)", file=sys.stderr)
        try:
            res = run_loop(opts)
        except SitlError as exc:
            res = LoopResult(options={}, reason=str(exc))
        failed = judge(name, res, args.quick)
        rows.append(row(name, res, failed))
        print(f"{name}: {'ok' if not failed else 'FAILED: ' + '; '.join(failed)}", file=sys.stderr)
    if args.json:
        print(json.dumps({"scenarios": rows}, default=str))
    else:
        print(table(rows))
    return 1 if any(r["failed"] for r in rows) else 0


if __name__ == "__main__":
    sys.exit(main())
