"""The daemon feeds its pose to an autopilot: sim:// rover, a mock ArduPilot over loopback UDP."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np

from drivers.mavlink_mock import MockAutopilot
from robotd.config import load_config
from robotd.daemon import Daemon
from tests.support.tolerances import FLOAT32_ROUNDING_TOL


def _run_daemon(ap: MockAutopilot, state_dir: Path, seconds: float) -> Daemon:
    """The daemon on sim:// at 10 Hz for ``seconds``, its pose going to ``ap`` over MAVLink."""
    cfg = load_config(
        None,
        {
            "camera": {"url": "sim://?fps=10"},
            "vehicle": {"url": "sim://?fps=10"},
            "zenoh": {"enabled": False},
            "mavlink": {"enabled": True, "url": ap.url, "system_id": 7},
            "persistence": {"state_dir": str(state_dir), "save_period_s": 0.0},
        },
    )
    d = Daemon(cfg, duration_s=seconds, environ={})
    th = threading.Thread(target=d.run)
    th.start()
    th.join(30 + seconds)
    assert not th.is_alive()
    return d


def test_daemon_sends_odometry_to_the_autopilot(tmp_path: Path) -> None:
    with MockAutopilot(sysid=7) as ap:
        d = _run_daemon(ap, tmp_path, 6.0)
        odo = [r for r in ap.messages("ODOMETRY")]
        hb = [r for r in ap.messages("HEARTBEAT")]
    assert d.stats.steps > 10
    assert len(odo) >= 0.8 * d.stats.steps, f"{len(odo)} ODOMETRY for {d.stats.steps} steps"
    m = odo[-1].msg
    assert (m.frame_id, m.child_frame_id) == (20, 12)
    assert m.get_srcSystem() == 7 and m.get_srcComponent() == 197
    assert abs(np.linalg.norm(m.q) - 1.0) < FLOAT32_ROUNDING_TOL  # float32 on the wire
    t_us = [r.msg.time_usec for r in odo]
    assert np.all(np.diff(t_us) > 0), "time_usec must be strictly increasing"
    # data-driven at the frame rate: never the 300 ms silence ArduPilot calls unhealthy
    arrivals = np.array([r.t_ns for r in odo[2:]]) / 1e9
    assert np.max(np.diff(arrivals)) < 0.3
    assert hb and all(h.msg.get_srcComponent() == 197 for h in hb)
    # the rover moved forward: +x in LOCAL_FRD
    assert m.x > 0.5
    # a smooth drive is one segment for the autopilot: no reset, and ODOMETRY's velocity is the
    # rover's (sim:// drives at 1 m/s; the body frame is FRD, so forward is +vx)
    assert {r.msg.reset_counter for r in odo} == {0}, d.reset_policy.last_reason
    moving = [r.msg for r in odo if r.msg.x > 0.5]
    assert moving and all(0.6 < o.vx < 1.4 and abs(o.vy) < 0.3 and abs(o.vz) < 0.3 for o in moving)


def test_a_restarted_daemon_starts_a_new_segment_for_the_autopilot(tmp_path: Path) -> None:
    # the second run's counter differs from the last one the first run sent, so the autopilot
    # takes its first pose (a new map's origin, or a resumed map's relocalised pose) as a reset
    counters = []
    for _run in range(2):
        with MockAutopilot(sysid=7) as ap:
            _run_daemon(ap, tmp_path, 3.0)
            counters.append({r.msg.reset_counter for r in ap.messages("ODOMETRY")})
    assert counters[0] == {0} and counters[1] == {1}
    assert (tmp_path / "reset_counter").read_text().strip() == "1"
