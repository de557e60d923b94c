"""Tests of ``drivers``; this directory mirrors drivers/."""
