"""bench/fuzz.py (the long fuzz runs of issue 15): a short run over the five real targets gives
the JSON document it documents, and the bench can fail: a target whose oracle raises, kills its
worker, uses 100 MB or hangs is counted (crash, crash, crash, hang), its reproducers are saved
and replay, and the exit status is 1."""

from __future__ import annotations

import importlib.util
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from types import ModuleType

import pytest

from tests.fuzz.planted import Faulty
from tests.fuzz.targets import TARGETS
from tests.support.paths import REPO


def _bench() -> ModuleType:
    spec = importlib.util.spec_from_file_location("bench_fuzz", REPO / "bench" / "fuzz.py")
    assert spec is not None and spec.loader is not None
    bench = importlib.util.module_from_spec(spec)
    sys.modules["bench_fuzz"] = bench  # its dataclasses look their module up there
    spec.loader.exec_module(bench)
    return bench


ROW_KEYS = {"target", "inputs", "planned", "crashes", "hangs", "inputs_per_s", "slowest_input_ms", "outcomes"}


def test_a_short_run_over_the_five_targets(tmp_path: Path) -> None:
    bench = _bench()
    scratch = tmp_path / "tmp"
    scratch.mkdir()
    # 1000 inputs by the weights: 350 serial and MAVLink, 200 config, 90 recordings, 10 maps. In a
    # process of its own, as a user runs it: the bench forks its workers, and a fork of the test
    # process would inherit the threads earlier tests left (a worker deadlocked on one's lock in CI)
    cmd = [sys.executable, str(REPO / "bench" / "fuzz.py"), "--json", "--inputs", "1000", "--seed", "5"]
    p = subprocess.run(
        [*cmd, "--out", str(tmp_path / "out")],
        capture_output=True,
        text=True,
        timeout=240,
        cwd=tmp_path,
        env=dict(os.environ, TMPDIR=str(scratch), PYTHONPATH=str(REPO)),
    )
    doc = json.loads(p.stdout)
    code = p.returncode
    assert code == 0, doc["findings"]
    rows = {r["target"]: r for r in doc["targets"]}
    assert list(rows) == ["serial", "mavlink", "config", "mapfile", "recording"]
    for name, r in rows.items():
        assert ROW_KEYS <= set(r), name
        assert r["inputs"] == r["planned"] == bench.plan(1000, list(rows))[name]
        assert r["crashes"] == r["hangs"] == 0
        assert r["inputs_per_s"] > 0 and 0 < r["slowest_input_ms"] < 1000 * bench.HANG_S
        assert sum(r["outcomes"].values()) == r["inputs"]
    assert doc["total"] == dict(doc["total"], inputs=1000, crashes=0, hangs=0)
    # each oracle sees both of its outcomes: the mutations reach past the first check
    assert set(rows["config"]["outcomes"]) == {"loaded", "refused"}
    assert set(rows["mapfile"]["outcomes"]) == {"resumed", "refused"}
    assert {"read", "stopped"} <= set(rows["recording"]["outcomes"])
    assert set(rows["mavlink"]["outcomes"]) == {"clean", "bad data"}
    assert not (tmp_path / "out").exists()  # nothing to reproduce
    assert not list(scratch.iterdir())  # the workers' scratch files are gone


def test_inputs_are_deterministic_from_the_seed() -> None:
    bench = _bench()
    for name, factory in TARGETS.items():
        if name == "mapfile":
            continue  # builds real maps (seconds): its generator is the same code path
        t, again = factory(), factory()  # two seed corpora, as in two worker processes
        t.setup()
        time.sleep(0.01)  # a corpus that carried the wall clock would differ
        again.setup()
        a = [t.generate(bench.case_rng(3, name, i)).data for i in range(20)]
        assert a == [again.generate(bench.case_rng(3, name, i)).data for i in range(20)], name
        assert a != [t.generate(bench.case_rng(4, name, i)).data for i in range(20)], name


def test_planted_crashes_and_hangs_are_counted_saved_and_replayed(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    bench = _bench()
    monkeypatch.setitem(TARGETS, "faulty", Faulty)
    n = 150
    kinds = [bench.case_rng(1, "faulty", i).randrange(100) for i in range(n)]
    raised, died, hung = sum(k < 10 for k in kinds), kinds.count(10), sum(k in (11, 12, 13) for k in kinds)
    hogs = kinds.count(14)  # each in another worker (a death or hang between): each raises its peak
    assert raised and died and hung and hogs  # the seed plants each kind
    out = tmp_path / "out"
    # the planted hangs sleep 30 s; the limit leaves a busy machine room for the others (a clean
    # clone's CI counted a 100 MB input as a hang against 0.5 s: 7 hangs for 6)
    args = ["--targets", "faulty", "--per-target", str(n), "--hang-s", "2.5", "--memory-mb", "50", "--out", str(out)]
    # the bench forks its workers: run it in a process of its own (tests.fuzz.planted adds the
    # target), not in this one, whose threads left by earlier tests a fork would inherit
    p = subprocess.run(
        [sys.executable, "-m", "tests.fuzz.planted", "--json", *args],
        capture_output=True,
        text=True,
        timeout=240,
        cwd=REPO,
        env=dict(os.environ, PYTHONPATH=str(REPO)),
    )
    doc = json.loads(p.stdout)
    code = p.returncode
    assert code == 1
    (row,) = doc["targets"]
    assert (row["inputs"], row["crashes"], row["hangs"]) == (n, raised + died + hogs, hung)
    assert row["workers"] == 1 + died + hung  # a new worker after each death and each hang
    assert row["outcomes"] == {"clean": n - raised - died - hung - hogs}  # the rest finished
    by_index = {f["index"]: f for f in doc["findings"]}
    assert sorted(by_index) == [i for i, k in enumerate(kinds) if k <= 14]
    for i, f in by_index.items():
        assert f["kind"] == ("hang" if kinds[i] in (11, 12, 13) else "crash")
        if kinds[i] < 10:
            assert f["error"] == f"KeyError: 'planted {kinds[i]}'"
        elif kinds[i] == 10:
            assert f["error"] == f"the worker process died (signal {int(signal.SIGKILL)})"
        elif kinds[i] == 14:
            assert f["error"].startswith("peak RSS rose ") and f["error"].endswith("(limit 50 MB)")
    # reproducers: the input's bytes (also for the killed inputs) and a replayable .json
    seg = next(f for i, f in by_index.items() if kinds[i] == 10)
    assert Path(seg["reproducer"]).with_suffix(".bin").read_bytes() == bytes([10])
    first = next(f for i, f in by_index.items() if kinds[i] < 10)
    assert bench.main(["--replay", first["reproducer"]]) == 1
    assert "KeyError: 'planted" in capsys.readouterr().err
    # the table says how to replay
    doc["out"] = str(out)
    assert "python bench/fuzz.py --replay " in bench.table(doc)


def test_bad_arguments_exit_2_and_the_split_of_the_inputs(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bench = _bench()
    with pytest.raises(SystemExit) as exc:
        bench.main(["--targets", "serial,nope"])
    assert exc.value.code == 2
    assert "--targets: unknown nope" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        bench.main(["--replay", str(tmp_path / "missing.json")])
    assert exc.value.code == 2
    assert "--replay" in capsys.readouterr().err.splitlines()[-1]
    assert bench.plan(1_000_000, list(bench.WEIGHTS)) == {
        "serial": 350_000, "mavlink": 350_000, "config": 200_000, "recording": 90_000, "mapfile": 10_000,
    }  # fmt: skip
    assert sum(bench.plan(7, ["serial", "config", "mapfile"]).values()) == 7
