"""Under journald every line robotd writes carries its syslog priority, so ``journalctl -p err``
filters (robotd.tools.journal): log lines with their continuation lines, the CLI's error line, argparse's
errors, warnings, tracebacks and what native libraries print. "Under journald" is systemd's own
test: $JOURNAL_STREAM names the device and inode of the stream, and stderr must still be it."""

from __future__ import annotations

import logging
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.support.paths import REPO

SCRIPT = """
import logging
from robotd.tools.cli import configure_logging
configure_logging("DEBUG")
log = logging.getLogger("robotd.test")
log.debug("d"); log.info("i"); log.warning("w"); log.error("e\\nsecond line")
"""


def _run(argv: list[str], journal: bool | str = True, timeout: float = 120.0) -> tuple[int, list[str]]:
    """Run ``python argv`` with stdout and stderr on one pipe, as systemd connects a service to its
    journal stream, with $JOURNAL_STREAM naming that pipe (``journal`` True), another stream
    ("elsewhere"), or unset (False). Returns the exit status and the lines written."""
    env = {k: v for k, v in os.environ.items() if k != "JOURNAL_STREAM"}
    env["PYTHONPATH"] = str(REPO)
    r, w = os.pipe()
    try:
        st = os.fstat(w)
        if journal is True:
            env["JOURNAL_STREAM"] = f"{st.st_dev}:{st.st_ino}"
        elif journal == "elsewhere":  # the journal is another stream than this pipe
            env["JOURNAL_STREAM"] = f"{st.st_dev}:{st.st_ino + 1}"
        proc = subprocess.Popen([sys.executable, *argv], stdout=w, stderr=w, env=env, cwd=REPO)
    finally:
        os.close(w)
    out = b""
    with os.fdopen(r, "rb") as fh:  # to the end: robotd's and its relay's copies of the pipe closed
        out = fh.read()
    return proc.wait(timeout=timeout), out.decode().splitlines()


@pytest.mark.parametrize("journal", [True, "elsewhere", False], ids=["journald", "redirected", "terminal"])
def test_priorities_under_journald_timestamps_elsewhere(journal: bool | str) -> None:
    code, lines = _run(["-c", SCRIPT], journal)
    assert code == 0 and len(lines) == 5, lines
    if journal is True:
        assert [x[:3] for x in lines] == ["<7>", "<6>", "<4>", "<3>", "<3>"]
        assert lines[3:] == ["<3>ERROR robotd.test: e", "<3>second line"], "each continuation line too"
    else:  # $JOURNAL_STREAM inherited, but stderr is another stream now (systemd.exec(5)), or unset
        assert all(x[2] == ":" and not x.startswith("<") for x in lines[:4])  # HH:MM:SS.mmm first
        assert lines[3].endswith("ERROR robotd.test: e") and lines[4] == "second line"


def test_the_priority_table_covers_every_level() -> None:
    from robotd.tools.cli import SYSLOG_PRIORITY

    assert sorted(SYSLOG_PRIORITY) == [logging.DEBUG, logging.INFO, logging.WARNING, logging.ERROR, logging.CRITICAL]


def test_a_bad_config_and_a_bad_argument_are_errors_in_the_journal(tmp_path: Path) -> None:
    """Issue 27, item 4: `robotd: error: …` and argparse's lines carried no priority, so
    `journalctl -p err -u robotd` (the README's advice) did not show a config error."""
    bad = tmp_path / "bad.toml"
    bad.write_text("[slam]\nn_particles = 0\n")
    code, lines = _run(["-m", "robotd", "run", "--config", str(bad)])
    assert code == 2 and lines == [f"<3>robotd: error: slam.n_particles: expected an integer >= 1, got 0 (in {bad})"]
    # a bad argument: argparse's usage and its error line, both errors
    code, lines = _run(["-m", "robotd", "run", "--duration", "soon"])
    assert code == 2 and len(lines) >= 2, lines
    assert all(x.startswith("<3>") for x in lines), lines
    assert lines[0].startswith("<3>usage: robotd run") and "--duration: expected seconds" in lines[-1]
    code, lines = _run(["-m", "robotd", "--bogus"])
    assert code == 2 and lines and all(x.startswith("<3>") for x in lines), lines
    # not under journald: the same lines, plain
    code, lines = _run(["-m", "robotd", "run", "--config", str(bad)], journal=False)
    assert code == 2 and lines == [f"robotd: error: slam.n_particles: expected an integer >= 1, got 0 (in {bad})"]


JOURNAL_SCRIPT = r"""
import logging, os, sys, threading, warnings
from robotd.tools import journal
assert journal.install()
from robotd.tools.cli import configure_logging
configure_logging("INFO")
try:
    1 / 0
except ZeroDivisionError:
    logging.getLogger("robotd.t").exception("a failure")
warnings.warn("a library's warning")
import cv2
cv2.imread("/nonexistent/robotd-test.png")  # OpenCV's own [ WARN:…] line on fd 2
os.write(2, b"[2024-01-01 00:00:00.000] [depthai] [error] a native error\nan untagged native line\n")
print("a line on stdout")
t = threading.Thread(target=lambda: 1 / 0)
t.start()
t.join()  # else its traceback and the main thread's are written at once, and may share a line
raise RuntimeError("the end\nof the process")
"""


def test_warnings_tracebacks_threads_and_native_lines_each_carry_a_priority() -> None:
    code, lines = _run(["-c", JOURNAL_SCRIPT])
    assert code == 1
    assert lines and all(x[:1] == "<" and x[1] in "01234567" and x[2] == ">" for x in lines), lines
    prio = {x[3:]: int(x[1]) for x in lines}
    assert prio["ERROR robotd.t: a failure"] == 3 and prio["ZeroDivisionError: division by zero"] == 3
    assert prio["Traceback (most recent call last):"] == 3
    assert next(p for t, p in prio.items() if "UserWarning: a library's warning" in t) == 4
    assert next(p for t, p in prio.items() if "WARN:" in t and "robotd-test.png" in t) == 4  # OpenCV
    assert prio["[2024-01-01 00:00:00.000] [depthai] [error] a native error"] == 3
    assert prio["an untagged native line"] == 4
    assert prio["a line on stdout"] == 6
    assert next(p for t, p in prio.items() if t.startswith("Exception in thread")) == 3
    assert prio["RuntimeError: the end"] == 3 and prio["of the process"] == 3


def test_native_priorities_from_level_tags() -> None:
    from robotd.tools.journal import native_priority

    assert native_priority(b"[14442C10D13EABCE00] [1.1] [2.345] [system] [critical] temperature", 4) == 2
    assert native_priority(b"[ERROR:0@1.000] global foo.cpp:1 bar", 4) == 3
    assert native_priority(b"2025-01-01T00:00:00.000000Z  WARN zenoh::net: link lost", 6) == 4
    assert native_priority(b"2025-01-01T00:00:00.000000Z  INFO zenoh: started", 4) == 6
    assert native_priority(b"libusb: error [op_open] something", 4) == 3
    assert native_priority(b"Dropping client 127.0.0.1:1: handshake failed", 6) == 6
