"""The table of ``robotd replay-many``: one row per (source, configuration), in Markdown, JSON and CSV.

Columns (CSV names; the Markdown table shows the first dozen): the source's name and URL, the
configuration, the status (``ok``; ``error``: the replay raised; ``timeout``, ``memory``, ``died``,
``interrupted``), frames, lost frames, drift (% of the path; in metres on a path under 1 m), ATE
and RPE against the source's truth, the step time's p50 and p95, landmarks, the health events
(:func:`robotd.tools.batch.jobs.events_of`) or the error, and whether the row was reused from an
earlier run. Then the comparison with the baseline (the first configuration) on the same
source: ``ate_delta_m``, ``ate_delta_pct``, ``drift_delta``, ``lost_delta``. Then the keys:
``key``, ``source_digest``, ``config_digest``, ``robotd_version``, the trajectory file and its
SHA-256, the worker, the wall time and the peak memory.

With more than one configuration, the Markdown has a second table: one row per source, each
configuration's ATE and, for every configuration but the baseline, its change against it, with
the median of each column at the bottom.
"""

from __future__ import annotations

import csv
import io
import math
import statistics
from collections.abc import Sequence
from typing import Any

from robotd.tools.batch.configs import Configuration
from robotd.tools.batch.jobs import OK
from robotd.tools.batch.sources import Source

CSV_COLUMNS = (
    "source",
    "url",
    "config",
    "status",
    "frames",
    "lost_frames",
    "drift_pct",
    "drift_m",
    "ate_m",
    "rpe_m",
    "path_length_m",
    "step_ms_p50",
    "step_ms_p95",
    "landmarks",
    "odometry",
    "events",
    "error",
    "reused",
    "baseline",
    "ate_delta_m",
    "ate_delta_pct",
    "drift_delta",
    "lost_delta",
    "key",
    "source_digest",
    "config_digest",
    "robotd_version",
    "trajectory",
    "trajectory_sha256",
    "worker",
    "wall_s",
    "peak_rss_mb",
)


def flat(row: dict[str, Any]) -> dict[str, Any]:
    """A stored row -> the table's columns (without the comparison)."""
    s = row.get("summary") or {}
    return {
        "source": row.get("source_name", row["source"]),
        "url": row["source"],
        "config": row["config"],
        "status": row.get("status"),
        "frames": s.get("frames"),
        "lost_frames": s.get("lost_frames"),
        "drift_pct": s.get("truth_drift_pct"),
        "drift_m": s.get("truth_drift_m"),
        "ate_m": s.get("truth_ate_rmse_m"),
        "rpe_m": s.get("truth_rpe_trans_m"),
        "path_length_m": s.get("truth_path_length_m"),
        "step_ms_p50": s.get("step_ms_p50"),
        "step_ms_p95": s.get("step_ms_p95"),
        "landmarks": s.get("landmarks"),
        "odometry": s.get("odometry"),
        "events": "; ".join(row.get("events") or []),
        "error": row.get("error"),
        "reused": bool(row.get("reused")),
        "key": row["key"],
        "source_digest": row["source_digest"],
        "config_digest": row["config_digest"],
        "robotd_version": row.get("robotd_version"),
        "trajectory": row.get("trajectory"),
        "trajectory_sha256": row.get("trajectory_sha256"),
        "worker": row.get("worker"),
        "wall_s": row.get("wall_s"),
        "peak_rss_mb": row.get("peak_rss_mb"),
    }


def _drift(r: dict[str, Any]) -> float | None:
    """The drift to compare: % of the path where defined, else metres."""
    return r["drift_pct"] if r.get("drift_pct") is not None else r.get("drift_m")


def compare_with_baseline(rows: list[dict[str, Any]], baseline: str) -> None:
    """Adds the comparison columns to flat rows (in place), against the baseline's row of the
    same source."""
    base = {r["url"]: r for r in rows if r["config"] == baseline}
    for r in rows:
        r["baseline"] = baseline
        b = base.get(r["url"])
        r["ate_delta_m"] = r["ate_delta_pct"] = r["drift_delta"] = r["lost_delta"] = None
        if b is None or r is b or r["status"] != OK or b["status"] != OK:
            continue
        if r["ate_m"] is not None and b["ate_m"] is not None:
            r["ate_delta_m"] = r["ate_m"] - b["ate_m"]
            r["ate_delta_pct"] = 100.0 * r["ate_delta_m"] / b["ate_m"] if b["ate_m"] > 0 else None
        d, db = _drift(r), _drift(b)
        if d is not None and db is not None and (r.get("drift_pct") is None) == (b.get("drift_pct") is None):
            r["drift_delta"] = d - db
        if r["lost_frames"] is not None and b["lost_frames"] is not None:
            r["lost_delta"] = r["lost_frames"] - b["lost_frames"]


def build(
    rows_by_key: dict[str, dict[str, Any]],
    sources: Sequence[Source],
    configurations: Sequence[Configuration],
    keys: dict[tuple[str, str], str],
) -> list[dict[str, Any]]:
    """The table's rows in (source, configuration) order, with the comparison columns."""
    out: list[dict[str, Any]] = []
    for s in sources:
        for c in configurations:
            row = rows_by_key.get(keys[(s.url, c.name)])
            if row is not None:
                out.append(flat(row))
    if configurations:
        compare_with_baseline(out, configurations[0].name)
    return out


# --------------------------------------------------------------------------------------------
# rendering


def _f(v: Any, fmt: str, none: str = "–") -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return none
    return format(v, fmt)


def _drift_text(r: dict[str, Any]) -> str:
    if r.get("drift_pct") is not None:
        return f"{r['drift_pct']:.2f} %"
    if r.get("drift_m") is not None:
        return f"{r['drift_m']:.3f} m"
    return "–"


def _vs(r: dict[str, Any]) -> str:
    if r["config"] == r.get("baseline"):
        return "baseline"
    parts: list[str] = []
    if r.get("ate_delta_m") is not None:
        pct = f" ({r['ate_delta_pct']:+.0f} %)" if r.get("ate_delta_pct") is not None else ""
        parts.append(f"ATE {r['ate_delta_m']:+.4f} m{pct}")
    if r.get("lost_delta"):
        parts.append(f"lost {r['lost_delta']:+d}")
    return ", ".join(parts) if parts else ("–" if r["status"] != OK else "same")


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def markdown(rows: Sequence[dict[str, Any]], configurations: Sequence[Configuration], header: str) -> str:
    lines = [header, ""]
    lines.append(
        "| source | configuration | status | frames | lost | drift | ATE m | RPE m | step ms p50 / p95 "
        "| events or error | vs baseline |"
    )
    lines.append("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        status = r["status"] + (" (reused)" if r.get("reused") else "")
        note = r["events"] if r["status"] == OK else (r.get("error") or "")
        lines.append(
            f"| {_cell(r['source'])} | {_cell(r['config'])} | {status} | {_f(r['frames'], 'd')} "
            f"| {_f(r['lost_frames'], 'd')} | {_drift_text(r)} | {_f(r['ate_m'], '.4f')} | {_f(r['rpe_m'], '.4f')} "
            f"| {_f(r['step_ms_p50'], '.1f')} / {_f(r['step_ms_p95'], '.1f')} | {_cell(note)} | {_vs(r)} |"
        )
    if len(configurations) > 1:
        lines += ["", comparison_markdown(rows, configurations)]
    return "\n".join(lines) + "\n"


def comparison_markdown(rows: Sequence[dict[str, Any]], configurations: Sequence[Configuration]) -> str:
    """One row per source: each configuration's ATE and each one's change against the baseline."""
    names = [c.name for c in configurations]
    base = names[0]
    by = {(r["url"], r["config"]): r for r in rows}
    urls = list(dict.fromkeys(r["url"] for r in rows))
    head = ["source", *(f"ATE m {n}" for n in names), *(f"Δ ATE {n} vs {base}" for n in names[1:])]
    lines = ["| " + " | ".join(_cell(h) for h in head) + " |", "|" + "---|" * len(head)]
    cols: dict[str, list[float]] = {h: [] for h in head[1:]}
    for u in urls:
        src = next(r["source"] for r in rows if r["url"] == u)
        cells = [_cell(src)]
        for n in names:
            r = by.get((u, n))
            v = r["ate_m"] if r is not None and r["status"] == OK else None
            cells.append(_f(v, ".4f") if r is None or r["status"] == OK else r["status"])
            if v is not None:
                cols[f"ATE m {n}"].append(v)
        for n in names[1:]:
            r = by.get((u, n))
            d = r.get("ate_delta_pct") if r is not None else None
            cells.append(_f(d, "+.1f") + (" %" if d is not None else ""))
            if d is not None:
                cols[f"Δ ATE {n} vs {base}"].append(d)
        lines.append("| " + " | ".join(cells) + " |")
    med = ["**median**"]
    for h in head[1:]:
        vals = cols[h]
        if not vals:
            med.append("–")
        elif h.startswith("Δ"):
            med.append(f"{statistics.median(vals):+.1f} %")
        else:
            med.append(f"{statistics.median(vals):.4f}")
    lines.append("| " + " | ".join(med) + " |")
    return "\n".join(lines)


def to_csv(rows: Sequence[dict[str, Any]]) -> str:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(CSV_COLUMNS), extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: ("" if r.get(k) is None else r.get(k)) for k in CSV_COLUMNS})
    return buf.getvalue()
