"""``robotd replay-many --ray local`` (robotd/tools/batch/ray_engine.py): the same table as the local engine,
trajectory for trajectory, and a Ray worker process killed mid-run costs only its row, which Ray
retries (one run, one Ray instance, for both). Skipped where Ray is not installed
(``pip install 'robotd[cluster]'``)."""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from robotd.tools.cli import main
from tests.robotd.tools.batch.conftest import LocalRun
from tests.support.paths import REPO
from tests.support.waiting import wait_for

pytest.importorskip(
    "ray", reason="Ray is not installed here (pip install 'robotd[cluster]'): the Ray engine is untested"
)

TABLE_COLUMNS = ("status", "frames", "lost_frames", "drift_pct", "drift_m", "ate_m", "rpe_m", "trajectory_sha256")


def _replay_many(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "robotd", "replay-many", *args, "--ray", "local", "--workers", "2", "--quiet", "--json"],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def _children(pid: int) -> list[int]:
    """Every process below ``pid`` (from /proc), so a test only ever touches the ones its run started."""
    parent: dict[int, int] = {}
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                parent[int(d.name)] = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        kids = [c for c, pp in parent.items() if pp == p]
        out += kids
        todo += kids
    return out


def _cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return ""


def test_a_local_ray_cluster_gives_the_same_table_and_a_killed_worker_costs_only_its_retried_row(
    local_run: LocalRun, tmp_path: Path
) -> None:
    # one Ray instance for both properties (starting one is most of the cost): the local engine's
    # rows, and three sims long enough (60 frames each) that replays are running when a worker dies
    sims = [f"sim://yard?duration=12&realtime=0&width=160&height=100&fps=5&seed={s}" for s in (41, 42, 43)]
    proc = _replay_many(
        *local_run.sources, local_run.damaged, *sims, "--out", str(tmp_path / "ray"), "--max-retries", "2"
    )
    killed: list[int] = []
    try:

        def a_replaying_worker() -> bool:
            for pid in _children(proc.pid):
                if _cmdline(pid).startswith("ray::robotd_replay"):
                    os.kill(pid, signal.SIGKILL)
                    killed.append(pid)
                    return True
            return proc.poll() is not None

        assert wait_for(a_replaying_worker, 120.0) and killed, "no Ray worker was seen replaying"
        out, err = proc.communicate(timeout=600)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 1, err[-3000:]  # the damaged recording, as locally
    doc = json.loads(out.strip().splitlines()[-1])
    assert doc["engine"].startswith("ray, a local Ray instance")
    rows = {r["url"]: r for r in doc["rows"]}
    local_rows = {r["url"]: r for r in local_run.doc["rows"]}
    assert set(rows) == set(local_rows) | set(sims)
    for url, lr in local_rows.items():
        rr = rows[url]
        assert {k: rr[k] for k in TABLE_COLUMNS} == {k: lr[k] for k in TABLE_COLUMNS}, url
        assert rr["key"] == lr["key"]
    assert rows[local_run.damaged]["error"] == local_rows[local_run.damaged]["error"]
    assert all(rows[u]["status"] == "ok" for u in [*local_run.sources, *sims]), rows
    assert all(not r["worker"].endswith(f":{killed[0]}") for r in rows.values()), "a row from the killed worker"
    for k, url in enumerate(sims):  # the retried replay is the replay
        single = tmp_path / f"single-{k}.txt"
        assert main(["replay", url, "--out", str(single), "--quiet", "--log-level", "WARNING"]) == 0
        assert rows[url]["trajectory_sha256"] == hashlib.sha256(single.read_bytes()).hexdigest(), url
