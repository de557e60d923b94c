"""Tests of ``robotd.slam``; this directory mirrors robotd/slam/."""
