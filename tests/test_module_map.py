"""docs/architecture.md "Module map" names every module under robotd/ and drivers/.

A module counts as named when the page holds its repository path (``robotd/pipeline/step.py``), or
when one entry of the page (a table row, a list item or a paragraph) holds both its package's
path (``robotd/outputs/``, ``drivers/oak/``; ``robotd/`` for the top-level modules) and its file
name in backticks (`` `runner.py` ``). A package's ``__init__.py`` and its private ``_*.py``
modules are covered by an entry that names the package's path, as the page says.
"""

from __future__ import annotations

import re

from tests.support.paths import REPO

DOC = REPO / "docs" / "architecture.md"
ROOTS = ("robotd", "drivers")


def entries(text: str) -> list[str]:
    """The page cut into entries: a table row, a list item (with its continuation lines) or a
    paragraph each."""
    out: list[str] = []
    cur: list[str] = []
    for line in text.splitlines():
        starts = not line.strip() or line.lstrip().startswith(("|", "- ")) or re.match(r"\s*\d+\. ", line)
        if starts and cur:
            out.append("\n".join(cur))
            cur = []
        if line.strip():
            cur.append(line)
    if cur:
        out.append("\n".join(cur))
    return out


def unnamed(text: str, modules: list[str]) -> list[str]:
    """The modules (repository paths) the page ``text`` does not name, by the rule above."""
    parts = entries(text)
    missing: list[str] = []
    for rel in modules:
        pkg, _, name = rel.rpartition("/")
        pkg += "/"
        if rel in text:
            continue
        if name == "__init__.py" or name.startswith("_"):
            if any(pkg in e for e in parts):
                continue
        elif any(pkg in e and f"`{name}`" in e for e in parts):
            continue
        missing.append(rel)
    return missing


def python_modules() -> list[str]:
    files = [p for root in ROOTS for p in sorted((REPO / root).rglob("*.py"))]
    return [p.relative_to(REPO).as_posix() for p in files if "__pycache__" not in p.parts]


def test_every_module_is_in_the_module_map() -> None:
    modules = python_modules()
    assert "robotd/pipeline/step.py" in modules and "drivers/sim.py" in modules
    missing = unnamed(DOC.read_text(encoding="utf-8"), modules)
    assert not missing, f"{DOC.relative_to(REPO)} does not name: {missing}"


def test_the_rule_catches_what_it_is_for() -> None:
    page = "| core | `robotd/core/geometry.py`, `robotd/slam/` (`ekf.py`) |\n\n- `drivers/`: `sim.py`\n"
    assert (
        unnamed(page, ["robotd/core/geometry.py", "robotd/slam/ekf.py", "robotd/slam/_book.py", "drivers/sim.py"]) == []
    )
    assert unnamed(page, ["robotd/slam/fastslam.py"]) == ["robotd/slam/fastslam.py"]
    # a file name next to another package's path does not count
    assert unnamed(page, ["drivers/ekf.py"]) == ["drivers/ekf.py"]
    assert unnamed(page, ["robotd/outputs/__init__.py"]) == ["robotd/outputs/__init__.py"]


def test_the_page_states_the_rule() -> None:
    assert re.search(r"`_\*\.py`", DOC.read_text(encoding="utf-8")), "the page no longer states the rule for `_*.py`"
