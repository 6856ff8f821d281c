"""What each environment strategy costs a pass: the cost model of the plan.

The plan (:mod:`.chooser`) weighs each strategy's variance against the time it adds
to a pass. By default that time comes from a :class:`CostModel`, not from a clock:
the same scene, options and machine then give the same plan in every process (as
FFTW plans by its estimate unless asked to measure). The model is, in order of
preference:

- the machine's own calibration (:func:`calibrate`, ``python -m mitsuba_shsampling
  calibrate``): timed pilot passes of the built-in material studio, made once per
  machine, variant and package code, and kept in the user's cache folder
  (:func:`calibration_path`);
- else :data:`SHIPPED`, measured the same way on the development machine (an AMD
  EPYC with 2 cores, AVX2, ``llvm_ad_rgb``).

``plan`` ``measure`` times the pilots in the user's scene instead
(:meth:`CostModel.from_pass_times`), as the chooser always did before.

Units: every figure is a share of the *lean* pass, the kernel without product code
(every material on one of Mitsuba's own strategies, at Mitsuba's cost), for the same
film and sample count. A strategy's figure is the time it adds to a pass per unit of
the film's camera samples that hit its material: a material covering a fifth of the
film on a strategy of cost 0.5 makes a pass 10 % longer. Where rays are dearer (a
large mesh, deep paths) the same walk costs a smaller share, so the figures of
``sh_direct`` and of the path integrators are calibrated apart.
"""

from __future__ import annotations

import dataclasses
import json
import os

import mitsuba as mi

from ..build_cache import cache_folder, code_digest
from .strategy import CARRYING_MITSUBA_STRATEGIES, Strategy

CALIBRATION_FILE = "costs-{variant}.json"
"""Name of the calibration file in the cache folder (per variant)."""


@dataclasses.dataclass(frozen=True)
class CostModel:
    """Time each strategy adds to a pass, in lean passes (module docstring)."""

    product_code: float
    """Every pass whose kernel holds the product's code, whatever its lanes run (the
    product's registers and branches slow the lanes that skip it)."""
    environment_only: float
    """Per unit film share on ``environment_only`` (a second map sample and shadow ray
    instead of the BSDF sample's occlusion query)."""
    product_walk: float
    """Per unit film share on ``product``, a lobe walked in SH."""
    product_table: float
    """Per unit film share on ``product``, a clamped cosine read from the cosine tables."""
    product_only_walk: float
    """Per unit film share on ``product_only``, SH walk."""
    product_only_table: float
    """Per unit film share on ``product_only``, cosine tables."""
    product_only_shared_walk: float = 0.70
    """Per unit film share on ``product_only``, SH walk, with the BSDF's share
    (``bsdf_defensive_share``): not timed by the pilots (their ``product_only`` runs each
    material as the plan weighs it), so the shipped figure."""
    bsdf_only: float = 0.0
    """Per unit film share on ``bsdf_only`` (in each slot a BSDF sample, a shadow ray and the
    map's value, where the environment strategy's BSDF sample traces a whole intersection).
    Less than the environment strategy's own cost on the calibration scene: -0.03 to -0.15
    lean passes (median -0.07) in five calibrations on a 2-core Xeon, AVX-512 (2026-12-07),
    against +0.06 to +0.14 for ``environment_only``; 0, as every figure is kept at 0 or more
    (:meth:`from_pass_times`). ``sh_path`` does not offer it."""
    emitter_sample: float = 0.15
    """Per unit film share of smooth lanes, ``sh_direct``'s sample of the other emitters
    beside the environment's (``emitter_selection`` ``each`` against ``one``: a BSDF
    evaluation and a shadow ray). Not timed by the calibration, whose studio has no other
    emitters: the shipped figure, from ``scripts/bench_lights.py`` on the studio at 480 px, where
    every camera ray hits a smooth BSDF (``each``'s pass over ``one``'s, less 1: 0.138 with a sun,
    0.152 with two area lights; ``docs/bench_lights_studio_480px.json``). On the cheaper rays of
    the preview scene it was 0.43 with a sun and -0.07 with two area lights
    (``docs/bench_lights_preview_320px.json``): where that matters, ``plan`` ``measure`` times
    the two designs in the scene."""
    source: str = "shipped"
    """Where the figures come from: ``shipped``, the calibration file's path, or
    ``measured in the scene``."""

    def extra(self, strategy: Strategy, tabled: bool, shared: bool = False) -> float:
        """Time per unit film share of a material on ``strategy`` (``tabled``: its lobe is
        read from the cosine tables; ``shared``: its ``product_only`` gives the BSDF its share)."""
        walk = self.product_only_shared_walk if shared else self.product_only_walk
        return {Strategy.ENVIRONMENT: 0.0, Strategy.ENVIRONMENT_ONLY: self.environment_only,
                Strategy.BSDF_ONLY: self.bsdf_only,
                Strategy.PRODUCT: self.product_table if tabled else self.product_walk,
                Strategy.PRODUCT_ONLY: self.product_only_table if tabled else walk}[strategy]

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)

    @property
    def key(self) -> str:
        """The figures as a plan kept in the cache folder is keyed by them (not where they
        came from: the same figures give the same plan)."""
        return "costs " + repr(sorted((k, v) for k, v in self.as_dict().items() if k != "source"))

    @classmethod
    def from_pass_times(cls, times: dict, shares: dict, source: str) -> "CostModel":
        """The model of timed pilot passes.

        ``times``: pilot -> pass time (s), with ``lean`` and ``environment`` and any of
        ``environment_only``, ``bsdf_only``, ``product (cosine lobes)``, ``product``, ``product_only
        (cosine lobes)``, ``product_only`` (each strategy on every material that can run
        it; the ``(cosine lobes)`` ones on the materials with a cosine table alone).
        ``shares``: the film shares those pilots switch: ``environment_only`` and ``bsdf_only`` -> a share,
        ``product`` and ``product_only`` -> (tabled share, walked share). A figure without
        its pilot or share is :data:`SHIPPED`'s."""
        lean = times["lean"]
        if not lean > 0:  # nothing was timed (passes that launched no kernel)
            return dataclasses.replace(SHIPPED, source=f"{source}: no time measured, shipped figures")
        base = times.get(Strategy.ENVIRONMENT.label, lean)

        def per_share(after: str, before: float, share: float, default: float) -> float:
            if after not in times or share <= 0:
                return default
            return max(times[after] - before, 0.0) / share / lean

        figures = {"product_code": max(base / lean - 1.0, 0.0)}
        for alone in CARRYING_MITSUBA_STRATEGIES:
            figures[alone.label] = per_share(alone.label, base, shares.get(alone.label, 0.0),
                                             getattr(SHIPPED, alone.label))
        for strategy in (Strategy.PRODUCT, Strategy.PRODUCT_ONLY):
            walk, table = f"{strategy.label}_walk", f"{strategy.label}_table"
            tabled, walked = shares.get(strategy.label, (0.0, 0.0))
            tabled_pilot = f"{strategy.label} (cosine lobes)"
            if tabled_pilot in times:
                figures[table] = per_share(tabled_pilot, base, tabled, getattr(SHIPPED, table))
                figures[walk] = per_share(strategy.label, times[tabled_pilot], walked, getattr(SHIPPED, walk))
            else:  # one pilot for every lobe of the strategy: one figure for its kind(s)
                both = per_share(strategy.label, base, tabled + walked, getattr(SHIPPED, walk))
                figures[walk] = both if walked > 0 else getattr(SHIPPED, walk)
                figures[table] = both if tabled > 0 else getattr(SHIPPED, table)
        return cls(**figures, source=source)


#: Measured with :func:`calibrate` on the development machine (module docstring), the
#: median of nine runs: ``python -m mitsuba_shsampling calibrate --runs 9 --print-only``
#: (2026-12-05). ``sh_path``'s calibration runs neither ``environment_only`` nor
#: ``product_only`` on the studio (its plan does not offer them there), so those two
#: figures of the path model are ``sh_direct``'s, which overstate them (a path's
#: rays are dearer, so the same work is a smaller share of its pass).
#: ``product_only_shared_walk`` is ``product_only_walk`` scaled by what the BSDF's share
#: (``bsdf_defensive_share``) adds to it: 0.509 x 1.38 = 0.70, the ratio of the medians of
#: six calibrations with the share on every material and six without, alternated on a
#: 2-core Xeon (0.65 and 0.47; docs/MEASUREMENTS.md, "A BSDF share in product_only").
SHIPPED_MODELS = {
    "direct": CostModel(product_code=0.052, environment_only=0.079, product_walk=0.255, product_table=0.112,
                        product_only_walk=0.509, product_only_table=0.250, product_only_shared_walk=0.70),
    "path": CostModel(product_code=0.076, environment_only=0.079, product_walk=0.086, product_table=0.090,
                      product_only_walk=0.509, product_only_table=0.250, product_only_shared_walk=0.70),
}
SHIPPED = SHIPPED_MODELS["direct"]

SHIPPED_BACKENDS = ("llvm",)
"""Backends the shipped figures were measured on. On another (``cuda``) they mislead: on
an H200 a plan priced with them put the product on eight studio materials under a sunset
map and ran at 0.57x Mitsuba's efficiency (issue 47). There the first plan calibrates the
machine (:func:`cost_model`)."""

#: Calibrations made in this process where the cache folder is off (variant -> models).
_calibrated_here: dict = {}

#: What calibrates this machine (:func:`mitsuba_shsampling.calibration.calibrate`, set by that
#: module, which sits above the integrators): returns (kind -> model, seconds).
_calibrator = None


def set_calibrator(calibrator) -> None:
    """Set what :func:`calibrate_now` calls (``calibrator()`` -> (kind -> model, seconds))."""
    global _calibrator
    _calibrator = calibrator


def calibration_path(variant: str | None = None) -> str | None:
    """Where this machine's calibration for ``variant`` (default: the current one) is kept,
    None where the disk cache is off (:mod:`~mitsuba_shsampling.build_cache`)."""
    folder = cache_folder()
    return os.path.join(folder, CALIBRATION_FILE.format(variant=variant or mi.variant())) if folder else None


def cost_model(kind: str) -> CostModel:
    """The model of ``kind`` (``direct`` or ``path``): this machine's calibration where
    one was made for this variant and package code, else the shipped one; on a backend
    the shipped figures were not measured on (:data:`SHIPPED_BACKENDS`), a calibration
    made now, once per machine (logged; kept in the cache folder, or in the process where
    the folder is off)."""
    path = calibration_path()
    if path and os.path.exists(path):
        try:
            with open(path) as f:
                stored = json.load(f)
            if stored.get("code") == code_digest():
                figures = stored["models"][kind]
                return CostModel(**{**figures, "source": path})
        except (OSError, ValueError, KeyError, TypeError):
            pass  # unreadable or foreign: the shipped model (a calibration never decides correctness)
    if backend_of(mi.variant()) in SHIPPED_BACKENDS:
        return SHIPPED_MODELS[kind]
    return calibrate_now(path)[kind]


def backend_of(variant: str) -> str:
    """``llvm`` or ``cuda`` (a JIT variant's first word)."""
    return variant.split("_", 1)[0]


def calibrate_now(path: str | None) -> dict:
    """This machine's models, calibrated now (:func:`~mitsuba_shsampling.calibration.calibrate`),
    kept at ``path`` (or in this process where there is none)."""
    variant = mi.variant()
    if variant in _calibrated_here:
        return _calibrated_here[variant]
    if _calibrator is None:
        raise RuntimeError(f"mitsuba_shsampling: no cost model for the {backend_of(variant)} backend: run "
                           f"'python -m mitsuba_shsampling calibrate --variant {variant}' once on this machine")
    mi.Log(mi.LogLevel.Warn, f"mitsuba_shsampling: no shipped cost model for the {backend_of(variant)} backend: "
                             "calibrating this machine once (python -m mitsuba_shsampling calibrate)")
    models, seconds = _calibrator()
    if path:
        save_calibration(models, seconds)
        models = {kind: CostModel(**{**m.as_dict(), "source": path}) for kind, m in models.items()}
    else:
        _calibrated_here[variant] = models
    mi.Log(mi.LogLevel.Info, f"mitsuba_shsampling: calibration took {seconds:.1f} s")
    return models


def save_calibration(models: dict, seconds: float, variant: str | None = None) -> str:
    """Write ``models`` (kind -> :class:`CostModel`) as this machine's calibration; returns the path."""
    path = calibration_path(variant)
    if path is None:
        raise OSError("the cache folder is off (SHSAMPLING_CACHE_DIR): a calibration has nowhere to go")
    os.makedirs(os.path.dirname(path), exist_ok=True)
    record = {"code": code_digest(), "variant": variant or mi.variant(), "seconds": seconds,
              "models": {kind: {k: v for k, v in m.as_dict().items() if k != "source"} for kind, m in models.items()}}
    with open(path, "w") as f:
        json.dump(record, f, indent=1)
    return path
