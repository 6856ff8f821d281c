"""Per-scene state of the SH product strategy, shared by the integrators.

Built once per scene, on the host, before the first render pass (never while a
pass is being traced): the environment pyramid, the BSDF lobe table and the
product warp. A scene without an environment map, or whose BSDFs are all
delta/unsupported, builds nothing and the integrators behave like their
Mitsuba counterparts.

Where it is built, the environment is sampled by this package at every shading
point with a smooth BSDF, with the strategy (:mod:`.strategy`) of the lane's
material: the product, the product carrying every sample, or the environment
alone (Mitsuba's own envmap sampling, MIS-compensated like the product:
:class:`~mitsuba_shsampling.envmap.emitter.EmitterDirections`). Materials without a product lobe
(transmissive BSDFs) use the environment alone; anisotropic BSDFs have an
isotropic proxy, ``bumpmap``/``normalmap`` their nested BSDF's lobe about the
perturbed normal (:mod:`~mitsuba_shsampling.lobes.perturbed_frames`). With
``strategy`` ``auto`` the integrators choose per material before the first pass
(:mod:`.chooser`). Mitsuba's emitter sampling is left with the other emitters.
"""

from __future__ import annotations

import contextlib
import gc
import math
import time
import warnings
from typing import Callable, NamedTuple

import drjit as dr
import mitsuba as mi
import numpy as np

from ..build_cache import kept_in_process
from ..envmap.emitter import EmitterDirections, compensated_copy
from ..envmap.evaluated import EVALUATED_EMITTERS, is_evaluated, sky_components
from ..envmap.pyramid import BLACK_MAP_REASON, EnvPyramid, finest_level_kept
from ..lobes import SceneLobes
from ..scene_materials import registry_id, scene_materials
from ..timing import kernels_compiled
from ..traversal import readable_parameters
from ..warp.product import ProductWarp
from ..warp.proxy_lobe import ProxyLobe
from ..warp.sky_mixture import SkyMixture
from .options import DEFAULT_BSDF_DEFENSIVE_SHARE, OptionError, PathOptions, ProductOptions
from .strategy import AUTO, MaterialFlags, Strategy, StrategyTable, strategy_named


FRAME_DIRAC_BOUNCES = 3
"""Dirac bounces (mirrors, glass) a camera ray of a path plugin's quadrature follows to the
first rough hit at most: a glass block's two faces and a mirror beyond them."""


def frame_dirac_bounces(options) -> int:
    """:attr:`ProductEnvironment.frame_dirac_bounces` for a plugin's options: none for
    ``sh_direct`` (it shades the first hit alone); for the path plugins
    :data:`FRAME_DIRAC_BOUNCES`, fewer where ``max_depth`` leaves a vertex behind that
    many no emitter sample (vertex k samples emitters while k + 1 < max_depth)."""
    if not isinstance(options, PathOptions):
        return 0
    return int(max(0, min(FRAME_DIRAC_BOUNCES, options.depth_limit - 2)))


def emitter_id(emitter: mi.Emitter | None) -> mi.UInt32 | None:
    """The registry id of ``emitter`` as an opaque value, for :func:`is_emitter` (None for
    no emitter).

    Opaque, not a literal: Mitsuba loads a scene's objects in parallel by default, so
    their registry ids change from run to run, and a literal id would make every kernel
    that tests it new to Dr.Jit's kernel cache in each process (compiled again:
    seconds of a first render's set-up)."""
    if emitter is None:
        return None
    return dr.opaque(mi.UInt32, int(dr.reinterpret_array(mi.UInt32, mi.EmitterPtr(emitter))[0]))


def is_emitter(emitter: mi.EmitterPtr, which: mi.UInt32) -> mi.Bool:
    """Per-lane test: is ``emitter`` the emitter whose id (:func:`emitter_id`) is ``which``."""
    return dr.reinterpret_array(mi.UInt32, emitter) == which


class OtherEmitterSelection(NamedTuple):
    """Mitsuba's emitter selection (``Scene.sample_emitter``) restricted to every emitter but
    the environment, each drawn in proportion to its own selection probability: the
    environment's interval of the selection's cumulative distribution is cut out of the
    1D sample (:meth:`remap`), and each emitter's pdf is divided by ``share``."""

    share: mi.Float
    """The other emitters' share of the scene's selection."""
    start: mi.Float
    """Where the environment's interval starts."""
    skip: mi.Float
    """The environment's selection probability (the interval's length)."""
    below: mi.Float
    """The largest sample the scene maps to an emitter before the environment (0: none)."""
    above: mi.Float
    """The smallest sample it maps to one after it (1: none)."""

    @classmethod
    def of(cls, scene: mi.Scene, index: int, pmf) -> OtherEmitterSelection | None:
        """The selection of ``scene`` without its emitter ``index`` (``pmf``: the scene's
        selection probabilities); None where the others have no share."""
        start, share = float(np.sum(pmf[:index])), float(1.0 - pmf[index])
        if share <= 0.0:
            return None

        def first_outside(value: float, towards: float, side) -> float:
            # The sample's mapping is monotonic but computed in float32: step from the
            # interval's end, one float at a time, to the first value the scene maps outside it
            # (an opaque value: one small kernel for every probe and scene, not one each).
            value = np.float32(value)
            for _ in range(64):
                if side(int(scene.sample_emitter(dr.opaque(mi.Float, float(value)))[0].numpy()[0])):
                    return float(value)
                value = np.nextafter(value, np.float32(towards))
            raise RuntimeError("mitsuba_shsampling: could not find the environment's interval of the "
                               "scene's emitter selection")

        below = first_outside(start, 0.0, lambda i: i < index) if index > 0 else 0.0
        above = first_outside(start + pmf[index], 1.0, lambda i: i > index) if index < len(pmf) - 1 else 1.0
        return cls(*(dr.opaque(mi.Float, v) for v in (share, start, float(pmf[index]), below, above)))

    def remap(self, u: mi.Float) -> mi.Float:
        """``u`` (uniform in [0, 1)) mapped to where the scene's selection draws an emitter
        other than the environment; it reprojects the sample for the chosen emitter."""
        u = u * self.share
        return dr.select(u >= self.start, dr.maximum(u + self.skip, self.above), dr.minimum(u, self.below))


class EnvironmentState:
    """What every per-scene environment state has (:class:`ProductEnvironment`,
    the oracle's): the scene's environment emitter and its registry id, why this
    package does not sample it (``reason``, empty where it does), and Mitsuba's
    emitter sampling of what it leaves to Mitsuba.

    ``needs_emitter_sampling`` (bool): Mitsuba's emitter sampling has work to do
    (emitters besides the environment, or the environment where this package does
    not sample it); subclasses set it once they know."""

    #: Environments without texels (``sunsky``, ``constant``) are sampled through their
    #: evaluated radiance (:mod:`~mitsuba_shsampling.envmap.evaluated`).
    samples_evaluated_emitters = False
    #: This package samples the environment (subclasses set it once they know).
    active = False

    def __init__(self, scene: mi.Scene):
        self.emitter = scene.environment()
        self.emitter_id = emitter_id(self.emitter)
        #: The environment's index among the scene's emitters and the probability with which
        #: the scene draws it (``Scene.sample_emitter``), for ``emitter_selection`` ``one``;
        #: opaque for the reason :func:`emitter_id` gives.
        self.emitter_index = self.selection = None
        #: Where this package samples the environment, Mitsuba's emitter sampling draws among
        #: the other emitters only (:func:`~.estimators.mitsuba_nee`): how
        #: (:class:`OtherEmitterSelection`; None where they have no share or there is no environment).
        self.others = None
        if self.emitter is not None:
            emitters = scene.emitters()
            index = next(i for i, e in enumerate(emitters) if e is self.emitter)
            # (Under uniform selection Mitsuba answers with one value for every index.)
            pmf = (dr.zeros(mi.Float, len(emitters)) + scene.pdf_emitter(dr.arange(mi.UInt32, len(emitters)))).numpy()
            self.emitter_index = dr.opaque(mi.UInt32, index)
            self.selection = dr.opaque(mi.Float, float(pmf[index]))
            self.others = OtherEmitterSelection.of(scene, index, pmf)
        # A flag, not the emitters: an area emitter kept alive past its scene points at a
        # freed shape, and Mitsuba's virtual calls over every live emitter would reach it.
        self.has_other_emitters = any(e is not self.emitter for e in scene.emitters())
        self.needs_emitter_sampling = True
        if self.emitter is None:
            self.reason = "the scene has no environment emitter"
        elif not (self.emitter.class_name() == "EnvironmentMapEmitter"
                  or (self.samples_evaluated_emitters and is_evaluated(self.emitter))):
            kinds = "'envmap'" + ("".join(f", '{k}'" for k in EVALUATED_EMITTERS.values())
                                  if self.samples_evaluated_emitters else "")
            self.reason = (f"the environment emitter is '{self.emitter.class_name()}', not one of {kinds}; "
                           "it keeps Mitsuba's own sampling")
        else:
            self.reason = ""

    def is_environment(self, emitter: mi.EmitterPtr) -> mi.Bool:
        """Per-lane test: is ``emitter`` the environment map."""
        return is_emitter(emitter, self.emitter_id)

    def hit_pdf(self, emitter, strategy_pdf, emitter_pdf, others_only: bool = True):
        """Emitter-strategy pdf of a BSDF-sampled ray that hit ``emitter``: the lane's
        environment strategy (:meth:`pdf`) for the environment, Mitsuba's otherwise
        (``emitter_pdf``, drawn among the other emitters only where ``others_only``:
        :func:`~.estimators.mitsuba_nee`)."""
        if not self.active:
            return emitter_pdf
        others_pdf = emitter_pdf if self.others is None or not others_only else emitter_pdf / self.others.share
        return dr.select(self.is_environment(emitter), strategy_pdf, others_pdf)


class ProductEnvironment(EnvironmentState):
    """Environment sampling for one scene, with a strategy per material.

    Built from the plugin's checked ``options`` (``max_bands``, ``sh_depth``,
    ``proxy_depth``, ``mis_compensation``, ``defensive_share``, ``strategy``);
    ``carry_all`` allows the strategies that carry every sample of a lane
    (:attr:`Strategy.PRODUCT_ONLY`, :attr:`Strategy.ENVIRONMENT_ONLY`,
    :attr:`Strategy.BSDF_ONLY`: ``sh_direct`` with BSDF samples); the first needs the
    product with the uncompensated map (:attr:`warp_plain`).

    Attributes: ``emitter`` (the envmap or None), ``active`` (bool: this package
    samples the environment in this scene), ``reason`` (why not, when inactive),
    ``pyramid``, ``lobes``, ``warp`` (the product; None where no material may run
    it), ``env_directions`` (the environment alone, compensated like the
    pyramid), ``env_plain`` (the environment alone, uncompensated),
    ``strategies`` (:class:`StrategyTable`: each material's strategy),
    ``choice`` (the chooser's :class:`~.chooser.StrategyChoice` once made),
    ``needs_emitter_sampling`` (bool: Mitsuba's emitter sampling has work to do:
    emitters besides the environment, or any emitter where this object is inactive; so
    also whether Mitsuba's pdf of a hit emitter is needed), ``has_dirac_materials`` (bool),
    ``frame_dirac_bounces`` (the Dirac bounces the plan's frames follow from the camera:
    :func:`frame_dirac_bounces`).
    """

    samples_evaluated_emitters = True

    def __init__(self, scene: mi.Scene, options: ProductOptions, carry_all: bool = False):
        start = time.perf_counter()
        super().__init__(scene)
        self.scene = scene
        self.pyramid = self.lobes = self.warp = self.warp_plain = self.env_directions = self.env_plain = None
        #: The evaluated environment's image and sun (:class:`~..envmap.evaluated.SkyComponents`; None: an
        #: ``envmap``); the strategy table and the plan.
        self.sky = self.strategies = self.choice = None
        self.strategy_option = options.default_strategy
        #: The plugin's name, for messages; what a stored plan must match (:mod:`.plan_file`).
        self.plugin, self.options_key = options.PLUGIN, options.plan_key
        #: Registry id -> the strategy ``strategy`` names for that material.
        self.forced: dict[int, Strategy] = {}
        #: Time the build took (s): the set-up before the plan.
        self.build_seconds = 0.0
        #: Registry id -> the scene's material (:mod:`~mitsuba_shsampling.scene_materials`).
        self._materials = {registry_id(m.bsdf): m for m in scene_materials(scene)}
        #: Some material has a Dirac component (which only a BSDF sample reaches).
        self.has_dirac_materials = any(mi.has_flag(m.bsdf.flags(), mi.BSDFFlags.Delta) for m in self._materials.values())
        self.carry_all = carry_all
        self.frame_dirac_bounces = frame_dirac_bounces(options)
        #: ``product_only``'s BSDF share (``sh_direct``'s ``bsdf_defensive_share``, else its default).
        self.bsdf_share = getattr(options, "bsdf_defensive_share", DEFAULT_BSDF_DEFENSIVE_SHARE) if carry_all else 0.0
        #: Trace the cosine tables' and the SH walk's code whatever the materials run, and bsdf_only's draw
        #: where one of them runs it: the chooser's pilot passes (:func:`~.pilots.measure_pass_costs`).
        self.pilot_walks = self.pilot_bsdf_alone = False
        #: ``emitter_selection`` as traced, and whether the plan prices it (:mod:`.emitter_selection`).
        self.emitter_selection, self.prices_emitter_selection = initial_emitter_selection(options)
        self.active = False
        if self.reason:
            if self.emitter is not None:  # an environment of another kind: say so once
                warnings.warn(f"mitsuba_shsampling: {self.reason}")
            return
        forced = None if options.default_strategy == AUTO else strategy_named(options.default_strategy)
        named = {name: strategy_named(value) for name, value in options.material_strategies.items()
                 if value != AUTO}
        wants_plain = (carry_all and options.mis_compensation
                       and (forced is None or forced.uses_product or any(s.uses_product for s in named.values())))
        plain_pyramid = self._fit_lobes_and_build_pyramids(scene, options, wants_plain)
        if self.pyramid is None:  # every BSDF is delta (reason says so)
            return
        if self.pyramid.is_black:
            self.reason = BLACK_MAP_REASON
            return
        # The environment strategies are Mitsuba's own envmap sampling (compensated
        # like the pyramid): the strategies of Mitsuba's `direct`, at its cost. A
        # telescoped descent of the pyramid (removed) had 2.4x the variance on a
        # diffuse plane under a 0.5-degree sun (docs/MEASUREMENTS.md).
        self.env_plain = EmitterDirections(self.emitter)
        self.env_directions = (EmitterDirections(compensated_copy(self.emitter)) if self.pyramid.mis_compensation
                               else self.env_plain)
        # A forced strategy that keeps the BSDF sample leaves nothing to trace for lanes without it.
        self.carry_all = carry_all and (forced is None or forced.carries_all
                                        or any(s.carries_all for s in named.values()))
        #: The product with the map itself (not compensated): the strategy of
        #: lanes where it carries every sample, so that nothing is left to a
        #: BSDF sample that does not run there. The same warp when the scene's
        #: pyramid is not compensated; built only where that strategy is
        #: allowed (``carry_all``, a second pyramid) otherwise.
        if self.lobes.has_product_lobes and (forced is None or forced.uses_product
                                             or any(s.uses_product for s in named.values())):
            # Diffuse materials' lanes sample the product from the cosine tables (no SH walk).
            warp_options = dict(sh_depth=options.warp_sh_depth, defensive_share=options.defensive_share,
                                proxy_depth=options.warp_proxy_depth, cosine_tables=self.lobes.has_cosine_lobes)
            self.warp = self.warp_plain = self._with_sun(ProductWarp(self.pyramid, **warp_options))
            if self.pyramid.mis_compensation:
                self.warp_plain = ProductWarp(plain_pyramid, **warp_options) if carry_all else None
        first = forced or Strategy.PRODUCT
        self.strategies = StrategyTable({key: self._runnable(key, first) for key, m in self._materials.items()
                                         if mi.has_flag(m.bsdf.flags(), mi.BSDFFlags.Smooth)})
        #: Materials whose ``product_only`` shares (:meth:`mixes_bsdf`): all until a plan weighs it.
        self.bsdf_shared = MaterialFlags(self.strategies.ids, True)
        self.forced = self._resolve_named(named)
        if forced is not None:  # no plan to make: the named materials get theirs now
            self.strategies.assign(self.forced)
        self.active, self.reason = True, ""
        # Mitsuba's emitter sampling is only traced when some lane can use it: every
        # smooth lane samples the environment through this object.
        self.needs_emitter_sampling = self.has_other_emitters
        self.build_seconds = time.perf_counter() - start

    def _with_sun(self, warp):
        """``warp``, or where the pyramid leaves a sun out, ``warp`` mixed with the emitter's
        own sampling, which draws the sun, for each lane in the share its lobe gives it."""
        if self.sky is None or self.sky.sun is None:
            return warp
        sun = self.pyramid.grid_from_world(mi.Vector3f(self.sky.sun))
        return SkyMixture(warp, self.env_plain, mi.ScalarVector3f(sun.x[0], sun.y[0], sun.z[0]),
                          self.sky.sun_power, self.pyramid.total, self.sky.sun_sampling_share)

    def _fit_lobes_and_build_pyramids(self, scene, options: ProductOptions, wants_plain: bool):
        """Set ``lobes`` and ``pyramid`` (or ``reason`` where every BSDF is delta); returns
        the uncompensated pyramid where ``wants_plain`` and a product lobe needs it.

        One after the other, on this thread. The pyramids were once built in threads beside
        the lobe fits, when they were numpy work; now both are Dr.Jit kernels that use every
        core, the threads saved nothing (a new scene's state 0.50-0.55 s with them, 0.46-0.53 s
        without, docs/MEASUREMENTS.md), and Dr.Jit work from two Python threads deadlocked
        under Dr.Jit's ``Info`` log level."""
        if is_evaluated(self.emitter):
            # Evaluated on the host first: the sun's sun_scale is set to 0 while the sky is.
            # Its sampling is never compensated (Mitsuba's sampling of it has no such option,
            # and a constant one would compensate to nothing): one pyramid serves every lane.
            self.sky = sky_components(self.emitter)
            wants_plain = False
            build = lambda compensated: EnvPyramid.from_latlong(self.sky.image)  # noqa: E731
        else:
            build = lambda compensated: EnvPyramid(self.emitter, mis_compensation=compensated)  # noqa: E731
        self.lobes = SceneLobes(scene, max_bands=options.max_bands)
        if not (self.lobes.has_product_lobes or self.lobes.has_unsupported_lobes):
            self.reason = "every BSDF in the scene is delta: no shading point samples the environment"
            return None
        with finest_level_kept():  # the plain pyramid reuses the compensated one's finest level
            self.pyramid = build(options.mis_compensation)
            needs_plain = wants_plain and self.lobes.has_product_lobes and self.pyramid.mis_compensation
            return build(False) if needs_plain else None

    def _resolve_named(self, named: dict[str, Strategy]) -> dict[int, Strategy]:
        """Registry id -> strategy of the materials ``strategy`` names; an unknown name, or
        a strategy the material cannot run, is an :class:`~.options.OptionError`."""
        by_name = {m.name: key for key, m in self._materials.items()}
        resolved = {}
        for name, strategy in named.items():
            key = by_name.get(name)
            if key is None:
                raise OptionError(f"{self.plugin}: parameter 'strategy' names material '{name}', which the scene "
                                  f"does not have (its materials: {', '.join(sorted(by_name)) or 'none'})")
            can_run = self.allowed(key) if key in self.strategies.ids else []
            if strategy not in can_run:
                raise OptionError(f"{self.plugin}: parameter 'strategy': material '{name}' cannot run "
                                  f"'{strategy.label}' here (it can run: "
                                  f"{', '.join(s.label for s in can_run) or 'none: it samples no environment'})")
            resolved[key] = strategy
        return resolved

    # -- Host side: the strategy of each material -----------------------------

    @property
    def awaits_choice(self) -> bool:
        """``strategy`` is ``auto`` and the chooser has not run for this scene yet."""
        return self.strategies is not None and self.strategy_option == AUTO and self.choice is None

    def allowed(self, key: int) -> list[Strategy]:
        """The strategies material ``key`` (registry id) can run: the environment
        always; the product where its BSDF has a product lobe and the product is
        built; the strategies without a BSDF sample where the integrator allows
        them and the BSDF has no Dirac part (which only a BSDF sample reaches)."""
        bsdf = self._bsdf(key)
        if bsdf is None:
            return [Strategy.ENVIRONMENT]
        no_delta = not mi.has_flag(bsdf.flags(), mi.BSDFFlags.Delta)
        lobed = self.warp is not None and key in self.lobes.bsdfs_with_lobes
        result = [Strategy.ENVIRONMENT]
        result += [Strategy.ENVIRONMENT_ONLY, Strategy.BSDF_ONLY] if self.carry_all and no_delta else []
        result += [Strategy.PRODUCT] if lobed else []
        result += [Strategy.PRODUCT_ONLY] if lobed and no_delta and self.carry_all and self.warp_plain else []
        return result

    def _runnable(self, key: int, strategy: Strategy) -> Strategy:
        """``strategy``, or the nearest one material ``key`` can run."""
        while strategy not in self.allowed(key):
            strategy = strategy.fallback
        return strategy

    def _bsdf(self, key: int):
        material = self._materials.get(key)
        return material.bsdf if material is not None else None

    def material_name(self, key: int) -> str:
        """The report name (:mod:`~mitsuba_shsampling.scene_materials`) of the material
        whose BSDF has registry id ``key``."""
        material = self._materials.get(key)
        return material.name if material is not None else f"bsdf#{key}"

    def drop_product(self) -> None:
        """Trace no product code from now on: materials on a product strategy fall
        back to the environment, in a kernel as lean as Mitsuba's ``direct`` (the
        product's code in a kernel costs its other lanes 7-30 % even where skipped)."""
        self.warp = self.warp_plain = None
        self.strategies.assign({key: self._runnable(key, self.strategies.of(key)) for key in self.strategies.ids})

    # Per-lane pieces shared by the integrators. When the scene does not use
    # product sampling they reduce to Mitsuba's own strategies and trace nothing.

    @property
    def cosine_tables(self) -> bool:
        """The product samples diffuse lobes from its cosine tables
        (:class:`~mitsuba_shsampling.warp.cosine_table.CosineTable`)."""
        return self.warp is not None and self.warp.cosine_table is not None

    def samples_from_cosine_table(self, key: int) -> bool:
        """Material ``key`` (registry id) has a clamped-cosine lobe, which the product
        samples from its cosine tables, at about the environment's own cost."""
        return self.cosine_tables and key in self.lobes.tabled_ids

    def lobe(self, si: mi.SurfaceInteraction3f, smooth: mi.Bool):
        """(lobe, use_product): the lobe proxy at ``si`` in the grid frame
        (:class:`LaneLobe`), and the lanes whose material runs a product strategy;
        (None, False) where no material can. Lanes on the environment strategy
        look up no lobe (masked gathers, a skipped rotation)."""
        if self.warp is None:
            return None, mi.Bool(False)
        smooth = mi.Bool(smooth)
        code = self.strategies.lane(si, smooth)
        wants_product = smooth & ((code == int(Strategy.PRODUCT)) | (code == int(Strategy.PRODUCT_ONLY)))
        # Only the walks that some material on a product strategy runs are traced: no SH
        # code where all of them draw from the cosine tables, no table code where none does.
        # The chooser's pilots trace both (`pilot_walks`), so that what they time is the kernel
        # that a choice of both kinds runs: the two walks in one kernel cost more than apart.
        on_product = [key for key in self.strategies.ids if self.strategies.of(key).uses_product]
        tables = any(self.samples_from_cosine_table(key) for key in (self.strategies.ids if self.pilot_walks
                                                                     else on_product))
        sh_lobes = self.pilot_walks or not tables or any(not self.samples_from_cosine_table(key)
                                                         for key in on_product)
        coeffs, proxy, use_product = self.lobes.coefficients_and_proxy(si, self.pyramid.grid_from_world,
                                                                       wants_product, tables, sh_lobes)
        shared = self.bsdf_shared.lane(si, wants_product) if self.draws_bsdf else None
        return LaneLobe(coeffs, proxy, shared), use_product & wants_product

    def carries_all(self, si, bsdf, smooth: mi.Bool) -> mi.Bool:
        """Per lane: the lane's material runs a strategy that carries every sample
        (:attr:`Strategy.PRODUCT_ONLY`, :attr:`Strategy.ENVIRONMENT_ONLY`,
        :attr:`Strategy.BSDF_ONLY`): no BSDF
        sample runs there, and the strategy draws from the uncompensated map
        (coverage without a BSDF sample). False (no lane, nothing traced) where the
        integrator does not allow it."""
        if not self.active or not self.carry_all:
            return False
        code = self.strategies.lane(si, smooth)
        no_delta = ~mi.has_flag(bsdf.flags(), mi.BSDFFlags.Delta)
        carrying = mi.Bool(False)
        for strategy in (s for s in Strategy if s.carries_all):
            carrying |= code == int(strategy)
        return mi.Bool(smooth) & no_delta & carrying

    @property
    def draws_bsdf_alone(self) -> bool:
        """Some material runs ``bsdf_only`` (or the pilots do): only then is its draw traced."""
        if not self.active or not self.carry_all or self.strategies is None:
            return False
        if self.pilot_walks:
            return self.pilot_bsdf_alone
        return any(self.strategies.of(key) == Strategy.BSDF_ONLY for key in self.strategies.ids)

    def bsdf_alone(self, si, smooth: mi.Bool) -> mi.Bool | bool:
        """Per lane: the lane's material runs ``bsdf_only``; False (nothing traced) where
        no material does (:attr:`draws_bsdf_alone`)."""
        if not self.draws_bsdf_alone:
            return False
        return mi.Bool(smooth) & (self.strategies.lane(si, smooth) == int(Strategy.BSDF_ONLY))

    def sample_product(self, lobe, u: mi.Point2f, plain):
        """(direction, exact pdf) of one product sample: from :attr:`warp_plain`
        in ``plain`` lanes, from :attr:`warp` in the others (a symbolic branch,
        so a SIMD packet runs only the walk its lanes need).

        Lanes of a diffuse lobe (``lobe.proxy.cosine_only``) read the warp's cosine
        tables instead of walking their SH lobe (:class:`~mitsuba_shsampling.warp.product.ProductWarp`;
        docs/MEASUREMENTS.md, "Cosine tables")."""
        if plain is False or self.warp_plain is self.warp:
            return self.warp.sample(lobe.coeffs, u, lobe.proxy)
        if plain is True:
            return self.warp_plain.sample(lobe.coeffs, u, lobe.proxy)
        return dr.if_stmt(args=(lobe, u), cond=plain,
                          true_fn=lambda c, v: self.warp_plain.sample(c.coeffs, v, c.proxy),
                          false_fn=lambda c, v: self.warp.sample(c.coeffs, v, c.proxy))

    def sample_alone(self, u: mi.Point2f, plain):
        """(direction, pdf) of the environment alone: uncompensated in ``plain`` lanes."""
        if plain is False or self.env_plain is self.env_directions:
            return self.env_directions.sample(u)
        if plain is True:
            return self.env_plain.sample(u)
        return dr.if_stmt(args=(u,), cond=plain, true_fn=self.env_plain.sample,
                          false_fn=self.env_directions.sample)

    def sample_environment(self, lobe, u: mi.Point2f, use_product, carries_all, bsdf_draw=None, alone=None):
        """(direction, exact pdf) of one sample of the lane's environment strategy: the
        product (:meth:`sample_product`) in ``use_product`` lanes, the environment alone
        elsewhere, from the uncompensated map in ``carries_all`` lanes, and the BSDF's own
        sampling in the ``bsdf_only`` lanes of ``alone`` (:class:`BSDFAlone`; None: no such
        lane). Symbolic branches: a SIMD packet runs only the walks its lanes need.

        Given ``bsdf_draw`` (:class:`BSDFDraw`: a BSDF sample's slot), the lanes of
        ``product_only``'s mixture (:meth:`mixes_bsdf`) draw from the BSDF with
        probability ``bsdf_draw.share``, from the product otherwise; the pdf returned is
        then the *product's* at the direction (0 where the BSDF's draw failed), which
        :meth:`carried_weight` turns into the sample's balance weight."""
        if alone is None:
            return self._sample_strategy(lobe, u, use_product, carries_all, bsdf_draw)
        lanes = alone.lanes
        d, pdf = dr.if_stmt(args=(lobe, u), cond=~lanes,
                            true_fn=lambda c, v: self._sample_strategy(c, v, use_product, carries_all, bsdf_draw),
                            false_fn=lambda c, v: (mi.Vector3f(0.0, 0.0, 1.0), mi.Float(0.0)))
        # The BSDF's own draw, with its own pdf: each sample then weighs BSDF x radiance / pdf,
        # the estimate of Mitsuba's BSDF sample (a failed draw is a sample of value 0).
        bs, _ = alone.bsdf.sample(alone.ctx, alone.si, alone.u_component, u, lanes)
        drew = lanes & (bs.pdf > 0)
        return dr.select(drew, alone.si.to_world(bs.wo), d), dr.select(lanes, dr.select(drew, bs.pdf, 0.0), pdf)

    def _sample_strategy(self, lobe, u: mi.Point2f, use_product, carries_all, bsdf_draw):
        """:meth:`sample_environment` in the lanes that sample the environment."""
        if self.warp is None:
            return self.sample_alone(u, carries_all)
        mixes = self.mixes_bsdf(lobe, use_product, carries_all) if bsdf_draw is not None else False
        if mixes is False:
            return dr.if_stmt(args=(lobe, u), cond=mi.Bool(use_product),
                              true_fn=lambda c, v: self.sample_product(c, v, carries_all),
                              false_fn=lambda c, v: self.sample_alone(v, carries_all))
        draw = bsdf_draw
        chose_bsdf = mixes & (draw.u_choice < draw.share)
        # Three ways, each walk only in the packets whose lanes need it.
        d, pdf = dr.if_stmt(args=(lobe, u), cond=mi.Bool(use_product) & ~chose_bsdf,
                            true_fn=lambda c, v: self.sample_product(c, v, carries_all),
                            false_fn=lambda c, v: dr.if_stmt(
                                args=(v,), cond=~chose_bsdf, true_fn=lambda w: self.sample_alone(w, carries_all),
                                false_fn=lambda w: (mi.Vector3f(0.0, 0.0, 1.0), mi.Float(0.0))))
        # The BSDF's draw reuses the 2D sample and the choice rescaled (both uniform there).
        bs, _ = draw.bsdf.sample(draw.ctx, draw.si, draw.u_choice / draw.share, u, chose_bsdf)
        drew = chose_bsdf & (bs.pdf > 0)
        d_bsdf = draw.si.to_world(bs.wo)
        # The product's pdf of the BSDF's direction: one walk, in the packets that drew one.
        pdf_bsdf = dr.if_stmt(args=(lobe, d_bsdf), cond=drew,
                              true_fn=lambda c, v: self.warp_plain.pdf(c.coeffs, v, c.proxy),
                              false_fn=lambda c, v: mi.Float(0.0))
        return dr.select(drew, d_bsdf, d), dr.select(chose_bsdf, pdf_bsdf, pdf)

    def mixes_bsdf(self, lobe, use_product, carries_all):
        """Per lane: the sample is ``product_only``'s mixture with the BSDF, a lane of that
        strategy whose lobe is walked in SH; False (nothing traced) where no material runs
        such a lane. A lobe read from the cosine tables is the BSDF's exact shape (a
        clamped cosine about the normal), so its product bounds the samples' values by
        itself there."""
        if not self.draws_bsdf or carries_all is False or lobe.bsdf_shared is None:
            return False
        cosine = lobe.proxy.cosine_only if lobe.proxy is not None else False
        return mi.Bool(use_product) & carries_all & ~mi.Bool(cosine) & lobe.bsdf_shared

    @property
    def draws_bsdf(self) -> bool:
        """``product_only``'s mixture has a BSDF share and some material runs it with an SH
        lobe and the share (or the chooser's pilots trace every walk): only then is its code
        traced."""
        if self.bsdf_share <= 0 or self.warp_plain is None or self.strategies is None:
            return False
        return self.pilot_walks or any(self.strategies.of(key) == Strategy.PRODUCT_ONLY
                                       and self.bsdf_shared.of(key) and not self.samples_from_cosine_table(key)
                                       for key in self.strategies.ids)

    def share_bsdf(self, keys) -> None:
        """Give the BSDF its share in ``product_only`` on the materials ``keys`` (registry
        ids) and on no other."""
        self.bsdf_shared.set({key: key in set(keys) for key in self.strategies.ids})

    def carried_slots(self, frac_e: float, frac_b: float, selection=1.0) -> CarriedSlots:
        """How a lane that carries every sample draws them (:class:`CarriedSlots`), with
        sample-count shares ``frac_e``, ``frac_b`` and an emitter sample that draws the
        environment with probability ``selection``: the BSDF samples' slots draw from the
        BSDF with the probability that gives it :attr:`bsdf_share` of the lane's samples
        (all of them where that is more than their share)."""
        return CarriedSlots(frac_e, frac_b, selection, min(1.0, self.bsdf_share / frac_b) if frac_b > 0 else 0.0)

    def carried_weight(self, lobe, slot_pdf, product_pdf, bsdf_pdf, use_product, carries_all, slots):
        """Per lane, the factor that makes a ``carries_all`` sample of ``slot_pdf`` (its
        slot's density of the direction; the product's there is ``product_pdf``, the
        BSDF's ``bsdf_pdf``) the balance heuristic's over the lane's ``slots``
        (:class:`CarriedSlots`): ``slot_pdf`` / q, q = ``frac_e`` x ``selection`` x
        ``product_pdf`` + ``frac_b`` x ((1 - t) ``product_pdf`` + t ``bsdf_pdf``), where
        the lane :meth:`mixes_bsdf`; 1 (equal weights) elsewhere. Every slot's sample is
        then worth BSDF x radiance / (N q) whichever slot drew it, at most the BSDF
        sample's weight x radiance / (N b)."""
        mixes = self.mixes_bsdf(lobe, use_product, carries_all)
        if mixes is False:
            return 1.0
        t = slots.bsdf_in_slot
        q = (slots.frac_e * slots.selection * product_pdf
             + slots.frac_b * ((1.0 - t) * product_pdf + t * bsdf_pdf))
        return dr.select(mixes & (q > 0), slot_pdf / q, 1.0)

    def pdf(self, lobe, use_product, d: mi.Vector3f, active: mi.Bool) -> mi.Float:
        """Pdf of world direction ``d`` under the lane's environment strategy: the
        product's in ``use_product`` lanes, the environment alone's in the others
        (0 where not ``active``, and everywhere when the scene builds nothing)."""
        if not self.active:
            return mi.Float(0.0)
        active = mi.Bool(active)
        # Symbolic branches: a SIMD packet with no lane that needs a walk (sky, delta or
        # occluded BSDF samples) skips it.
        env_pdf = dr.if_stmt(args=(d,), cond=active & ~use_product,
                             true_fn=lambda v: self.env_directions.pdf(v),
                             false_fn=lambda v: mi.Float(0.0))
        if self.warp is None:
            return env_pdf
        product_pdf = dr.if_stmt(args=(lobe, d), cond=active & use_product,
                                 true_fn=lambda c, v: self.warp.pdf(c.coeffs, v, c.proxy),
                                 false_fn=lambda c, v: mi.Float(0.0))
        return dr.select(use_product, product_pdf, env_pdf)


class BSDFDraw(NamedTuple):
    """What a BSDF sample's slot of ``product_only`` draws with
    (:meth:`ProductEnvironment.sample_environment`)."""

    si: mi.SurfaceInteraction3f
    bsdf: mi.BSDFPtr
    ctx: mi.BSDFContext
    u_choice: mi.Float
    """A uniform sample: below ``share`` the BSDF draws (and this, rescaled, picks its component)."""
    share: float
    """The probability that the BSDF draws (:attr:`CarriedSlots.bsdf_in_slot`)."""


class BSDFAlone(NamedTuple):
    """What the lanes of ``bsdf_only`` draw with in a strategy sample's slot
    (:meth:`ProductEnvironment.sample_environment`)."""

    si: mi.SurfaceInteraction3f
    bsdf: mi.BSDFPtr
    ctx: mi.BSDFContext
    u_component: mi.Float
    """The BSDF sample's 1D sample (its component's choice)."""
    lanes: mi.Bool
    """The lanes whose material runs ``bsdf_only`` (:meth:`ProductEnvironment.bsdf_alone`)."""


class CarriedSlots(NamedTuple):
    """How a lane of ``product_only`` draws its samples, for their balance weights
    (:meth:`ProductEnvironment.carried_weight`).

    Its emitter samples' slots draw from the product (the environment with probability
    ``selection``), its BSDF samples' slots from the BSDF with probability
    ``bsdf_in_slot`` and from the product otherwise. Only the BSDF slots draw from the
    BSDF: the same share drawn in every slot put nearly twice as many SIMD packets through
    the product's pdf walk (``product_only`` cost 0.77-0.83 lean passes per unit film
    share against 0.62-0.75 this way and 0.35-0.62 without the share: ``calibrate``,
    docs/MEASUREMENTS.md, "A BSDF share in product_only")."""

    frac_e: float
    """The emitter samples' share of the lane's samples."""
    frac_b: float
    """The BSDF samples' share."""
    selection: float | mi.Float
    """The probability that an emitter sample draws the environment (1 unless one emitter
    is drawn per sample)."""
    bsdf_in_slot: float
    """The probability that a BSDF sample's slot draws from the BSDF."""


def initial_emitter_selection(options) -> tuple[str, bool]:
    """(design, priced): ``sh_direct``'s ``emitter_selection`` as the kernel first runs it
    (``auto``: ``each`` until the plan prices both designs) and whether the plan prices them;
    ``each`` for the integrators without the option."""
    selection = getattr(options, "emitter_selection", "each")
    return ("one" if selection == "one" else "each"), selection == "auto"


class LaneLobe(NamedTuple):
    """The lobe proxy of each lane, in the two forms the product warp uses."""

    coeffs: list
    """SH coefficients (grid frame), for the SH levels."""
    proxy: ProxyLobe | None
    """The same proxy in closed form, for the levels below them (see ``proxy_depth``)."""
    bsdf_shared: mi.Bool | None = None
    """The lane's material gives the BSDF its share in ``product_only``
    (:meth:`ProductEnvironment.mixes_bsdf`); None where no lane can."""


class FrozenBeforePlanError(RuntimeError):
    """A ``dr.freeze`` recording reached an integrator that has no state for its scene yet."""


def _flat_values(value) -> mi.Float | None:
    """A parameter's values as one flat float array (tensors, colours, vectors, scalars),
    None for what has no such form (a transform)."""
    if dr.is_tensor_v(value):
        return mi.Float(dr.detach(value.array))
    if dr.is_array_v(value) and dr.depth_v(value) == 1:
        return mi.Float(dr.detach(value))
    if dr.is_array_v(value) and dr.depth_v(value) == 2 and not dr.is_matrix_v(value):
        return mi.Float(dr.ravel(dr.detach(value)))
    return None


_cycle_collections = 0
"""Python cycle collections run by :func:`collect_cycles` in this process."""


def collect_cycles() -> None:
    """Run Python's cycle collector (and count it: :func:`cycle_collections`). Objects of a
    dropped scene that only the collector frees are still registered with Dr.Jit until it
    runs, and its virtual calls would trace them."""
    global _cycle_collections
    gc.collect()
    _cycle_collections += 1


def cycle_collections() -> int:
    """How many :func:`collect_cycles` have run in this process (a caller that needs a
    collection since some point compares two counts; each costs ~20 ms)."""
    return _cycle_collections


class SceneCache:
    """Builds a per-scene state with ``build(scene)`` (:class:`ProductEnvironment`,
    the oracle's state), and again whenever the scene's inputs change.

    The state is built from the environment emitter's traversed parameters
    (``data``, ``scale``, ``to_world``) and those of every BSDF. Each
    :meth:`get` reads them again (on the host, no kernel) and compares
    their Dr.Jit variable indices: ``params.update()`` installs new variables,
    and a write into a parameter in place gets a new variable too, because the
    cache holds a second reference to the old one (copy on write). Holding
    those references also keeps the old indices from being recycled.

    The objects are traversed once per scene: a ``SceneParameters`` reads each
    value from the object when asked, so reading it again sees every update:
    0.16 ms a pass on the material studio and 0.02 ms on a sphere, against 1.1
    and 0.25 ms for traversing again, which each pass paid before.
    """

    def __init__(self, build: Callable[[mi.Scene], object]):
        self._build = build
        self._scene, self._env = None, None
        self._key, self._held = None, []
        self._traversed: list[mi.SceneParameters] = []

    @property
    def scene(self) -> mi.Scene | None:
        """The scene of the state held (None before the first :meth:`get`)."""
        return self._scene

    def get(self, scene: mi.Scene, stale_ok: bool = False, tolerance: float = 0.0):
        """The state ``build`` made for ``scene``, built again when its inputs changed;
        with ``stale_ok`` only for another scene (the inputs are not even read); with a
        ``tolerance`` > 0 only when they moved by more than it (:meth:`motion`).

        While ``dr.freeze`` records a function, the state made before is used as it is
        (a recording can neither read arrays on the host nor build), and a scene without
        one is a :class:`FrozenBeforePlanError`."""
        if dr.flag(dr.JitFlag.FreezingScope):
            if self._scene is not scene:
                raise FrozenBeforePlanError(
                    "the integrator's per-scene state (environment pyramid, lobe fits, plan) is built on "
                    "the host, which a dr.freeze recording cannot do: call integrator.plan(scene) before "
                    "the frozen function's first call, and again outside it to refresh the state")
            return self._env
        if self._scene is not scene or (not stale_ok and self._changed(tolerance)):
            # Objects of dropped scenes that only the cycle collector frees are still registered
            # with Dr.Jit, and its virtual calls trace them too: with two sunsky emitters that
            # aborted the process in LLVM ("invalid redefinition of function", tests/test_skies.py
            # on 2 workers, 6 runs in 8 before this line, 0 in 11 after). A build is host work of
            # a second or more; a collection is milliseconds.
            collect_cycles()
            # A rebuild for changed parameters: its builds stay in the process (build_cache).
            with kept_in_process() if self._scene is scene else contextlib.nullcontext(), \
                    kernels_compiled() as compiled:
                self._env = self._build(scene)
            #: What the build compiled (the plan's Info line adds the plan's: chooser.before_render).
            self._env.kernels_compiled = compiled.kernels
            self._scene = scene
            self._traversed = self._traverse(scene)
            # Read after the build, which may have sanitised the envmap's data.
            inputs = self._inputs()
            self._key = self._identity(inputs)
            # Detached references (None for host values): a copy of a parameter whose gradient is
            # enabled would be an AD edge from it, which a later forward-mode render must not traverse.
            self._held = [(dr.detach(value) if dr.is_diff_v(value) else type(value)(value))
                          if dr.detail.collect_indices(value) else None for value in inputs]
        return self._env

    def _changed(self, tolerance: float) -> bool:
        """The inputs changed since the build (moved by more than ``tolerance``, where > 0)."""
        inputs = self._inputs()
        if self._identity(inputs) == self._key:
            return False
        return tolerance <= 0 or self.motion(inputs) > tolerance

    def motion(self, inputs: list | None = None) -> float:
        """How far the inputs moved since the state was built: the largest, over the
        parameters that changed, of |x - x_built|_2 / |x_built|_2 (all values of one parameter
        together: texels, a colour's channels). Infinite where a host value (a transform, a
        flag) changed, a parameter appeared, went, changed shape or was zero. One reduction per changed
        parameter, read back together."""
        inputs = self._inputs() if inputs is None else inputs
        if len(inputs) != len(self._key):  # a parameter appeared or went
            return math.inf
        sums = []
        for value, key, held in zip(inputs, self._key, self._held):
            if held is None or tuple(dr.detail.collect_indices(value)) == key:
                if held is None and repr(value) != key:
                    return math.inf
                continue
            new, old = _flat_values(value), _flat_values(held)
            if new is None or old is None or dr.width(new) != dr.width(old):
                return math.inf
            sums += [dr.sum(dr.square(new - old)), dr.sum(dr.square(old))]
        if not sums:
            return 0.0
        dr.eval(*sums)
        worst = 0.0
        for change, size in zip(sums[::2], sums[1::2]):
            change, size = float(change[0]), float(size[0])
            worst = max(worst, math.sqrt(change / size) if size > 0 else (math.inf if change > 0 else 0.0))
        return worst

    @staticmethod
    def _traverse(scene: mi.Scene) -> list:
        """The traversed parameters of the environment emitter and of each distinct BSDF."""
        objects = [scene.environment()] + [m.bsdf for m in scene_materials(scene)]
        return [mi.traverse(obj) for obj in objects if obj is not None]

    def _inputs(self) -> list:
        """The current values of the traversed parameters."""
        values = []
        for params in self._traversed:
            values += [value for _, value in readable_parameters(params)]
        return values

    @staticmethod
    def _identity(values: list) -> tuple:
        """Each value's Dr.Jit variable indices, or its repr for host values."""
        return tuple(tuple(dr.detail.collect_indices(v)) or repr(v) for v in values)
