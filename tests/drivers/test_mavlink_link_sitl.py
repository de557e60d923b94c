"""The MAVLink link against the real autopilot: ArduPilot Rover built for SITL
(``../shared/tools/ardupilot-sitl/``, its README), issue 24.

Skipped, with the path it looked at, when the binary is absent; ``ROBOTD_ARDUPILOT_SITL`` names
another binary (or its folder). SITL runs as its README shows: loopback only, every serial port
mapped, ``--model rover`` (its own physics, on wall time), in a temporary directory, killed by
the fixture. Nothing here judges wall-clock times or rates: only the autopilot's answers, message
counts, and the autopilot's own time stamps (through the TIMESYNC mapping).
"""

from __future__ import annotations

import itertools
import logging
import os
import signal
import socket
import subprocess
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from drivers.mavlink_link import MavlinkVehicle
from drivers.mavlink_options import DEFAULT_RATES_HZ
from robotd.pipeline.odometry import OdometryIntegrator
from tests.support.paths import REPO

SITL_ENV = "ROBOTD_ARDUPILOT_SITL"
S = 1_000_000_000


def sitl_binary() -> Path:
    """``$ROBOTD_ARDUPILOT_SITL`` (the binary or its folder), else the shared tools beside the repository."""
    env = os.environ.get(SITL_ENV)
    if env:
        p = Path(env)
        return p / "ardurover" if p.is_dir() else p
    return REPO.parent / "shared" / "tools" / "ardupilot-sitl" / "ardurover"


def wait_for(cond: Callable[[], bool], timeout_s: float) -> bool:
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        if cond():
            return True
        time.sleep(0.05)
    return cond()


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _free_instance() -> int:
    """A SITL instance number whose RC-input port (5501 + 10 I, which SITL binds on every
    address) no other SITL on this machine holds (a bind on loopback fails then too)."""
    for instance in range(11, 60):
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            try:
                s.bind(("127.0.0.1", 5501 + 10 * instance))
            except OSError:
                continue
            return instance
    pytest.skip("no free SITL instance number (RC-input ports 5611-6091 all taken)")


@dataclass
class Sitl:
    proc: subprocess.Popen[bytes]
    url: str  # robotd's side of SITL's SERIAL1 (MAVLink 2)
    log: Path


@pytest.fixture
def sitl(tmp_path: Path) -> Iterator[Sitl]:
    binary = sitl_binary()
    if not (binary.is_file() and os.access(binary, os.X_OK)):
        pytest.skip(f"ArduPilot SITL not found at {binary} (set {SITL_ENV} to the ardurover binary)")
    parm = binary.parent / "rover.parm"
    (tmp_path / "extra.parm").write_text("SERIAL1_PROTOCOL 2\n")
    gcs = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)  # SERIAL0's ground station: a sink
    gcs.bind(("127.0.0.1", 0))
    port = _free_udp_port()
    log = tmp_path / "sitl.log"
    # the README's command line, with this test's ports and instance
    cmd = [
        str(binary),
        "-w",
        "--model",
        "rover",
        "--speedup",
        "1",
        "--defaults",
        f"{parm},extra.parm",
        f"-I{_free_instance()}",
        "--home",
        "-35.363261,149.165230,584,0",
        "--sim-address=127.0.0.1",
        "--serial0",
        f"udpclient:127.0.0.1:{gcs.getsockname()[1]}",
        "--serial1",
        f"udpclient:127.0.0.1:{port}",
        *itertools.chain.from_iterable(("--serial" + str(n), "none") for n in (2, 5, 6, 7, 8)),
    ]
    with open(log, "wb") as out:
        proc = subprocess.Popen(cmd, cwd=tmp_path, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        yield Sitl(proc, f"mavlink+udp://127.0.0.1:{port}?mode=in", log)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGTERM)  # its own session: SITL and anything it started
            try:
                proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait(timeout=5)
        gcs.close()


def test_rover_grants_the_default_rates_refuses_the_rest_and_its_odometry_covers_every_frame(
    sitl: Sitl, caplog: pytest.LogCaptureFixture
) -> None:
    """ArduPilot Rover (SCHED_LOOP_RATE 50): robotd's default rates are all granted; ATTITUDE at
    50 Hz is refused and granted at 25 Hz; WHEEL_DISTANCE is refused at any rate (issue 24,
    item 5). The LOCAL_POSITION_NED odometry then reaches the integrator without a hole: every
    15 Hz frame across it is covered (item 6: about half were not)."""
    caplog.set_level(logging.INFO, logger="drivers.mavlink_link")
    rates = {**DEFAULT_RATES_HZ, "ATTITUDE": 50.0, "WHEEL_DISTANCE": 10.0}
    link = MavlinkVehicle(sitl.url, rates_hz=rates)
    link._setup.rates.ack_timeout_s = 5.0  # SITL answers within a loop or two; a busy CI machine may be slower
    n_requests = len(rates) + 2  # ATTITUDE and WHEEL_DISTANCE asked twice
    with link:
        assert wait_for(lambda: link.link_up, 20.0), f"no heartbeat from SITL (log: {sitl.log})"
        done = lambda: sum(link.stats()[k] for k in ("rates_accepted", "rates_refused", "rates_unacknowledged"))  # noqa: E731
        assert wait_for(lambda: done() >= n_requests, 30.0), link.stats()
        st = link.stats()
        # the odometry: LOCAL_POSITION_NED once the SITL's EKF has a position (its first ~10 s)
        assert wait_for(lambda: link.stats()["odometry"] >= 5, 40.0), f"no LOCAL_POSITION_NED: {link.stats()}"
        link.drain()
        rx0 = dict(link.stats()["rx_types"])
        odo: list = []
        assert wait_for(lambda: bool(odo.extend(link.drain())) or len(odo) >= 40, 30.0), len(odo)
        st2 = link.stats()
        odo += link.drain()
    # -- item 5: what was granted and refused, each refusal in the log and in stats()
    assert st["rates_unacknowledged"] == 0
    assert st["rates_granted"] == [f"{k} {hz:g} Hz" for k, hz in DEFAULT_RATES_HZ.items()]
    refused = [m.split(": ") for m in st["rates_refused_messages"]]
    assert [r[0] for r in refused] == ["ATTITUDE 50 Hz", "WHEEL_DISTANCE 10 Hz", "WHEEL_DISTANCE 5 Hz"]
    assert all(r[1] in ("MAV_RESULT_DENIED", "MAV_RESULT_FAILED") for r in refused)  # DENIED in 4.7
    assert st["rates_refused"] == 3 and st["state"] == "ok"
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING and "refused" in r.getMessage()]
    assert len(warnings) == 3
    # ATTITUDE at the granted rate, judged against SITL's own 1 Hz SYSTEM_TIME (granted too)
    rx = {k: st2["rx_types"].get(k, 0) - rx0.get(k, 0) for k in ("ATTITUDE", "SYSTEM_TIME", "LOCAL_POSITION_NED")}
    assert rx["ATTITUDE"] >= 10 * max(rx["SYSTEM_TIME"], 1), rx
    # -- item 6: every LOCAL_POSITION_NED became a sample; no holes on the autopilot's clock
    assert st2["no_attitude"] == 0
    assert len(odo) >= rx["LOCAL_POSITION_NED"] - 2, (len(odo), rx)
    t = np.array([o.t_ns for o in odo])
    assert np.all(np.diff(t) > 0) and np.max(np.diff(t)) < 0.5 * S, np.diff(t) / S
    integ = OdometryIntegrator(max_gap_s=0.5)
    for o in odo:
        integ.add(o)
    frames = np.arange(t[0], t[-1], S // 15)
    covered = [integ.integrate(int(a), int(b)) is not None for a, b in itertools.pairwise(frames)]
    assert all(covered), f"{covered.count(False)} of {len(covered)} frames without odometry"
