"""sGCC (spline generic central / non-central camera) fit: LM core, start values, mesh choice."""
