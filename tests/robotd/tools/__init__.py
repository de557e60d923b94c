"""Tests of the ``robotd.tools`` package; this directory mirrors robotd/tools/."""
