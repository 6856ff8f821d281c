"""What the pilot images say about each material: the variance a strategy removes on its pixels.

The quadrature (:mod:`.quadrature`) predicts each material's variance under each strategy
from a few thousand shading points; where a material's variance sits in a few of its
pixels (a sun's highlight on a small glossy ball) it can miss nearly all of it. The pilots
(:mod:`.pilots`) see every pixel. Their per-pixel variances, split by the material that
each pixel's centre sees first, measure a material's *difference* between the environment
strategy and a product strategy directly: the pilots of a round share their random
numbers, so what every strategy shares (antialiasing, textures, other paths) is the same
in both pilots at a pixel and cancels from the difference there.

That measured difference is weighed against the quadrature's (calibrated) one (:func:`refine`,
:func:`weighed_difference`): a prior that trusts the quadrature within :data:`MATERIAL_PRIOR_SD`
of the material's environment variance, or with probability :data:`MISSED_SHARE` within all
of it, and the measurement with its standard error over the material's pixels. On the
material studio (gold GGX 0.05 ball under the sun-and-sky map) the quadrature put the product
7e-5 *worse* than the environment strategy on the gold ball; its pilots measured it
1.6e-3 +- 0.6e-3 better, and rendering with the gold ball on the product had 0.74x the
variance at 1.02x the time (docs/MEASUREMENTS.md, "Each material's difference,
measured by the pilots").
"""

from __future__ import annotations

import dataclasses

import drjit as dr
import mitsuba as mi
import numpy as np

from .pilots import Pilots, pilot_pixels
from .quadrature import rough_hits
from .strategy import Strategy

MATERIAL_PRIOR_SD = 0.06
"""How far a material's (calibrated) quadrature difference between two strategies is
believed off, where the quadrature saw what matters on the material: this share of its
environment variance. With :data:`MISSED_SHARE`, the prior's maximum-likelihood fit to the
395 material differences that the pilots measured in the 65 plans of the realistic scenes
(``sh_direct``, ``sh_path``) and the sphere table (docs/MEASUREMENTS.md, "Each material's
difference, measured by the pilots"; ``scripts/bench_material_pilots.py``): where the pilots
measured closely (error under 5 % of the environment variance), the quadrature was off by
2.3 % of it at the median, 9.5 % at the 90th percentile."""

MISSED_SHARE = 0.03
"""The prior probability that the quadrature missed what matters on a material (a highlight
that a few pixels hold), its difference then off by up to the material's whole environment
variance (the larger of the quadrature's and the environment pilot's on its pixels). The
prior is the mixture of the two: a measurement within its noise of the quadrature's figure
moves it little, however loose; one far from it, by many of its errors, moves it to itself.
(A single normal prior a quarter of the environment variance wide let the pilots' noise on a
small film move plans: a GGX 0.05 sphere at 128 x 96 lost the product that measured 1.45x
there at equal time.)"""

NO_MATERIAL = 0xFFFFFFFF
"""Material of a pilot lane whose camera ray hits nothing."""

PILOTED = (Strategy.PRODUCT, Strategy.PRODUCT_ONLY)
"""The strategies whose pilots put every material that can run them on them."""


@dataclasses.dataclass(frozen=True)
class MaterialDifference:
    """What the pilots measured on one material's pixels for one strategy, in quadrature
    units (the film's mean, per unit variance of a camera sample)."""

    difference: float
    """The environment pilot's variance there less the strategy's pilot's."""
    error: float
    """Its standard error: the per-pixel differences' spread, over the pixels."""
    environment: float
    """The environment pilot's variance there (what every strategy shares included)."""
    quadrature: tuple
    """The material's quadrature row (strategy label, variance) it was measured against: a
    later plan with other figures for it (its BSDF changed) does not use the measurement."""


def quadrature_row(variances: dict) -> tuple:
    """A material's quadrature figures (strategy -> variance) as :class:`MaterialDifference`
    keeps them."""
    return tuple(sorted((s.label, float(v)) for s, v in variances.items()))


def lane_materials(scene: mi.Scene, sensor: mi.Sensor, lanes: int, dirac_bounces: int = 0) -> np.ndarray:
    """The registry id of the BSDF that a ray through the centre of each pilot lane's pixel
    (:func:`~.pilots.pilot_pixels`) hits first, or first behind up to ``dirac_bounces`` Dirac
    bounces, as the quadrature's frames (:func:`~.quadrature.rough_hits`); :data:`NO_MATERIAL`
    where it hits nothing."""
    size = sensor.film().crop_size()
    width = int(size[0])
    pixel = pilot_pixels(sensor, lanes)
    # As the pilots place their samples: relative to the crop window.
    position = (mi.Vector2f(mi.Float(pixel % width), mi.Float(pixel // width)) + 0.5) / mi.ScalarVector2f(size)
    si, bsdf, _ = rough_hits(scene, sensor, mi.Point2f(position), dirac_bounces)
    ids = dr.select(si.is_valid(), dr.reinterpret_array(mi.UInt32, bsdf), NO_MATERIAL)
    return np.broadcast_to(np.asarray(ids.numpy(), dtype=np.uint32), (lanes,))


def material_differences(pilots: Pilots, materials: np.ndarray, candidates: dict, quadrature: dict,
                         environment: str) -> dict:
    """Registry id -> strategy -> :class:`MaterialDifference`, for each material that a
    :data:`PILOTED` strategy's pilot ran on that strategy and some lane sees.
    ``materials``: :func:`lane_materials` of the pilots' lanes; ``environment``: the name of
    the pilot with every material on the environment strategy; ``quadrature``: the
    predictions' variance rows (registry id -> strategy -> variance)."""
    env_pixels = pilots.pixel_variance.get(environment)
    if env_pixels is None:
        return {}
    lanes = len(materials)
    scale = 1.0 / (lanes * pilots.film_factor)
    env = np.asarray(env_pixels.numpy(), dtype=np.float64)
    keys = sorted({int(k) for k in np.unique(materials)} - {NO_MATERIAL})
    index = np.searchsorted(keys, materials)
    seen = np.isin(materials, keys)
    bins = len(keys)

    def per_material(values):  # sums over each material's lanes (host, in a fixed order)
        return np.bincount(index[seen], weights=values[seen], minlength=bins)

    counts = per_material(np.ones(lanes))
    env_sums = per_material(env)
    out: dict = {}
    for strategy in PILOTED:
        candidate, pixels = candidates.get(strategy.label), pilots.pixel_variance.get(strategy.label)
        if candidate is None or pixels is None:
            continue
        d = env - np.asarray(pixels.numpy(), dtype=np.float64)
        sums, squares = per_material(d), per_material(d * d)
        for i, key in enumerate(keys):
            n = counts[i]
            if candidate.assignment.get(key) != strategy or n < 2 or key not in quadrature:
                continue
            spread = max(squares[i] - sums[i] * sums[i] / n, 0.0) / (n - 1)
            out.setdefault(key, {})[strategy] = MaterialDifference(
                float(sums[i] * scale), float(np.sqrt(n * spread) * scale), float(env_sums[i] * scale),
                quadrature_row(quadrature[key]))
    return out


def refine(variance: dict, shared: float, measured: dict, quadrature: dict) -> tuple[dict, float]:
    """``(variance, shared)`` with each measured material's differences weighed in.

    For material ``k`` and strategy ``s`` of ``measured``: the difference
    ``variance[k][environment] - variance[k][s]`` becomes its posterior mean given the pilots'
    measurement (:func:`weighed_difference`, about the quadrature's). Where that leaves a
    strategy below its own quadrature variance, the quadrature missed part of the environment
    strategy's variance on the material: the material's row is raised by the shortfall, and
    ``shared`` (the variance the environment pilot had beyond the quadrature, taken as shared by
    every strategy) lowered by it, no further than 0 (a strategy still below 0 is then set to
    0). Either way the film's variance under each assignment is the same, only the material's
    figures read as what they are. Measurements made against another quadrature row of the
    material (its parameters changed since) are left out. ``variance`` is not modified."""
    out = {k: dict(row) for k, row in variance.items()}
    for key, by_strategy in measured.items():
        if key not in out or key not in quadrature:
            continue
        row = quadrature_row(quadrature[key])
        base = out[key][Strategy.ENVIRONMENT]
        refined = {}
        for strategy, m in by_strategy.items():
            if m.quadrature != row or strategy not in out[key]:
                continue
            predicted = base - variance[key][strategy]
            close, missed = MATERIAL_PRIOR_SD * base, max(m.environment, base)
            if not (missed > 0 and np.isfinite(predicted)):
                continue
            difference = weighed_difference(predicted, close, missed, m.difference, m.error)
            refined[strategy] = base - difference
        if not refined:
            continue
        raise_by = max(0.0, max(variance[key][s] - v for s, v in refined.items()))
        raise_by = min(raise_by, shared)
        out[key] = {s: max(v + raise_by, 0.0) for s, v in {**out[key], **refined}.items()}
        shared -= raise_by
    return out, shared


def weighed_difference(predicted: float, close: float, missed: float, measured: float, error: float) -> float:
    """The posterior mean of a difference that the quadrature put at ``predicted`` and the
    pilots measured as ``measured`` +- ``error`` (normal), under the prior: normal about
    ``predicted``, ``close`` wide, or with probability :data:`MISSED_SHARE` ``missed`` wide.
    Each part's posterior (the inverse-variance mean of its prior and the measurement) weighed
    by how likely it makes the measurement."""
    if not error > 0:
        return measured
    means, weights = [], []
    for share, width in ((1.0 - MISSED_SHARE, close), (MISSED_SHARE, missed)):
        if not width > 0:
            continue
        spread = width * width + error * error
        weights.append(share * np.exp(-0.5 * (measured - predicted) ** 2 / spread) / np.sqrt(spread))
        means.append((predicted / width ** 2 + measured / error ** 2) / (1.0 / width ** 2 + 1.0 / error ** 2))
    total = sum(weights)
    if not total > 0:  # the measurement is far beyond both parts' reach: the wider part's
        return means[-1]
    return float(sum(w * x for w, x in zip(weights, means)) / total)
