"""Hierarchical sample warps over the equal-area (z, phi) cylinder."""
