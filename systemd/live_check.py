#!/usr/bin/env python3
"""Run robotd.service under a real systemd and check its lifecycle. For a throwaway VM or container.

A machine without systemd as PID 1 (a CI container) can still run the real manager: this script
boots ``/usr/bin/systemd`` as PID 1 of a new PID and mount namespace (needs root and
CAP_SYS_ADMIN), installs robotd as README.md's "Running under systemd" says (the ``robotd`` user,
``/opt/robotd/.venv``, ``/etc/robotd/robotd.toml`` with the embedded ``sim://`` default, the unit
file unchanged), then checks through ``systemctl``:

1. ``start`` returns once the daemon sent READY=1 (Type=notify), and the unit is running;
2. STATUS= carries the health line; the unit keeps running past several WatchdogSec periods;
3. ``stop`` (SIGTERM) ends with result ``success`` and exit status 0, and the map is saved under
   the StateDirectory;
4. with ``persistence.resume = true`` a restart resumes from the saved map;
5. a frozen process (SIGSTOP: no more WATCHDOG=1) is killed by the watchdog (result ``watchdog``,
   SIGABRT) and restarted by Restart=on-failure;
6. ``systemd-analyze security`` of the loaded unit.

It changes the machine (a system user, files in /opt, /etc and /var), so run it only where that
is fine. The manager is stopped at the end. Usage: sudo python3 systemd/live_check.py [--keep]
(``--keep`` leaves the manager running; its PID is printed for ``nsenter -t PID -m -p``).
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
PREFIX = Path("/opt/robotd")


def sh(*cmd: str, check: bool = True) -> str:
    proc = subprocess.run(list(cmd), capture_output=True, text=True)
    if check and proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({proc.returncode}): {proc.stderr.strip()[-500:]}")
    return proc.stdout


def install() -> None:
    if subprocess.run(["id", "robotd"], capture_output=True).returncode != 0:
        sh("useradd", "--system", "--groups", "dialout,plugdev", "robotd")
    python = shutil.which("python3.11", path="/usr/bin:/usr/local/bin") or "/usr/bin/python3"
    if not (PREFIX / ".venv" / "bin" / "robotd").exists():
        PREFIX.mkdir(parents=True, exist_ok=True)
        sh(python, "-m", "venv", str(PREFIX / ".venv"))
    # this checkout with its dependencies, then its own code afresh (not editable: the service
    # must not read the source tree)
    pip = str(PREFIX / ".venv" / "bin" / "pip")
    sh(pip, "install", "-q", str(REPO))
    sh(pip, "install", "-q", "--force-reinstall", "--no-deps", str(REPO))
    conf = Path("/etc/robotd/robotd.toml")
    conf.parent.mkdir(parents=True, exist_ok=True)
    shutil.copy(REPO / "config" / "robotd.toml", conf)
    shutil.copy(HERE / "robotd.service", "/etc/systemd/system/robotd.service")
    state = Path("/var/lib/robotd/map.robotd")
    if state.exists():
        state.unlink()


def boot() -> int:
    """Start systemd as PID 1 of new PID and mount namespaces; returns its PID outside."""
    env = {**os.environ, "container": "robotd-live-check"}
    unshare = ["unshare", "--pid", "--fork", "--mount", "--mount-proc", "--propagation", "private"]
    subprocess.Popen(
        [*unshare, "/usr/bin/systemd", "--system", "--unit=multi-user.target", "--log-target=journal"],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    t_end = time.monotonic() + 60
    while time.monotonic() < t_end:
        pids = sh("pgrep", "-f", "^/usr/bin/systemd --system --unit=multi-user.target", check=False).split()
        if pids:
            pid = int(pids[0])
            state = subprocess.run(
                ["nsenter", "-t", str(pid), "-m", "-p", "systemctl", "is-system-running"],
                capture_output=True,
                text=True,
            ).stdout.strip()
            if state in ("running", "degraded"):
                return pid
        time.sleep(0.5)
    raise SystemExit("systemd did not come up within 60 s")


def main(argv: list[str]) -> int:
    if os.geteuid() != 0:
        print("run as root (it installs a system user and a unit)", file=sys.stderr)
        return 1
    install()
    pid = boot()
    ns = ["nsenter", "-t", str(pid), "-m", "-p"]

    def ctl(*args: str, check: bool = True) -> str:
        return sh(*ns, "systemctl", *args, check=check)

    def show(*props: str) -> dict[str, str]:
        out = ctl("show", "robotd", *(f"-p{p}" for p in props))
        return dict(line.split("=", 1) for line in out.splitlines() if "=" in line)

    failures: list[str] = []

    def check(name: str, ok: bool, detail: str) -> None:
        print(f"{'PASS' if ok else 'FAIL'}  {name}: {detail}")
        if not ok:
            failures.append(name)

    try:
        ctl("daemon-reload")
        cold = not any(Path("/var/cache/robotd/numba").glob("**/*.nbi"))
        t0 = time.monotonic()
        ctl("start", "robotd")  # Type=notify: returns after READY=1
        s = show("ActiveState", "SubState", "StatusText")
        dt = time.monotonic() - t0
        check("start", s["SubState"] == "running", f"READY after {dt:.1f} s ({'cold' if cold else 'warm'} numba cache)")
        time.sleep(12)  # > 2 × WatchdogSec
        s = show("ActiveState", "NRestarts", "StatusText")
        check("running past the watchdog", s["ActiveState"] == "active" and s["NRestarts"] == "0", s["StatusText"])
        t0 = time.monotonic()
        ctl("stop", "robotd")
        s = show("Result", "ExecMainStatus")
        saved = Path("/var/lib/robotd/map.robotd").exists()
        ok = s["Result"] == "success" and s["ExecMainStatus"] == "0" and saved
        check(
            "stop",
            ok,
            f"{time.monotonic() - t0:.2f} s, result {s['Result']}, status {s['ExecMainStatus']}, map saved {saved}",
        )

        conf = Path("/etc/robotd/robotd.toml")
        conf.write_text(conf.read_text().replace("resume = false", "resume = true"))
        t0 = time.monotonic()
        ctl("start", "robotd")
        dt = time.monotonic() - t0
        time.sleep(3)
        log = sh(*ns, "journalctl", "-u", "robotd", "-n", "80", "--no-pager")
        check("restart with resume (warm cache)", "resumed from saved map" in log, f"READY after {dt:.1f} s")

        ctl("kill", "-s", "SIGSTOP", "robotd")
        time.sleep(20)  # WatchdogSec 5 s, the abort, RestartSec 2 s, a warm start
        s = show("ActiveState", "NRestarts")
        log = sh(*ns, "journalctl", "-n", "400", "--no-pager")
        ok = "Failed with result 'watchdog'" in log and s["ActiveState"] == "active" and int(s["NRestarts"]) >= 1
        check("frozen process", ok, f"watchdog kill and restart: NRestarts {s['NRestarts']}, {s['ActiveState']}")

        sec = sh(*ns, "systemd-analyze", "security", "robotd", "--no-pager", check=False).strip().splitlines()
        print(f"INFO  {sec[-1] if sec else 'systemd-analyze security: no output'}")
        ctl("stop", "robotd", check=False)
    finally:
        if "--keep" in argv:
            print(f"systemd left running: PID {pid} (nsenter -t {pid} -m -p systemctl ...)")
        else:
            os.kill(pid, signal.SIGRTMIN + 4)  # systemd: SIGRTMIN+4 = poweroff
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
