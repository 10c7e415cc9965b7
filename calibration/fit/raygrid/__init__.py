"""Raygrid fit: per-pixel rays and screen poses jointly (Sturm-Ramalingam)."""
