"""``robotd replay-many compare A B``: which recordings got worse from A to B, beyond a tolerance,
with the worst ones' trajectories plotted side by side.

A and B are results of ``robotd replay-many`` (its ``--out`` folder, or the ``results.json`` in
it), each optionally suffixed ``#CONFIG`` to take one configuration's rows: two robotd versions
(run into two folders) or two configurations of one run (``DIR#default DIR#ekf``). Rows pair up by
source digest (the same data, wherever it lay), else by URL.

B's row is worse than A's when

- it failed where A's was ok (an error, a timeout, out of memory, a dead worker);
- it lost more frames than A's (``--lost N``: more than N more; default 0);
- its ATE exceeds A's × (1 + ``--tolerance``) + ``--ate-m`` (defaults 10 % and 5 mm), or its drift
  A's × (1 + ``--tolerance``) + ``--drift-pct`` percentage points (0.1; ``--drift-m`` 5 mm on a
  path under 1 m, where drift is in metres).

The report (Markdown, or ``--json``) lists every worse row, the worst first (by the ratio of the
ATEs; a failure first of all), and counts the better and the unchanged ones. For the ``--worst N``
worst (5) whose trajectories are in both folders it draws A's and B's estimate beside each other,
each over the source's ground truth when it had one: PNG files in ``--plots DIR`` (default: a
``compare/`` folder in B's). Exit status 1 when something got worse, else 0.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from robotd.core.errors import InputError
from robotd.tools.batch.jobs import OK


@dataclass(frozen=True)
class Tolerance:
    rel: float = 0.10
    ate_m: float = 0.005
    drift_pct: float = 0.1
    drift_m: float = 0.005
    lost: int = 0


@dataclass
class ResultSet:
    label: str
    folder: Path
    version: str | None
    config: str | None
    rows: list[dict[str, Any]] = field(default_factory=list)


def load(spec: str) -> ResultSet:
    """``PATH[#CONFIG]`` -> its rows (one configuration's)."""
    path_text, _, named = spec.partition("#")
    config: str | None = named or None
    path = Path(path_text)
    doc_path = path / "results.json" if path.is_dir() else path
    try:
        doc = json.loads(doc_path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise InputError(
            f"compare: {doc_path}: {exc.strerror or exc} (a replay-many --out folder or its results.json)"
        ) from None
    except ValueError as exc:
        raise InputError(f"compare: {doc_path}: not JSON ({exc})") from None
    if not isinstance(doc, dict) or doc.get("command") != "replay-many":
        raise InputError(f"compare: {doc_path}: not the results of robotd replay-many")
    names = [c["name"] for c in doc.get("configurations", [])]
    if not config:
        if len(names) > 1:
            raise InputError(
                f"compare: {doc_path} holds {len(names)} configurations ({', '.join(names)}): name one as {spec}#NAME"
            )
        config = names[0] if names else None
    elif config not in names:
        raise InputError(f"compare: {doc_path} has no configuration {config!r}; it has {', '.join(names)}")
    rows = [r for r in doc.get("rows", []) if r.get("config") == config]
    label = f"{path_text}#{config}" if config else path_text
    return ResultSet(label, doc_path.parent, doc.get("robotd_version"), config, rows)


def _drift(r: dict[str, Any]) -> tuple[float | None, str]:
    if r.get("drift_pct") is not None:
        return r["drift_pct"], "%"
    return r.get("drift_m"), "m"


def judge(a: dict[str, Any], b: dict[str, Any], tol: Tolerance) -> tuple[str, list[str], float]:
    """("worse" | "better" | "same", the reasons, a severity for sorting: B's ATE over A's)."""
    if a.get("status") == OK and b.get("status") != OK:
        return "worse", [f"{b.get('status')}: {b.get('error')}"], math.inf
    if b.get("status") != OK:
        return "same", [f"failed in both ({b.get('status')})"], 0.0
    if a.get("status") != OK:
        return "better", [f"ok now (was {a.get('status')})"], 0.0
    worse: list[str] = []
    better: list[str] = []
    la, lb = a.get("lost_frames") or 0, b.get("lost_frames") or 0
    if lb > la + tol.lost:
        worse.append(f"lost frames {la} → {lb}")
    elif lb < la:
        better.append(f"lost frames {la} → {lb}")
    ea, eb = a.get("ate_m"), b.get("ate_m")
    ratio = 1.0
    if ea is not None and eb is not None:
        ratio = eb / ea if ea > 0 else (math.inf if eb > 0 else 1.0)
        if eb > ea * (1 + tol.rel) + tol.ate_m:
            worse.append(f"ATE {ea:.4f} → {eb:.4f} m ({100 * (eb - ea) / ea:+.0f} %)" if ea > 0 else f"ATE → {eb:.4f}")
        elif ea > eb * (1 + tol.rel) + tol.ate_m:
            better.append(f"ATE {ea:.4f} → {eb:.4f} m")
    (da, ua), (db, ub) = _drift(a), _drift(b)
    if da is not None and db is not None and ua == ub:
        slack = tol.drift_pct if ua == "%" else tol.drift_m
        if db > da * (1 + tol.rel) + slack:
            worse.append(f"drift {da:.3g} → {db:.3g} {ua}")
        elif da > db * (1 + tol.rel) + slack:
            better.append(f"drift {da:.3g} → {db:.3g} {ua}")
    if worse:
        return "worse", worse, max(ratio, 1.0 + 1e-9)
    if better:
        return "better", better, ratio
    return "same", [], ratio


def compare(a: ResultSet, b: ResultSet, tol: Tolerance) -> dict[str, Any]:
    def index(rows: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
        return {r.get("source_digest") or r["url"]: r for r in rows}

    ia, ib = index(a.rows), index(b.rows)
    pairs: list[dict[str, Any]] = []
    for k, rb in ib.items():
        ra = ia.get(k)
        if ra is None:
            continue
        verdict, reasons, severity = judge(ra, rb, tol)
        pairs.append(
            {
                "source": rb.get("source", rb["url"]),
                "url": rb["url"],
                "verdict": verdict,
                "reasons": reasons,
                "severity": severity,
                "a": {
                    k2: ra.get(k2) for k2 in ("status", "ate_m", "drift_pct", "drift_m", "lost_frames", "trajectory")
                },
                "b": {
                    k2: rb.get(k2) for k2 in ("status", "ate_m", "drift_pct", "drift_m", "lost_frames", "trajectory")
                },
                "a_truth": _truth_path(ra),
                "b_truth": _truth_path(rb),
            }
        )
    worse = sorted((p for p in pairs if p["verdict"] == "worse"), key=lambda p: -p["severity"])
    return {
        "command": "replay-many compare",
        "a": {"label": a.label, "version": a.version, "config": a.config, "rows": len(a.rows)},
        "b": {"label": b.label, "version": b.version, "config": b.config, "rows": len(b.rows)},
        "tolerance": tol.__dict__,
        "pairs": len(pairs),
        "unpaired": len(ib) + len(ia) - 2 * len(pairs),
        "worse": worse,
        "better": sum(p["verdict"] == "better" for p in pairs),
        "same": sum(p["verdict"] == "same" for p in pairs),
        "plots": [],
    }


def _truth_path(row: dict[str, Any]) -> str | None:
    t = row.get("trajectory")
    return t.replace(".txt", ".truth.txt") if t else None


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", text)[:80].strip("_") or "source"


def plot_pairs(report: dict[str, Any], a: ResultSet, b: ResultSet, out_dir: Path, worst: int) -> list[str]:
    """A's and B's trajectories of the worst rows, side by side over the truth (PNG, Agg)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from robotd.research.evaluate import read_trajectory

    out_dir.mkdir(parents=True, exist_ok=True)
    written: list[str] = []
    for k, p in enumerate(report["worse"][:worst], start=1):
        ta, tb = p["a"].get("trajectory"), p["b"].get("trajectory")
        if not ta or not tb or not (a.folder / ta).is_file() or not (b.folder / tb).is_file():
            continue
        fig, axes = plt.subplots(1, 2, figsize=(11, 5))
        xs: list[float] = []
        ys: list[float] = []
        for ax, rs, side, key in ((axes[0], a, p["a"], "a_truth"), (axes[1], b, p["b"], "b_truth")):
            est = read_trajectory(rs.folder / side["trajectory"])
            truth_rel = p.get(key)
            if truth_rel and (rs.folder / truth_rel).is_file():
                gt = read_trajectory(rs.folder / truth_rel)
                ax.plot(gt.T[:, 1, 3], gt.T[:, 0, 3], color="0.6", lw=2, label="truth")
                xs += list(gt.T[:, 1, 3])
                ys += list(gt.T[:, 0, 3])
            ax.plot(est.T[:, 1, 3], est.T[:, 0, 3], lw=1.2, label="estimate")
            xs += list(est.T[:, 1, 3])
            ys += list(est.T[:, 0, 3])
            ate = side.get("ate_m")
            status = side.get("status")
            sub = f"ATE {ate:.4f} m" if ate is not None else str(status)
            ax.set_title(f"{rs.label}\n{sub}", fontsize=9)
            ax.set_xlabel("y (right) [m]")
            ax.grid(True, alpha=0.3)
            ax.legend(fontsize=8, loc="best")
        # the same square window on both sides, so the two drives compare at a glance
        cx, cy = (min(xs) + max(xs)) / 2, (min(ys) + max(ys)) / 2
        half = max(max(xs) - min(xs), max(ys) - min(ys), 0.1) * 0.55
        for ax in axes:
            ax.set_xlim(cx - half, cx + half)
            ax.set_ylim(cy - half, cy + half)
            ax.set_aspect("equal", adjustable="box")
        axes[0].set_ylabel("x (forward) [m]")
        fig.suptitle(f"{p['source']}: {'; '.join(p['reasons'])}", fontsize=9)
        fig.tight_layout()
        path = out_dir / f"{k:02d}-{_slug(p['source'])}.png"
        fig.savefig(path, dpi=90)
        plt.close(fig)
        p["plot"] = str(path)
        written.append(str(path))
    report["plots"] = written
    return written


def markdown(report: dict[str, Any]) -> str:
    a, b = report["a"], report["b"]
    tol = report["tolerance"]
    lines = [
        f"Regression report: A = {a['label']} (robotd {a['version']}), B = {b['label']} (robotd {b['version']})",
        "",
        f"{report['pairs']} sources in both ({report['unpaired']} in one only): {len(report['worse'])} worse "
        f"beyond the tolerance, {report['better']} better, {report['same']} within it. "
        f"Tolerance: ×(1 + {tol['rel']:g}) plus "
        f"{tol['ate_m']:g} m of ATE, {tol['drift_pct']:g} points of drift % ({tol['drift_m']:g} m on short paths), "
        f"{tol['lost']} lost frames.",
    ]
    if report["worse"]:
        lines += ["", "| source | what got worse | ATE A m | ATE B m | plot |", "|---|---|---|---|---|"]
        for p in report["worse"]:
            ea, eb = p["a"].get("ate_m"), p["b"].get("ate_m")
            lines.append(
                f"| {p['source']} | {'; '.join(p['reasons'])} | {'–' if ea is None else f'{ea:.4f}'} "
                f"| {'–' if eb is None else f'{eb:.4f}'} | {p.get('plot', '')} |"
            )
    return "\n".join(lines) + "\n"
