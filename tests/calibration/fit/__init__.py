"""Tests of `calibration.fit`."""
