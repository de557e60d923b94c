"""Tests of ``robotd.research``; this directory mirrors robotd/research/."""
