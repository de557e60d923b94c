"""Tests of ``robotd``; this directory mirrors robotd/."""
