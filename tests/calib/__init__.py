"""Tests of ``calib``; this directory mirrors calib/."""
