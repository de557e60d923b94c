#!/usr/bin/env python3
"""Set up the development environment and run robotd or its test suite.

    python3 dev.py run    # create .venv, install robotd, run the daemon on the simulated rover
    python3 dev.py test   # create .venv, install robotd[dev], run ruff, mypy, the unit check and pytest

Only the standard library is used here, so it works on a fresh machine with Python 3.11 and pip.
The virtual environment is re-installed when pyproject.toml changes.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import sys
import venv
from pathlib import Path

ROOT = Path(__file__).resolve().parent
VENV = ROOT / ".venv"
BIN = VENV / ("Scripts" if os.name == "nt" else "bin")
STAMP = VENV / ".robotd-installed"


def _run(*cmd: str | os.PathLike[str], check: bool = True) -> int:
    print("+", " ".join(str(c) for c in cmd), flush=True)
    return subprocess.run([str(c) for c in cmd], cwd=ROOT, check=check).returncode


def ensure_venv() -> None:
    want = hashlib.sha256((ROOT / "pyproject.toml").read_bytes()).hexdigest()
    if STAMP.exists() and STAMP.read_text().strip() == want:
        return
    if not (BIN / "python").exists():
        print(f"creating {VENV}", flush=True)
        venv.EnvBuilder(with_pip=True).create(VENV)
    _run(BIN / "python", "-m", "pip", "install", "-q", "--upgrade", "pip")
    _run(BIN / "python", "-m", "pip", "install", "-q", "-e", ".[dev]")
    STAMP.write_text(want)


def cmd_run(args: list[str]) -> int:
    ensure_venv()
    cmd = [str(BIN / "robotd"), "run", *args]
    print("+", " ".join(cmd), flush=True)
    proc = subprocess.Popen(cmd, cwd=ROOT)
    while True:
        try:
            return proc.wait()
        except KeyboardInterrupt:
            # Ctrl-C reaches robotd too; it shuts down gracefully (saving its map): wait for it
            continue


def cmd_test(args: list[str]) -> int:
    ensure_venv()
    _run(BIN / "ruff", "check", ".")
    _run(BIN / "ruff", "format", "--check", ".")
    _run(BIN / "mypy")
    analyze = shutil.which("systemd-analyze")
    if analyze:
        _run(sys.executable, "systemd/verify.py")
    else:
        print("systemd-analyze not found: skipping the unit-file check (apt-get install systemd)", flush=True)
    return _run(BIN / "python", "-m", "pytest", "-q", *args, check=False)


def main() -> int:
    if len(sys.argv) < 2 or sys.argv[1] not in ("run", "test"):
        print(__doc__)
        return 2
    try:
        return {"run": cmd_run, "test": cmd_test}[sys.argv[1]](sys.argv[2:])
    except subprocess.CalledProcessError as exc:
        return exc.returncode or 1


if __name__ == "__main__":
    sys.exit(main())
