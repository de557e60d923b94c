"""Accuracy of the default configuration on every real folder and on the simulated rover (issues 13, 26).

For each KITTI folder in ../shared/data (a folder with ``calib.txt`` and ``image_0/`` or ``image_l/``),
each EuRoC folder (``mav0/cam0``, ``mav0/cam1``; reported, not judged) and each ``sim://`` case,
every detector × filter runs ``robotd.tools.replay.replay`` with the default configuration (or
``--config FILE``, loaded as ``robotd replay --config`` does) and only
``frontend.detector`` and ``slam.filter`` changed. The plain OpenCV stereo PnP odometry
(robotd/research/pnp_baseline.py) runs on the same frames in the same invocation, as a row of its
own per place. Per run: drift in % of the path (first pose aligned), ATE after a rigid alignment,
RPE over one frame (translation), lost frames, milliseconds per frame (p50 of the step's total;
only meaningful with --jobs 1 on an otherwise idle machine), and ATE / PnP ATE. Also (issue 26):
KITTI-style segment drift over 100-800 m segments (``robotd eval --segments``; "–" on a path
shorter than 100 m, which every shared folder is), and the share of poses whose position NEES lies
in the 95 % χ²(3) band after aligning by positions over the first ``ALIGN_POSITIONS_M`` metres
(``robotd eval --align-positions``; robotd rows only, the PnP baseline reports no covariance; "–"
on a path no longer than that, e.g. the stationary EuRoC piece). Both come from the replay's
summary (truth_segment_*, truth_aligned_*), which computes them with these settings.

Verdicts (KITTI rows; issue 13's targets): 0 lost frames, ATE < 0.10 m, ATE at most half the PnP
baseline's on the same folder, and drift < 1.0 % where the truth is the KITTI odometry benchmark's.
A folder converted from KITTI raw (it has a ``raw/`` folder: truth computed from the GPS/INS
through a calibration chain good to about 1°) has its drift reported, not judged. ``target`` marks
the rows the issue's targets name (ORB and SIFT with the default filter). Sim rows are reported,
not judged; robotd fuses the simulated rover's wheel odometry there ("input" column), the PnP
baseline never does.

Sim cases: ``--sim`` takes world names (``yard`` becomes ``sim://?world=yard&duration=D&realtime=0``)
or full ``sim://`` URLs; by default every world in ``drivers.simworld.WORLDS`` at run time plus
``SIM_EXTRA``.

The robotd runs go through ``robotd replay-many``'s engine (robotd.tools.batch): one configuration per
detector × filter, the KITTI places under every one and the sim places under the default one,
on ``--jobs N`` local worker processes or on a Ray cluster (``--ray ADDRESS``, ``--ray local``);
``--out DIR`` keeps the results folder, so a rerun replays only what changed (robotd's code, the
data, the settings). The PnP baseline runs in this process. ``--max-frames N`` cuts each source
(KITTI ``stop=N``, sim ``duration``) for both.

    python bench/accuracy.py [--json] [--quick] [--folders kitti-seq1,...] [--detectors orb,sift,surf]
        [--filters fastslam2,fastslam1,ekf] [--sim yard ...] [--max-frames N] [--jobs N] [--ray ADDRESS] [--out DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, NamedTuple
from urllib.parse import parse_qsl, urlsplit

# as the robotd command does (robotd.tools.cli), before numpy loads: one BLAS thread, sleeping OpenMP workers
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_WAIT_POLICY", "passive")

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from robotd.core.choices import DETECTORS  # noqa: E402
from robotd.research.evaluate import ALIGN_POSITIONS_M  # noqa: E402
from robotd.slam.factory import ESTIMATORS  # noqa: E402

# ALIGN_POSITIONS_M (10 m): the positions-aligned NEES column aligns the estimate to the truth by
# the positions over the first 10 m of true path and judges the poses after them; it is the M a
# replay's summary uses (robotd.research.evaluate), named here so the table can say it.

DEFAULT_DATA = Path(os.environ.get("ROBOTD_SHARED_DATA", REPO.parent / "shared" / "data"))
SIM_DURATION_S = 4.0  # a world name's default run: 120 frames at the sim's 30 fps
# existing worlds under harder settings, run besides WORLDS: the yard rocking; open terrain at a car's
# metre per frame through its 98° curve, on the exact rig and with a 0.4 px calibration error
# (issue 26's hard case, vision only as the held-out sequence was judged; docs/frontend.md "Far points
# and the disparity offset"); and the whole 764 m lap at that pace, whose end returns to the first
# landmarks (a loop the filter does not close today: docs/benchmarks.md, issue 26 session 13)
SIM_EXTRA = (
    "sim://?world=yard&tilt=5",
    "sim://open_terrain?speed=5&fps=5&duration=14&odometry=0",
    "sim://open_terrain?speed=5&fps=5&duration=14&odometry=0&disparity_error=-0.4",
    "sim://open_terrain?speed=5&fps=5&duration=153&odometry=0",
    # a hand-held camera shaken hard (issue 26's held-out D): EuRoC's rig, blur of a 5 ms exposure
    # that the frames do not report, as D's folder does not (robotd estimates it: docs/frontend.md)
    "sim://?shake=5&exposure_ms=5&exposure_report=0&fps=20&width=752&height=480&baseline=0.11&duration=10&odometry=0",
)
# issue 13's targets
MAX_ATE_M = 0.10
MAX_DRIFT_PCT = 1.0
MAX_ATE_RATIO = 0.5  # beat the PnP baseline's ATE by at least 2x
TARGET_DETECTORS = ("orb", "sift")


class Place(NamedTuple):
    name: str  # "kitti-seq1", "euroc-v101-micro", "sim:yard"
    kind: str  # "kitti" | "euroc" | "sim"
    source: str  # the URL both robotd and the baseline read
    judge_drift: bool = False  # drift judged (KITTI odometry truth) or reported only


def _bar(total: int, unit: str, desc: str) -> Any:
    """The benchmark's progress on stderr (robotd.tools.progress); cleared at the end, so the table or the
    JSON object on stdout is all that stays."""
    from robotd.tools.progress import progress_bar

    return progress_bar(total, unit, desc, leave=False, mininterval=0.5)


# --------------------------------------------------------------------------------------------
# What to run


def is_kitti_folder(p: Path) -> bool:
    return (p / "calib.txt").is_file() and ((p / "image_0").is_dir() or (p / "image_l").is_dir())


def is_euroc_folder(p: Path) -> bool:
    return (p / "mav0" / "cam0").is_dir() and (p / "mav0" / "cam1").is_dir()


def real_places(root: Path, names: list[str] | None) -> list[Place]:
    """Every real folder under ``root`` (sorted): KITTI folders, then EuRoC ones (``mav0/``,
    reported, not judged: the targets are KITTI's); or the named ones (names under root, or paths)."""
    if names is None:
        found = sorted(p for p in root.iterdir() if p.is_dir()) if root.is_dir() else []
        folders = [p for p in found if is_kitti_folder(p)] + [p for p in found if is_euroc_folder(p)]
    else:
        folders = [Path(n) if Path(n).is_dir() else root / n for n in names]
        bad = [str(f) for f in folders if not (is_kitti_folder(f) or is_euroc_folder(f))]
        if bad:
            raise SystemExit(
                "not a KITTI folder (calib.txt and image_0/ or image_l/) or a EuRoC one (mav0/cam0, mav0/cam1): "
                + ", ".join(bad)
            )
    return [
        Place(f.name, "kitti", f"kitti://{f.resolve()}", judge_drift=not (f / "raw").is_dir())
        if is_kitti_folder(f)
        else Place(f.name, "euroc", f"euroc://{f.resolve()}")
        for f in folders
    ]


def default_sim_items() -> list[str]:
    from drivers.simworld import WORLDS

    return [*WORLDS, *SIM_EXTRA]


def sim_place(item: str, duration_s: float) -> Place:
    """A world name or a ``sim://`` URL -> a Place; frames as fast as pulled (realtime=0) and a
    finite duration unless the URL sets them."""
    if not item.startswith("sim://"):
        item = f"sim://?world={item}"
    parts = urlsplit(item)
    q = dict(parse_qsl(parts.query))
    world = parts.netloc or q.get("world", "yard")
    extra = [f"{k}={v}" for k, v in q.items() if k not in ("world", "duration", "realtime")]
    sep = "&" if parts.query else "?"
    if "realtime" not in q:
        item, sep = f"{item}{sep}realtime=0", "&"
    if "duration" not in q:
        item = f"{item}{sep}duration={duration_s:g}"
    return Place(f"sim:{world}" + (f" ({', '.join(extra)})" if extra else ""), "sim", item)


# --------------------------------------------------------------------------------------------
# One run (a process-pool task: plain arguments in, a plain dict out)


def run_task(
    method: str, place: Place, detector: str | None, filt: str | None, cfg_path: str | None, max_frames: int
) -> dict[str, Any]:
    row: dict[str, Any] = {
        "place": place.name,
        "kind": place.kind,
        "source": place.source,
        "method": method,
        "detector": detector,
        "filter": filt,
    }
    try:
        if method == "pnp":
            from robotd.research.pnp_baseline import run_pnp

            s = run_pnp(place.source, max_frames=max_frames)
        else:
            from robotd.config import load_config
            from robotd.tools.replay import replay

            cfg = load_config(cfg_path, {"frontend": {"detector": detector}, "slam": {"filter": filt}})
            s = replay(cfg, place.source, max_frames=max_frames, progress=False)
    except Exception as exc:  # one failed run is a row saying so, not the end of the benchmark
        row["error"] = f"{type(exc).__name__}: {exc}"
        return row
    row.update(_figures(s))
    return row


def _figures(s: dict[str, Any]) -> dict[str, Any]:
    """A replay summary's figures as a row's columns (one run in process or on the engine)."""
    return dict(
        frames=s["frames"],
        lost_frames=s["lost_frames"],
        drift_pct=s.get("truth_drift_pct"),
        drift_m=s.get("truth_drift_m"),
        ate_m=s.get("truth_ate_rmse_m"),
        rpe_m=s.get("truth_rpe_trans_m"),
        rpe_rot_deg=s.get("truth_rpe_rot_deg"),
        path_length_m=s.get("truth_path_length_m"),
        segment_drift_pct=s.get("truth_segment_drift_pct"),
        segment_rot_deg_per_m=s.get("truth_segment_rot_deg_per_m"),
        segment_count=s.get("truth_segment_count"),
        nees_aligned_in_band_frac=s.get("truth_aligned_nees_pos_in_band_frac"),
        nees_aligned_mean=s.get("truth_aligned_nees_pos_mean"),
        nees_aligned_frames=s.get("truth_aligned_nees_pos_frames"),
        alignment=s.get("truth_alignment"),
        ms_per_frame=s["step_ms_p50"],
        ms_per_frame_p95=s["step_ms_p95"],
        wall_s=s["wall_s"],
        odometry=bool(s.get("odometry_priors", 0)),
    )


def limit_frames(place: Place, max_frames: int) -> Place:
    """The place cut to ``max_frames`` frames in its URL (KITTI ``stop``, sim ``duration``), so the
    baseline and robotd's replays read the same frames."""
    if not max_frames:
        return place
    base, _, query = place.source.partition("?")
    q = dict(parse_qsl(query))
    if place.kind in ("kitti", "euroc"):
        start, stride = int(q.get("start", 0)), int(q.get("stride", 1))
        stop = start + max_frames * stride
        q["stop"] = str(min(stop, int(q["stop"])) if "stop" in q else stop)
    else:
        fps = float(q.get("fps", 30.0))
        q["duration"] = f"{min(float(q.get('duration', 0) or 1e9), max_frames / fps):g}"
    return place._replace(source=f"{base}?{'&'.join(f'{k}={v}' for k, v in q.items())}")


def robotd_rows(
    grid: list[tuple[list[Place], list[tuple[str, str]]]], cfg_path: str | None, args: argparse.Namespace
) -> list[dict[str, Any]]:
    """robotd's replays through replay-many's engine: for each (places, [(detector, filter)]) the
    places × those configurations; rows in run_task's form."""
    from robotd.tools.batch.configs import build_configurations
    from robotd.tools.batch.run import Options, replay_many
    from robotd.tools.batch.sources import Source

    rows: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="robotd-accuracy-") as tmp:
        opts = Options(out_dir=Path(args.out or tmp), workers=args.jobs, ray=args.ray, memory_mb=args.memory_mb)
        for places, combos in grid:
            if not places or not combos:
                continue
            variants = [f'{d}-{f}: frontend.detector="{d}" slam.filter="{f}"' for d, f in combos]
            configs = build_configurations([cfg_path] if cfg_path else [], [], variants)
            which = {c.name: combo for c, combo in zip(configs, combos)}
            out = replay_many([Source(p.source, p.name) for p in places], configs, opts)
            by_url = {p.source: p for p in places}
            for r in out.doc["rows"]:
                place = by_url[r["url"]]
                d, f = which[r["config"]]
                row: dict[str, Any] = {
                    "place": place.name,
                    "kind": place.kind,
                    "source": place.source,
                    "method": "robotd",
                    "detector": d,
                    "filter": f,
                }
                s = r.get("summary")
                if r["status"] != "ok" or not s:
                    row["error"] = r.get("error") or r["status"]
                else:
                    row.update(_figures(s))
                rows.append(row)
    return rows


def judge(rows: list[dict[str, Any]], places: list[Place], default_filter: str) -> None:
    """Adds ate_vs_pnp, checks, verdict and target to each robotd row (in place)."""
    by_name = {p.name: p for p in places}
    pnp_ate = {r["place"]: r.get("ate_m") for r in rows if r["method"] == "pnp"}
    for r in rows:
        if r["method"] != "robotd":
            continue
        ref = pnp_ate.get(r["place"])
        ate = r.get("ate_m")
        r["ate_vs_pnp"] = ate / ref if (ate is not None and ref) else None
        place = by_name[r["place"]]
        r["target"] = place.kind == "kitti" and r["detector"] in TARGET_DETECTORS and r["filter"] == default_filter
        if place.kind != "kitti":
            r["verdict"] = None
            continue
        if "error" in r:
            r["checks"], r["verdict"] = {}, "fail"
            continue
        checks: dict[str, bool | None] = {
            "no_lost_frames": r["lost_frames"] == 0,
            "ate": ate is not None and ate < MAX_ATE_M,
            "beats_pnp_2x": r["ate_vs_pnp"] is not None and r["ate_vs_pnp"] <= MAX_ATE_RATIO,
            "drift": (r["drift_pct"] is not None and r["drift_pct"] < MAX_DRIFT_PCT) if place.judge_drift else None,
        }
        r["checks"] = checks
        r["verdict"] = "pass" if all(v is not False for v in checks.values()) else "fail"


# --------------------------------------------------------------------------------------------
# Output


def _f(v: Any, fmt: str) -> str:
    return "–" if v is None else format(v, fmt)


def _nees_cell(r: dict[str, Any]) -> str:
    """The share in band over how many poses, marked when a straight start took its rotation about
    the path from the first pose ("roll from pose 0") or positions could not align at all."""
    frac = r.get("nees_aligned_in_band_frac")
    if frac is None:
        return "–"
    how = {"positions+first-pose-roll": ", roll from pose 0", "first-pose": ", first pose"}.get(
        r.get("alignment") or ""
    )
    return f"{frac:.2f} of {r.get('nees_aligned_frames')}{how or ''}"


def _verdict(r: dict[str, Any]) -> str:
    if r.get("verdict") is None:
        return ""
    if r["verdict"] == "pass":
        return "pass"
    failed = [k for k, v in r.get("checks", {}).items() if v is False]
    return "**fail**" + (f" ({', '.join(failed)})" if failed else "")


def print_table(out: dict[str, Any]) -> None:
    print(f"Accuracy, default configuration ({out['config']}), commit {out['commit']}, {out['host']}\n")
    print(
        "| place | method | detector | filter | input | frames | lost | drift % | ATE m | RPE m "
        f"| seg. drift % | seg. deg/m | NEES in band, aligned {ALIGN_POSITIONS_M:g} m "
        "| ms/frame p50 | ATE / PnP ATE | target | verdict |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in out["rows"]:
        if "error" in r:
            print(
                f"| {r['place']} | {r['method']} | {r['detector'] or ''} | {r['filter'] or ''} | | | | | | | | | | | | "
                f"{'yes' if r.get('target') else ''} | error: {r['error']} |"
            )
            continue
        name = "PnP baseline" if r["method"] == "pnp" else "robotd"
        drift = _f(r["drift_pct"], ".2f") if r["drift_pct"] is not None else f"({_f(r['drift_m'], '.3f')} m)"
        print(
            f"| {r['place']} | {name} | {r['detector'] or 'orb (cv2)'} | {r['filter'] or '–'} "
            f"| {'vision+odometry' if r['odometry'] else 'vision'} | {r['frames']} | {r['lost_frames']} | {drift} "
            f"| {_f(r['ate_m'], '.3f')} | {_f(r['rpe_m'], '.4f')} | {_f(r.get('segment_drift_pct'), '.2f')} "
            f"| {_f(r.get('segment_rot_deg_per_m'), '.4f')} | {_nees_cell(r)} | {r['ms_per_frame']:.1f} "
            f"| {_f(r.get('ate_vs_pnp'), '.2f')} | {'yes' if r.get('target') else ''} | {_verdict(r)} |"
        )
    t = [r for r in out["rows"] if r.get("target")]
    print(
        f"\ntargets (ORB and SIFT, default filter, KITTI): {sum(r['verdict'] == 'pass' for r in t)}/{len(t)} pass; "
        f"all judged rows: {sum(r.get('verdict') == 'pass' for r in out['rows'])}"
        f"/{sum(r.get('verdict') is not None for r in out['rows'])} pass"
    )
    print(
        f"criteria: 0 lost, ATE < {MAX_ATE_M} m, ATE / PnP ATE <= {MAX_ATE_RATIO}, drift < {MAX_DRIFT_PCT} % "
        "(KITTI odometry truth only; raw-derived truth: reported)"
    )
    print(
        "seg.: KITTI-style segment drift over 100-800 m segments (– under 100 m of path); NEES: share of "
        f"poses in the 95 % chi2(3) band [0.216, 9.35] after aligning by positions over the first "
        f"{ALIGN_POSITIONS_M:g} m, on the poses after them (reported, not judged)"
    )
    if out["skipped"]:
        print(f"skipped: {'; '.join(out['skipped'])}")
    jobs = out["jobs"]
    print(
        f"wall time {out['wall_s']:.0f} s, --jobs {jobs}"
        + (" (ms/frame disturbed by parallel runs)" if jobs > 1 else "")
    )


def _commit() -> str:
    try:
        rev = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
        dirty = subprocess.run(["git", "-C", str(REPO), "status", "--porcelain"], capture_output=True, text=True)
    except OSError:
        return "unknown"
    return rev.stdout.strip() + ("-dirty" if dirty.stdout.strip() else "") if rev.returncode == 0 else "unknown"


def _host() -> str:
    model = ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{model or platform.processor() or platform.machine()}, {os.cpu_count()} CPUs"


# --------------------------------------------------------------------------------------------


def _names(text: str, known: tuple[str, ...], what: str) -> list[str]:
    names = [n.strip() for n in text.split(",") if n.strip()]
    bad = [n for n in names if n not in known]
    if bad:
        raise SystemExit(f"--{what}: unknown {bad}; known: {', '.join(known)}")
    return names


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--data", type=Path, default=DEFAULT_DATA, help="folder holding the KITTI and EuRoC folders (../shared/data)"
    )
    ap.add_argument(
        "--folders", help="comma-separated KITTI or EuRoC folders (names under --data, or paths); default: all found"
    )
    ap.add_argument("--detectors", default=",".join(("orb", "sift", "surf")))
    ap.add_argument("--filters", default=",".join(("fastslam2", "fastslam1", "ekf")))
    ap.add_argument(
        "--sim",
        nargs="*",
        metavar="WORLD|URL",
        help="sim cases (world names or sim:// URLs), run with the default detector and filter; default: every "
        "world of drivers.simworld.WORLDS and SIM_EXTRA; --sim with none: no sim runs",
    )
    ap.add_argument("--sim-duration", type=float, default=SIM_DURATION_S, help="simulated seconds of a world name")
    ap.add_argument("--config", metavar="FILE", help="TOML file overriding the built-in defaults (as robotd replay)")
    ap.add_argument("--max-frames", type=int, default=0, help="frames per run at most (0: all)")
    ap.add_argument("--jobs", type=int, default=1, help="local worker processes (ms/frame is only meaningful with 1)")
    ap.add_argument("--ray", metavar="ADDRESS", help="run robotd's replays on Ray: a cluster's address, or 'local'")
    ap.add_argument("--out", metavar="DIR", help="keep replay-many's results folder here (a rerun reuses it)")
    ap.add_argument("--memory-mb", type=float, default=4000.0, help="a replay's memory limit (Ray: its request)")
    ap.add_argument(
        "--quick", action="store_true", help="one KITTI folder x orb x fastslam2 + PnP; sim only with --sim"
    )
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)

    from robotd.config import load_config
    from robotd.frontend.detectors import surf_available

    default_filter = load_config(args.config).slam.filter
    skipped: list[str] = []
    detectors = _names(args.detectors, DETECTORS, "detectors")
    filters = _names(args.filters, tuple(ESTIMATORS), "filters")
    places = real_places(args.data, args.folders.split(",") if args.folders else None)
    if not places:
        skipped.append(
            f"real data: no KITTI (calib.txt, image_0/ or image_l/) or EuRoC (mav0/) folder under {args.data}"
        )
    sim_items = args.sim if args.sim is not None else ([] if args.quick else default_sim_items())
    if args.quick:
        seq1 = [p for p in places if p.name == "kitti-seq1"]
        places = (seq1 or places)[:1]
        detectors, filters = ["orb"], [default_filter]
    places += [sim_place(s, args.sim_duration) for s in sim_items]
    if "surf" in detectors and not surf_available():
        detectors.remove("surf")
        skipped.append("surf (robotd.frontend.surf not importable)")
    if not places:
        print("nothing to run: " + "; ".join(skipped), file=sys.stderr)
        return 2

    places = [limit_frames(p, args.max_frames) for p in places]
    d0 = "orb" if "orb" in detectors else detectors[0]
    f0 = default_filter if default_filter in filters else filters[0]
    t0 = time.perf_counter()
    rows: list[dict[str, Any]] = []
    # the baseline first, in this process; then robotd's replays on the engine: the KITTI grid, and
    # the sim cases with the default detector and filter only (the full grid there took 2 h, EKF with
    # SIFT on 300 frames alone most of it); the KITTI grid is the judged one
    with _bar(len(places), "place", "PnP baseline") as bar:
        for p in places:
            rows.append(run_task("pnp", p, None, None, args.config, 0))
            bar.update(1)
    kitti = [p for p in places if p.kind != "sim"]  # the real folders, KITTI and EuRoC
    sims = [p for p in places if p.kind == "sim"]
    rows += robotd_rows([(kitti, [(d, f) for d in detectors for f in filters]), (sims, [(d0, f0)])], args.config, args)
    order = {p.name: k for k, p in enumerate(places)}
    rows.sort(key=lambda r: (order[r["place"]], r["method"] != "pnp"))  # each place's baseline first
    judge(rows, places, default_filter)
    out = {
        "benchmark": "accuracy",
        "commit": _commit(),
        "host": _host(),
        "config": args.config or "built-in defaults",
        "default_filter": default_filter,
        "max_frames": args.max_frames,
        "jobs": args.jobs,
        "engine": f"ray {args.ray}" if args.ray else f"local, {args.jobs} worker process(es)",
        "criteria": {"max_ate_m": MAX_ATE_M, "max_drift_pct": MAX_DRIFT_PCT, "max_ate_vs_pnp": MAX_ATE_RATIO},
        "align_positions_m": ALIGN_POSITIONS_M,
        "places": [{"name": p.name, "kind": p.kind, "source": p.source, "judge_drift": p.judge_drift} for p in places],
        "skipped": skipped,
        "wall_s": time.perf_counter() - t0,
        "rows": rows,
    }
    if args.json:
        json.dump(out, sys.stdout)
        sys.stdout.write("\n")
    else:
        print_table(out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
