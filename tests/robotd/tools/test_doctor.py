"""robotd doctor: each check's ok and failing case made real where it can be (sockets, a pty, the
mock autopilot, calibration files, a fake sysfs tree), and the CLI's exit codes and JSON."""

from __future__ import annotations

import dataclasses
import json
import os
import socket
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from calib.camchain import save_calibration
from drivers.mavlink_link import wait_heartbeat
from drivers.mavlink_mock import MockAutopilot
from drivers.mcu_sim import open_pty
from drivers.oak import host as oak_host
from robotd.config import Config, load_config
from robotd.tools import doctor
from robotd.tools.cli import main
from tests.calib.test_camchain import _calib


def cfg_with(**sections: dict[str, Any]) -> Config:
    return load_config(None, sections)


def free_tcp_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


# -- OAK --------------------------------------------------------------------------------------


def fake_sysfs(root: Path, devices: dict[str, tuple[str, str]]) -> Path:
    for name, (vendor, product) in devices.items():
        (root / name).mkdir(parents=True)
        (root / name / "idVendor").write_text(vendor + "\n")
        (root / name / "idProduct").write_text(product + "\n")
    return root


def _camera_host(cfg: Config) -> dict[str, doctor.CheckResult]:
    return {r.name: r for r in doctor.check_camera_host(cfg)}


def test_the_oak_checks_are_its_drivers_run_for_an_oak_and_skipped_for_another_camera(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # the checks themselves: tests/drivers/oak/test_host.py; here, that doctor runs them by the driver
    monkeypatch.setattr(oak_host, "SYSFS_USB", fake_sysfs(tmp_path / "a", {"1-1": ("03e7", "2485")}))
    monkeypatch.setattr(oak_host, "UDEV_RULE_DIRS", (tmp_path / "missing",))
    oak = _camera_host(cfg_with(camera={"url": "oak://"}))
    assert oak["oak-usb"].status == doctor.OK and "1-1 (03e7:2485)" in oak["oak-usb"].message
    assert oak["oak-udev"].status == doctor.FAIL and "60-robotd-oak.rules" in oak["oak-udev"].message
    sim = _camera_host(cfg_with())  # the default camera, the simulated rover
    assert {r.status for r in sim.values()} == {doctor.SKIP} and set(sim) == set(oak)
    assert sim["oak-usb"].message == f"camera.url is {cfg_with().camera.url!r}, not oak://"
    # a camera.url no driver takes: the camera's checks are skipped (the URL's own check fails it)
    assert {r.status for r in doctor.check_camera_host(cfg_with(camera={"url": "cam://x"}))} == {doctor.SKIP}


# -- serial -----------------------------------------------------------------------------------


def test_serial_device_on_a_pty_and_missing_or_wrong_paths(tmp_path: Path) -> None:
    master, slave, path = open_pty()
    try:
        r = doctor.check_serial(cfg_with(vehicle={"url": f"serial://{path}?baud=115200"}))
        assert r.status == doctor.OK and path in r.message
    finally:
        os.close(master)
        os.close(slave)
    missing = doctor.check_serial(cfg_with(vehicle={"url": f"serial://{tmp_path}/ttyACM9"}))
    assert missing.status == doctor.FAIL and "not found" in missing.message and "vehicle.url" in missing.message
    (tmp_path / "ttyFile").write_text("")
    regular = doctor.check_serial(cfg_with(vehicle={"url": f"serial://{tmp_path}/ttyFile"}))
    assert regular.status == doctor.FAIL and "not a character device" in regular.message
    assert doctor.check_serial(cfg_with()).status == doctor.SKIP


def test_serial_without_access_names_the_group(monkeypatch: pytest.MonkeyPatch) -> None:
    # tests run as root, for whom os.access always succeeds: only the refusal is simulated
    master, slave, path = open_pty()
    try:
        monkeypatch.setattr(os, "access", lambda *_a, **_k: False)
        monkeypatch.setattr(os, "getgroups", lambda: [])
        monkeypatch.setattr(os, "getgid", lambda: -1)
        r = doctor.check_serial(cfg_with(vehicle={"url": f"serial://{path}"}))
    finally:
        os.close(master)
        os.close(slave)
    assert r.status == doctor.FAIL and "no read/write access" in r.message
    assert "is not in group" in r.message and "usermod -aG" in r.message


# -- MAVLink ----------------------------------------------------------------------------------


def test_wait_heartbeat_from_the_mock_autopilot_and_a_silent_port() -> None:
    with MockAutopilot(sysid=7) as ap:
        assert wait_heartbeat(ap.url, 3.0) == (7, "MAV_AUTOPILOT_ARDUPILOTMEGA")
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as silent:
        silent.bind(("127.0.0.1", 0))
        assert wait_heartbeat(f"mavlink+udp://127.0.0.1:{silent.getsockname()[1]}", 0.5) is None


def test_mavlink_check_ok_silent_and_skipped() -> None:
    with MockAutopilot(sysid=7) as ap:
        r = doctor.check_mavlink(cfg_with(vehicle={"url": ap.url}), timeout_s=3.0)
        assert r.status == doctor.OK and "sysid 7" in r.message
        # the autopilot link of mavlink.enabled when the odometry comes from elsewhere
        r = doctor.check_mavlink(cfg_with(mavlink={"enabled": True, "url": ap.url}), timeout_s=3.0)
        assert r.status == doctor.OK
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as silent:
        silent.bind(("127.0.0.1", 0))
        url = f"mavlink+udp://127.0.0.1:{silent.getsockname()[1]}"
        r = doctor.check_mavlink(cfg_with(vehicle={"url": url}), timeout_s=0.5)
    assert r.status == doctor.FAIL and "no autopilot HEARTBEAT" in r.message and "vehicle.url" in r.message
    assert doctor.check_mavlink(cfg_with()).status == doctor.SKIP
    # a missing serial device is the serial check's failure, not a second one here
    url = "mavlink+serial:///nonexistent/ttyACM0?baud=921600"
    r = doctor.check_mavlink(cfg_with(vehicle={"url": url}))
    assert r.status == doctor.SKIP and "see the serial check" in r.message


# -- Zenoh ------------------------------------------------------------------------------------


def test_zenoh_port_free_and_held() -> None:
    with socket.socket() as holder:
        holder.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        holder.bind(("127.0.0.1", 0))
        holder.listen()
        endpoint = f"tcp/127.0.0.1:{holder.getsockname()[1]}"
        (held,) = doctor.check_zenoh(cfg_with(zenoh={"listen": [endpoint]}))
    assert held.status == doctor.FAIL and endpoint in held.message and "zenoh.listen" in held.message
    free = f"tcp/127.0.0.1:{free_tcp_port()}"
    (ok,) = doctor.check_zenoh(cfg_with(zenoh={"listen": [free]}))
    assert ok.status == doctor.OK and free in ok.message
    assert doctor.check_zenoh(cfg_with(zenoh={"enabled": False}))[0].status == doctor.SKIP
    (bad,) = doctor.check_zenoh(cfg_with(zenoh={"listen": ["tcp/7447"]}))
    assert bad.status == doctor.FAIL and "zenoh.listen" in bad.message


# -- state directory, numba cache ------------------------------------------------------------


def test_state_dir_created_and_unwritable(tmp_path: Path) -> None:
    r = doctor.check_state_dir(cfg_with(persistence={"state_dir": str(tmp_path / "new" / "state")}))
    assert r.status == doctor.OK and "created" in r.message and (tmp_path / "new" / "state").is_dir()
    assert list((tmp_path / "new" / "state").iterdir()) == []  # the probe file is gone
    (tmp_path / "file").write_text("")
    # tests run as root, so a chmod'ed directory would still be writable: a path under a file is not
    bad = doctor.check_state_dir(cfg_with(persistence={"state_dir": str(tmp_path / "file" / "state")}))
    assert bad.status == doctor.FAIL and "persistence.state_dir" in bad.message


def test_kernel_modules_are_the_jit_decorated_ones() -> None:
    names = {p.name for p in doctor.kernel_modules()}
    assert {"_kernels.py", "_outlier_kernels.py", "_detect_kernels.py", "_stereo_kernels.py"} <= names
    assert "jit.py" not in names and "doctor.py" not in names


def test_numba_cache_cold_and_warm(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    mod = tmp_path / "pkg" / "_k.py"
    mod.parent.mkdir()
    mod.write_text("")
    cold = doctor.check_numba_cache(cfg_with(), modules=[mod])
    assert cold.status == doctor.WARN and "tens of seconds" in cold.message and "--warm" in cold.message
    (mod.parent / "__pycache__").mkdir()
    (mod.parent / "__pycache__" / "_k.kernel-12.py311.nbi").write_bytes(b"")
    assert doctor.check_numba_cache(cfg_with(), modules=[mod]).status == doctor.OK
    # NUMBA_CACHE_DIR: numba looks only there, in a subdirectory named after the source directory
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "cache"))
    assert doctor.check_numba_cache(cfg_with(), modules=[mod]).status == doctor.WARN
    (tmp_path / "cache" / "pkg").mkdir(parents=True)
    (tmp_path / "cache" / "pkg" / "_k.kernel-12.py311.nbi").write_bytes(b"")
    r = doctor.check_numba_cache(cfg_with(), modules=[mod])
    assert r.status == doctor.OK and "NUMBA_CACHE_DIR" in r.message


# -- calibration ------------------------------------------------------------------------------


def test_calibration_size_against_the_oak_resolution(tmp_path: Path) -> None:
    calib = _calib(np.random.default_rng(3))  # 640x400, the OAK driver's default size
    good = save_calibration(calib, tmp_path / "good.yaml")
    wide = save_calibration(dataclasses.replace(calib, image_size=(1280, 800)), tmp_path / "wide.yaml")
    ok = doctor.check_calibration(cfg_with(camera={"url": "oak://", "calibration": str(good)}))
    assert ok.status == doctor.OK and "640x400" in ok.message
    bad = doctor.check_calibration(cfg_with(camera={"url": "oak://", "calibration": str(wide)}))
    assert bad.status == doctor.FAIL and "1280x800" in bad.message and "640x400" in bad.message
    url = "oak://?width=1280&height=800"
    assert doctor.check_calibration(cfg_with(camera={"url": url, "calibration": str(wide)})).status == doctor.OK
    missing = doctor.check_calibration(cfg_with(camera={"url": "oak://", "calibration": str(tmp_path / "no.yaml")}))
    assert missing.status == doctor.FAIL and "camera.calibration" in missing.message
    factory = doctor.check_calibration(cfg_with(camera={"url": "oak://"}))
    assert factory.status == doctor.OK and "factory calibration" in factory.message
    assert doctor.check_calibration(cfg_with()).status == doctor.SKIP


def test_calibration_judged_by_the_camera_that_would_use_it(tmp_path: Path) -> None:
    """As the daemon judges it: a source with its own rig refuses a calibration file (FAIL, naming
    the key), a dataset that rectifies raw images takes it (its size is checked when it opens)."""
    path = save_calibration(_calib(np.random.default_rng(3)), tmp_path / "rig.yaml")
    sim = doctor.check_calibration(cfg_with(camera={"url": "sim://", "calibration": str(path)}))
    assert sim.status == doctor.FAIL and "takes no calibration file" in sim.message
    assert "camera.calibration" in sim.message
    euroc = doctor.check_calibration(cfg_with(camera={"url": "euroc:///data/v101", "calibration": str(path)}))
    assert euroc.status == doctor.OK and "rectifies with it" in euroc.message
    device = doctor.check_calibration(cfg_with(camera={"url": "oak://?rectify=device", "calibration": str(path)}))
    assert device.status == doctor.FAIL and "rectify=host" in device.message


# -- the command ------------------------------------------------------------------------------


def write_config(path: Path, state_dir: Path, port: int) -> Path:
    path.write_text(f'[zenoh]\nlisten = ["tcp/127.0.0.1:{port}"]\n\n[persistence]\nstate_dir = "{state_dir}"\n')
    return path


def test_cli_healthy_sim_config_exits_0(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cfg = write_config(tmp_path / "robotd.toml", tmp_path / "state", free_tcp_port())
    assert main(["doctor", "--config", str(cfg)]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 9 and lines[-1].startswith("doctor: no failures")
    assert any(line.startswith("ok   zenoh: tcp/127.0.0.1:") for line in lines)
    assert any(line.startswith("skip serial:") for line in lines)


def test_cli_failing_check_exits_1_and_json(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "file").write_text("")
    cfg = write_config(tmp_path / "robotd.toml", tmp_path / "file" / "state", free_tcp_port())
    assert main(["doctor", "--config", str(cfg)]) == 1
    out = capsys.readouterr().out
    assert "FAIL state-dir:" in out and "1 failed" in out
    assert main(["doctor", "--config", str(cfg), "--json"]) == 1
    doc = json.loads(capsys.readouterr().out)
    assert doc["ok"] is False and doc["failed"] == 1
    by_name = {c["name"]: c for c in doc["checks"]}
    assert by_name["state-dir"]["status"] == "fail" and by_name["oak-usb"]["status"] == "skip"


def test_cli_config_error_exits_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["doctor", "--config", str(tmp_path / "missing.toml")]) == 2
    assert "missing.toml" in capsys.readouterr().err


def test_warm_runs_the_pipeline_warmup_and_reports_seconds(monkeypatch: pytest.MonkeyPatch) -> None:
    from robotd.pipeline.step import Pipeline

    calls: list[tuple[tuple[str, ...], tuple[int, ...]]] = []
    monkeypatch.setattr(Pipeline, "warmup", staticmethod(lambda models, dims: calls.append((models, dims)) or 1.5))
    r = doctor.check_numba_cache(cfg_with(), warm=True)
    # the configured measurement model and dimension only: each pair is a compilation of its own
    assert calls == [(("pixel",), (3,))] and "warmed in 1.5 s" in r.message
