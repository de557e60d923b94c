"""The issue's stall, in the daemon (issue 15): the sim:// camera silent for 4 s and the vehicle's
samples of that time lost (a stopped host), while the rover drives on. Before, the pose after
it was tens of metres off (the constant-velocity prior's σ of 84 m spread the particles) and the
steps failed at the pitch singularity; now the motion across the gap is the constant-velocity
guess (robotd.pipeline.stall), or the images across it where they share enough points, and the
error stays within what driving 4 m blind allows.

The run ends 30 poses after the stall (3 s of the rover's time), not after 11 s of the host's: on a
busy machine those may hold far fewer poses (tests/support/daemon_runs.py)."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import pytest

import robotd.outputs as outputs_mod
from robotd.config import load_config
from robotd.daemon import Daemon
from robotd.outputs import Output, StepReport
from tests.support.daemon_runs import HANG_GUARD_S, run_until


class Collect(Output):
    name = "collect"
    health_period_s = 0.2

    def __init__(self) -> None:
        self.docs: list[dict[str, Any]] = []
        self.frame_seqs: list[int] = []

    def publish(self, report: StepReport) -> None:
        self.frame_seqs.append(report.frame_seq)

    def publish_health(self, health: Mapping[str, Any]) -> None:
        self.docs.append(dict(health))


def test_a_4s_stall_while_driving_leaves_the_daemon_on_track(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    out = Collect()
    monkeypatch.setattr(outputs_mod, "FACTORIES", (*outputs_mod.FACTORIES, ("collect", lambda ctx: out)))
    url = "sim://?fps=10&stall_at=3&stall_s=4"
    cfg = load_config(
        None,
        {
            "camera": {"url": url},
            "vehicle": {"url": url},
            "zenoh": {"enabled": False},
            "persistence": {"state_dir": str(tmp_path), "save_period_s": 0.0},
        },
    )
    d = Daemon(cfg, duration_s=HANG_GUARD_S, environ={})
    stall_end = 70  # frames 30..69 (3 s to 7 s at 10 fps) are never captured

    def done() -> bool:  # 30 poses after the stall, and health documents after it
        after = [k for k, seq in enumerate(list(out.frame_seqs), 1) if seq >= stall_end]
        return len(after) >= 30 and sum(h["frames_processed"] >= after[0] for h in list(out.docs)) >= 10

    status, reached = run_until(d, done)
    assert status == 0 and reached, (d.stop_reason, d.stats.steps)
    # the stall no odometry covers (a busy machine may add short gaps of its own, which it covers)
    assert d.stats.stalls >= 1 and d.stats.stalls_without_odometry == 1
    assert d.stats.step_errors == 0
    after = [h for h in out.docs if h["stalls"] >= 1 and h["error_vs_truth_m"] is not None]
    assert len(after) >= 10
    # 4 m driven blind on a winding loop: the guess's heading may be tens of degrees off, so the
    # error grows after it, but stays metres, not tens of metres (before: 20 m and failing steps)
    assert max(h["error_vs_truth_m"] for h in after) < 5.0, [h["error_vs_truth_m"] for h in after]
    # and health says how uncertain the pose is: the error lies within the 95 % bound its sigma
    # implies. pose_sigma_m is √trace of the position covariance, at least each axis's σ, so 2σ
    # bounds any one axis at 95 % (1.96σ). Blind, the guess's bound (metres) covers it easily;
    # since far points count (2 px disparity), the images bridge this gap (40 inliers across 4 m),
    # mostly through far points, whose depth is only as good as the rig's disparity offset: known to
    # 0.25 px here, which moves the jump by 0.28 m (its sensitivity, 1.1 m per pixel, handed to the
    # reported covariance). Measured: errors 0.12-0.41 m against a sigma of 0.34-0.49 m; without
    # the offset's share, and the filter's spread counted once (docs/slam.md), 0.19-0.44 against
    # 0.19, which this bound caught.
    assert all(h["pose_sigma_m"] is not None and 2.0 * h["pose_sigma_m"] > h["error_vs_truth_m"] for h in after), [
        (h["pose_sigma_m"], round(h["error_vs_truth_m"], 3)) for h in after
    ]
