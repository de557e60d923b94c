"""Tests of ``robotd.outputs``; this directory mirrors robotd/outputs/."""
