"""Test-only support code (not part of the robotd package).

``reference_*.py`` hold the readable numpy/Python twins of robotd's numba kernels: each computes
what a kernel computes, written for reading rather than speed, and the tests hold the kernel to
it (bit for bit, or to a stated tolerance). They live here, not in the hot modules, because
nothing at runtime calls them. ``slam_world.py`` is the small inline landmark world of the SLAM
scenario tests; ``tolerances.py`` names the numerical tolerances the tests share.

Tests import them through the ``tests`` package, ``from tests.support.reference_frontend import ...``
(pytest puts the repository root on ``sys.path`` for the ``tests`` package). ``tests/`` itself must
not be on ``sys.path``: ``tests/robotd/`` would then shadow the real ``robotd`` package.
"""
