"""Spherical-harmonics mathematics (real SH, z-up, Condon-Shortley phase)."""
