"""Tests of the ``robotd.core`` package; this directory mirrors robotd/core/."""
