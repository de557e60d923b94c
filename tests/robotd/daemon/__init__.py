"""Tests of ``robotd.daemon``; this directory mirrors robotd/daemon/."""
