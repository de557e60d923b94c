"""Tests of the ``robotd.formats`` package; this directory mirrors robotd/formats/."""
