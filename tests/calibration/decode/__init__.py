"""Tests of `calibration.decode`."""
