"""Progress bars a person can read, for work that takes more than a few seconds (replay,
experiments, benchmarks): tqdm on stderr with n/total and ETA, drawn only when stderr is a terminal,
so logs, CI and ``> file.json`` runs get nothing but their own output."""

from __future__ import annotations

import sys
from typing import Any


def progress_bar(
    total: int | None, unit: str, desc: str, enabled: bool = True, leave: bool = True, mininterval: float = 0.2
) -> Any:
    """A tqdm bar over ``total`` units (None: unknown), off when not ``enabled`` or stderr is no
    terminal. ``leave=False`` clears it at the end, so a table printed after it stays clean."""
    from tqdm import tqdm

    return tqdm(
        total=total,
        unit=unit,
        desc=desc,
        file=sys.stderr,
        disable=not (enabled and sys.stderr.isatty()),
        leave=leave,
        dynamic_ncols=True,
        mininterval=mininterval,
    )
