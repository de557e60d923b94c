"""The replay-many run the engine tests share: at least 20 sources and a damaged recording,
replayed once on the local engine (two workers), through the command itself."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from tests.support.batch_sources import fleet_sources


class LocalRun:
    def __init__(self, root: Path) -> None:
        self.root = root
        self.sources, self.damaged = fleet_sources(root)
        self.out = root / "local"
        self.argv = ["replay-many", *self.sources, self.damaged, "--out", str(self.out), "--workers", "2", "--quiet"]
        self.code, self.doc = run_cli([*self.argv, "--json"])


def run_cli(argv: list[str]) -> tuple[int, dict[str, Any]]:
    """``robotd ARGV`` in this process (its workers are processes of their own); (exit status, the JSON
    document printed on stdout)."""
    import contextlib
    import io

    from robotd.tools.cli import main

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        code = main(argv)
    return code, json.loads(buf.getvalue().strip().splitlines()[-1])


@pytest.fixture(scope="session")
def local_run(tmp_path_factory: pytest.TempPathFactory) -> LocalRun:
    return LocalRun(tmp_path_factory.mktemp("replay-many"))
