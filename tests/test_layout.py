"""The test tree mirrors the source tree, and the mirror never shadows the packages it tests.

tests/robotd/ is the ``tests.robotd`` package. If ``tests/`` were on ``sys.path`` ahead of the
repository root, ``import robotd`` would find it instead of the real robotd and the tests of robotd
would test nothing (checked: pytest's ``pythonpath = ["tests"]`` with ``--import-mode=importlib``
does exactly that; in the default prepend mode the conftest import happens to put the root first).
"""

from __future__ import annotations

import importlib
from pathlib import Path

from tests.support.paths import REPO

PACKAGES = ("robotd", "drivers", "calib", "systemd")
MIRRORED = (*PACKAGES, "bench")  # bench/ holds scripts, not a package: tests/bench/ tests them
TESTS = REPO / "tests"
# repository-wide tests that belong to no one module (test_dev.py mirrors dev.py at the root)
TOP_LEVEL_TESTS = {"test_layering.py", "test_layout.py", "test_dev.py", "test_docs.py", "test_module_map.py"}
NOT_MIRRORS = {"support", "fuzz", "__pycache__"}  # fuzz: property tests across packages (issue 15)


def test_the_packages_under_test_are_the_real_ones() -> None:
    for name in ("robotd", "drivers", "calib"):
        mod = importlib.import_module(name)
        path = Path(mod.__file__ or "").resolve()
        assert not path.is_relative_to(TESTS), f"`import {name}` found the test package {path}"
        assert path.parent.name == name, path


def test_every_test_directory_mirrors_a_source_directory() -> None:
    bad: list[str] = []
    for d in sorted(p for p in TESTS.rglob("*") if p.is_dir()):
        rel = d.relative_to(TESTS)
        if rel.parts[0] in NOT_MIRRORS or "__pycache__" in rel.parts:
            continue
        if rel.parts[0] not in MIRRORED or not (REPO / rel).is_dir():
            bad.append(f"tests/{rel.as_posix()}/ mirrors no source directory {rel.as_posix()}/")
        if not (d / "__init__.py").is_file():
            bad.append(f"tests/{rel.as_posix()}/ has no __init__.py (its modules would not be tests.*)")
    assert not bad, "\n".join(bad)


def test_only_repository_wide_tests_sit_at_the_top() -> None:
    top = {p.name for p in TESTS.glob("test_*.py")}
    assert top <= TOP_LEVEL_TESTS, f"move these into the mirrored tree: {sorted(top - TOP_LEVEL_TESTS)}"
