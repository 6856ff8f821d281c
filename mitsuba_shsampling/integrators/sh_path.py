"""``sh_path``: a path tracer with SH product sampling for environment NEE."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from .chooser import StrategyChooser
from .environment import ProductEnvironment
from .estimators import has_emitting_shapes, mis_weight, mitsuba_hit_pdf
from .options import PathOptions, document_parameters
from .sharing import plan, shared_planning


@document_parameters(PathOptions)
class SHPathIntegrator(mi.SamplingIntegrator):
    r"""
    .. _integrator-sh_path:

    SH product path tracer (:monosp:`sh_path`)
    ------------------------------------------

    .. pluginparameters::

    .. The rows are generated from integrators/options.py (PathOptions).

    Mitsuba's :monosp:`path` with one change: at every vertex whose BSDF has a
    smooth lobe, next-event estimation towards the environment map draws its
    direction with the strategy of the vertex's material (``strategy``): from the
    product of the BSDF lobe proxy (spherical harmonics, rotated per vertex) and
    the environment's luminance, or from the environment alone; with ``auto``
    each material gets the one predicted to give the least error at equal time,
    chosen before the first pass at the camera's first hits. The product runs at
    the first ``product_depth`` vertices of a path (the first hits, by default);
    deeper vertices sample the environment alone. It is combined with
    BSDF sampling by the power heuristic; the product pdf of each BSDF-sampled
    direction is evaluated at the vertex that sampled it and carried to the
    next one (one float of loop state). Other emitters keep Mitsuba's emitter
    sampling; without an ``envmap`` nothing is built and it runs like
    :monosp:`path`.

    .. tabs::
        .. code-tab:: xml

            <integrator type="sh_path">
                <integer name="max_depth" value="8"/>
            </integrator>

        .. code-tab:: python

            'type': 'sh_path', 'max_depth': 8
    """

    def __init__(self, props: mi.Properties):
        super().__init__(props)
        self.options = options = PathOptions.from_properties(props)
        # One environment sample and one BSDF sample per vertex.
        self.shared = shared_planning(
            options, (), lambda scene: ProductEnvironment(scene, options),
            lambda: StrategyChooser(1, 1, "path", options.plan, options.plan_file))
        self.scenes, self.chooser = self.shared.scenes, self.shared.chooser

    def prepare_scene(self, scene, sensor=0):
        """The host-side work before a pass: state and choice (see ``sh_direct``'s)."""
        return self.chooser.prepare(self, self.scenes.get(scene), scene, sensor)

    def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
        if not self.chooser.piloting:  # a pilot pass (StrategyChooser.piloting) renders as configured
            self.prepare_scene(scene, sensor)
        return super().render(scene, sensor, seed, spp, develop, evaluate)

    plan = plan

    def choice(self, scene):
        """The strategy chosen for each material of ``scene`` (see ``sh_direct``)."""
        return self.scenes.get(scene).choice

    @dr.syntax
    def sample(self, scene, sampler, ray, medium=None, active=True):
        # As Mitsuba's path: max_depth 0 renders nothing (not even emitters, alpha 0).
        if dr.hint(self.options.max_depth == 0, mode="scalar"):
            return mi.Spectrum(0.0), mi.Bool(False), []
        env = self.scenes.get(scene)
        max_depth, product_depth = self.options.depth_limit, self.options.product_depth_limit
        ctx = mi.BSDFContext()

        # --------------------- Configure loop state ----------------------
        ray = mi.Ray3f(ray)
        active = mi.Bool(active)
        L = mi.Spectrum(0.0)
        beta = mi.Spectrum(1.0)
        eta = mi.Float(1.0)
        depth = mi.UInt32(0)
        valid_ray = mi.Bool(not self.options.hide_emitters and scene.environment() is not None)
        prev_si = dr.zeros(mi.Interaction3f)
        prev_bsdf_pdf = mi.Float(1.0)
        prev_bsdf_delta = mi.Bool(True)
        # Pdf of the current ray under the previous vertex's environment strategy.
        prev_env_pdf = mi.Float(0.0)
        occlusion_ends_paths = not has_emitting_shapes(scene)
        # Each ray is intersected where it is spawned (the camera rays here, coherently, as
        # Mitsuba's path traces them), so that the vertex that sampled it knows whether it
        # escapes before it evaluates its environment pdf; the loop carries the preliminary hit.
        hit = scene.ray_intersect_preliminary(ray, coherent=True, active=active)

        while active:
            si = hit.compute_surface_interaction(ray, mi.RayFlags.All, active)

            # ---------------- Emitter hit by the BSDF-sampled ray ----------------
            emitter = si.emitter(scene, active)
            # (Mitsuba's pdf only where Mitsuba samples some emitter.)
            em_pdf = env.hit_pdf(emitter, prev_env_pdf, mitsuba_hit_pdf(
                scene, si, prev_si, active & ~prev_bsdf_delta, env.needs_emitter_sampling))
            em_pdf = dr.select(prev_bsdf_delta, 0.0, em_pdf)
            visible = active & ((depth > 0) | (not self.options.hide_emitters))
            L += dr.select(visible, beta * mis_weight(prev_bsdf_pdf, em_pdf) * emitter.eval(si, visible), 0.0)

            active_next = active & si.is_valid() & (depth + 1 < max_depth)
            valid_ray |= active & si.is_valid()
            bsdf = si.bsdf(ray)

            # -------------------------- Next-event estimation --------------------------
            # One sample per strategy: equal fractions (the power heuristic
            # only sees their ratio).
            smooth = active_next & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
            # The product only at the first product_depth vertices: deeper ones sample the map alone.
            lobe, use_product = env.lobe(si, smooth & (depth < product_depth))
            # The BSDF sample always runs (it continues the path): no lane is product-only.
            # Random numbers are drawn as Mitsuba's path draws them: in every lane still in
            # the loop, one 2D sample for the emitters, 1D + 2D for the BSDF, 1D for the
            # roulette, whether or not the lane uses them. At one seed the BSDF-sampled
            # paths of the two integrators are then the same (where the environment is the
            # only emitter), so noise they share, such as a caustic seen through glass,
            # cancels in a paired comparison instead of deciding it.
            L += beta * env.product_nee(scene, sampler.next_2d(active), si, bsdf, ctx, lobe,
                                        use_product, smooth, False, 0.5, 0.5)
            L += beta * env.emitter_nee(scene, sampler, si, bsdf, ctx, smooth, 0.5, 0.5)

            # ------------------------------ BSDF sampling ------------------------------
            bs, bsdf_weight = bsdf.sample(ctx, si, sampler.next_1d(active),
                                          sampler.next_2d(active), active_next)
            d = si.to_world(bs.wo)
            delta = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
            prev_si = mi.Interaction3f(si)
            prev_bsdf_pdf = bs.pdf
            prev_bsdf_delta = delta
            ray = si.spawn_ray(d)
            beta *= bsdf_weight
            eta *= bs.eta

            # ---------------------------- Russian roulette ----------------------------
            beta_max = dr.max(beta * dr.square(eta))
            rr_active = depth >= self.options.rr_depth
            rr_prob = dr.minimum(beta_max, 0.95)
            rr_continue = sampler.next_1d(active) < rr_prob
            beta = dr.select(rr_active, beta * dr.rcp(rr_prob), beta)
            active = active_next & (~rr_active | rr_continue) & (beta_max != 0) & (bs.pdf > 0)
            depth += 1

            # The environment pdf of the new ray is only read where it escapes to the
            # environment: the product's pdf walk (about a fifth of a direct pass's
            # operations) is skipped for rays that hit the scene, in every packet
            # where no lane escapes (walls, floors, the inside of a room).
            #
            # A ray to the path's last vertex, where nothing is sampled, counts only if it reaches
            # an emitter: without emitting shapes, only if it escapes. An occlusion query (which
            # may stop at any hit) answers that; the lanes it stops end, the others see a miss.
            if dr.hint(occlusion_ends_paths, mode="scalar"):
                last = depth + 1 >= max_depth
                hit = scene.ray_intersect_preliminary(ray, coherent=False, active=active & ~last)
                active &= ~scene.ray_test(ray, active & last)
            else:
                hit = scene.ray_intersect_preliminary(ray, coherent=False, active=active)
            prev_env_pdf = env.pdf(lobe, use_product, d, active & smooth & ~delta & ~hit.is_valid())

        return L, valid_ray, []

    def to_string(self):
        return f"SHPathIntegrator[{self.options}]"
