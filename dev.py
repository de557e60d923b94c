#!/usr/bin/env python3
"""Set up the development environment and run robotd or its test suite.

    python3 dev.py run    # create .venv, install robotd, run the daemon on the simulated rover
    python3 dev.py test   # create .venv, install robotd[dev], run ruff, mypy, the unit check and pytest

``test`` runs pytest in two worker processes (pytest-xdist) where the machine has two CPUs or
more: most of the suite's time is spent waiting on sockets, subprocesses and simulated worlds, so
two workers take the suite from about 12 to about 7 minutes on a 2-core machine. Arguments after
``test`` go to pytest; ``-n 0`` runs it in one process, ``-n N`` chooses the workers.

Only the standard library is used here, so it works on a fresh machine with Python 3.11 and pip.
``run`` installs what running needs; ``test`` adds the dev tools. The virtual environment is
re-installed when pyproject.toml changes, and pip shows its progress (the first install takes
about a minute).

``dev.py run`` passes SIGINT and SIGTERM on to robotd and waits for it: a Ctrl-C in a terminal, a
service manager, an IDE or ``timeout`` signalling this process alone all stop robotd cleanly (it
saves its map), and this process exits with robotd's status.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import signal
import subprocess
import sys
import venv
from pathlib import Path
from types import FrameType

ROOT = Path(__file__).resolve().parent
VENV = ROOT / ".venv"
BIN = VENV / ("Scripts" if os.name == "nt" else "bin")
STAMP = VENV / ".robotd-installed"


def _run(*cmd: str | os.PathLike[str], check: bool = True) -> int:
    print("+", " ".join(str(c) for c in cmd), flush=True)
    return subprocess.run([str(c) for c in cmd], cwd=ROOT, check=check).returncode


def ensure_venv(extras: str = "") -> None:
    """Install robotd (with ``extras``, e.g. "dev") unless this pyproject.toml with these extras
    is installed already; a venv that has "dev" also serves ``run``."""
    digest = hashlib.sha256((ROOT / "pyproject.toml").read_bytes()).hexdigest()
    have = STAMP.read_text().split() if STAMP.exists() else []
    if have and have[0] == digest and (not extras or extras in have[1:]):
        return
    if not (BIN / "python").exists():
        print(f"creating {VENV}", flush=True)
        venv.EnvBuilder(with_pip=True).create(VENV)
    print("installing robotd and its dependencies (first time: about a minute)", flush=True)
    _run(BIN / "python", "-m", "pip", "install", "--upgrade", "pip")
    _run(BIN / "python", "-m", "pip", "install", "-e", f".[{extras}]" if extras else ".")
    STAMP.write_text(" ".join([digest, *([extras] if extras else [])]))


def cmd_run(args: list[str]) -> int:
    ensure_venv()
    cmd = [str(BIN / "robotd"), "run", *args]
    print("+", " ".join(cmd), flush=True)
    proc = subprocess.Popen(cmd, cwd=ROOT)

    def forward(signum: int, _frame: FrameType | None) -> None:
        # robotd shuts down gracefully on either signal (saving its map); a terminal's Ctrl-C may
        # already have reached it through the process group, and a second one changes nothing
        if proc.poll() is None:
            proc.send_signal(signum)

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, forward)
    return proc.wait()


def cmd_test(args: list[str]) -> int:
    ensure_venv("dev")
    _run(BIN / "ruff", "check", ".")
    _run(BIN / "ruff", "format", "--check", ".")
    _run(BIN / "mypy")
    analyze = shutil.which("systemd-analyze")
    if analyze:
        _run(sys.executable, "systemd/verify.py")
    else:
        print("systemd-analyze not found: skipping the unit-file check (apt-get install systemd)", flush=True)
    return _run(BIN / "python", "-m", "pytest", "-q", *_workers(args), *args, check=False)


def _workers(args: list[str]) -> list[str]:
    """pytest-xdist's options for ``args``: two workers unless the caller chose (``-n``,
    ``--numprocesses``, ``-p no:xdist``) or the process may use a single CPU. Two, not one per
    CPU: the suite's concurrent tests (loopback ports, SITL, Ray) are checked at two."""
    chosen = any(a.startswith(("-n", "--numprocesses", "no:xdist")) for a in args)
    try:
        cpus = len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        cpus = os.cpu_count() or 1
    return [] if chosen or cpus < 2 else ["-n", "2"]


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
