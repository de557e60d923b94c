"""Tests of the ``robotd.config`` package; this directory mirrors robotd/config/."""
