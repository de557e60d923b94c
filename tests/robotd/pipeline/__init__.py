"""Tests of the ``robotd.pipeline`` package; this directory mirrors robotd/pipeline/."""
