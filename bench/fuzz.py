#!/usr/bin/env python3
"""Long fuzz runs over robotd's five input parsers: a count of inputs, crashes and hangs per target.

    python bench/fuzz.py --json --inputs 1000000
    python bench/fuzz.py --targets serial,config --inputs 20000 --seed 3 --time-limit 60
    python bench/fuzz.py --replay fuzz-out/serial-1-1234.json      # one saved crash, in this process

The targets (``tests/fuzz/targets.py``, shared with the property tests in tests/fuzz/): the serial
decoder and handler, the MAVLink parser and handlers, the config loader, the map loader (valid
checksum, mutated content, then three pipeline steps) and the recording reader. Each input is a
mutation of a real seed (frames, pymavlink messages, config/*.toml, saved maps, recordings), made
from ``random.Random(f"{seed}:{target}:{index}")``: deterministic, and any one input can be made
again from its index alone.

``--inputs`` is split across the chosen targets by fixed weights (``WEIGHTS``) that follow each
target's cost per input, so that no target takes most of the time: serial 35 %, MAVLink 35 %,
config 20 %, recording 9 %, map file 1 % (the map target resumes and steps a SLAM pipeline,
0.08–0.15 s an input, against 0.2–0.5 ms for the serial one). ``--per-target N`` gives each target N instead.

Each target runs in a forked worker process, one at a time. A crash is any exception from the
target's oracle (outside its clean-error contract, or an ``AssertionError`` for a broken
invariant), one input raising the worker's peak RSS by more than ``--memory-mb`` (300 MB: a forged
size allocated), or the worker dying on an input (a signal, the OOM killer); a hang is an input that
runs longer than ``--hang-s`` (2 s): the watchdog kills the worker, counts the hang and starts a
new worker after that input. Every crash and hang is saved under ``--out`` as the input's bytes
(``.bin``) and a ``.json`` (target, seed, index, the traceback and its last line); ``--replay``
runs one again. The exit status is 1 when any crash or hang was found, 2 on a bad argument.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import multiprocessing as mp
import os
import platform
import random
import resource
import signal
import sys
import tempfile
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tests.fuzz.targets import TARGETS

WEIGHTS = {"serial": 0.35, "mavlink": 0.35, "config": 0.20, "recording": 0.09, "mapfile": 0.01}
HANG_S = 2.0
MEMORY_MB = 300.0  # one input raising the worker's peak RSS by more is a crash (a forged size allocated)
SETUP_TIMEOUT_S = 600.0  # building the seed corpus (the map target steps SLAM on sim:// frames)
# a worker's counts live in shared memory (exact even when the worker is killed): the input
# running and since when (0: none), inputs done, their time, the slowest, then one count per outcome
RUNNING, SINCE, DONE, BUSY_S, SLOWEST_S, SLOWEST_INDEX, PEAK_MB, OUTCOMES = range(8)
MAX_OUTCOMES = 16
KEEP_PER_SITE = 5  # reproducers saved per distinct error (every crash is counted)


def plan(total: int, names: list[str]) -> dict[str, int]:
    """``total`` inputs split across ``names`` by ``WEIGHTS`` (renormalised over the chosen
    targets, largest remainders rounded up), at least one each."""
    w = {n: WEIGHTS.get(n, 1.0) for n in names}
    s = sum(w.values())
    exact = {n: total * w[n] / s for n in names}
    out = {n: int(exact[n]) for n in names}
    for n in sorted(names, key=lambda n: out[n] - exact[n])[: total - sum(out.values())]:
        out[n] += 1
    for n in names:  # one each, taken from the largest
        if out[n] == 0:
            out[n] = 1
            out[max(names, key=lambda m: out[m])] -= 1
    return out


def case_rng(seed: int, name: str, index: int) -> random.Random:
    return random.Random(f"{seed}:{name}:{index}")


# ----------------------------------------------------------------------------------- the worker


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # kB on Linux


def _worker(factory: Callable[[], Any], name: str, seed: int, start: int, stop: int, regenerate: list[int],
            conn: Any, shared: Any, stop_flag: Any, hang_s: float, memory_mb: float, quiet: bool) -> None:  # fmt: skip
    """Runs inputs start..stop-1 of ``name``, keeping its counts in ``shared`` (the layout above;
    the watchdog reads RUNNING and SINCE) and sending crashes (an exception, or the peak RSS
    rising more than ``memory_mb`` on one input), slow inputs and the name of each new outcome
    through ``conn``."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle
    if quiet:  # libpng and the targets' log lines would bury the table
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, 1)
        os.dup2(devnull, 2)
    logging.getLogger().addHandler(logging.NullHandler())
    t0 = time.perf_counter()
    target = factory()
    target.setup()
    conn.send(("ready", time.perf_counter() - t0))
    for i in regenerate:  # the inputs a killed worker was running: their bytes for the reproducers
        conn.send(("input", i, target.generate(case_rng(seed, name, i)).data))
    labels: dict[str, int] = {}
    peak = shared[PEAK_MB] = _peak_rss_mb()
    for i in range(start, stop):
        if stop_flag.value:
            break
        case = target.generate(case_rng(seed, name, i))
        shared[RUNNING], shared[SINCE] = float(i), time.monotonic()
        t = time.perf_counter()
        try:
            outcome = target.check(case)
        except BaseException as exc:  # the point: anything that comes out is a finding
            if isinstance(exc, KeyboardInterrupt | SystemExit) and stop_flag.value:
                break
            tb = traceback.format_exc()
            conn.send(("crash", i, tb, _last_line(tb), _site(exc), case.data))
            outcome = "crash"
        dt = time.perf_counter() - t
        if (now_peak := _peak_rss_mb()) > peak:  # a high-water mark: each rise is this input's
            if now_peak - peak > memory_mb and outcome != "crash":
                error = f"peak RSS rose {now_peak - peak:.0f} MB to {now_peak:.0f} MB (limit {memory_mb:.0f} MB)"
                conn.send(("crash", i, error, error, "peak RSS", case.data))
                outcome = "crash"
            peak = shared[PEAK_MB] = now_peak
        if outcome not in labels:
            labels[outcome] = min(len(labels), MAX_OUTCOMES - 1)  # the last slot: all the others
            conn.send(("outcome", labels[outcome], str(outcome)[:40]))
        shared[OUTCOMES + labels[outcome]] += 1
        shared[DONE] += 1
        shared[BUSY_S] += dt
        if dt > shared[SLOWEST_S]:
            shared[SLOWEST_S], shared[SLOWEST_INDEX] = dt, float(i)
        shared[SINCE] = 0.0
        if dt > hang_s:  # finished, but too late: a hang all the same
            conn.send(("slow", i, dt, case.data))
    conn.send(("done",))


def _last_line(tb: str) -> str:
    lines = [ln for ln in tb.strip().splitlines() if ln.strip()]
    return lines[-1].strip()[:300] if lines else "?"


def _site(exc: BaseException) -> str:
    """Where the exception was raised (innermost frame), for grouping crashes by site."""
    frames = traceback.extract_tb(exc.__traceback__)
    if not frames:
        return type(exc).__name__
    f = frames[-1]
    path = Path(f.filename)
    try:
        path = path.resolve().relative_to(Path(__file__).resolve().parents[1])
    except ValueError:
        pass
    return f"{type(exc).__name__} at {path}:{f.lineno}"


# ----------------------------------------------------------------------------------- the parent


@dataclass
class TargetResult:
    name: str
    planned: int
    inputs: int = 0
    crashes: int = 0
    hangs: int = 0
    busy_s: float = 0.0
    wall_s: float = 0.0
    setup_s: float = 0.0
    slowest_s: float = 0.0
    slowest_index: int | None = None
    workers: int = 0
    peak_rss_mb: float = 0.0
    outcomes: dict[str, int] = field(default_factory=dict)
    findings: list[dict[str, Any]] = field(default_factory=list)
    stopped_by_time_limit: bool = False

    def add(self, shared: Any, labels: dict[int, str]) -> None:
        """A worker's counts (``shared``, the layout above) added."""
        self.inputs += int(shared[DONE])
        self.busy_s += shared[BUSY_S]
        for k, label in labels.items():
            if label != "crash":  # counted as crashes
                self.outcomes[label] = self.outcomes.get(label, 0) + int(shared[OUTCOMES + k])
        if shared[SLOWEST_S] > self.slowest_s:
            self.slowest_s, self.slowest_index = shared[SLOWEST_S], int(shared[SLOWEST_INDEX])
        self.peak_rss_mb = max(self.peak_rss_mb, shared[PEAK_MB])

    def row(self) -> dict[str, Any]:
        return {
            "target": self.name,
            "inputs": self.inputs,
            "planned": self.planned,
            "crashes": self.crashes,
            "hangs": self.hangs,
            "inputs_per_s": round(self.inputs / self.wall_s, 1) if self.wall_s > 0 else 0.0,
            "slowest_input_ms": round(1e3 * self.slowest_s, 1),
            "slowest_index": self.slowest_index,
            "mean_input_ms": round(1e3 * self.busy_s / self.inputs, 3) if self.inputs else 0.0,
            "wall_s": round(self.wall_s, 1),
            "setup_s": round(self.setup_s, 1),
            "workers": self.workers,
            "peak_rss_mb": round(self.peak_rss_mb),
            "outcomes": dict(sorted(self.outcomes.items())),
            "stopped_by_time_limit": self.stopped_by_time_limit,
        }


class Findings:
    """Writes reproducers: ``<target>-<seed>-<index>.bin`` (the input) and ``.json`` (what happened)."""

    def __init__(self, out: Path, seed: int, hang_s: float) -> None:
        self.out, self.seed, self.hang_s = out, seed, hang_s
        self.per_site: dict[tuple[str, str], int] = {}

    def save(
        self, res: TargetResult, kind: str, index: int, error: str, site: str, tb: str, data: bytes | None
    ) -> None:
        entry: dict[str, Any] = {"target": res.name, "kind": kind, "index": index, "error": error, "site": site}
        n = self.per_site.get((res.name, site), 0)
        self.per_site[(res.name, site)] = n + 1
        if n < KEEP_PER_SITE:
            self.out.mkdir(parents=True, exist_ok=True)
            stem = self.out / f"{res.name}-{self.seed}-{index}"
            bin_name = None
            if data is not None:
                stem.with_suffix(".bin").write_bytes(data)
                bin_name = stem.with_suffix(".bin").name
            doc = dict(entry, seed=self.seed, hang_s=self.hang_s, traceback=tb, input=bin_name)
            stem.with_suffix(".json").write_text(json.dumps(doc, indent=1) + "\n")
            entry["reproducer"] = str(stem.with_suffix(".json"))
        res.findings.append(entry)


class _Incarnation:
    """One worker process of a target and the parent's side of its pipe and shared counts."""

    def __init__(self, ctx: Any, factory: Callable[[], Any], res: TargetResult, seed: int, start: int,
                 pending: dict[int, dict[str, Any]], findings: Findings, hang_s: float, memory_mb: float, quiet: bool,
                 log: Callable[[str], None]) -> None:  # fmt: skip
        self.res, self.pending, self.findings, self.hang_s, self.log = res, pending, findings, hang_s, log
        self.shared = ctx.Array("d", OUTCOMES + MAX_OUTCOMES, lock=False)
        self.stop_flag = ctx.Value("b", 0, lock=False)
        self.conn, child_end = ctx.Pipe(duplex=False)
        args = (factory, res.name, seed, start, res.planned, sorted(pending), child_end, self.shared,
                self.stop_flag, hang_s, memory_mb, quiet)  # fmt: skip
        self.proc = ctx.Process(target=_worker, args=args, daemon=True)
        self.proc.start()
        child_end.close()
        self.labels: dict[int, str] = {}
        self.ready = self.done = self.eof = False
        self.setup_s = 0.0

    def receive(self, timeout: float) -> None:
        """Handle the worker's messages for up to ``timeout`` (all that are waiting, at least)."""
        while not self.eof and self.conn.poll(timeout):
            timeout = 0.0
            try:
                msg = self.conn.recv()
            except EOFError:  # the worker is gone
                self.eof = True
                return
            res, kind = self.res, msg[0]
            if kind == "ready":
                self.ready, self.setup_s = True, msg[1]
            elif kind == "input" and msg[1] in self.pending:
                self.findings.save(res, data=msg[2], **self.pending.pop(msg[1]))
            elif kind == "crash":
                _, i, tb, last, site, data = msg
                res.crashes += 1
                self.findings.save(res, "crash", i, last, site, tb, data)
                self.log(f"{res.name}: crash at input {i}: {last}")
            elif kind == "slow":
                _, i, dt, data = msg
                res.hangs += 1
                error = f"took {dt:.2f} s (limit {self.hang_s} s)"
                self.findings.save(res, "hang", i, error, "slow input", "", data)
                self.log(f"{res.name}: input {i} took {dt:.2f} s")
            elif kind == "outcome":
                self.labels[msg[1]] = msg[2] if msg[1] < MAX_OUTCOMES - 1 else "other"
            elif kind == "done":
                self.done = True

    def running(self) -> tuple[int, float] | None:
        """The input running and since when (monotonic), or None between inputs."""
        since = self.shared[SINCE]
        return (int(self.shared[RUNNING]), since) if since > 0 else None

    def lost(self, index: int, kind: str, error: str) -> None:
        """Input ``index`` killed the worker (or was killed): counted, its reproducer waits for
        its bytes from the next worker."""
        self.proc.kill()
        self.proc.join()
        self.receive(0.0)  # what it sent before
        if kind == "hang":
            self.res.hangs += 1
        else:
            self.res.crashes += 1
        self.log(f"{self.res.name}: input {index}: {error}")
        self.pending[index] = {"kind": kind, "index": index, "error": error, "site": error, "tb": ""}

    def close(self) -> None:
        self.proc.join(timeout=10)
        self.conn.close()
        self.res.add(self.shared, self.labels)


def run_target(factory: Callable[[], Any], name: str, n: int, seed: int, findings: Findings, hang_s: float = HANG_S,
               time_limit_s: float | None = None, quiet: bool = True, log: Callable[[str], None] = lambda s: None,
               memory_mb: float = MEMORY_MB) -> TargetResult:  # fmt: skip
    """Inputs 0..n-1 of one target in worker processes; after a hang or a death, a new worker
    goes on after that input (and first makes its bytes again for the reproducer)."""
    ctx = mp.get_context("fork")  # the worker inherits the factory (tests inject their own)
    res = TargetResult(name, n)
    pending: dict[int, dict[str, Any]] = {}  # killed inputs waiting for their bytes
    start = 0
    ready_at: float | None = None
    t_begin = time.monotonic()
    while start < n:
        w = _Incarnation(ctx, factory, res, seed, start, pending, findings, hang_s, memory_mb, quiet, log)
        res.workers += 1
        try:
            t_spawn = last_log = time.monotonic()
            lost: int | None = None
            while not w.done and lost is None:
                w.receive(0.1)
                t = time.monotonic()
                if w.ready and ready_at is None:
                    ready_at = t
                if time_limit_s is not None and ready_at is not None and t - ready_at > time_limit_s:
                    w.stop_flag.value = 1
                    res.stopped_by_time_limit = True
                running = w.running()
                if not w.ready and t - t_spawn > SETUP_TIMEOUT_S:
                    w.proc.kill()
                    raise RuntimeError(f"{name}: the worker did not finish its setup in {SETUP_TIMEOUT_S:.0f} s")
                if running is not None and t - running[1] > hang_s:  # the watchdog
                    lost = running[0]
                    w.lost(lost, "hang", f"still running after {hang_s} s (killed)")
                elif not w.done and (w.eof or not w.proc.is_alive()):
                    w.receive(0.0)
                    if w.done:
                        break
                    w.proc.join()
                    code = w.proc.exitcode or 0
                    how = f"signal {-code}" if code < 0 else f"exit code {code}"
                    if running is None:
                        raise RuntimeError(f"{name}: the worker ended outside an input ({how}); see it with --verbose")
                    lost = running[0]  # died on an input (a signal, the OOM killer, os._exit): a crash
                    w.lost(lost, "crash", f"the worker process died ({how})")
                elif t - last_log > 30:
                    log(f"{name}: {start + int(w.shared[DONE])}/{n} inputs, {res.crashes} crashes, {res.hangs} hangs")
                    last_log = t
        finally:  # interrupted (Ctrl-C, SIGTERM): the worker goes too
            if w.proc.is_alive() and not w.done:
                w.proc.kill()
        w.close()
        res.setup_s += w.setup_s
        if lost is None or res.stopped_by_time_limit:
            break
        res.inputs += 1  # the lost input
        start = lost + 1
    for info in pending.values():  # the run ended before a new worker made their bytes again
        findings.save(res, data=None, **info)
    res.wall_s = time.monotonic() - (ready_at if ready_at is not None else t_begin)
    return res


def run(names: list[str], counts: dict[str, int], seed: int, out: Path, hang_s: float = HANG_S,
        time_limit_s: float | None = None, factories: dict[str, Callable[[], Any]] | None = None,
        quiet: bool = True, log: Callable[[str], None] = lambda s: None,
        memory_mb: float = MEMORY_MB) -> dict[str, Any]:  # fmt: skip
    """The whole run: each target in turn; the JSON document ``--json`` prints."""
    factories = factories or TARGETS
    findings = Findings(out, seed, hang_s)
    t0 = time.monotonic()
    results = []
    saved_tempdir = tempfile.tempdir
    with tempfile.TemporaryDirectory(prefix="robotd-fuzz-") as tmp:
        tempfile.tempdir = tmp  # the workers' scratch files (also a killed worker's) go here and go with it
        try:
            for name in names:
                log(f"{name}: {counts[name]} inputs")
                res = run_target(
                    factories[name], name, counts[name], seed, findings, hang_s, time_limit_s, quiet, log, memory_mb
                )
                log(f"{name}: {res.inputs} inputs, {res.crashes} crashes, {res.hangs} hangs in {res.wall_s:.0f} s")
                results.append(res)
        finally:
            tempfile.tempdir = saved_tempdir
    rows = [r.row() for r in results]
    return {
        "seed": seed,
        "hang_s": hang_s,
        "memory_mb": memory_mb,
        "time_limit_s": time_limit_s,
        "targets": rows,
        "total": {
            "inputs": sum(r["inputs"] for r in rows),
            "crashes": sum(r["crashes"] for r in rows),
            "hangs": sum(r["hangs"] for r in rows),
            "wall_s": round(time.monotonic() - t0, 1),
        },
        "findings": [f for r in results for f in r.findings],
        "out": str(out),
        "machine": {"cpus": os.cpu_count(), "machine": platform.machine(), "python": platform.python_version()},
    }


def table(doc: dict[str, Any]) -> str:
    lines = [
        "| target | inputs | crashes | hangs | inputs/s | slowest input ms |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for r in doc["targets"]:
        short = " (time limit)" if r["stopped_by_time_limit"] else ""
        lines.append(
            f"| {r['target']} | {r['inputs']}{short} | {r['crashes']} | {r['hangs']} | {r['inputs_per_s']:.0f} "
            f"| {r['slowest_input_ms']:.0f} |"
        )
    t = doc["total"]
    lines.append(f"| **total** | {t['inputs']} | {t['crashes']} | {t['hangs']} | | |")
    lines.append("")
    lines.append(f"seed {doc['seed']}, {t['wall_s']:.0f} s; outcomes: " + "; ".join(
        f"{r['target']} " + ", ".join(f"{k} {v}" for k, v in r["outcomes"].items()) for r in doc["targets"]
    ))  # fmt: skip
    saved = [f for f in doc["findings"] if "reproducer" in f]
    for f in doc["findings"][:20]:
        lines.append(f"- {f['target']} {f['kind']} at input {f['index']}: {f['error']} ({f['site']})")
    if saved:
        lines.append(f"reproducers in {doc['out']}/; replay one with:")
        lines.append(f"    python bench/fuzz.py --replay {saved[0]['reproducer']}")
    return "\n".join(lines)


# ------------------------------------------------------------------------------------- replay


def replay(path: Path, factories: dict[str, Callable[[], Any]] | None = None) -> int:
    """Make a saved input again from its seed and index (the saved bytes win if they differ) and
    run the oracle on it in this process, printing its outcome or its whole traceback; 1 when it
    crashes or takes longer than the hang limit."""
    factories = factories or TARGETS
    doc = json.loads(path.read_text())
    target = factories[doc["target"]]()
    target.setup()
    case = target.generate(case_rng(doc["seed"], doc["target"], doc["index"]))
    if doc.get("input"):
        saved = (path.parent / doc["input"]).read_bytes()
        if saved != case.data:  # the saved bytes win (the context, e.g. the serial frames, is made again)
            print(f"note: input {doc['index']} made again differs from the saved one (the generator or its seed "
                  "corpus changed since): running the saved bytes", file=sys.stderr)  # fmt: skip
            case = dataclasses.replace(case, data=saved)
    t = time.perf_counter()
    try:
        outcome = target.check(case)
    except BaseException:  # show whatever comes out
        traceback.print_exc()
        print(f"{doc['target']} input {doc['index']}: crash ({time.perf_counter() - t:.2f} s)")
        return 1
    dt = time.perf_counter() - t
    print(f"{doc['target']} input {doc['index']}: {outcome} in {dt:.3f} s (was: {doc['error']})")
    return 1 if dt > doc.get("hang_s", HANG_S) else 0


# --------------------------------------------------------------------------------------- main


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--inputs", type=int, default=10_000, help="inputs in total, split by WEIGHTS (default 10000)")
    ap.add_argument("--per-target", type=int, help="this many inputs for each target instead")
    ap.add_argument("--targets", default=",".join(TARGETS), help="comma-separated (default: all five)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--time-limit", type=float, help="at most this many seconds per target")
    ap.add_argument("--hang-s", type=float, default=HANG_S, help="an input taking longer is a hang (default 2)")
    ap.add_argument("--memory-mb", type=float, default=MEMORY_MB,
                    help="one input raising the peak RSS by more is a crash (default 300)")  # fmt: skip
    ap.add_argument("--out", type=Path, default=Path("fuzz-out"), help="reproducers go here (default fuzz-out/)")
    ap.add_argument("--json", action="store_true", help="print exactly one JSON object")
    ap.add_argument("--verbose", action="store_true", help="let the workers print (libpng, log lines)")
    ap.add_argument("--replay", type=Path, help="run one saved reproducer (.json) again, in this process")
    args = ap.parse_args(argv)
    if args.replay is not None:
        try:
            doc = json.loads(args.replay.read_text())
            ok = doc["target"] in TARGETS and all(isinstance(doc[k], int) for k in ("seed", "index"))
        except (OSError, UnicodeDecodeError, ValueError, KeyError, TypeError) as exc:
            ap.error(f"--replay {args.replay}: not a reproducer written by this bench ({type(exc).__name__}: {exc})")
        if not ok:
            ap.error(f"--replay {args.replay}: not a reproducer of one of {', '.join(TARGETS)}")
        return replay(args.replay)
    names = [n.strip() for n in args.targets.split(",") if n.strip()]
    unknown = [n for n in names if n not in TARGETS]
    if unknown or not names:
        ap.error(f"--targets: unknown {', '.join(unknown) or '(none given)'}; expected some of {', '.join(TARGETS)}")
    if args.inputs < len(names) or (args.per_target is not None and args.per_target < 1):
        ap.error(f"--inputs {args.inputs}: at least one per target ({len(names)})")
    if args.hang_s <= 0 or args.memory_mb <= 0 or (args.time_limit is not None and args.time_limit <= 0):
        ap.error("--hang-s, --memory-mb and --time-limit must be > 0")
    counts = {n: args.per_target for n in names} if args.per_target else plan(args.inputs, names)
    doc = run(names, counts, args.seed, args.out, args.hang_s, args.time_limit, quiet=not args.verbose,
              log=lambda s: print(s, file=sys.stderr, flush=True), memory_mb=args.memory_mb)  # fmt: skip
    doc["command"] = "python bench/fuzz.py " + " ".join(sys.argv[1:] if argv is None else argv)
    print(json.dumps(doc) if args.json else table(doc))
    return 1 if doc["total"]["crashes"] or doc["total"]["hangs"] else 0


if __name__ == "__main__":
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(128 + signal.SIGTERM))  # so that the worker is ended too
    sys.exit(main())
