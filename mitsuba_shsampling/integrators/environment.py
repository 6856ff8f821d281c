"""Per-scene state of the SH product strategy, shared by the integrators.

Built once per scene, on the host, before the first render pass (never while a
pass is being traced): the environment pyramid, the BSDF lobe table and the
product warp. A scene without an environment map, or whose BSDFs are all
delta/unsupported, builds nothing and the integrators behave like their
Mitsuba counterparts.

Where it is built, the environment is sampled by this package at every shading
point with a smooth BSDF: the product where the BSDF has a product lobe, the
environment alone (:class:`~mitsuba_shsampling.warp.product.EnvironmentWarp`, on
the same pyramid, so MIS-compensated like the product) where it has none
(anisotropic, transmissive and frame-perturbing BSDFs). Mitsuba's emitter
sampling is left with the other emitters.
"""

from __future__ import annotations

import warnings
from typing import Callable, NamedTuple

import drjit as dr
import mitsuba as mi

from ..envmap.pyramid import EnvPyramid
from ..lobes import SceneLobes
from ..lobes.scene_lobes import registry_id
from ..traversal import readable_parameters
from ..warp.product import EnvironmentWarp, ProductWarp
from ..warp.proxy_lobe import ProxyLobe
from .estimators import environment_ray_target, is_emitter, mis_weight, mitsuba_emitter_sample
from .options import ProductOptions


class ProductEnvironment:
    """Environment product sampling for one scene.

    Built from the plugin's checked ``options`` (``max_bands``, ``sh_depth``,
    ``proxy_depth``, ``mis_compensation``, ``defensive_share``); ``plain_product``
    also builds the product with the uncompensated map (:attr:`warp_plain`).

    Attributes: ``emitter`` (the envmap or None), ``active`` (bool: product
    sampling runs for this scene), ``reason`` (why not, when inactive),
    ``pyramid``, ``lobes``, ``warp``, ``env_warp`` (the environment alone, for
    smooth lanes without a product lobe), ``needs_emitter_sampling`` (bool:
    Mitsuba's emitter sampling has work to do: emitters besides the environment).
    """

    def __init__(self, scene: mi.Scene, options: ProductOptions, plain_product: bool = False):
        self.scene = scene
        self.emitter = scene.environment()
        self.pyramid = self.lobes = self.warp = self.env_warp = None
        self.active = False
        self.needs_emitter_sampling = True
        other_emitters = [e for e in scene.emitters() if self.emitter is None or e is not self.emitter]
        if self.emitter is None:
            self.reason = "the scene has no environment emitter"
            return
        if self.emitter.class_name() != "EnvironmentMapEmitter":
            self.reason = (f"the environment emitter is '{self.emitter.class_name()}', not an 'envmap'; "
                           "it keeps Mitsuba's own sampling")
            warnings.warn(f"mitsuba_shsampling: {self.reason}")
            return
        self.lobes = SceneLobes(scene, max_bands=options.max_bands)
        if not (self.lobes.has_product_lobes or self.lobes.has_unsupported_lobes):
            self.reason = "every BSDF in the scene is delta: no shading point samples the environment"
            return
        self.pyramid = EnvPyramid(self.emitter, mis_compensation=options.mis_compensation)
        if self.pyramid.is_black:
            self.reason = "the environment map is black"
            return
        self.env_warp = EnvironmentWarp(self.pyramid)
        #: The product with the map itself (not compensated): the strategy of
        #: lanes where it carries every sample, so that nothing is left to a
        #: BSDF sample that does not run there. The same warp when the scene's
        #: pyramid is not compensated; built only on request (``plain_product``,
        #: a second pyramid) otherwise, and None without it.
        self.warp_plain = None
        if self.lobes.has_product_lobes:
            warp_options = dict(sh_depth=options.warp_sh_depth, defensive_share=options.defensive_share,
                                proxy_depth=options.warp_proxy_depth)
            self.warp = self.warp_plain = ProductWarp(self.pyramid, **warp_options)
            if self.pyramid.mis_compensation:
                self.warp_plain = ProductWarp(EnvPyramid(self.emitter), **warp_options) if plain_product else None
        self.active = True
        self.reason = ""
        # Mitsuba's emitter sampling is only traced when some lane can use it: every
        # smooth lane samples the environment through this object.
        self.needs_emitter_sampling = bool(other_emitters)

    # Per-lane pieces shared by the integrators. When the scene does not use
    # product sampling they reduce to Mitsuba's own strategies and trace nothing.

    def lobe(self, si: mi.SurfaceInteraction3f, smooth: mi.Bool):
        """(lobe, use_product): the lobe proxy at ``si`` in the grid frame
        (:class:`LaneLobe`); (None, False) where product sampling does not run."""
        if self.warp is None:
            return None, mi.Bool(False)
        coeffs, proxy, use_product = self.lobes.coefficients_and_proxy(si, self.pyramid.grid_from_world, smooth)
        return LaneLobe(coeffs, proxy), use_product & smooth

    def product_carries_all(self, si, bsdf, use_product: mi.Bool) -> mi.Bool:
        """Per lane: the product alone follows the integrand closely (its lobe
        needs no widening, :meth:`SceneLobes.represents_exactly`) and the BSDF
        has no Dirac part, so every sample of the lane goes to the product,
        drawn from the map itself (coverage without a BSDF sample). False
        (no lane) when the uncompensated product was not built."""
        if not self.active or self.warp_plain is None:
            return False
        no_delta = ~mi.has_flag(bsdf.flags(), mi.BSDFFlags.Delta)
        return use_product & no_delta & self.lobes.represents_exactly(si, use_product)

    def sample_product(self, lobe, u: mi.Point2f, plain):
        """(direction, exact pdf) of one product sample: from :attr:`warp_plain`
        in ``plain`` lanes, from :attr:`warp` in the others (a symbolic branch,
        so a SIMD packet runs only the walk its lanes need).

        Diffuse lanes walk all the bands: a further branch with only the 3
        that describe them cost more (a larger kernel) than it saved
        (docs/MEASUREMENTS.md, "Product allocation")."""
        if plain is False or self.warp_plain is self.warp:
            return self.warp.sample(lobe.coeffs, u, lobe.proxy)
        return dr.if_stmt(args=(lobe, u), cond=plain,
                          true_fn=lambda c, v: self.warp_plain.sample(c.coeffs, v, c.proxy),
                          false_fn=lambda c, v: self.warp.sample(c.coeffs, v, c.proxy))

    def sample_environment(self, lobe, u: mi.Point2f, use_product, product_only):
        """(direction, exact pdf) of one sample of the lane's environment strategy: the
        product (:meth:`sample_product`) in ``use_product`` lanes, the environment alone
        elsewhere. Symbolic branches: a SIMD packet runs only the walks its lanes need."""
        if self.warp is None:
            return self.env_warp.sample(u)
        return dr.if_stmt(args=(lobe, u), cond=mi.Bool(use_product),
                          true_fn=lambda c, v: self.sample_product(c, v, product_only),
                          false_fn=lambda c, v: self.env_warp.sample(v))

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
                             true_fn=lambda v: self.env_warp.pdf(v),
                             false_fn=lambda v: mi.Float(0.0))
        if self.warp is None:
            return env_pdf
        product_pdf = dr.if_stmt(args=(lobe, d), cond=active & use_product,
                                 true_fn=lambda c, v: self.warp.pdf(c.coeffs, v, c.proxy),
                                 false_fn=lambda c, v: mi.Float(0.0))
        return dr.select(use_product, product_pdf, env_pdf)

    def hit_pdf(self, emitter, strategy_pdf, emitter_pdf):
        """Emitter-strategy pdf of a BSDF-sampled ray that hit ``emitter``: the lane's
        environment strategy (:meth:`pdf`) for the environment, Mitsuba's otherwise."""
        if not self.active:
            return emitter_pdf
        return dr.select(self.is_environment(emitter), strategy_pdf, emitter_pdf)

    def product_nee(self, scene, u, si, bsdf, ctx, lobe, use_product, smooth, product_only,
                    frac_e, frac_b):
        """One sample of the environment (BSDF value x radiance / pdf) in the ``smooth``
        lanes: from the product in ``use_product`` lanes, from the environment alone in
        the others (:meth:`sample_environment`).

        In ``product_only`` lanes (:meth:`product_carries_all`) it is one of
        the lane's equally weighted samples: weight ``frac_e``. Elsewhere it
        is power-heuristic weighted against BSDF sampling with the
        strategies' sample-count fractions."""
        if not self.active:
            return mi.Spectrum(0.0)
        smooth = mi.Bool(smooth)
        # Packets without a smooth lane (sky, delta BSDFs) skip the walks.
        d, pdf_e = dr.if_stmt(args=(lobe, u), cond=smooth,
                              true_fn=lambda c, v: self.sample_environment(c, v, use_product, product_only),
                              false_fn=lambda c, v: (mi.Vector3f(0.0, 0.0, 1.0), mi.Float(0.0)))
        act = smooth & (pdf_e > 0)
        bsdf_val, bsdf_pdf = bsdf.eval_pdf(ctx, si, si.to_local(d), act)
        act &= ~scene.ray_test(si.spawn_ray(d), act)
        Le = self.emitter.eval(environment_ray_target(d), act)
        weight = dr.select(product_only, frac_e, mis_weight(pdf_e * frac_e, bsdf_pdf * frac_b))
        return dr.select(act, bsdf_val * Le * (weight / pdf_e), 0.0)

    def emitter_nee(self, scene, sampler, si, bsdf, ctx, smooth, frac_e, frac_b, product_only=False):
        """One sample of Mitsuba's emitter sampling, without the environment's
        share where this object samples it (:meth:`product_nee`); not traced at all
        when no lane can use it. In ``product_only`` lanes no BSDF sample runs, so
        its weight is 1."""
        if not self.needs_emitter_sampling:
            return mi.Spectrum(0.0)
        def left_out(emitter):
            return self.is_environment(emitter) if self.active else mi.Bool(False)

        return mitsuba_emitter_sample(scene, sampler.next_2d(smooth), si, bsdf, ctx, smooth, left_out,
                                      frac_e, frac_b, weight_one=product_only)

    def is_environment(self, emitter: mi.EmitterPtr) -> mi.Bool:
        """Per-lane test: is ``emitter`` the environment map."""
        return is_emitter(emitter, self.emitter)


class LaneLobe(NamedTuple):
    """The lobe proxy of each lane, in the two forms the product warp uses."""

    coeffs: list
    """SH coefficients (grid frame), for the SH levels."""
    proxy: ProxyLobe | None
    """The same proxy in closed form, for the levels below them (see ``proxy_depth``)."""


class SceneCache:
    """Builds a per-scene state with ``build(scene)`` (:class:`ProductEnvironment`,
    the oracle's state), and again whenever the scene's inputs change.

    The state is built from the environment emitter's traversed parameters
    (``data``, ``scale``, ``to_world``) and those of every BSDF. Each
    :meth:`get` traverses them again (on the host, no kernel) and compares
    their Dr.Jit variable indices: ``params.update()`` installs new variables,
    and a write into a parameter in place gets a new variable too, because the
    cache holds a second reference to the old one (copy on write). Holding
    those references also keeps the old indices from being recycled.
    """

    def __init__(self, build: Callable[[mi.Scene], object]):
        self._build = build
        self._scene, self._env = None, None
        self._key, self._held = None, []

    def get(self, scene: mi.Scene):
        """The state ``build`` made for ``scene``, built again when its inputs changed."""
        if self._scene is not scene or self._identity(self._inputs(scene)) != self._key:
            self._env = self._build(scene)
            self._scene = scene
            # Read after the build, which may have sanitised the envmap's data.
            inputs = self._inputs(scene)
            self._key = self._identity(inputs)
            self._held = [type(value)(value) for value in inputs if dr.detail.collect_indices(value)]
        return self._env

    @staticmethod
    def _inputs(scene: mi.Scene) -> list:
        """Traversed parameter values of the environment emitter and of each distinct BSDF."""
        objects = [scene.environment()]
        seen = set()
        for shape in scene.shapes():
            bsdf = shape.bsdf()
            if bsdf is not None and registry_id(bsdf) not in seen:
                seen.add(registry_id(bsdf))
                objects.append(bsdf)
        values = []
        for obj in objects:
            if obj is not None:
                values += [value for _, value in readable_parameters(mi.traverse(obj))]
        return values

    @staticmethod
    def _identity(values: list) -> tuple:
        """Each value's Dr.Jit variable indices, or its repr for host values."""
        return tuple(tuple(dr.detail.collect_indices(v)) or repr(v) for v in values)
