"""Health tells the truth (issue 15, item 8): stalls, frames without odometry and a silent vehicle
link show in the health document and its ``state``, which is never ``ok`` while they last; a stall
that no odometry covers is a pose discontinuity for the autopilot (reset_counter)."""

from __future__ import annotations

import dataclasses
import os
import threading
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import pytest

import drivers.sim
import robotd.outputs as outputs_mod
from robotd.config import load_config
from robotd.daemon import Daemon
from robotd.daemon.health import MAX_POSE_SIGMA_M, HealthMonitor
from robotd.outputs import Output, StepReport


class Collect(Output):
    """Every health document and step report the daemon publishes."""

    name = "collect"
    health_period_s = 0.2

    def __init__(self) -> None:
        self.docs: list[dict[str, Any]] = []
        self.reports: list[StepReport] = []

    def publish(self, report: StepReport) -> None:
        self.reports.append(report)

    def publish_health(self, health: Mapping[str, Any]) -> None:
        self.docs.append(dict(health))


@pytest.fixture
def collect(monkeypatch: pytest.MonkeyPatch) -> Collect:
    out = Collect()
    monkeypatch.setattr(outputs_mod, "FACTORIES", (*outputs_mod.FACTORIES, ("collect", lambda ctx: out)))
    return out


def _daemon(tmp_path: Path, vehicle: str = "sim://?fps=20", duration_s: float = 5.0) -> Daemon:
    cfg = load_config(
        None,
        {
            "camera": {"url": "sim://?fps=20"},
            "vehicle": {"url": vehicle},
            "zenoh": {"enabled": False},
            "persistence": {"state_dir": str(tmp_path), "save_period_s": 0.0},
        },
    )
    return Daemon(cfg, duration_s=duration_s, environ={})


def test_a_stall_without_odometry_is_counted_shown_and_a_discontinuity(tmp_path, monkeypatch, collect) -> None:
    stalling = threading.Event()
    real_frames, real_odometry = drivers.sim.SimCamera.frames, drivers.sim.SimVehicle.odometry

    def frames(self, timeout_s: float = 1.0):
        for k, frame in enumerate(real_frames(self, timeout_s)):
            if k == 30:  # the camera (and with it the rover's USB hub) stops for 1.5 s
                stalling.set()
                time.sleep(1.5)
                stalling.clear()
            yield frame

    def odometry(self, timeout_s: float = 1.0):
        for odo in real_odometry(self, timeout_s):
            if not stalling.is_set():
                yield odo

    monkeypatch.setattr(drivers.sim.SimCamera, "frames", frames)
    monkeypatch.setattr(drivers.sim.SimVehicle, "odometry", odometry)
    d = _daemon(tmp_path)
    assert d.run() == 0
    st = d.stats
    assert st.stalls == 1 and st.camera_stalls == 1 and st.stalls_without_odometry == 1
    assert 1.3 < st.longest_stall_s < 2.5
    assert st.frames_missed >= 20  # the camera's frames during the stall, which "dropped 0" hid
    assert st.frames_without_odometry >= 1
    after = [h for h in collect.docs if h["stalls"] >= 1]
    assert after and all(h["state"] != "ok" for h in after if h["since_stall_s"] < 4.0)
    assert any(p.startswith("stall 1.") for h in after for p in h["problems"])
    # the autopilot hears of the discontinuity: reset_counter changes at the first pose after it
    seqs = [r.frame_seq for r in collect.reports]
    k = next(i for i in range(1, len(seqs)) if seqs[i] - seqs[i - 1] > 20)
    assert collect.reports[k].reset_counter != collect.reports[k - 1].reset_counter
    line = d.health.status_line(d.health_doc(), 20.0)
    assert f"dropped {st.frames_missed + d.frame_q.dropped} " in line


def test_odometry_two_seconds_behind_the_frames_is_counted(tmp_path, monkeypatch, collect) -> None:
    real_odometry = drivers.sim.SimVehicle.odometry

    def odometry(self, timeout_s: float = 1.0):
        for odo in real_odometry(self, timeout_s):  # the MCU's clock mapping is 2 s off
            yield dataclasses.replace(odo, t_ns=odo.t_ns - 2_000_000_000)

    monkeypatch.setattr(drivers.sim.SimVehicle, "odometry", odometry)
    d = _daemon(tmp_path, duration_s=4.0)
    assert d.run() == 0
    assert d.stats.steps > 20
    assert d.stats.frames_without_odometry >= d.stats.steps - 2  # every frame after the first
    late = [h for h in collect.docs if h["frames_processed"] > 5]
    assert late and all(h["state"] != "ok" for h in late)
    assert any(p.startswith("frames without odometry") for p in late[-1]["problems"])
    assert late[-1]["odometry"]["gaps"] >= late[-1]["frames_processed"] - 2


def test_frames_before_the_first_odometry_are_not_frames_without_it(tmp_path, monkeypatch, collect) -> None:
    # an autopilot's EKF sends no velocity for its first seconds: the frames before the vehicle's
    # first sample are counted apart, and the link is not blamed for them
    real_odometry = drivers.sim.SimVehicle.odometry

    def odometry(self, timeout_s: float = 1.0):
        for odo in real_odometry(self, timeout_s):
            if odo.t_ns >= self.t0_ns + 1_500_000_000:
                yield odo

    monkeypatch.setattr(drivers.sim.SimVehicle, "odometry", odometry)
    d = _daemon(tmp_path, duration_s=4.0)
    assert d.run() == 0
    assert d.stats.steps > 20
    assert d.stats.frames_before_odometry >= 5
    assert d.stats.frames_without_odometry <= 1  # at most the frame the first sample lands in
    assert collect.docs and collect.docs[-1]["frames_before_odometry"] == d.stats.frames_before_odometry
    assert not any(p.startswith("frames without odometry") for p in collect.docs[-1]["problems"])


def test_a_silent_serial_vehicle_is_never_ok(tmp_path, collect) -> None:
    master, slave = os.openpty()
    try:
        path = os.ttyname(slave)
        d = _daemon(tmp_path, vehicle=f"serial://{path}?baud=115200", duration_s=4.0)
        assert d.run() == 0
    finally:
        os.close(master)
        os.close(slave)
    docs = [h for h in collect.docs if h["frames_processed"] > 0]
    assert docs and all(h["state"] != "ok" for h in docs)
    assert docs[-1]["vehicle"]["state"] == "lost" and "vehicle link lost" in docs[-1]["problems"]


def _doc(**kw: Any) -> dict[str, Any]:
    doc: dict[str, Any] = {"tracking": True, "budget": {"level": 0}, "vehicle": {"state": "ok"}, "map_file": {}}
    doc["pose_sigma_m"] = 0.05
    doc.update(kw)
    return doc


def test_assess_reports_each_problem_and_ok_only_without_any() -> None:
    h = HealthMonitor()
    assert h.assess(_doc(), needs_vehicle=True)["state"] == "starting"
    h._last = object()  # type: ignore[assignment]  # a step was published
    h.stats.last_step_ns = time.monotonic_ns()
    assert h.assess(_doc(), needs_vehicle=True) | {} == {**_doc(), "state": "ok", "problems": []}
    cases = {
        "vehicle link degraded": _doc(vehicle={"state": "degraded"}),
        "map save failed (3)": _doc(map_file={"last_failed": True, "failures": 3}),
        f"pose sigma {2 * MAX_POSE_SIGMA_M:.2g} m": _doc(pose_sigma_m=2 * MAX_POSE_SIGMA_M),
        "pose sigma inf m": _doc(pose_sigma_m=None),
        "budget L2": _doc(budget={"level": 2}),
    }
    for problem, doc in cases.items():
        got = h.assess(doc, needs_vehicle=True)
        assert got["state"] == "degraded" and got["problems"] == [problem], (problem, got["problems"])
    h.stats.last_step_error_ns, h.stats.step_errors = time.monotonic_ns(), 7
    assert h.assess(_doc(), needs_vehicle=True)["problems"] == ["frames failing (7)"]
    h.stats.last_step_error_ns = 0
    h.stats.last_step_ns = time.monotonic_ns() - 3_000_000_000
    assert h.assess(_doc(), needs_vehicle=True)["problems"] == ["no SLAM step for 3.0 s"]
    h.stats.last_step_ns = time.monotonic_ns() - 6_000_000_000
    assert h.assess(_doc(), needs_vehicle=True)["state"] == "failed"
    h.stats.last_step_ns = time.monotonic_ns()
    got = h.assess(_doc(tracking=False), needs_vehicle=True)
    assert got["state"] == "failed" and got["problems"] == ["tracking lost"]
    assert h.assess(_doc(vehicle={"state": "lost"}), needs_vehicle=False)["state"] == "ok"  # none://
