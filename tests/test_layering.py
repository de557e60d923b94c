"""The estimator core never imports I/O (design.md §1): walk the imports and enforce it."""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
CORE = [
    "robotd/geometry.py",
    "robotd/stereo.py",
    "robotd/msgs.py",
    "robotd/outliers.py",
    "robotd/_outlier_kernels.py",
    "robotd/jit.py",
    "robotd/frontend",
    "robotd/slam",
]
ALLOWED_THIRD_PARTY = {"numpy", "scipy", "cv2", "numba"}
ALLOWED_ROBOTD = (
    "robotd.msgs",
    "robotd.geometry",
    "robotd.errors",
    "robotd.stereo",
    "robotd.frontend",
    "robotd.slam",
    "robotd.outliers",
    "robotd._outlier_kernels",
    "robotd.jit",
)
STDLIB_OK = {
    "__future__",
    "dataclasses",
    "typing",
    "math",
    "logging",
    "time",
    "collections",
    "functools",
    "itertools",
    "enum",
    "abc",
    "warnings",
    "os",
    "collections.abc",
    "concurrent",  # compute parallelism (both images detected at once), not I/O
}
# the I/O libraries that must stay in drivers/ and the daemon
FORBIDDEN = {"zenoh", "serial", "pymavlink", "depthai", "socket", "mcap", "threading", "subprocess", "matplotlib"}


def _core_files() -> list[Path]:
    files: list[Path] = []
    for c in CORE:
        p = REPO / c
        files += sorted(p.rglob("*.py")) if p.is_dir() else ([p] if p.exists() else [])
    return files


def _imports(path: Path) -> list[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"))
    names: list[str] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.append(node.module)
    return names


def test_core_imports_only_numeric_libraries() -> None:
    files = _core_files()
    assert files, "no core files found"
    bad: list[str] = []
    for f in files:
        for name in _imports(f):
            top = name.split(".")[0]
            if top in FORBIDDEN:
                bad.append(f"{f.relative_to(REPO)} imports {name}")
            elif top == "robotd" and not name.startswith(ALLOWED_ROBOTD):
                bad.append(f"{f.relative_to(REPO)} imports {name}")
            elif top not in ALLOWED_THIRD_PARTY and top != "robotd" and top not in STDLIB_OK:
                bad.append(f"{f.relative_to(REPO)} imports {name}")
    assert not bad, "core modules import I/O or unexpected libraries:\n" + "\n".join(bad)


def test_each_hardware_library_has_one_importer() -> None:
    owners = {"depthai": "drivers/oak", "serial": "drivers/serial_link.py", "pymavlink": "drivers/mavlink_link.py"}
    bad: list[str] = []
    for f in sorted(REPO.glob("**/*.py")):
        rel = f.relative_to(REPO).as_posix()
        if rel.startswith((".venv", "tests/", "bench/", "build/")):
            continue
        for name in _imports(f):
            top = name.split(".")[0]
            if top in owners and not rel.startswith(owners[top]):
                bad.append(f"{rel} imports {name} (only {owners[top]} may)")
    assert not bad, "\n".join(bad)
