"""How closely a sampler follows its exact target: figures for tests and benchmarks.

Kept apart from the warps (which only sample and evaluate densities): these
functions tabulate the exact target in float64 on the host and compare.
"""

from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np

from .grid import grid_direction
from .sh.basis import sh_eval_sum
from .warp.product import ProductWarp


def product_fidelity(warp: ProductWarp, coeffs: list) -> dict:
    """How closely ``warp`` follows the exact normalised product, for one lobe.

    The reference is max(f_SH, 0) x L on the warp's leaf grid
    (2^depth x 2^depth equal-area cells), in float64: the lobe is evaluated
    at each leaf centre and multiplied by the pyramid's exact luminance
    integral over the leaf, then normalised. The warp's pdf is constant on a
    leaf, so its leaf probabilities are pdf(centre) x leaf area.

    Parameter ``coeffs``: n^2 Python floats (one lobe, grid frame).

    Returns a dict of float64 figures (P_e: exact leaf probability, P_s: the
    warp's):

    * ``mean_relative_error``: sum over P_e > 0 of P_e |P_s / P_e - 1|, the
      mean relative pdf error weighted by the product (0 = exact);
    * ``relative_variance``: sum over P_s > 0 of P_e^2 / P_s, minus
      (1 - missed_mass)^2: the variance of the one-sample estimate of the
      product's integral divided by its square (0 for a perfect sampler);
    * ``missed_mass``: sum of P_e over leaves the warp never samples;
    * ``wasted_mass``: sum of P_s over leaves where the product is 0;
    * ``probability_sum``: sum of P_s (1 unless the product has no mass);
    * ``tail_mass``: sum of P_e where the lobe is below 5 % of its peak.
      Truncated SH lobes ring; where a lobe faces a dark region most of the
      exact product can sit in such tails (clamped cell integrals hide them
      from the warp), which inflates the other figures without concerning
      the lobe's main part.
    """
    cells = 1 << warp.depth
    centres = (np.arange(cells) + 0.5) / cells
    z = np.repeat(-1.0 + 2.0 * centres, cells)   # row iz, column iphi
    phi = np.tile(2.0 * math.pi * centres, cells)
    env = warp.pyramid.level_numpy(warp.depth).astype(np.float64).ravel()

    float64 = dr.float64_array_t(mi.Float)
    z64, phi64 = float64(z), float64(phi)
    lobe = sh_eval_sum([float(c) for c in coeffs], grid_direction(z64, phi64)).numpy()
    exact = np.maximum(lobe, 0.0) * env
    total = exact.sum()
    if not total > 0:
        raise ValueError("product_fidelity: the product of this lobe and map has no mass")
    exact /= total

    world = warp.pyramid.world_from_grid(grid_direction(mi.Float(z), mi.Float(phi)))
    opaque = [dr.opaque(mi.Float, float(c)) for c in coeffs]
    sampled = warp.pdf(opaque, world).numpy().astype(np.float64) * (4.0 * math.pi / cells**2)

    on = exact > 0
    reached = sampled > 0
    missed = float(exact[on & ~reached].sum())
    return {
        "mean_relative_error": float(np.abs(sampled[on] - exact[on]).sum()),
        "relative_variance": float((exact[reached] ** 2 / sampled[reached]).sum() - (1.0 - missed) ** 2),
        "missed_mass": missed,
        "wasted_mass": float(sampled[~on].sum()),
        "probability_sum": float(sampled.sum()),
        "tail_mass": float(exact[lobe < 0.05 * lobe.max()].sum()),
    }
