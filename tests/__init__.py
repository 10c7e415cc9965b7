"""phasecal tests, laid out like the source tree (one folder per package)."""
