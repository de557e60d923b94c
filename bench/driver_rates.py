#!/usr/bin/env python3
"""Driver throughput: each driver must sustain at least 2× its nominal rate without drops.

Runs the link benchmark (serial frames/s over a real pseudo-terminal with the MCU simulator,
MAVLink messages/s over loopback UDP with the mock autopilot) and the camera benchmark (frames/s
through a real depthai host-side Sync node, dataset read + rectify) as subprocesses, so each gets
a clean interpreter, and merges their JSON.

    python bench/driver_rates.py [--json]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent


def _run(script: str, extra: list[str], what: str) -> dict[str, Any]:
    if sys.stderr.isatty():  # what runs and for how long, before the silent subprocess
        print(f"running {script}: {what}", file=sys.stderr, flush=True)
    out = subprocess.run(
        [sys.executable, str(HERE / script), "--json", *extra],
        capture_output=True,
        text=True,
        check=False,
    )
    if out.returncode != 0:
        return {"error": f"{script} exited {out.returncode}: {out.stderr[-500:]}"}
    lines = [ln for ln in out.stdout.splitlines() if ln.startswith("{")]
    return json.loads(lines[-1]) if lines else {"error": f"{script}: no JSON on stdout"}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    links = _run("drivers_links.py", [], "serial and MAVLink links, 3 s each (about 10 s)")
    camera = _run("drivers_camera.py", [], "camera sources over 180 stereo pairs (about 15 s)")
    if args.json:
        print(json.dumps({"links": links, "camera": camera}, sort_keys=True))
        return 0
    print("## Vehicle links\n")
    print("```json\n" + json.dumps(links, indent=1, sort_keys=True) + "\n```\n")
    print("## Camera sources\n")
    rows = camera.get("rows", [])
    if rows:
        cols = sorted({k for r in rows for k in r})
        print("| " + " | ".join(cols) + " |")
        print("|" + "---|" * len(cols))
        for r in rows:
            print("| " + " | ".join(str(r.get(c, "")) for c in cols) + " |")
    else:
        print(camera)
    return 0


if __name__ == "__main__":
    sys.exit(main())
