"""Benchmark of the vehicle links: serial frames/s over a pty and MAVLink messages/s over loopback UDP.

    python bench/drivers_links.py [--seconds 3] [--json]

Serial: the reference MCU simulator writes wheel-odometry frames as fast as the pty takes them;
the ``serial://`` link decodes them and the bench drains its queue. Nominal is 100 Hz; the target
is at least 2x with no frame lost (sequence gaps), no CRC/COBS error and no queue drop.

MAVLink: the mock Rover streams ATTITUDE and WHEEL_DISTANCE at ``--stream-hz`` each while robotd
sends ODOMETRY for every pose the bench offers as fast as it can (data-driven: a newer pose
supersedes an unsent one). Nominal is 30 Hz ODOMETRY; the target is at least 2x plus the inputs.

Prints a Markdown table, or exactly one JSON object on stdout with ``--json``. Figures depend on
the machine's load: state it with the numbers.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from typing import Any

import numpy as np

from drivers.mavlink_link import MavlinkVehicle
from drivers.mavlink_mock import MockAutopilot
from drivers.mcu_sim import McuSimulator, open_pty
from drivers.serial_link import SerialVehicle
from drivers.serial_protocol import WheelOdometry, encode_frame
from robotd.core.msgs import PoseEstimate


def bench_serial(seconds: float) -> dict[str, Any]:
    master, slave, path = open_pty()
    sim = McuSimulator(master, rate_hz=0.0, control_hz=0.0, heartbeat_hz=1.0)
    try:
        with SerialVehicle(f"serial://{path}?baud=115200", queue_size=100_000) as link:
            sim.start()
            time.sleep(0.2)  # warm-up
            s0 = link.stats()
            link.drain()
            n_odo = 0
            t0 = time.perf_counter()
            while time.perf_counter() - t0 < seconds:
                n_odo += len(link.drain())
                time.sleep(0.005)
            dt = time.perf_counter() - t0
            s1 = link.stats()
            sim.stop()
    finally:
        sim.stop()
        os.close(master)
        os.close(slave)
    frames = s1["frames"] - s0["frames"]
    wire = len(encode_frame(WheelOdometry(3, 0, 0, 0.0, 0.0), 0, 0))
    return {
        "frames_per_s": frames / dt,
        "odometry_per_s": n_odo / dt,
        "frames_lost": s1["frames_lost"],
        "crc_errors": s1["crc_errors"],
        "cobs_errors": s1["cobs_errors"],
        "drops": s1["drops"],
        "wheel_frame_bytes": wire,
        "capacity_115200_baud_hz": 115200 / 10 / wire,  # 8N1: 10 bits per byte
        "seconds": dt,
    }


def bench_mavlink(seconds: float, stream_hz: float) -> dict[str, Any]:
    with MockAutopilot(stream_hz=stream_hz, track_width_m=0.4) as ap:
        # no rate requests: the mock keeps ATTITUDE at --stream-hz (it grants at most 40 Hz, as a Rover)
        with MavlinkVehicle(ap.url, track_width_m=0.4, heartbeat_hz=1.0, request_rates=False) as link:
            t_end = time.monotonic() + 3.0
            while not link.link_up and time.monotonic() < t_end:
                time.sleep(0.01)
            time.sleep(0.2)
            s0 = link.stats()
            n_ap0 = len(ap.messages("ODOMETRY"))
            n_poses = 0
            n_odo = 0
            cov = np.eye(6) * 0.01
            t0 = time.perf_counter()
            while time.perf_counter() - t0 < seconds:
                link.autopilot.send_pose(
                    PoseEstimate(time.monotonic_ns(), np.array([n_poses * 1e-3, 0, 0]), np.zeros(3), cov), 80, 0
                )
                n_poses += 1
                n_odo += len(link.drain())
                time.sleep(0.001)
            dt = time.perf_counter() - t0
            time.sleep(0.1)
            s1 = link.stats()
            odo = ap.messages("ODOMETRY")[n_ap0:]
    gaps = np.diff([r.t_ns for r in odo]) * 1e-6 if len(odo) > 1 else np.array([np.nan])
    return {
        "odometry_sent_per_s": (s1["odometry_sent"] - s0["odometry_sent"]) / dt,
        "odometry_received_per_s": len(odo) / dt,
        "poses_offered_per_s": n_poses / dt,
        "poses_superseded": s1["poses_superseded"] - s0["poses_superseded"],
        "max_gap_ms": float(np.max(gaps)),
        "inputs_received_per_s": (s1["rx_messages"] - s0["rx_messages"]) / dt,
        "input_odometry_per_s": n_odo / dt,
        "stream_hz_each": stream_hz,
        "seconds": dt,
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else None)
    p.add_argument("--seconds", type=float, default=3.0)
    p.add_argument("--stream-hz", type=float, default=100.0, help="mock ATTITUDE and WHEEL_DISTANCE rate each")
    p.add_argument("--json", action="store_true")
    a = p.parse_args(argv)
    ser = bench_serial(a.seconds)
    mav = bench_mavlink(a.seconds, a.stream_hz)
    result = {
        "serial": ser,
        "mavlink": mav,
        "conditions": {"cpus": os.cpu_count(), "loadavg_1min": os.getloadavg()[0], "python": sys.version.split()[0]},
        "pass": {
            "serial_2x_100hz_no_loss": ser["frames_per_s"] >= 200
            and ser["frames_lost"] == 0
            and ser["drops"] == 0
            and ser["crc_errors"] == 0,
            "mavlink_2x_30hz_odometry": mav["odometry_received_per_s"] >= 60,
        },
    }
    if a.json:
        print(json.dumps(result))
        return 0
    print(f"Vehicle links ({a.seconds:.1f} s each; {os.cpu_count()} CPUs, load {os.getloadavg()[0]:.1f})\n")
    print("| link | measure | value | target |")
    print("|---|---|---|---|")
    print(f"| serial (pty) | frames/s decoded | {ser['frames_per_s']:.0f} | ≥ 200 (2 × 100 Hz) |")
    print(f"| serial (pty) | odometry samples/s | {ser['odometry_per_s']:.0f} | |")
    print(
        f"| serial (pty) | frames lost / CRC / COBS / drops | {ser['frames_lost']} / {ser['crc_errors']} / "
        f"{ser['cobs_errors']} / {ser['drops']} | 0 |"
    )
    print(
        f"| serial | wheel frame on the wire; max rate at 115200 baud | {ser['wheel_frame_bytes']} B; "
        f"{ser['capacity_115200_baud_hz']:.0f} Hz | ≥ 200 Hz |"
    )
    print(f"| MAVLink (UDP) | ODOMETRY received/s | {mav['odometry_received_per_s']:.0f} | ≥ 60 (2 × 30 Hz) |")
    print(f"| MAVLink (UDP) | max gap between ODOMETRY | {mav['max_gap_ms']:.1f} ms | < 300 ms |")
    print(f"| MAVLink (UDP) | input messages received/s | {mav['inputs_received_per_s']:.0f} | |")
    print(f"| MAVLink (UDP) | input odometry samples/s | {mav['input_odometry_per_s']:.0f} | |")
    print(f"\npass: {result['pass']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
