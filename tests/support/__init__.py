"""Test-only support code (not part of the robotd package).

``reference_*.py`` hold the readable numpy/Python twins of robotd's numba kernels: each computes
what a kernel computes, written for reading rather than speed, and the tests hold the kernel to
it (bit for bit, or to a stated tolerance). They live here, not in the hot modules, because
nothing at runtime calls them. pyproject.toml puts ``tests/`` on the path, so tests import them as
``from support.reference_frontend import ...``.
"""
