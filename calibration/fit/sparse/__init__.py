"""Fits in pixel space on sparse target observations (boards, surveyed points): projection
with analytic Jacobians, the weighted robust fit, its uncertainty and cross-validation."""
