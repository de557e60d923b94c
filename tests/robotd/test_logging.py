"""Logging under journald: each line carries its syslog priority, so ``journalctl -p err`` filters."""

from __future__ import annotations

import logging
import subprocess
import sys

import pytest

from tests.support.paths import REPO

SCRIPT = """
import logging
from robotd.cli import configure_logging
configure_logging("DEBUG")
log = logging.getLogger("robotd.test")
log.debug("d"); log.info("i"); log.warning("w"); log.error("e")
"""


def _lines(env: dict[str, str]) -> list[str]:
    out = subprocess.run(
        [sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=60, env=env, cwd=REPO, check=True
    )
    return out.stderr.strip().splitlines()


@pytest.mark.parametrize("journal", [True, False], ids=["journald", "terminal"])
def test_priorities_under_journald_timestamps_on_a_terminal(journal: bool, monkeypatch: pytest.MonkeyPatch) -> None:
    import os

    env = {k: v for k, v in os.environ.items() if k != "JOURNAL_STREAM"}
    if journal:
        env["JOURNAL_STREAM"] = "8:12345"
    lines = _lines(env)
    assert len(lines) == 4
    if journal:
        assert [x[:3] for x in lines] == ["<7>", "<6>", "<4>", "<3>"]
        assert lines[3] == "<3>ERROR robotd.test: e"
    else:
        assert all(x[2] == ":" and not x.startswith("<") for x in lines)  # HH:MM:SS.mmm first
        assert lines[3].endswith("ERROR robotd.test: e")


def test_the_priority_table_covers_every_level() -> None:
    from robotd.cli import SYSLOG_PRIORITY

    assert sorted(SYSLOG_PRIORITY) == [logging.DEBUG, logging.INFO, logging.WARNING, logging.ERROR, logging.CRITICAL]
