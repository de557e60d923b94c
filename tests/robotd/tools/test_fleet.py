"""A fleet on one Zenoh network (robotd/tools/fleet.py): three robotd on loopback, each a peer of one router
(``robotd router``), each publishing under its own robot id; ``robotd fleet`` lists the three live
rovers with their health, then two once one is stopped; each keeps its own state directory, and a
fourth pointed at a directory in use is refused in one line."""

from __future__ import annotations

import contextlib
import io
import json
import signal
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

import pytest
import zenoh

from robotd.formats.persist import MapStore
from robotd.tools.cli import main
from tests.support.net import free_port, zenoh_client
from tests.support.paths import REPO
from tests.support.waiting import wait_for

ROBOTS = ("r1", "r2", "r3")


def _config(tmp: Path, rid: str, router: int, state_dir: Path | None = None) -> Path:
    cfg = tmp / f"{rid}.toml"
    cfg.write_text(
        f'[robot]\nid = "{rid}"\n'
        '[camera]\nurl = "sim://?fps=10&width=160&height=100"\n[vehicle]\nurl = "sim://?fps=10"\n'
        f'[zenoh]\nmode = "peer"\nlisten = ["tcp/127.0.0.1:{free_port()}"]\nconnect = ["tcp/127.0.0.1:{router}"]\n'
        f'[persistence]\nstate_dir = "{state_dir or tmp / f"state-{rid}"}"\n'
    )
    return cfg


def _robotd(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "robotd", *args], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
    )


def _fleet(router: int) -> dict[str, Any]:
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        main(["fleet", "--connect", f"tcp/127.0.0.1:{router}", "--json", "--wait", "8"])
    return json.loads(buf.getvalue().strip().splitlines()[-1])


def _exited(proc: subprocess.Popen[str], timeout_s: float) -> bool:
    try:
        proc.wait(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        return False
    return True


def _stop(proc: subprocess.Popen[str]) -> str:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
    try:
        out, _ = proc.communicate(timeout=60)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, _ = proc.communicate()
    return out


@pytest.mark.slow
def test_three_rovers_through_one_router_each_under_its_own_id(tmp_path: Path) -> None:
    port = free_port()
    router = _robotd("router", "--listen", f"tcp/127.0.0.1:{port}")
    rovers: dict[str, subprocess.Popen[str]] = {}
    poses: dict[str, list[tuple[str, dict[str, Any]]]] = {r: [] for r in ROBOTS}
    tokens: list[tuple[str, str]] = []
    lock = threading.Lock()
    session = None
    try:
        assert router.stdout is not None
        line = router.stdout.readline()
        assert "robotd router" in line and "listening" in line, line
        session = zenoh.open(zenoh_client(port))

        def on_pose(sample: zenoh.Sample) -> None:
            key = str(sample.key_expr)
            with lock:
                poses.setdefault(key.split("/")[1], []).append((key, json.loads(sample.payload.to_bytes())))

        def on_token(sample: zenoh.Sample) -> None:
            with lock:
                tokens.append((str(sample.key_expr), "put" if sample.kind == zenoh.SampleKind.PUT else "delete"))

        subs = [
            session.declare_subscriber("robotd/*/pose", on_pose),
            session.liveliness().declare_subscriber("robotd/*/alive", on_token, history=True),
        ]
        for rid in ROBOTS:
            rovers[rid] = _robotd("run", "--config", str(_config(tmp_path, rid, port)))

        # each one's topics arrive under its own robot id, and say so in their payload
        assert wait_for(lambda: all(len(poses[r]) >= 3 for r in ROBOTS), 60.0), {r: len(p) for r, p in poses.items()}
        with lock:
            for rid in ROBOTS:
                assert {k for k, _ in poses[rid]} == {f"robotd/{rid}/pose"}
                assert {d["robot"] for _, d in poses[rid]} == {rid}
            assert set(poses) == set(ROBOTS), "poses of a robot nobody started"

        # the fleet view: three live rovers, each with its own health
        view = _fleet(port)
        assert [r["robot"] for r in view["robots"]] == list(ROBOTS)
        for r in view["robots"]:
            assert r["robot_in_payload"] == r["robot"] and r["state"] in ("starting", "ok", "degraded"), r
            assert r["xyz_m"] is not None and r["fps"] is not None

        # a fourth robotd on r1's state directory is refused in one line, before anything slow
        r4 = _config(tmp_path, "r4", port, state_dir=tmp_path / "state-r1")
        fourth = _robotd("run", "--config", str(r4), "--duration", "30")  # bounded, should it run
        out4 = _stop(fourth) if not _exited(fourth, 120.0) else fourth.communicate()[0]
        errors = [ln for ln in out4.splitlines() if "ERROR" in ln]
        assert fourth.returncode == 2 and len(errors) == 1, out4[-3000:]
        assert f"persistence.state_dir {tmp_path / 'state-r1'} is in use by robotd r1" in errors[0]

        # r2 stops: its token goes, the fleet shows two
        out2 = _stop(rovers.pop("r2"))
        assert "map saved" in out2, out2[-3000:]
        assert wait_for(lambda: ("robotd/r2/alive", "delete") in tokens, 30.0), tokens
        assert [r["robot"] for r in _fleet(port)["robots"]] == ["r1", "r3"]
        with lock:
            assert {k for k, kind in tokens if kind == "put"} == {f"robotd/{r}/alive" for r in ROBOTS}
            assert ("robotd/r1/alive", "delete") not in tokens and ("robotd/r3/alive", "delete") not in tokens
        for s in subs:
            s.undeclare()
    finally:
        outs = {rid: _stop(p) for rid, p in rovers.items()}
        _stop(router)
        if session is not None:
            session.close()
    assert all("map saved" in o for o in outs.values()), {k: v[-2000:] for k, v in outs.items()}
    # nothing of one rover's map in another's state: each directory holds its own robot's map only
    for rid in ROBOTS:
        state = tmp_path / f"state-{rid}"
        assert MapStore(state, rid).load()["state"], rid  # the map there is this robot's (else refused)
        assert (state / "robotd.lock").read_text().split()[0] == rid
        assert not list(state.glob("map.robotd.bad-*")) and not list(state.glob("map.2*.robotd"))


def test_the_fleet_configurations_load_and_the_rover_limits_what_crosses_its_radio(tmp_path: Path) -> None:
    """config/zenoh-base-station.json5 and config/zenoh-rover.json5 are valid for this Zenoh; the
    rover's radio rules (here on loopback instead of wlan0) let through the pose at 5 Hz, the map at
    0.1 Hz and every health message."""
    import time

    for name in ("zenoh-base-station.json5", "zenoh-rover.json5"):
        zenoh.Config.from_file(str(REPO / "config" / name))
    rover_file = tmp_path / "rover-lo.json5"
    rover_file.write_text((REPO / "config" / "zenoh-rover.json5").read_text().replace('"wlan0"', '"lo"'))
    port = free_port()
    conf = zenoh.Config.from_file(str(rover_file))
    conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    conf.insert_json5("listen/endpoints", json.dumps(["tcp/127.0.0.1:0"]))
    router = zenoh.Config()
    router.insert_json5("mode", '"router"')
    router.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    router.insert_json5("scouting/multicast/enabled", "false")
    got: dict[str, int] = {}
    with zenoh.open(router), zenoh.open(zenoh_client(port)) as ground:
        ground.declare_subscriber(
            "robotd/**", lambda s: got.__setitem__(str(s.key_expr), got.get(str(s.key_expr), 0) + 1)
        )
        with zenoh.open(conf) as rover:
            pubs = {k: rover.declare_publisher(f"robotd/r1/{k}") for k in ("pose", "map", "health")}
            assert wait_for(lambda: (pubs["health"].put("x"), got.get("robotd/r1/health", 0) > 0)[1], 10.0)
            got.clear()
            t0 = time.monotonic()
            for _ in range(60):  # 2 s at 30 Hz
                for p in pubs.values():
                    p.put("x")
                time.sleep(1 / 30)
            elapsed = time.monotonic() - t0
            assert wait_for(lambda: got.get("robotd/r1/health", 0) >= 60, 10.0), got
    assert 1 <= got.get("robotd/r1/pose", 0) <= 5.0 * elapsed + 2, (got, elapsed)
    assert got.get("robotd/r1/map", 0) <= 0.1 * elapsed + 2, (got, elapsed)
