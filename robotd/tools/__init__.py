"""The tools layer (docs/architecture.md "Module map"): the ``robotd`` command (cli.py; its
``python -m robotd`` is robotd/__main__.py) and what its commands run: ``robotd doctor``, replay,
``robotd echo``, ``robotd fleet`` and ``robotd router``, ``robotd replay-many`` (batch/), the
journal's priorities and the progress bars. The calibration tool, ``robotd-calib``, is the
top-level calib package, in this layer too.
"""
