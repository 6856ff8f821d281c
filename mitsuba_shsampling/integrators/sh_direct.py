"""``sh_direct``: direct illumination with SH product sampling of the environment."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from .chooser import StrategyChooser
from .environment import BSDFAlone, ProductEnvironment
from .estimators import (bsdf_sample_of_emitters, dirac_sample_of_emitters, emitter_nee, first_hit, product_nee,
                         selected_emitter_nee)
from .options import DirectOptions, document_parameters
from .sharing import SceneSlot, plan, planned_render, shared_planning


@document_parameters(DirectOptions)
class SHDirectIntegrator(mi.SamplingIntegrator):
    r"""
    .. _integrator-sh_direct:

    SH product direct illumination (:monosp:`sh_direct`)
    ----------------------------------------------------

    .. pluginparameters::

    .. The rows are generated from integrators/options.py (DirectOptions).

    Like Mitsuba's :monosp:`direct`, but environment-map next-event estimation
    can draw directions in proportion to (BSDF lobe proxy) x (environment
    luminance) with the hierarchical product warp of
    :mod:`mitsuba_shsampling.warp.product`. Each material (BSDF instance) runs
    one environment strategy (``strategy``): the product, the product carrying
    every sample, the environment alone (with the BSDF samples or carrying every
    sample), or the BSDF's own sampling carrying every sample; with ``auto`` (the default) the
    one predicted to give the least error at equal time is chosen per
    material before the first pass. Strategy and BSDF samples are combined
    with the power heuristic using sample-count fractions, exactly as
    :monosp:`direct` combines its strategies. Other emitters (area, point,
    directional, ...) use Mitsuba's emitter sampling, drawn among themselves (the
    environment's share of Mitsuba's selection goes to its own sample), or with
    ``emitter_selection`` ``one`` a single emitter per sample; with ``auto`` (the default)
    the plan prices the two and runs the better. Transmissive BSDFs have no product
    lobe and sample the environment alone (MIS-compensated); ``bumpmap`` and
    ``normalmap`` are product-sampled with their nested BSDF's lobe about the
    perturbed normal; delta BSDFs
    and scenes without an ``envmap`` use Mitsuba's own sampling and build
    nothing. With ``bsdf_samples`` 0, unlike :monosp:`direct`, the Dirac
    components of a BSDF (glass, a plastic's coating, a mirror) still get one
    sample of their own, so nothing the emitters light is left black.
    ``integrator.plan(scene)`` makes the plan before the first render (which makes
    it otherwise) and returns it; ``integrator.choice(scene)`` returns it once made.
    The 2D sample of each product sample comes from the scene's sampler (``next_2d``), so stratification carries through the warp.
    """

    def __init__(self, props: mi.Properties):
        super().__init__(props)
        self.options = options = DirectOptions.from_properties(props)
        # Without BSDF samples every environment sample already carries the lane.
        carry_all = options.bsdf_samples > 0
        self.shared = shared_planning(
            options, (carry_all,), lambda scene: ProductEnvironment(scene, options, carry_all),
            lambda: StrategyChooser(options.emitter_samples, options.bsdf_samples, "direct", options.plan,
                                    options.plan_file))
        self.scenes, self.chooser = SceneSlot(self.shared), self.shared.chooser

    def prepare_scene(self, scene, sensor=0):
        """What :meth:`render` does on the host before it traces a pass: build (or
        rebuild) the per-scene state and, with ``strategy`` ``auto``, choose each
        material's strategy (pilot passes) the first time. Returns the state.
        :class:`~mitsuba_shsampling.frozen.FrozenPass` calls it before each replay,
        which runs no Python."""
        return self.chooser.prepare(self, self.scenes.get(scene), scene, sensor)

    render = planned_render(mi.SamplingIntegrator)
    plan = plan

    def choice(self, scene):
        """The strategy chosen for each material of ``scene``
        (:class:`~mitsuba_shsampling.integrators.chooser.StrategyChoice`), None before
        the first render or when ``strategy`` is forced or nothing is product-sampled."""
        return self.scenes.get(scene).choice

    def sample(self, scene, sampler, ray, medium=None, active=True):
        env, options = self.scenes.get(scene), self.options
        n_e, n_b, (frac_e, frac_b) = options.emitter_samples, options.bsdf_samples, options.sample_shares
        hit = first_hit(scene, ray, active, options.hide_emitters)
        L, si, bsdf, ctx, smooth = hit.emitted, hit.si, hit.bsdf, hit.ctx, hit.smooth

        lobe, use_product = env.lobe(si, smooth)
        # Lanes of materials whose strategy carries every sample (product_only,
        # environment_only, bsdf_only) give it the BSDF samples' share too, drawn from the
        # uncompensated map; the others combine one strategy per sample type under MIS.
        carries_all = env.carries_all(si, bsdf, smooth) if n_b > 0 else False

        # ------ Environment: product (or environment-alone) sampling; other emitters: Mitsuba's ------
        # With other emitters and `emitter_selection` `one`, each sample draws one emitter first.
        one_emitter = env.emitter_selection == "one" and env.active and env.has_other_emitters
        # In product_only's lanes the BSDF samples' slots draw from the BSDF or the product
        # and every sample gets the balance weight over the slots (environment.CarriedSlots).
        draws_bsdf = carries_all is not False and env.draws_bsdf
        # In bsdf_only's lanes every slot draws from the BSDF: a 1D sample more per slot, for its
        # component (drawn only where some material runs it, so other plans keep their sample streams).
        alone_lanes = env.bsdf_alone(si, smooth) if carries_all is not False else False

        def alone(u_component):
            return None if alone_lanes is False else BSDFAlone(si, bsdf, ctx, u_component, alone_lanes)
        slots = env.carried_slots(frac_e, frac_b, env.selection if one_emitter else 1.0) if env.active else None
        for _ in range(n_e):
            nee = selected_emitter_nee if one_emitter else product_nee
            u = sampler.next_2d(smooth)
            drawn_alone = alone(sampler.next_1d(smooth)) if alone_lanes is not False else None
            L += nee(env, scene, u, si, bsdf, ctx, lobe=lobe, use_product=use_product, smooth=smooth,
                     carries_all=carries_all, frac_e=frac_e, frac_b=frac_b, slots=slots, alone=drawn_alone) / n_e
        for _ in range(0 if one_emitter else n_e):
            L += emitter_nee(env, scene, sampler, si, bsdf, ctx, smooth, frac_e, frac_b, carries_all) / n_e

        # The emitter strategy of a BSDF-sampled direction: the lane's environment
        # strategy for the environment (times its selection probability where one emitter
        # is drawn), Mitsuba's sampling (its own selection included) for other emitters.
        def strategy_pdf(emitter, d, act, mitsuba_pdf):
            act = act & env.is_environment(emitter) if env.active else act
            env_pdf = env.pdf(lobe, use_product, d, act)
            if one_emitter:
                return env.hit_pdf(emitter, env_pdf * env.selection, mitsuba_pdf, others_only=False)
            return env.hit_pdf(emitter, env_pdf, mitsuba_pdf)


        # ------- BSDF sampling (a further strategy sample where the strategy carries all) -------
        for _ in range(n_b):
            sample_1, sample_2 = sampler.next_1d(hit.active), sampler.next_2d(hit.active)
            if carries_all is False:  # no such lane: not even a branch is traced
                L += bsdf_sample_of_emitters(scene, hit, sample_1, sample_2, strategy_pdf, frac_e, frac_b,
                                             env.needs_emitter_sampling) / n_b
                continue
            L += dr.if_stmt(
                args=(sample_1, sample_2), cond=carries_all,
                # A strategy sample in a BSDF sample's slot: its share of the lane's samples is frac_b.
                true_fn=lambda u1, u: product_nee(env, scene, u, si, bsdf, ctx, lobe=lobe, use_product=use_product,
                                                  smooth=smooth, carries_all=True, share=frac_b,
                                                  u_choice=u1 if draws_bsdf else None, slots=slots,
                                                  alone=alone(u1)) / n_b,
                false_fn=lambda u1, u2: bsdf_sample_of_emitters(scene, hit, u1, u2, strategy_pdf,
                                                                frac_e, frac_b, env.needs_emitter_sampling) / n_b)

        # Without BSDF samples nothing else reaches a Dirac component (Mitsuba's direct then
        # leaves it black): one sample of those components alone, where the scene has any.
        if n_b == 0 and env.has_dirac_materials:
            L += dirac_sample_of_emitters(scene, hit, sampler.next_1d(hit.active), sampler.next_2d(hit.active))

        sees_environment = not options.hide_emitters and scene.environment() is not None
        return L, si.is_valid() | sees_environment, []

    def to_string(self):
        return f"SHDirectIntegrator[{self.options}]"
