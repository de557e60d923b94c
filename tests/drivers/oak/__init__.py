"""Tests of ``drivers.oak``; this directory mirrors drivers/oak/."""
