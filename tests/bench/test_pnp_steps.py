"""bench/pnp_steps.py: the PnP's step against the simulator's truth, one JSON object, and a clear
error for a duration that is not one."""

from __future__ import annotations

import json
from types import ModuleType

import pytest

from tests.support.paths import load_bench


def _bench() -> ModuleType:
    return load_bench("pnp_steps")


def test_the_yards_steps_match_the_truth_and_the_summary_is_one_json_object(capsys: pytest.CaptureFixture[str]) -> None:
    # 320x200, half a second at 30 Hz: the yard's walls give pixels of flow, so the PnP's step is
    # the truth's within a few per cent (a ratio of 0 or 2 would mean a broken comparison)
    url = "sim://?world=yard&speed=1&fps=30&width=320&height=200"
    assert _bench().main(["--seconds", "0.5", "--json", url]) == 0
    (row,) = json.loads(capsys.readouterr().out)["rows"]
    assert row["url"] == url and row["detector"] == "orb" and row["increments"] >= 10
    assert 0.025 < row["step_m"] < 0.045  # 1 m/s at 30 Hz, within the speed's ±15 %
    assert 0.9 < row["step_ratio"] < 1.1
    assert row["step_ratio_iqr"][0] <= row["step_ratio"] <= row["step_ratio_iqr"][1]
    assert row["nees_t_median"] > 0.0 and row["nees_rot_median"] > 0.0


def test_a_duration_that_is_not_positive_is_refused(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        _bench().main(["--seconds", "0"])
    assert "--seconds: expected a positive duration, got 0.0" in capsys.readouterr().err
