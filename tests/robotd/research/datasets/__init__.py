"""Tests of ``robotd.research.datasets``; this directory mirrors robotd/research/datasets/."""
