"""``robotd replay-many`` on the local engine (robotd/tools/batch/run.py): at least 20 sources in one
table, every trajectory byte for byte the one a single ``robotd replay`` writes, a failing source a
row of its own, and a rerun that replays nothing that is done."""

from __future__ import annotations

import csv
import hashlib
from pathlib import Path

import pytest

from robotd.tools.cli import main
from tests.robotd.tools.batch.conftest import LocalRun, run_cli
from tests.support.batch_sources import sim_url


def test_twenty_sources_make_one_table_and_a_failing_source_is_a_row(local_run: LocalRun) -> None:
    doc = local_run.doc
    rows = {r["url"]: r for r in doc["rows"]}
    assert len(local_run.sources) >= 20
    assert len(doc["rows"]) == len(local_run.sources) + 1
    assert local_run.code == 1, "a failed row makes the exit status 1"
    bad = rows[local_run.damaged]
    assert bad["status"] == "error" and "not a readable MCAP file" in bad["error"], bad
    for url in local_run.sources:
        r = rows[url]
        assert r["status"] == "ok", r
        assert r["frames"] and r["frames"] > 0
        assert r["trajectory_sha256"]
        assert r["ate_m"] is not None or url.startswith("euroc://"), r  # 8 EuRoC frames: too few with truth
    assert doc["counts"] == {"replays": len(rows), "run": len(rows), "reused": 0, "failed": 1}
    # the same table as CSV and Markdown in the results folder
    with open(local_run.out / "table.csv", newline="") as f:
        csv_rows = list(csv.DictReader(f))
    assert [r["url"] for r in csv_rows] == [r["url"] for r in doc["rows"]]
    md = (local_run.out / "table.md").read_text()
    assert md.count("\n| ") == len(rows) + 1 and "| error |" in md


def test_trajectories_are_byte_for_byte_those_of_single_replays(local_run: LocalRun, tmp_path: Path) -> None:
    rows = {r["url"]: r for r in local_run.doc["rows"]}
    # a sim drive, a vision-only one, a recording and (when there) a KITTI and an EuRoC sequence
    picks = [local_run.sources[0], local_run.sources[15], *[s for s in local_run.sources if s.endswith(".mcap")][:1]]
    picks += [s for s in local_run.sources if s.startswith(("kitti://", "euroc://"))]
    for k, url in enumerate(picks):
        out = tmp_path / f"single-{k}.txt"
        assert main(["replay", url, "--out", str(out), "--quiet", "--log-level", "WARNING"]) == 0
        single = hashlib.sha256(out.read_bytes()).hexdigest()
        stored = local_run.out / rows[url]["trajectory"]
        assert hashlib.sha256(stored.read_bytes()).hexdigest() == single == rows[url]["trajectory_sha256"], url
        cov = out.with_name(f"{out.stem}.cov.txt")
        assert (local_run.out / rows[url]["trajectory"].replace(".txt", ".cov.txt")).read_bytes() == cov.read_bytes()


def test_a_rerun_skips_every_row_done_and_runs_only_what_is_new(local_run: LocalRun) -> None:
    code, doc = run_cli([*local_run.argv, "--json"])
    assert code == 1  # the damaged recording's row is still an error (reused: it would fail again)
    assert doc["counts"]["run"] == 0 and doc["counts"]["reused"] == len(local_run.sources) + 1
    assert all(r["reused"] for r in doc["rows"])
    new = sim_url(99)
    code, doc = run_cli(["replay-many", new, *local_run.argv[1:], "--json"])
    assert doc["counts"]["run"] == 1 and doc["counts"]["reused"] == len(local_run.sources) + 1
    assert [r["url"] for r in doc["rows"] if not r["reused"]] == [new]


def test_configurations_are_compared_with_the_first(tmp_path: Path) -> None:
    code, doc = run_cli(
        [
            "replay-many",
            sim_url(5),
            sim_url(6),
            "--variant",
            'fs2: slam.filter="fastslam2"',
            "--variant",
            'ekf: slam.filter="ekf"',
            "--out",
            str(tmp_path / "out"),
            "--workers",
            "1",
            "--quiet",
            "--json",
        ]
    )
    assert code == 0
    assert doc["baseline"] == "fs2" and [c["name"] for c in doc["configurations"]] == ["fs2", "ekf"]
    by = {(r["url"], r["config"]): r for r in doc["rows"]}
    for url in (sim_url(5), sim_url(6)):
        base, ekf = by[(url, "fs2")], by[(url, "ekf")]
        assert base["summary"]["filter"] == "fastslam2" and ekf["summary"]["filter"] == "ekf"
        assert ekf["ate_delta_m"] == pytest.approx(ekf["ate_m"] - base["ate_m"])
        assert base["ate_delta_m"] is None
    assert "Δ ATE ekf vs fs2" in (tmp_path / "out" / "table.md").read_text()


def test_bad_arguments_are_one_line_before_anything_runs(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "o"
    assert main(["replay-many", "sim://?fpz=3", "--out", str(out)]) == 2
    assert "unknown parameter 'fpz'" in capsys.readouterr().err
    assert main(["replay-many", str(tmp_path / "nothing-*.mcap"), "--out", str(out)]) == 2
    assert "no file or folder matches" in capsys.readouterr().err
    assert main(["replay-many", sim_url(1), "--variant", "slam.n_particles=0", "--out", str(out)]) == 2
    assert "slam.n_particles" in capsys.readouterr().err


def test_the_local_default_needs_no_ray(tmp_path: Path) -> None:
    import subprocess
    import sys

    from tests.support.paths import REPO

    code = (
        "import sys; sys.modules['ray'] = None  # any `import ray` now fails\n"
        "from robotd.tools.cli import main\n"
        f"sys.exit(main(['replay-many', {sim_url(7)!r}, '--out', {str(tmp_path / 'o')!r}, '--quiet']))\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "| ok |" in proc.stdout


def test_ctrl_c_keeps_the_finished_rows_and_tables_them(tmp_path: Path) -> None:
    """SIGINT to the command's process group, as a terminal's Ctrl-C sends it: the finished replays
    stay in the folder and the table, the unfinished ones are rows marked interrupted (run again next
    time), exit status 130."""
    import json
    import os
    import signal
    import subprocess
    import sys

    from tests.support.paths import REPO
    from tests.support.waiting import wait_for

    endless = "sim://yard?duration=600&realtime=1&width=160&height=100&fps=5&seed=8"
    out = tmp_path / "out"
    argv = ["replay-many", sim_url(2), endless, "--out", str(out), "--workers", "2", "--quiet", "--json"]
    # the output goes to files, not pipes nobody reads while the test waits
    out_file, err_file = tmp_path / "stdout.txt", tmp_path / "stderr.txt"
    with open(out_file, "w") as fo, open(err_file, "w") as fe:
        proc = subprocess.Popen(
            [sys.executable, "-m", "robotd", *argv],
            cwd=REPO,
            stdout=fo,
            stderr=fe,
            text=True,
            start_new_session=True,  # its own process group, as a terminal's foreground job
            # and SIGINT at its default, as a terminal's foreground job has it: a suite started in
            # the background of a non-interactive shell ignores SIGINT, the command inherited that
            # and never saw the Ctrl-C
            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
        )
        try:
            rows = out / "rows.jsonl"
            assert wait_for(lambda: rows.is_file() and rows.read_text().count("\n") >= 1, 180.0), "no row finished"
            os.killpg(proc.pid, signal.SIGINT)
            proc.wait(timeout=180)
        finally:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
    stdout, stderr = out_file.read_text(), err_file.read_text()
    assert proc.returncode == 130, stderr[-3000:]
    doc = json.loads(stdout.strip().splitlines()[-1])
    status = {r["url"]: r["status"] for r in doc["rows"]}
    assert status == {sim_url(2): "ok", endless: "interrupted"} and doc["interrupted"]
    assert "interrupted" in stderr.splitlines()[-1]
    code, again = run_cli(["replay-many", sim_url(2), "--out", str(out), "--quiet", "--json"])
    assert code == 0 and again["counts"]["reused"] == 1  # the finished row was kept


def test_a_terminal_gets_a_progress_bar(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    import sys

    monkeypatch.setattr(sys.stderr, "isatty", lambda: True)  # capsys's stderr stands in for a terminal
    assert main(["replay-many", sim_url(9), sim_url(10), "--out", str(tmp_path / "o"), "--workers", "1"]) == 0
    err = capsys.readouterr().err
    assert "replay-many: 100%" in err and "2/2" in err and "ok 2 failed 0" in err, err
