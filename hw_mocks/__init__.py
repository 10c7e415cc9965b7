"""Simulated rig with exact ground truth: display, camera, optics, timing and faults."""
