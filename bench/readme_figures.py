"""The figures README.md quotes in "Replay, recording and evaluation", regenerated (issue 27, item 9).

Runs the README's own commands on ../shared/data (``ROBOTD_SHARED_DATA`` elsewhere), each as a
``python -m robotd`` process, and prints what the README should say:

- ``replay``: ``robotd replay kitti://…/kitti-seq1 --out T.txt``, then ``robotd eval T.txt
  …/kitti-seq1/poses.txt --json``: drift and ATE (the comment beside the commands), and the replay's
  summary line (frames, lost, drift, ATE; its seconds and fps are this machine's);
- ``stall``: ``robotd replay 'kitti://…/kitti-seq1?drop=20-30' --json``: the ATE with 1 s left out;
- ``euroc``: ``robotd replay euroc://…/euroc-v101-micro --json``: the drift in metres on a path
  shorter than 1 m.

Each figure comes with the exact text the README holds for it; ``--check`` exits 1 when the README
lacks one (tests/bench/test_readme_figures.py checks the cheapest). Prints a Markdown table, or
one JSON object with --json.

    python bench/readme_figures.py [--figures replay,stall,euroc] [--check] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("ROBOTD_SHARED_DATA", REPO.parent / "shared" / "data"))
SUMMARY = re.compile(r"replayed (\d+) frames in [\d.]+ s \(\d+ fps\): (\d+) lost; drift ([\d.]+) %, ATE ([\d.]+) m")


def _robotd(*args: str) -> subprocess.CompletedProcess[str]:
    out = subprocess.run(
        [sys.executable, "-m", "robotd", *args], cwd=REPO, capture_output=True, text=True, timeout=600, check=False
    )
    if out.returncode != 0:
        raise SystemExit(f"robotd {' '.join(args)}: exit {out.returncode}: {out.stderr[-2000:]}")
    return out


def replay_figure(data: Path = DATA) -> dict[str, Any]:
    """The README's first two commands: replay kitti-seq1 to a TUM file, evaluate it."""
    seq = data / "kitti-seq1"
    with tempfile.TemporaryDirectory() as tmp:
        traj = Path(tmp) / "t.txt"
        rep = _robotd("replay", f"kitti://{seq}", "--out", str(traj))
        ev = json.loads(_robotd("eval", str(traj), str(seq / "poses.txt"), "--json").stdout)
    m = SUMMARY.search(rep.stderr)
    if m is None:
        raise SystemExit(f"no summary line in the replay's output: {rep.stderr[-1000:]}")
    frames, lost, drift, ate = int(m[1]), int(m[2]), float(m[3]), float(m[4])
    eval_figures = f"drift {ev['drift_pct']:.2f} %, ATE {ev['ate_rmse_m']:.3f} m"
    return {
        "figure": "replay",
        "frames": frames,
        "lost": lost,
        "drift_pct": ev["drift_pct"],
        "ate_rmse_m": ev["ate_rmse_m"],
        "summary_line": m[0],
        # what the README says: the comment beside `robotd eval`, and the summary line's figures
        "quotes": [f"# {eval_figures}", f"replayed {frames} frames in", f"{lost} lost; {eval_figures}"],
        # the replay's own truth figures are the same evaluation
        "consistent": f"drift {drift:.2f} %, ATE {ate:.3f} m" == eval_figures,
    }


def stall_figure(data: Path = DATA) -> dict[str, Any]:
    """kitti-seq1 with frames 20..29 (1 s) left out: the ATE README's stall paragraph quotes."""
    out = _robotd("replay", f"kitti://{data / 'kitti-seq1'}?drop=20-30", "--json")
    summary = json.loads(out.stdout.strip().splitlines()[-1])
    ate = summary["truth_ate_rmse_m"]
    return {
        "figure": "stall",
        "ate_rmse_m": ate,
        "lost": summary["lost_frames"],
        "quotes": [f"kitti-seq1 with 1 s left out gives ATE {ate:.3f} m"],
        "consistent": True,
    }


def euroc_figure(data: Path = DATA) -> dict[str, Any]:
    """EuRoC's stationary piece: drift in metres, with the path's length."""
    out = _robotd("replay", f"euroc://{data / 'euroc-v101-micro'}", "--json")
    summary = json.loads(out.stdout.strip().splitlines()[-1])
    drift, path = summary["truth_drift_m"], summary["truth_path_length_m"]
    return {
        "figure": "euroc",
        "drift_m": drift,
        "path_length_m": path,
        "quotes": [f"drift {drift:.3f} m (path {path:.2f} m)"],
        "consistent": True,
    }


FIGURES: dict[str, Callable[[Path], dict[str, Any]]] = {
    "replay": replay_figure,
    "stall": stall_figure,
    "euroc": euroc_figure,
}


def missing_quotes(readme: str, figure: dict[str, Any]) -> list[str]:
    """The figure's quotes the README does not hold (any run of spaces and line breaks counts as one
    space: the README wraps its prose and aligns its comments)."""
    flat = " ".join(readme.split())
    return [q for q in figure["quotes"] if " ".join(q.split()) not in flat]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--figures", default=",".join(FIGURES), help=f"comma-separated, of {', '.join(FIGURES)}")
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--check", action="store_true", help="exit 1 when README.md lacks a figure's text")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    names = [n for n in args.figures.split(",") if n]
    unknown = [n for n in names if n not in FIGURES]
    if unknown:
        ap.error(f"unknown figure(s) {unknown}; known: {list(FIGURES)}")
    readme = (REPO / "README.md").read_text(encoding="utf-8")
    results = []
    for name in names:
        fig = FIGURES[name](args.data)
        fig["missing_in_readme"] = missing_quotes(readme, fig)
        results.append(fig)
    if args.json:
        print(json.dumps({"figures": results}, sort_keys=True))
    else:
        print("| figure | what the README should say | in README.md |")
        print("|---|---|---|")
        for fig in results:
            for q in fig["quotes"]:
                said = "yes" if q not in fig["missing_in_readme"] else "**no**"
                print(f"| {fig['figure']} | `{q.strip()}` | {said} |")
    bad = [f["figure"] for f in results if f["missing_in_readme"] or not f["consistent"]]
    return 1 if args.check and bad else 0


if __name__ == "__main__":
    raise SystemExit(main())
