"""The daemon feeds its pose to an autopilot: sim:// rover, a mock ArduPilot over loopback UDP.

The runs end after a number of poses, not seconds, and the stream is judged by counts and stamps,
not by when the datagrams arrived: on a busy host the gaps between arrivals are the machine's
speed (0.58 s once), which the benchmarks measure (tests/support/daemon_runs.py).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import robotd.outputs as outputs_mod
from drivers.mavlink_mock import MockAutopilot, Received
from robotd.config import load_config
from robotd.daemon import Daemon
from robotd.formats.autopilot import ResetCounterPolicy
from robotd.outputs import Output, StepReport
from tests.support.daemon_runs import HANG_GUARD_S, run_until
from tests.support.tolerances import FLOAT32_ROUNDING_TOL


class Stamps(Output):
    """The capture time of every step the daemon publishes."""

    name = "stamps"

    def __init__(self) -> None:
        self.t_ns: list[int] = []

    def publish(self, report: StepReport) -> None:
        self.t_ns.append(report.result.t_ns)


@dataclass
class Drive:
    daemon: Daemon
    steps: list[int]  # every published step's capture time [ns]
    odometry: list[Received]  # what the autopilot received
    heartbeats: list[Received]
    link: dict[str, Any]  # the autopilot output's counters


def _wait_for(cond: Callable[[], bool], timeout_s: float = 30.0) -> bool:
    """Poll until ``cond()`` (the mock autopilot's receive thread has read what was sent)."""
    deadline = time.monotonic() + timeout_s
    while not cond() and time.monotonic() < deadline:
        time.sleep(0.02)
    return cond()


def _drive(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, poses: int) -> Drive:
    """The daemon on the sim:// rover at 10 fps until it has published ``poses`` poses, however long
    a busy machine takes for them, its pose going to a mock ArduPilot."""
    stamps = Stamps()
    others = tuple(f for f in outputs_mod.FACTORIES if f[0] != "stamps")  # an earlier run's
    monkeypatch.setattr(outputs_mod, "FACTORIES", (*others, ("stamps", lambda ctx: stamps)))
    with MockAutopilot(sysid=7) as ap:
        cfg = load_config(
            None,
            {
                "camera": {"url": "sim://?fps=10"},
                "vehicle": {"url": "sim://?fps=10"},
                "zenoh": {"enabled": False},
                "mavlink": {"enabled": True, "url": ap.url, "system_id": 7},
                "persistence": {"state_dir": str(tmp_path), "save_period_s": 0.0},
            },
        )
        d = Daemon(cfg, duration_s=HANG_GUARD_S, environ={})
        status, reached = run_until(d, lambda: len(stamps.t_ns) >= poses and len(ap.messages("HEARTBEAT")) > 0)
        assert status == 0 and reached, (d.stop_reason, d.stats.steps)
        link = next(o for o in d.outputs if o.name == "autopilot").stats()
        assert _wait_for(lambda: len(ap.messages("ODOMETRY")) >= link["odometry_sent"]), link
        return Drive(d, stamps.t_ns, ap.messages("ODOMETRY"), ap.messages("HEARTBEAT"), link)


def _gaps(steps: list[int]) -> int:
    """Silences between published poses long enough to start a new segment for the autopilot (a
    machine so busy that no frame was processed for over a second)."""
    return int(np.sum(np.diff(steps) > ResetCounterPolicy.max_gap_s * 1e9))


def test_daemon_sends_odometry_to_the_autopilot(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    run = _drive(tmp_path, monkeypatch, poses=30)  # 3 s of the rover's time at 10 fps
    d, odo, link, n = run.daemon, run.odometry, run.link, len(run.steps)
    assert n == d.stats.steps >= 30
    m = odo[-1].msg
    assert (m.frame_id, m.child_frame_id) == (20, 12)
    assert m.get_srcSystem() == 7 and m.get_srcComponent() == 197
    assert abs(np.linalg.norm(m.q) - 1.0) < FLOAT32_ROUNDING_TOL  # float32 on the wire
    t_us = [r.msg.time_usec for r in odo]
    assert np.all(np.diff(t_us) > 0), "time_usec must be strictly increasing"
    # data-driven: one ODOMETRY per step, stamped with its frame's capture time, so the stream has
    # the camera's cadence whenever SLAM keeps up (whether it does on a busy machine is the
    # benchmarks' question; ArduPilot calls 300 ms of silence unhealthy). A pose is only ever
    # superseded by a newer one the transmit thread had not sent yet, and the last one may still
    # be parked when the link closes.
    assert len(odo) == link["odometry_sent"] and link["poses_stale"] == 0
    assert n - 1 <= link["odometry_sent"] + link["poses_superseded"] <= n, (link, n)
    assert len(odo) >= 0.8 * n, f"{len(odo)} ODOMETRY for {n} steps"
    assert set(t_us) <= {t // 1000 for t in run.steps}, "an ODOMETRY not stamped with a step's frame"
    assert run.heartbeats and all(h.msg.get_srcComponent() == 197 for h in run.heartbeats)
    # the rover moved forward: +x in LOCAL_FRD
    assert m.x > 0.5
    # a smooth drive is one segment for the autopilot: no reset (but for a silence of over a
    # second, which only a starved machine makes), and ODOMETRY's velocity is the rover's
    # (sim:// drives at 1 m/s; the body frame is FRD, so forward is +vx)
    gaps = _gaps(run.steps)
    assert d.reset_policy.bumps == gaps, d.reset_policy.last_reason
    assert {r.msg.reset_counter for r in odo} <= set(range(gaps + 1)) and odo[0].msg.reset_counter == 0
    moving = [r.msg for r in odo if r.msg.x > 0.5]
    assert moving and all(0.6 < o.vx < 1.4 and abs(o.vy) < 0.3 and abs(o.vz) < 0.3 for o in moving)


def test_a_restarted_daemon_starts_a_new_segment_for_the_autopilot(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # the second run's counter differs from the last one the first run sent, so the autopilot
    # takes its first pose (a new map's origin, or a resumed map's relocalised pose) as a reset
    first = _drive(tmp_path, monkeypatch, poses=10)
    second = _drive(tmp_path, monkeypatch, poses=10)
    last = [run.daemon.reset_policy.counter for run in (first, second)]  # the last counter each sent
    assert first.odometry[0].msg.reset_counter == 0 and last[0] == _gaps(first.steps)
    assert second.odometry[0].msg.reset_counter == last[0] + 1 and last[1] == last[0] + 1 + _gaps(second.steps)
    assert (tmp_path / "reset_counter").read_text().strip() == str(last[1])
