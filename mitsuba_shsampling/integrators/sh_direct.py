"""``sh_direct``: direct illumination with SH product sampling of the environment."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from .environment import ProductEnvironment, SceneCache
from .estimators import bsdf_sample_of_emitters, first_hit
from .options import DirectOptions, document_parameters


@document_parameters(DirectOptions)
class SHDirectIntegrator(mi.SamplingIntegrator):
    r"""
    .. _integrator-sh_direct:

    SH product direct illumination (:monosp:`sh_direct`)
    ----------------------------------------------------

    .. pluginparameters::

    .. The rows are generated from integrators/options.py (DirectOptions).

    Like Mitsuba's :monosp:`direct`, but environment-map next-event estimation
    draws directions in proportion to (BSDF lobe proxy) x (environment
    luminance) with the hierarchical product warp of
    :mod:`mitsuba_shsampling.warp.product`. Product and BSDF samples are
    combined with the power heuristic using sample-count fractions, exactly as
    :monosp:`direct` combines its strategies. Other emitters (area, point,
    ...) use Mitsuba's emitter sampling. BSDFs without a product lobe
    (anisotropic, transmissive, ``bumpmap``/``normalmap``) sample the
    environment alone from the same (MIS-compensated) pyramid; delta BSDFs
    and scenes without an ``envmap`` use Mitsuba's own sampling and build
    nothing. The 2D sample of each product sample comes from the
    scene's sampler (``next_2d``), so stratification carries through the warp.

    .. tabs::
        .. code-tab:: xml

            <integrator type="sh_direct">
                <integer name="emitter_samples" value="1"/>
                <integer name="bsdf_samples" value="1"/>
            </integrator>

        .. code-tab:: python

            'type': 'sh_direct', 'emitter_samples': 1, 'bsdf_samples': 1
    """

    def __init__(self, props: mi.Properties):
        super().__init__(props)
        self.options = options = DirectOptions.from_properties(props)
        # Lanes that give every sample to the product need the uncompensated
        # product: built only when allocation can happen.
        plain_product = options.product_allocation and options.bsdf_samples > 0
        self.scenes = SceneCache(lambda scene: ProductEnvironment(scene, options, plain_product))

    def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
        self.scenes.get(scene)  # build host-side state before tracing the pass
        return super().render(scene, sensor, seed, spp, develop, evaluate)

    def sample(self, scene, sampler, ray, medium=None, active=True):
        env = self.scenes.get(scene)
        options = self.options
        hit = first_hit(scene, ray, active, options.hide_emitters)
        si, bsdf, ctx, smooth = hit.si, hit.bsdf, hit.ctx, hit.smooth
        L = hit.emitted
        n_e, n_b = options.emitter_samples, options.bsdf_samples
        frac_e, frac_b = n_e / (n_e + n_b), n_b / (n_e + n_b)

        lobe, use_product = env.lobe(si, smooth)
        # Lanes where the product alone follows the integrand give it every
        # sample (drawn from the uncompensated map); the others combine one
        # strategy per sample type under MIS.
        product_only = env.product_carries_all(si, bsdf, use_product) if options.product_allocation and n_b > 0 else False

        # ------ Environment: product (or environment-alone) sampling; other emitters: Mitsuba's ------
        for _ in range(n_e):
            L += env.product_nee(scene, sampler.next_2d(smooth), si, bsdf, ctx, lobe,
                                 use_product, smooth, product_only, frac_e, frac_b) / n_e
        for _ in range(n_e):
            L += env.emitter_nee(scene, sampler, si, bsdf, ctx, smooth, frac_e, frac_b, product_only) / n_e

        # The emitter strategy of a BSDF-sampled direction: the lane's environment
        # strategy for the environment, Mitsuba's sampling for other emitters.
        def strategy_pdf(emitter, d, act, mitsuba_pdf):
            act = act & env.is_environment(emitter) if env.active else act
            return env.hit_pdf(emitter, env.pdf(lobe, use_product, d, act), mitsuba_pdf)

        # ------------- BSDF sampling (a further product sample in product-only lanes) -------------
        for _ in range(n_b):
            sample_1, sample_2 = sampler.next_1d(hit.active), sampler.next_2d(hit.active)
            if product_only is False:  # no allocation: not even a branch is traced
                L += bsdf_sample_of_emitters(scene, hit, sample_1, sample_2, strategy_pdf, frac_e, frac_b) / n_b
                continue
            L += dr.if_stmt(
                args=(sample_1, sample_2), cond=product_only,
                # A product sample whose share of the lane's samples is frac_b.
                true_fn=lambda _, u: env.product_nee(scene, u, si, bsdf, ctx, lobe, use_product, smooth,
                                                     mi.Bool(True), frac_b, frac_e) / n_b,
                false_fn=lambda u1, u2: bsdf_sample_of_emitters(scene, hit, u1, u2, strategy_pdf,
                                                                frac_e, frac_b) / n_b)

        sees_environment = not options.hide_emitters and scene.environment() is not None
        return L, si.is_valid() | sees_environment, []

    def to_string(self):
        return f"SHDirectIntegrator[{self.options}]"
