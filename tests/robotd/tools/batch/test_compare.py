"""``robotd replay-many compare A B`` (robotd/tools/batch/compare.py): the rows that got worse beyond the
tolerance, worst first, with A's and B's trajectories plotted side by side."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from robotd.tools.batch.compare import Tolerance, judge
from robotd.tools.cli import main
from tests.robotd.tools.batch.conftest import LocalRun


def _row(**kw: object) -> dict[str, object]:
    return {"status": "ok", "ate_m": 0.10, "drift_pct": 1.0, "drift_m": 0.5, "lost_frames": 0, **kw}


def test_the_tolerance_decides_what_is_worse() -> None:
    tol = Tolerance(rel=0.10, ate_m=0.005, drift_pct=0.1, lost=0)
    assert judge(_row(), _row(ate_m=0.114), tol)[0] == "same"  # within 10 % + 5 mm
    verdict, reasons, severity = judge(_row(), _row(ate_m=0.116), tol)
    assert verdict == "worse" and reasons == ["ATE 0.1000 → 0.1160 m (+16 %)"] and severity == pytest.approx(1.16)
    assert judge(_row(), _row(drift_pct=1.3), tol)[1] == ["drift 1 → 1.3 %"]
    assert judge(_row(), _row(lost_frames=1), tol)[0] == "worse"
    assert judge(_row(), _row(lost_frames=1), Tolerance(lost=1))[0] == "same"
    assert judge(_row(), _row(status="timeout", error="timeout: …"), tol)[2] == float("inf")
    assert judge(_row(), _row(ate_m=0.05), tol)[0] == "better"
    assert judge(_row(status="error"), _row(), tol)[0] == "better"


def test_a_worse_candidate_is_reported_worst_first_with_plots(
    local_run: LocalRun, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # B: the same results with one replay's ATE tripled and another one failed
    b = tmp_path / "b"
    shutil.copytree(local_run.out, b, ignore=shutil.ignore_patterns(".lock"))
    doc = json.loads((b / "results.json").read_text())
    ok = [r for r in doc["rows"] if r["status"] == "ok" and r["ate_m"]]
    ok[3]["ate_m"] *= 3.0
    ok[5]["status"], ok[5]["error"] = "timeout", "timeout: still running after 60 s"
    (b / "results.json").write_text(json.dumps(doc))
    plots = tmp_path / "plots"
    assert main(["replay-many", "compare", str(local_run.out), str(b), "--plots", str(plots), "--json"]) == 1
    report = json.loads(capsys.readouterr().out)
    assert [p["url"] for p in report["worse"]] == [ok[5]["url"], ok[3]["url"]]  # a failure first
    assert report["worse"][1]["reasons"][0].startswith("ATE ") and "(+200 %)" in report["worse"][1]["reasons"][0]
    assert report["pairs"] == len(doc["rows"]) and report["same"] == len(doc["rows"]) - 2
    assert len(report["plots"]) == 2
    for p in report["plots"]:
        assert Path(p).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and Path(p).stat().st_size > 10_000
    # A against itself: nothing worse, exit status 0
    assert main(["replay-many", "compare", str(local_run.out), str(local_run.out / "results.json")]) == 0
    assert "0 worse beyond the tolerance" in capsys.readouterr().out


def test_a_folder_of_several_configurations_needs_one_named(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "results.json").write_text(
        json.dumps({"command": "replay-many", "configurations": [{"name": "a"}, {"name": "b"}], "rows": []})
    )
    assert main(["replay-many", "compare", str(tmp_path), str(tmp_path)]) == 2
    assert "holds 2 configurations (a, b)" in capsys.readouterr().err
    assert main(["replay-many", "compare", f"{tmp_path}#a", f"{tmp_path}#c"]) == 2
    assert "has no configuration 'c'" in capsys.readouterr().err
