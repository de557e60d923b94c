"""Where the repository is, for tests that read its files (config/, bench/) or run from its root.

Defined once here rather than as ``Path(__file__).parents[n]`` in each test, whose ``n`` depends on
how deep the test sits in the mirrored tree.
"""

from __future__ import annotations

from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
