"""Where the repository is, for tests that read its files (config/, bench/) or run from its root.

Defined once here rather than as ``Path(__file__).parents[n]`` in each test, whose ``n`` depends on
how deep the test sits in the mirrored tree.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

REPO = Path(__file__).resolve().parents[2]


def load_bench(name: str) -> ModuleType:
    """The script ``bench/<name>.py`` imported as a module (bench/ holds scripts, not a package),
    registered as ``bench_<name>`` so that its dataclasses and pickles resolve."""
    spec = importlib.util.spec_from_file_location(f"bench_{name}", REPO / "bench" / f"{name}.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod
