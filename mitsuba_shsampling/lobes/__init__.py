"""BSDF lobes in spherical harmonics, per shading point.

:class:`SceneLobes` fits a two-lobe zonal proxy (clamped cosine about the normal
plus a Phong lobe about the mirror direction) to every BSDF of a scene, from the
BSDF's own ``eval``, and evaluates its SH coefficients per lane in the
environment's grid frame, for product sampling (SH lobe x environment).
"""

from .fit import LobeQuadrature, TwoLobeFit, fit_two_lobe, mirror_quadrature, tabulate_lobe
from .scene_lobes import SceneLobes, bands_for_exponent, lobe_support, max_exponent_for_bands

__all__ = ["SceneLobes", "LobeQuadrature", "TwoLobeFit", "fit_two_lobe", "mirror_quadrature",
           "tabulate_lobe",
           "bands_for_exponent", "lobe_support", "max_exponent_for_bands"]
