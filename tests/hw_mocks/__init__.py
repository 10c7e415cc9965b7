"""Tests of `hw_mocks`."""
