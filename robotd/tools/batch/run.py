"""``robotd replay-many``: plan the (source, configuration) replays, skip the done ones, run the rest
on an engine, keep every row as it arrives, and write the table.

Exit status: 0 when every replay is ok, 1 when some row failed (the table says which and why),
130 after Ctrl-C (the finished rows are kept and tabled), 2 for a usage error.
"""

from __future__ import annotations

import json
import logging
import sys
import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

from robotd.tools.batch import table
from robotd.tools.batch.configs import Configuration
from robotd.tools.batch.jobs import OK, code_version
from robotd.tools.batch.sources import DigestCache, Source, source_digest
from robotd.tools.batch.store import ResultStore, row_key

logger = logging.getLogger("robotd.batch.run")  # its name before the layer packages: users filter by it

DEFAULT_MEMORY_MB = 4000.0  # a replay's resident memory limit (and its Ray memory request)


class Engine(Protocol):
    name: str

    def describe(self) -> str: ...

    def run(self, jobs: Sequence[dict[str, Any]], on_row: Any) -> None: ...


@dataclass
class Options:
    out_dir: Path
    workers: int = 0  # local: processes (0: one per core); --ray local: the CPUs Ray offers
    ray: str | None = None  # None: the local engine; "local" or a cluster address
    timeout_s: float = 0.0  # per replay; 0: none
    memory_mb: float = DEFAULT_MEMORY_MB
    max_retries: int = 3  # Ray: a task whose worker died is retried this often
    rerun: bool = False  # run every replay again, done or not
    progress: bool = True


@dataclass
class Outcome:
    rows: list[dict[str, Any]]  # the table's rows (robotd.tools.batch.table)
    doc: dict[str, Any]  # the JSON document
    markdown: str
    ran: int = 0
    reused: int = 0
    interrupted: bool = False
    failed: list[dict[str, Any]] = field(default_factory=list)

    @property
    def exit_code(self) -> int:
        if self.interrupted:
            return 130
        return 1 if self.failed else 0


def make_engine(opts: Options) -> Engine:
    if opts.ray:
        from robotd.tools.batch.ray_engine import RayEngine  # imported only here: the local default needs no ray

        return RayEngine(opts.ray, workers=opts.workers, max_retries=opts.max_retries)
    from robotd.tools.batch.local import LocalEngine

    return LocalEngine(opts.workers)


def source_digests(sources: Sequence[Source], cache: DigestCache) -> dict[str, str]:
    """Every source's digest; recordings hashed on a few threads (hashlib releases the GIL)."""
    with ThreadPoolExecutor(max_workers=4) as pool:
        digests = list(pool.map(lambda s: source_digest(s.url, cache), sources))
    return {s.url: d for s, d in zip(sources, digests)}


def replay_many(
    sources: Sequence[Source],
    configurations: Sequence[Configuration],
    opts: Options,
    engine: Engine | None = None,
) -> Outcome:
    engine = engine or make_engine(opts)
    t0 = time.monotonic()
    version = code_version()
    with ResultStore(opts.out_dir) as store:
        cache = DigestCache(store.dir / "digests.json")
        digests = source_digests(sources, cache)
        cache.save()
        keys: dict[tuple[str, str], str] = {}
        jobs: dict[str, dict[str, Any]] = {}
        reused: set[str] = set()
        for s in sources:
            for c in configurations:
                key = row_key(digests[s.url], c.digest, version)
                keys[(s.url, c.name)] = key
                if not opts.rerun and store.done(key) is not None:
                    reused.add(key)
                    continue
                jobs.setdefault(
                    key,
                    {
                        "key": key,
                        "source": s.url,
                        "source_name": s.name,
                        "source_digest": digests[s.url],
                        "config_name": c.name,
                        "config": c.data,
                        "config_digest": c.digest,
                        "robotd_version": version,
                        "timeout_s": opts.timeout_s,
                        "memory_mb": opts.memory_mb,
                    },
                )
        ran: set[str] = set()
        interrupted = False
        from robotd.tools.progress import progress_bar

        with progress_bar(len(jobs), "replay", "replay-many", enabled=opts.progress, leave=False) as bar:
            counts = {"ok": 0, "failed": 0}

            def on_row(row: dict[str, Any]) -> None:
                store.add(row)
                ran.add(row["key"])
                counts["ok" if row.get("status") == OK else "failed"] += 1
                bar.set_postfix_str(f"ok {counts['ok']} failed {counts['failed']}", refresh=False)
                bar.update(1)
                if row.get("status") != OK:
                    logger.warning("%s × %s: %s: %s", row["source"], row["config"], row["status"], row.get("error"))

            if jobs:
                try:
                    engine.run(list(jobs.values()), on_row)
                except KeyboardInterrupt:
                    interrupted = True
                    store.reload()  # what the folder kept is what the table shows
        rows_by_key = {k: ({**r, "reused": True} if k in reused else r) for k, r in store.rows.items()}
        rows = table.build(rows_by_key, sources, configurations, keys)
        wall = time.monotonic() - t0
        failed = [r for r in rows if r["status"] != OK]
        n_total = len(sources) * len(configurations)
        header = (
            f"replay-many: {len(sources)} sources × {len(configurations)} configurations = {n_total} replays "
            f"({len(ran)} run, {len(reused)} reused) on {engine.describe()}: {n_total - len(failed)} ok, "
            f"{len(failed)} failed{' (interrupted)' if interrupted else ''}; robotd {version}; {wall:.0f} s"
        )
        doc = {
            "command": "replay-many",
            "robotd_version": version,
            "engine": engine.describe(),
            "wall_s": wall,
            "replays_per_min": (len(ran) * 60.0 / wall) if ran and wall > 0 else None,
            "interrupted": interrupted,
            "sources": [{"url": s.url, "name": s.name, "digest": digests[s.url]} for s in sources],
            "configurations": [
                {"name": c.name, "digest": c.digest, "file": c.file, "overrides": c.overrides} for c in configurations
            ],
            "baseline": configurations[0].name if configurations else None,
            "counts": {"replays": n_total, "run": len(ran), "reused": len(reused), "failed": len(failed)},
            "out_dir": str(store.dir),
            "rows": [{**r, "summary": rows_by_key[r["key"]].get("summary")} for r in rows],
        }
        md = table.markdown(rows, configurations, header)
        (store.dir / "results.json").write_text(json.dumps(doc, sort_keys=True, indent=1) + "\n", encoding="utf-8")
        (store.dir / "table.md").write_text(md, encoding="utf-8")
        (store.dir / "table.csv").write_text(table.to_csv(rows), encoding="utf-8")
    return Outcome(rows, doc, md, len(ran), len(reused), interrupted, failed)


def closing_line(out: Outcome) -> str:
    c = out.doc["counts"]
    rate = out.doc.get("replays_per_min")
    return (
        f"replay-many: {c['replays']} replays ({c['run']} run, {c['reused']} reused): {c['replays'] - c['failed']} ok, "
        f"{c['failed']} failed{', interrupted' if out.interrupted else ''} in {out.doc['wall_s']:.0f} s on "
        f"{out.doc['engine']}" + (f" ({rate:.1f} replays/min)" if rate else "") + f"; table in {out.doc['out_dir']}/"
    )


def print_outcome(out: Outcome, as_json: bool) -> None:
    if as_json:
        print(json.dumps(out.doc, sort_keys=True))
    else:
        sys.stdout.write(out.markdown)
    print(closing_line(out), file=sys.stderr, flush=True)
