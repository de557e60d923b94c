"""Tests of ``robotd.frontend``; this directory mirrors robotd/frontend/."""
