"""bench/faults.py through its entry point: two refused configurations pass with the fields the
suite reports, and a fault whose protection is switched off (the odometry plausibility gate,
through ``--set``) is reported as failed, with exit status 1, so the suite can fail."""

from __future__ import annotations

import importlib.util
import json
import sys
from types import ModuleType

import pytest

from tests.support.paths import REPO

FIELDS = {"fault", "expected", "survived", "data_lost", "shown", "error_shown", "ok", "failed_checks", "figures"}


def _bench() -> ModuleType:
    spec = importlib.util.spec_from_file_location("bench_faults", REPO / "bench" / "faults.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # its dataclasses look their module up while it loads
    spec.loader.exec_module(mod)
    return mod


def _run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, dict]:
    code = _bench().main([*argv, "--json"])
    return code, json.loads(capsys.readouterr().out)


def test_refused_configurations_are_reported_survived_with_their_one_line(capsys) -> None:
    code, out = _run(capsys, "--faults", "config_n_particles_100000,config_not_utf8")
    assert code == 0, out
    by = {f["fault"]: f for f in out["faults"]}
    assert set(by) == {"config_n_particles_100000", "config_not_utf8"} and out["failed"] == []
    for f in by.values():
        assert FIELDS <= set(f)
        assert f["survived"] and not f["data_lost"] and f["shown"] and f["ok"] and not f["failed_checks"]
        assert f["figures"]["exit_status"] == 2 and f["figures"]["output_lines"] == 1
    assert by["config_n_particles_100000"]["error_shown"].startswith("robotd: error: slam.n_particles = 100000")
    assert "not UTF-8" in by["config_not_utf8"]["error_shown"]


@pytest.mark.slow
def test_a_tick_jump_with_the_plausibility_gate_off_is_reported_failed(capsys) -> None:
    # the gate off (speed, acceleration and turn rate: a jump on one wheel is also a 10^8 rad/s
    # turn): the 2^31 - 1 tick jump reaches the filter, and the suite must say so
    off = ["vehicle.max_speed_mps=1e30", "vehicle.max_accel_mps2=1e30", "vehicle.max_rate_radps=1e30"]
    code, out = _run(capsys, "--faults", "serial_tick_jump", *(a for kv in off for a in ("--set", kv)))
    assert code == 1 and out["failed"] == ["serial_tick_jump"]
    (f,) = out["faults"]
    assert not f["ok"] and f["data_lost"], f
    assert any(c.startswith("data: error against truth after the fault") for c in f["failed_checks"]), f
    assert f["figures"]["err_max_after_fault_m"] > 100 * f["figures"]["err_bound_m"], f
