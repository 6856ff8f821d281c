"""``sh_prb``: path replay backpropagation with SH product sampling for environment NEE."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from .chooser import StrategyChooser
from .environment import ProductEnvironment
from .estimators import environment_ray_target, mis_weight, mitsuba_hit_pdf
from .options import PRBOptions, document_parameters
from .sharing import plan, shared_planning

# Mitsuba's base of the replay integrators (primal pass, then the same paths again with adjoint
# radiance); bound to the variant active when this module runs, like the class below.
RBIntegrator = mi.ad.integrators.common.RBIntegrator


@document_parameters(PRBOptions)
class SHPRBIntegrator(RBIntegrator):
    r"""
    .. _integrator-sh_prb:

    SH product path replay backpropagation (:monosp:`sh_prb`)
    ---------------------------------------------------------

    .. pluginparameters::

    .. The rows are generated from integrators/options.py (PRBOptions).

    Mitsuba's :monosp:`prb` (path replay backpropagation, :cite:`Vicini2021`)
    with the next-event estimation of :monosp:`sh_path`: at every vertex whose
    BSDF has a smooth lobe, the environment map is sampled with the strategy of
    the vertex's material (``strategy``): from the product of the BSDF lobe
    proxy and the map, or from the map alone (with ``auto``, chosen per
    material before the first pass of each sampling state, as in
    :monosp:`sh_path`; the product at the first ``product_depth`` vertices, the
    map alone deeper), and combined with the BSDF sample that continues the
    path by the power heuristic (one sample each). Other emitters keep
    Mitsuba's emitter sampling; without an ``envmap`` it runs like :monosp:`prb`.

    The primal pass estimates the image and the total radiance of each path;
    the replay pass draws the same random numbers, so it follows the same
    paths with the same environment samples, and propagates adjoint radiance
    into the scene parameters at every vertex. As in :monosp:`prb`, sampling
    is *detached*: directions, pdfs and MIS weights carry no derivatives
    (the product's lobes and pyramid are built from the parameters' values,
    outside the AD graph); the BSDF values and the emitter values
    (``envmap`` ``data`` and ``scale``, area-light radiance) are
    differentiated. So material and emitter parameters get unbiased
    gradients; geometric parameters (vertex positions, transforms) and the
    parameters of Dirac BSDFs get none, and :monosp:`prb`'s partial
    treatment of moving surfaces is not reproduced. ``hide_emitters``
    hides what the camera sees directly, as in :monosp:`path` and
    :monosp:`sh_path` (it does not look through area emitters as
    :monosp:`prb` does).

    The sampling state (the environment pyramid, the lobe table) is built from
    the scene's parameters before the first render and rebuilt when they
    change, at most once every ``rebuild_interval`` renders: an optimisation
    changes them at every step, and a build costs many passes' time on a
    scene with many materials. In between, the state of slightly older
    parameters keeps images and gradients unbiased.

    .. tabs::
        .. code-tab:: xml

            <integrator type="sh_prb">
                <integer name="max_depth" value="6"/>
            </integrator>

        .. code-tab:: python

            'type': 'sh_prb', 'max_depth': 6
    """

    def __init__(self, props: mi.Properties):
        # Checked before Mitsuba's base reads max_depth and rr_depth, so that a bad value is
        # reported as an OptionError naming this plugin.
        options = PRBOptions.from_properties(props)
        super().__init__(props)
        self.options = options
        self.max_depth = options.depth_limit
        self.product_depth = options.product_depth_limit
        self.rr_depth = options.rr_depth

        def build(scene):
            # Optimised parameters (envmap texels, a roughness) may have gradients enabled:
            # the sampling state only needs their values and stays out of the AD graph.
            with dr.suspend_grad():
                return ProductEnvironment(scene, options)

        # One environment sample and one BSDF sample per vertex, as in sh_path.
        self.shared = shared_planning(
            options, (), build, lambda: StrategyChooser(1, 1, "path", options.plan, options.plan_file))
        self.scenes, self.chooser = self.shared.scenes, self.shared.chooser
        self._state, self._renders_since_build = None, 0

    # The per-scene state is built on the host before a pass is traced. A primal
    # render rebuilds it when its inputs changed (at most every rebuild_interval
    # renders), and with strategy auto chooses each material's strategy for a new
    # state (pilot primal passes); the derivative passes, which replay the primal
    # pass themselves, and the traced passes take it as it is.

    def prepare_scene(self, scene, sensor=0):
        """The host-side work before a pass (see ``sh_direct``'s), with the state rebuilt
        at most every ``rebuild_interval`` renders."""
        stale_ok = self._renders_since_build + 1 < self.options.rebuild_interval
        state = self.scenes.get(scene, stale_ok=stale_ok)
        self._renders_since_build = 0 if state is not self._state else self._renders_since_build + 1
        self._state = state
        def pilot_pass(pilot_spp, pilot_seed):
            return super(SHPRBIntegrator, self).render(scene, sensor, pilot_seed, pilot_spp)

        self.chooser.before_render(state, scene, sensor, pilot_pass, self)
        return state

    def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
        if not self.chooser.piloting:  # a pilot pass (StrategyChooser.piloting) renders as configured
            self.prepare_scene(scene, sensor)
        return super().render(scene, sensor, seed, spp, develop, evaluate)

    plan = plan

    def choice(self, scene):
        """The strategy chosen for each material of ``scene`` (see ``sh_direct``)."""
        return self.scenes.get(scene, stale_ok=True).choice

    def render_forward(self, scene, params, sensor=0, seed=0, spp=0):
        self.scenes.get(scene, stale_ok=True)
        return super().render_forward(scene, params, sensor, seed, spp)

    def render_backward(self, scene, params, grad_in, sensor=0, seed=0, spp=0):
        self.scenes.get(scene, stale_ok=True)
        return super().render_backward(scene, params, grad_in, sensor, seed, spp)

    @dr.syntax
    def sample(self, mode: dr.ADMode, scene: mi.Scene, sampler: mi.Sampler, ray: mi.Ray3f,
               δL: mi.Spectrum | None, state_in: mi.Spectrum | None, active: mi.Bool, **kwargs):
        """One path per lane: in ``Primal`` mode its radiance (returned twice: the image and
        the replay's input ``state_in``); in ``Forward``/``Backward`` mode the same path
        again, returning (forward) or propagating (backward, from ``δL``) derivatives.
        See ``ADIntegrator.sample`` in Mitsuba for the interface."""
        primal = mode == dr.ADMode.Primal
        # As Mitsuba's path: max_depth 0 renders nothing (not even emitters, alpha 0).
        if dr.hint(self.options.max_depth == 0, mode="scalar"):
            return mi.Spectrum(0.0), mi.Bool(False), [], mi.Spectrum(0.0)
        env = self.scenes.get(scene, stale_ok=True)
        hide_emitters = self.options.hide_emitters
        ctx = mi.BSDFContext()

        # --------------------- Configure loop state ----------------------
        ray = mi.Ray3f(dr.detach(ray))
        active = mi.Bool(active)
        # Primal: radiance gathered so far. Replay: radiance still to be gathered
        # further along the path (the primal total, minus each vertex's share).
        L = mi.Spectrum(0.0 if primal else state_in)
        δL = mi.Spectrum(δL if δL is not None else 0.0)
        β = mi.Spectrum(1.0)
        η = mi.Float(1.0)
        depth = mi.UInt32(0)
        valid_ray = mi.Bool(not hide_emitters and scene.environment() is not None)
        prev_si = dr.zeros(mi.Interaction3f)
        prev_bsdf_pdf = mi.Float(1.0)
        prev_bsdf_delta = mi.Bool(True)
        # Pdf of the current ray under the previous vertex's environment strategy.
        prev_env_pdf = mi.Float(0.0)
        # Each ray is intersected where it is spawned (as sh_path does: the vertex that
        # sampled it evaluates its environment pdf only if it escapes); camera rays coherently.
        hit = scene.ray_intersect_preliminary(ray, coherent=True, active=active)

        while dr.hint(active, max_iterations=self.max_depth, label=f"sh_prb ({mode.name})"):
            si = hit.compute_surface_interaction(ray, mi.RayFlags.All, active)
            bsdf = si.bsdf(ray)

            # ---------------- Emitter hit by the BSDF-sampled ray ----------------
            emitter = si.emitter(scene, active)
            # (Mitsuba's pdf only where Mitsuba samples some emitter.)
            em_pdf = env.hit_pdf(emitter, prev_env_pdf, mitsuba_hit_pdf(
                scene, si, prev_si, active & ~prev_bsdf_delta, env.needs_emitter_sampling))
            em_pdf = dr.select(prev_bsdf_delta, 0.0, em_pdf)
            visible = active & ((depth > 0) | (not hide_emitters))
            with dr.resume_grad(when=not primal):
                Le = dr.select(visible, β * mis_weight(prev_bsdf_pdf, em_pdf) * emitter.eval(si, visible), 0.0)

            active_next = active & si.is_valid() & (depth + 1 < self.max_depth)
            valid_ray |= active & si.is_valid()

            # -------------------------- Next-event estimation --------------------------
            # Sampled without derivatives (the lobe, the direction and its pdf), so
            # that the replay draws the same direction; evaluated with them.
            smooth = active_next & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
            lobe, use_product = env.lobe(si, smooth & (depth < self.product_depth))
            # Random numbers drawn as Mitsuba's prb draws them (as ``sh_path``: see there).
            Lr_env = self.environment_sample(env, scene, sampler.next_2d(active), si, bsdf, ctx,
                                             lobe, use_product, smooth, primal)
            Lr_em = mi.Spectrum(0.0)
            if dr.hint(env.needs_emitter_sampling, mode="scalar"):
                Lr_em = self.emitter_sample(env, scene, sampler.next_2d(smooth), si, bsdf, ctx,
                                            smooth, primal)
            with dr.resume_grad(when=not primal):
                # (Outside resume_grad, arithmetic drops its inputs' derivatives.)
                Lr_dir = β * (Lr_env + Lr_em)

            # ------------------------- Detached BSDF sampling --------------------------
            bs, bsdf_weight = bsdf.sample(ctx, si, sampler.next_1d(active),
                                          sampler.next_2d(active), active_next)
            d = si.to_world(bs.wo)
            delta = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)

            L = (L + Le + Lr_dir) if primal else (L - Le - Lr_dir)

            # -------------------- Replay: this vertex's derivatives --------------------
            if dr.hint(not primal, mode="scalar"):
                with dr.resume_grad():
                    # L now holds what reaches this vertex through the sampled
                    # direction, scaled by the detached BSDF value there: give it
                    # that value's relative derivative.
                    bsdf_val = bsdf.eval(ctx, si, bs.wo, active_next)
                    Lo = Le + Lr_dir + L * dr.relative_grad(bsdf_val)
                    if dr.hint(mode == dr.ADMode.Backward, mode="scalar"):
                        dr.backward_from(δL * Lo)
                    else:
                        δL += dr.forward_to(Lo)

            # ------------------------ Next vertex's MIS inputs -------------------------
            prev_si = mi.Interaction3f(si)
            prev_bsdf_pdf = bs.pdf
            prev_bsdf_delta = delta
            ray = si.spawn_ray(d)
            β *= bsdf_weight
            η *= bs.eta

            # ---------------------------- Russian roulette ----------------------------
            β_max = dr.max(β * dr.square(η))
            rr_active = depth >= self.rr_depth
            rr_prob = dr.minimum(β_max, 0.95)
            rr_continue = sampler.next_1d(active) < rr_prob
            β = dr.select(rr_active, β * dr.rcp(rr_prob), β)
            active = active_next & (~rr_active | rr_continue) & (β_max != 0) & (bs.pdf > 0)
            depth += 1
            hit = scene.ray_intersect_preliminary(ray, coherent=False, active=active)
            prev_env_pdf = env.pdf(lobe, use_product, d, active & smooth & ~delta & ~hit.is_valid())

        return (L if primal else δL), valid_ray, [], L

    def environment_sample(self, env: ProductEnvironment, scene, u: mi.Point2f, si, bsdf, ctx,
                           lobe, use_product, smooth, primal: bool) -> mi.Spectrum:
        """One sample of the lane's environment strategy (BSDF value x radiance x MIS
        weight / pdf) in the ``smooth`` lanes, differentiable in the BSDF and the map
        (``primal`` False); 0 when the scene builds no strategy (Mitsuba's emitter
        sampling then covers the environment)."""
        if not env.active:
            return mi.Spectrum(0.0)
        # Packets without a smooth lane (sky, delta BSDFs) skip the walks.
        d, pdf_e = dr.if_stmt(args=(lobe, u), cond=mi.Bool(smooth),
                              true_fn=lambda c, v: env.sample_environment(c, v, use_product, False),
                              false_fn=lambda c, v: (mi.Vector3f(0.0, 0.0, 1.0), mi.Float(0.0)))
        act = smooth & (pdf_e > 0)
        act &= ~scene.ray_test(si.spawn_ray(d), act)
        with dr.resume_grad(when=not primal):
            bsdf_val, bsdf_pdf = bsdf.eval_pdf(ctx, si, si.to_local(d), act)
            Le = env.emitter.eval(environment_ray_target(d), act)
            # The weight is a sampling decision: a derivative of it would have no
            # counterpart in the detached weight of the BSDF sample that hits the map.
            weight = mis_weight(pdf_e, dr.detach(bsdf_pdf)) / pdf_e
            return dr.select(act, bsdf_val * Le * weight, 0.0)

    def emitter_sample(self, env: ProductEnvironment, scene, u: mi.Point2f, si, bsdf, ctx, smooth,
                       primal: bool) -> mi.Spectrum:
        """One sample of Mitsuba's emitter sampling in the ``smooth`` lanes, without
        the environment where :meth:`environment_sample` covers it. The emitter sample
        is drawn without derivatives and its value evaluated again with them, so that
        emitter parameters are differentiated as in ``prb``."""
        ds, em_weight = scene.sample_emitter_direction(si, u, True, smooth)
        act = smooth & (ds.pdf != 0)
        if env.active:
            act &= ~env.is_environment(ds.emitter)
        with dr.resume_grad(when=not primal):
            if not primal:
                em_value = scene.eval_emitter_direction(si, ds, act)
                em_weight = dr.replace_grad(em_weight, em_value * dr.select(ds.pdf != 0, dr.rcp(ds.pdf), 0.0))
            bsdf_val, bsdf_pdf = bsdf.eval_pdf(ctx, si, si.to_local(ds.d), act)
            weight = dr.select(ds.delta, 1.0, mis_weight(ds.pdf, dr.detach(bsdf_pdf)))
            return dr.select(act, bsdf_val * em_weight * weight, 0.0)

    def to_string(self):
        return f"SHPRBIntegrator[{self.options}]"
