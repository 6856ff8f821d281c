"""Environment maps on the equal-area (z, phi) grid: :class:`EnvPyramid`."""

from .pyramid import DEFAULT_MAX_DEPTH, LEVEL_TOLERANCE, EnvmapError, EnvPyramid, auto_depth

__all__ = ["DEFAULT_MAX_DEPTH", "LEVEL_TOLERANCE", "EnvmapError", "EnvPyramid", "auto_depth"]
