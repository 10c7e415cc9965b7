"""Tests of `api.worker`."""
