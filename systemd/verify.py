#!/usr/bin/env python3
"""Check robotd.service with systemd-analyze: `verify` must pass; print the `security` exposure.

systemd-analyze verify wants the ExecStart binary to exist, so the unit is checked as a copy whose
ExecStart points at the robotd of this checkout's virtual environment (or any existing binary).
Exit status: 0 when verify passes, 1 otherwise. Run: python3 systemd/verify.py [--security]
"""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
UNIT = HERE / "robotd.service"


def main(argv: list[str]) -> int:
    analyze = shutil.which("systemd-analyze")
    if analyze is None:
        print("systemd-analyze not found (apt-get install systemd)", file=sys.stderr)
        return 1
    exe = HERE.parent / ".venv" / "bin" / "robotd"
    if not exe.exists():
        exe = Path(shutil.which("robotd") or "/bin/true")
    text = UNIT.read_text()
    text = re.sub(r"^ExecStart=\S+", f"ExecStart={exe}", text, flags=re.M)
    with tempfile.TemporaryDirectory() as tmp:
        unit = Path(tmp) / "robotd.service"
        unit.write_text(text)
        proc = subprocess.run([analyze, "verify", str(unit)], capture_output=True, text=True)
        # verify prints unrelated complaints about the host's own units on some machines; only
        # lines that name our unit count.
        ours = [ln for ln in (proc.stdout + proc.stderr).splitlines() if "robotd.service" in ln]
        for ln in ours:
            print(ln, file=sys.stderr)
        ok = proc.returncode == 0 and not ours
        print(f"systemd-analyze verify robotd.service: {'OK' if ok else 'FAILED'}")
        if "--security" in argv:
            sec = subprocess.run([analyze, "security", "--offline=true", str(unit)], capture_output=True, text=True)
            last = [ln for ln in sec.stdout.splitlines() if "Overall exposure level" in ln]
            print(last[-1] if last else sec.stdout[-2000:])
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
