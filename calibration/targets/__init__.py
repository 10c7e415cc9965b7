"""Passive calibration targets: board geometry (`board`) and corner detection in images
(`detect`), producing `phasecal.observations/1` views."""
