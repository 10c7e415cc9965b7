"""Tests of `calibration.worker`."""
