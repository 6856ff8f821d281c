"""Per-scene state of the SH product strategy, shared by the integrators.

Built once per scene, on the host, before the first render pass (never while a
pass is being traced): the environment pyramid, the BSDF lobe table and the
product warp. A scene without an environment map, or whose BSDFs are all
delta/unsupported, builds nothing and the integrators behave like their
Mitsuba counterparts.
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
from ..warp.product import ProductWarp
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
    ``pyramid``, ``lobes``, ``warp``, ``needs_emitter_sampling`` (bool:
    Mitsuba's emitter sampling has work to do besides the environment).
    """

    def __init__(self, scene: mi.Scene, options: ProductOptions, plain_product: bool = False):
        self.scene = scene
        self.emitter = scene.environment()
        self.pyramid = self.lobes = self.warp = None
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
        if not self.lobes.has_product_lobes:
            self.reason = "no BSDF in the scene has a lobe worth product sampling (all delta or unsupported)"
            return
        self.pyramid = EnvPyramid(self.emitter, mis_compensation=options.mis_compensation)
        if self.pyramid.is_black:
            self.reason = "the environment map is black"
            return
        warp_options = dict(sh_depth=options.warp_sh_depth, defensive_share=options.defensive_share,
                            proxy_depth=options.warp_proxy_depth)
        self.warp = ProductWarp(self.pyramid, **warp_options)
        #: The product with the map itself (not compensated): the strategy of
        #: lanes where it carries every sample, so that nothing is left to a
        #: BSDF sample that does not run there. The same warp when the scene's
        #: pyramid is not compensated; built only on request (``plain_product``,
        #: a second pyramid) otherwise, and None without it.
        self.warp_plain = self.warp
        if self.pyramid.mis_compensation:
            self.warp_plain = ProductWarp(EnvPyramid(self.emitter), **warp_options) if plain_product else None
        self.active = True
        self.reason = ""
        # Mitsuba's emitter sampling is only traced when some lane can use it:
        # other emitters, or smooth BSDFs without a product lobe.
        self.needs_emitter_sampling = bool(other_emitters) or self.lobes.has_unsupported_lobes

    # Per-lane pieces shared by the integrators. When the scene does not use
    # product sampling they reduce to Mitsuba's own strategies and trace nothing.

    def lobe(self, si: mi.SurfaceInteraction3f, smooth: mi.Bool):
        """(lobe, use_product): the lobe proxy at ``si`` in the grid frame
        (:class:`LaneLobe`); (None, False) where product sampling does not run."""
        if not self.active:
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

    def pdf(self, lobe, d: mi.Vector3f, active: mi.Bool) -> mi.Float:
        """Product-sampling pdf of world direction ``d`` (0 where inactive)."""
        if not self.active:
            return mi.Float(0.0)
        # A symbolic branch: a SIMD packet with no lane that needs the walk
        # (sky, delta or occluded BSDF samples) skips it.
        return dr.if_stmt(args=(lobe, d), cond=mi.Bool(active),
                          true_fn=lambda c, v: self.warp.pdf(c.coeffs, v, c.proxy),
                          false_fn=lambda c, v: mi.Float(0.0))

    def hit_pdf(self, emitter, use_product: mi.Bool, product_pdf, emitter_pdf):
        """Emitter-strategy pdf of a BSDF-sampled ray that hit ``emitter``: the
        product pdf for the environment in product lanes, Mitsuba's otherwise."""
        if not self.active:
            return emitter_pdf
        return dr.select(use_product & self.is_environment(emitter), product_pdf, emitter_pdf)

    def product_nee(self, scene, u, si, bsdf, ctx, lobe, use_product, product_only, frac_e, frac_b):
        """One product sample of the environment (BSDF value x radiance / pdf).

        In ``product_only`` lanes (:meth:`product_carries_all`) it is one of
        the lane's equally weighted samples: weight ``frac_e``. Elsewhere it
        is power-heuristic weighted against BSDF sampling with the
        strategies' sample-count fractions."""
        if not self.active:
            return mi.Spectrum(0.0)
        # Packets without a product lane (sky, delta BSDFs, unsupported lobes) skip the walk.
        d, pdf_p = dr.if_stmt(args=(lobe, u), cond=mi.Bool(use_product),
                              true_fn=lambda c, v: self.sample_product(c, v, product_only),
                              false_fn=lambda c, v: (mi.Vector3f(0.0, 0.0, 1.0), mi.Float(0.0)))
        act = use_product & (pdf_p > 0)
        bsdf_val, bsdf_pdf = bsdf.eval_pdf(ctx, si, si.to_local(d), act)
        act &= ~scene.ray_test(si.spawn_ray(d), act)
        Le = self.emitter.eval(environment_ray_target(d), act)
        weight = dr.select(product_only, frac_e, mis_weight(pdf_p * frac_e, bsdf_pdf * frac_b))
        return dr.select(act, bsdf_val * Le * (weight / pdf_p), 0.0)

    def emitter_nee(self, scene, sampler, si, bsdf, ctx, use_product, smooth, frac_e, frac_b,
                    product_only=False):
        """One sample of Mitsuba's emitter sampling, without the environment's
        share in product lanes (that belongs to :meth:`product_nee`); not
        traced at all when no lane can use it. In ``product_only`` lanes no
        BSDF sample runs, so its weight is 1."""
        if not self.needs_emitter_sampling:
            return mi.Spectrum(0.0)
        def left_out(emitter):
            return use_product & self.is_environment(emitter) if self.active else mi.Bool(False)

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
