"""``robotd-calib``: stereo calibration from chessboard pairs, OAK factory import, rectification check.

    robotd-calib stereo DIR --board 9x6 [--square M] --out FILE [--json]
    robotd-calib import-oak (DEVICE_ID|EEPROM.json) --size 640x400 --out FILE [--json]
    robotd-calib check CALIB LEFT RIGHT [--method opencv|thesis] [--json]
    robotd-calib ros-yaml CALIB [--out-dir DIR] [--json]
    robotd-calib upgrade CALIB --out FILE [--json]

stereo, import-oak and upgrade write a Kalibr camchain and, beside it, the ROS camera_info YAMLs
``<stem>_left.yaml`` and ``<stem>_right.yaml`` (``--no-ros-yaml``: not).

Logging goes to stderr (configured here only); results go to stdout, as text or, with --json,
as exactly one JSON object. A :class:`robotd.core.errors.RobotdError` becomes one line on stderr and
exit status 2; argument errors exit with 2 as well. docs/calibration.md has worked examples.
"""

from __future__ import annotations

import argparse
import json
import logging
import re
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from robotd.core.errors import CalibrationError, RobotdError

logger = logging.getLogger("robotd.calib")


def _size(text: str) -> tuple[int, int]:
    m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
    if not m or int(m.group(1)) <= 0 or int(m.group(2)) <= 0:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT such as 640x400, got {text!r}")
    return int(m.group(1)), int(m.group(2))


def _positive(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not v > 0:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}")
    return v


def _emit(args: argparse.Namespace, result: dict[str, Any], text_lines: list[str]) -> None:
    if args.json:
        sys.stdout.write(json.dumps(result, sort_keys=False) + "\n")
    else:
        sys.stdout.write("\n".join(text_lines) + "\n")


def _check_out(path: Path) -> None:
    if not path.parent.is_dir():
        raise CalibrationError(f"--out {path}: directory {path.parent} does not exist")


def _save(args: argparse.Namespace, calib: Any, out: Path, result: dict[str, Any]) -> list[str]:
    """The camchain and (unless --no-ros-yaml) the ROS YAMLs beside it; the text lines saying so."""
    from calib.camchain import calibration_to_dict, save_calibration
    from calib.ros_yaml import camera_info_paths, write_camera_info

    topics = (args.rostopic_left, args.rostopic_right)
    save_calibration(calib, out, rostopics=topics)
    fields = calibration_to_dict(calib, topics)["cam0"]["robotd"]["kalibr_fields"]
    result["kalibr_fields"] = fields
    what = "the raw cameras" if fields == "raw" else f"the rectified pinhole pair ({fields})"
    lines = [f"Kalibr fields: {what}"]
    result["ros_yaml"] = []
    if args.ros_yaml:
        paths = write_camera_info(calib, camera_info_paths(out))
        result["ros_yaml"] = [str(p) for p in paths]
        lines.append(f"ROS camera_info: {paths[0]}, {paths[1]}")
    return lines


def cmd_stereo(args: argparse.Namespace) -> int:
    from calib.chessboard import calibrate_directory, parse_board

    out = Path(args.out)
    _check_out(out)
    report = calibrate_directory(
        args.dir,
        board=parse_board(args.board),
        square_m=args.square,
        distortion=args.distortion,
        outlier_factor=args.outlier_factor,
        outlier_min_px=args.outlier_min_px,
        min_views=args.min_views,
    )
    result = report.as_dict()
    result["out"] = str(out)
    saved = _save(args, report.calibration, out, result)
    lines = [
        f"stereo calibration of {args.dir}: {len(report.views)} views used, {len(report.dropped)} dropped",
        "",
        "| view | RMS left px | RMS right px |",
        "|---|---|---|",
        *(f"| {v.name} | {v.rms_left_px:.3f} | {v.rms_right_px:.3f} |" for v in report.views),
        "",
        *(f"dropped {n}: {r}" for n, r in report.dropped),
        f"stereo RMS {report.stereo_rms_px:.3f} px (mono {report.mono_rms_left_px:.3f} / "
        f"{report.mono_rms_right_px:.3f} px)",
        f"left  fx {result['fx_left']:.2f} fy {result['fy_left']:.2f} cx {result['cx_left']:.2f} "
        f"cy {result['cy_left']:.2f}",
        f"baseline {report.calibration.baseline_m:.6g} m (square {args.square} m); written to {out}",
        *saved,
    ]
    _emit(args, result, lines)
    return 0


def cmd_import_oak(args: argparse.Namespace) -> int:
    try:
        from drivers.oak import import_oak_calibration
    except ImportError as exc:
        raise CalibrationError(f"import-oak needs depthai: {exc}") from exc
    out = Path(args.out)
    _check_out(out)
    w, h = args.size
    calib = import_oak_calibration(args.source, w, h)
    K = calib.K_left
    result: dict[str, Any] = {
        "source": calib.source,
        "size": [w, h],
        "baseline_m": calib.baseline_m,
        "fx": float(K[0, 0]),
        "fy": float(K[1, 1]),
        "cx": float(K[0, 2]),
        "cy": float(K[1, 2]),
        "fx_right": float(calib.K_right[0, 0]),
        "T_m": calib.T.tolist(),
        "distortion_model": calib.distortion_model,
        "out": str(out),
    }
    saved = _save(args, calib, out, result)
    lines = [
        f"{calib.source} at {w}x{h}",
        f"left fx {K[0, 0]:.2f} fy {K[1, 1]:.2f} cx {K[0, 2]:.2f} cy {K[1, 2]:.2f}",
        f"baseline {calib.baseline_m:.5f} m, T {[round(t, 6) for t in calib.T.tolist()]} m; written to {out}",
        *saved,
    ]
    _emit(args, result, lines)
    return 0


def cmd_check(args: argparse.Namespace) -> int:
    import cv2

    from calib.camchain import load_calibration
    from calib.check import check_pair
    from robotd.core.stereo import Rectifier

    calib = load_calibration(args.calib)
    images = []
    for p in (args.left, args.right):
        img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise CalibrationError(f"check: cannot read {p} as an image")
        images.append(img)
    res = check_pair(calib, images[0], images[1], method=args.method, detector=args.detector, ratio=args.ratio)
    model = Rectifier(calib, method=args.method).model
    result: dict[str, Any] = {
        **res.as_dict(),
        "method": args.method,
        "detector": args.detector,
        "f_px": model.f_px,
        "baseline_m": model.baseline_m,
    }
    lines = [
        f"{args.method} rectification, {args.detector}: {res.n_matches} verified matches "
        f"({res.n_candidates} before the epipolar check)",
        f"median |dy| {res.median_abs_dy_px:.3f} px, {100 * res.share_within_1px:.1f} % within 1 px, "
        f"mean dy {res.mean_dy_px:+.3f} px, p90 |dy| {res.p90_abs_dy_px:.3f} px",
    ]
    _emit(args, result, lines)
    return 0


def cmd_ros_yaml(args: argparse.Namespace) -> int:
    from calib.camchain import load_calibration
    from calib.ros_yaml import camera_info_paths, write_camera_info

    calib = load_calibration(args.calib)
    paths = write_camera_info(calib, camera_info_paths(args.calib, args.out_dir))
    result = {"calib": str(args.calib), "ros_yaml": [str(p) for p in paths]}
    _emit(args, result, [f"ROS camera_info: {paths[0]}, {paths[1]}"])
    return 0


def cmd_upgrade(args: argparse.Namespace) -> int:
    from calib.camchain import load_calibration

    out = Path(args.out)
    _check_out(out)
    calib = load_calibration(args.calib)
    result: dict[str, Any] = {"calib": str(args.calib), "out": str(out)}
    lines = [f"{args.calib} ({calib.distortion_model}, {calib.image_size[0]}x{calib.image_size[1]}) written to {out}"]
    lines += _save(args, calib, out, result)
    _emit(args, result, lines)
    return 0


def _output_options(p: argparse.ArgumentParser) -> None:
    from calib.camchain import DEFAULT_ROSTOPICS

    p.add_argument("--rostopic-left", default=DEFAULT_ROSTOPICS[0], help="cam0.rostopic: the left images in a bag")
    p.add_argument("--rostopic-right", default=DEFAULT_ROSTOPICS[1], help="cam1.rostopic: the right images in a bag")
    p.add_argument(
        "--no-ros-yaml", dest="ros_yaml", action="store_false", help="do not write <stem>_left/_right.yaml beside it"
    )


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="robotd-calib", description="robotd stereo calibration tools")
    p.add_argument("-v", "--verbose", action="store_true", help="INFO logging on stderr")
    sub = p.add_subparsers(dest="command", required=True)

    s = sub.add_parser("stereo", help="calibrate a stereo rig from chessboard pairs DIR/left*, DIR/right*")
    s.add_argument("dir", help="directory with left*.jpg|png and right*.jpg|png pairs")
    s.add_argument("--board", default="9x6", help="inner corners COLSxROWS (default 9x6)")
    s.add_argument("--square", type=_positive, default=1.0, help="square side in metres (default 1 = squares)")
    s.add_argument("--out", required=True, help="calibration file to write (camchain YAML)")
    s.add_argument("--distortion", choices=["radtan", "radtan-k3", "rational"], default="radtan")
    s.add_argument("--outlier-factor", type=_positive, default=3.0, help="drop views above F x median RMS")
    s.add_argument("--outlier-min-px", type=_positive, default=0.5, help="never drop views below this RMS")
    s.add_argument("--min-views", type=int, default=5)
    s.add_argument("--json", action="store_true", help="print one JSON object")
    _output_options(s)
    s.set_defaults(func=cmd_stereo)

    o = sub.add_parser("import-oak", help="import an OAK factory calibration (device id or EEPROM JSON)")
    o.add_argument("source", help="device id (MxID), '' for the first device, or an EEPROM .json file")
    o.add_argument("--size", type=_size, default=(640, 400), help="output size WxH (default 640x400)")
    o.add_argument("--out", required=True, help="calibration file to write")
    o.add_argument("--json", action="store_true")
    _output_options(o)
    o.set_defaults(func=cmd_import_oak)

    c = sub.add_parser("check", help="rectify a pair and measure the row offset of matched features")
    c.add_argument("calib", help="calibration file")
    c.add_argument("left")
    c.add_argument("right")
    c.add_argument("--method", choices=["opencv", "thesis"], default="opencv")
    c.add_argument("--detector", choices=["sift", "orb"], default="sift")
    c.add_argument("--ratio", type=_positive, default=0.8)
    c.add_argument("--json", action="store_true")
    c.set_defaults(func=cmd_check)

    r = sub.add_parser("ros-yaml", help="write the ROS camera_info YAMLs of a calibration file")
    r.add_argument("calib", help="calibration file (any version robotd reads)")
    r.add_argument("--out-dir", default=None, help="directory of <stem>_left/_right.yaml (default: beside CALIB)")
    r.add_argument("--json", action="store_true")
    r.set_defaults(func=cmd_ros_yaml)

    u = sub.add_parser("upgrade", help="rewrite a calibration file (any version) in the current, Kalibr-readable form")
    u.add_argument("calib", help="calibration file (any version robotd reads)")
    u.add_argument("--out", required=True, help="camchain YAML to write")
    u.add_argument("--json", action="store_true")
    _output_options(u)
    u.set_defaults(func=cmd_upgrade)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # argparse already printed the usage error
        return int(exc.code) if isinstance(exc.code, int) else 2
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING, format="%(levelname)s %(name)s: %(message)s"
    )
    try:
        return int(args.func(args))
    except RobotdError as exc:
        sys.stderr.write(f"robotd-calib {args.command}: error: {exc}\n")
        return 2


if __name__ == "__main__":
    sys.exit(main())
