"""Camera-driver throughput: the OAK pairing path through the real depthai Sync node (host-only
pipeline, no device) and dataset read (+ rectify) rates.

    python bench/drivers_camera.py [--json] [--pairs N] [--data DIR]

Prints a Markdown table, or exactly one JSON object with --json. The OAK rows feed 640×400 GRAY8
ImgFrames from a ThreadedHostNode into a host-side Sync node and consume them with the driver's
own OakCamera (PairGate, exposure-middle stamps, host rectification from the reference OAK-D
factory calibration when ../shared/data is present). "paced" runs emit at the stated rate and
must show zero drops; "unpaced" emits as fast as possible and shows the ceiling.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
import threading
import time
from datetime import timedelta
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
# depthai logs its warnings to stdout; --json must print exactly one JSON object there
os.environ.setdefault("DEPTHAI_LEVEL", "error")
DEFAULT_DATA = Path(os.environ.get("ROBOTD_SHARED_DATA", REPO.parent / "shared" / "data"))


def oak_host_run(n_pairs: int, rate_hz: float | None, calib_json: Path | None) -> dict[str, Any]:
    import depthai as dai

    from drivers._rectify import Rectifier
    from drivers.oak.camera import OakCamera, OakOptions, calibration_from_handler, make_sync

    rng = np.random.default_rng(0)
    images = [rng.integers(0, 256, (400, 640), dtype=np.uint8) for _ in range(4)]
    rectifier = None
    if calib_json is not None and calib_json.is_file():
        rectifier = Rectifier(calibration_from_handler(dai.CalibrationHandler(str(calib_json)), (640, 400)))  # type: ignore[call-overload]

    class Source(dai.node.ThreadedHostNode):
        def __init__(self) -> None:
            super().__init__()
            self.left = self.createOutput()
            self.right = self.createOutput()

        def run(self) -> None:
            t0 = time.monotonic()
            for i in range(n_pairs):
                if rate_hz:
                    delay = t0 + i / rate_hz - time.monotonic()
                    if delay > 0:
                        time.sleep(delay)
                t = time.monotonic()
                for out, dt in ((self.left, 0.0), (self.right, 0.0002)):
                    f = dai.ImgFrame()
                    f.setCvFrame(images[i % 4], dai.ImgFrame.Type.GRAY8)
                    f.setTimestamp(timedelta(seconds=t + dt))
                    f.setSequenceNum(i)
                    out.send(f)

    class Session:
        def __init__(self, opts: OakOptions) -> None:
            self._stack = contextlib.ExitStack()
            self.pipeline = self._stack.enter_context(dai.Pipeline(False))
            src = self.pipeline.create(Source)
            sync, self.queue = make_sync(self.pipeline, opts, run_on_host=True)
            src.left.link(sync.inputs["left"])
            src.right.link(sync.inputs["right"])
            self.rectifier = rectifier
            self.model = None if rectifier is None else rectifier.model
            self.rectified = rectifier is not None
            self.raw_calibration = None
            self.pipeline.start()

        def is_running(self) -> bool:
            return bool(self.pipeline.isRunning())

        def close(self) -> None:
            self.pipeline.stop()
            self._stack.close()

    cam = OakCamera("oak://", session_factory=Session, queue_size=8)  # type: ignore[arg-type]
    cam.open()
    expected = n_pairs / rate_hz if rate_hz else 0.0
    timer = threading.Timer(expected + 5.0, cam.close)
    timer.start()
    n = 0
    first = last = None
    for _ in cam.frames(timeout_s=0.3):
        last = time.perf_counter()
        first = first or last
        n += 1
        if n >= n_pairs:
            break
    timer.cancel()
    st = cam.stats()
    cam.close()
    lost = n_pairs - n
    return {
        "case": f"oak host Sync{' + rectify' if rectifier else ''}, "
        + (f"paced {rate_hz:g} fps" if rate_hz else "unpaced"),
        "frames": n,
        # rate between the first and the last delivered frame (not the idle wait after a lossy run)
        "fps": (n - 1) / (last - first) if n > 1 and first and last and last > first else 0.0,
        "lost": lost,
        "mismatched": st["mismatched"],
        "seq_missing": st["seq_missing"],
    }


def dataset_run(url: str, label: str) -> dict[str, Any]:
    from drivers import open_camera

    with open_camera(url) as cam:
        t0 = time.perf_counter()
        n = sum(1 for _ in cam.frames())
        t1 = time.perf_counter()
    return {"case": label, "frames": n, "fps": n / (t1 - t0), "lost": 0, "mismatched": 0, "seq_missing": 0}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--pairs", type=int, default=180)
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA)
    args = ap.parse_args(argv)
    calib = args.data / "oakd-calibration" / "BW1098OBC_14442C10218CCCD200.json"
    rows = [
        oak_host_run(args.pairs, 60.0, None),
        oak_host_run(args.pairs, 60.0, calib),
        oak_host_run(args.pairs, 120.0, calib),
        oak_host_run(args.pairs, None, calib),
    ]
    if (args.data / "kitti-seq1").is_dir():
        rows.append(dataset_run(f"kitti://{args.data / 'kitti-seq1'}", "kitti read (1226×370, rectified)"))
    if (args.data / "euroc-v101-micro").is_dir():
        rows.append(dataset_run(f"euroc://{args.data / 'euroc-v101-micro'}", "euroc read + rectify (752×480)"))
    conditions = {"cpus": os.cpu_count(), "python": sys.version.split()[0], "pairs": args.pairs}
    if args.json:
        print(json.dumps({"bench": "drivers_camera", "conditions": conditions, "rows": rows}, sort_keys=True))
        return 0
    print(f"conditions: {conditions}\n")
    print("| case | frames | frames/s | lost | mismatched | seq missing |")
    print("|---|---:|---:|---:|---:|---:|")
    for r in rows:
        print(
            f"| {r['case']} | {r['frames']} | {r['fps']:.1f} | {r['lost']} | {r['mismatched']} | {r['seq_missing']} |"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
