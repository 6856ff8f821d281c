"""``sh_prb``: path replay backpropagation with SH product sampling for environment NEE."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from .chooser import StrategyChooser
from .environment import ProductEnvironment
from .gradient_plan import plan_for_gradients
from .options import PRBOptions, document_parameters
from .path_loop import PathSettings, trace_paths
from .sharing import SceneSlot, plan, planned_render, shared_planning

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
    change, at most once every ``rebuild_interval`` renders and only once
    they moved by more than ``rebuild_tolerance``: an optimisation changes
    them at every step, and a build costs many passes' time on a scene with
    many materials. In between, the state of slightly older parameters keeps
    images and gradients unbiased. A rebuild refits only the BSDFs whose
    parameters changed and rebuilds the pyramid only for a changed map (the
    builds are cached by content).
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
        self.settings = PathSettings(max_depth=options.depth_limit, rr_depth=options.rr_depth,
                                     product_depth=options.product_depth_limit,
                                     hide_emitters=options.hide_emitters, label="sh_prb")

        def build(scene):
            # Optimised parameters (envmap texels, a roughness) may have gradients enabled:
            # the sampling state only needs their values and stays out of the AD graph.
            with dr.suspend_grad():
                return ProductEnvironment(scene, options)

        # One environment sample and one BSDF sample per vertex, as in sh_path.
        self.shared = shared_planning(
            options, (), build, lambda: StrategyChooser(1, 1, "path", options.plan, options.plan_file))
        self.scenes, self.chooser = SceneSlot(self.shared), self.shared.chooser
        self._state, self._renders_since_check = None, 0

    # The per-scene state is built on the host before a pass is traced. A primal
    # render rebuilds it when its inputs changed (at most every rebuild_interval
    # renders), and with strategy auto chooses each material's strategy for a new
    # state (pilot primal passes); the derivative passes, which replay the primal
    # pass themselves, and the traced passes take it as it is.

    def prepare_scene(self, scene, sensor=0):
        """The host-side work before a pass (see ``sh_direct``'s), with the state's inputs
        checked every ``rebuild_interval`` renders (rebuilt where they moved more than
        ``rebuild_tolerance``). Counted from the last check, not the last build: a check that
        keeps the state reads its inputs back (a reduction over each changed parameter, a
        large map's included), which is not work for every pass."""
        check = self._renders_since_check + 1 >= self.options.rebuild_interval
        state = self.scenes.get(scene, stale_ok=not check, tolerance=self.options.rebuild_tolerance)
        self._renders_since_check = 0 if check or state is not self._state else self._renders_since_check + 1
        self._state = state
        def pilot_pass(pilot_spp, pilot_seed):
            return super(SHPRBIntegrator, self).render(scene, sensor, pilot_seed, pilot_spp)

        # The product's warps as built: the plan may drop them, and the plan for the
        # gradients weighs the product again.
        warps = (state.warp, state.warp_plain) if state.awaits_choice else None
        def pilot_sample(scene, sampler, ray, active):
            return self.sample(dr.ADMode.Primal, scene, sampler, ray, None, None, active)[:2]

        self.chooser.before_render(state, scene, sensor, pilot_pass, self, pilot_sample)
        if warps is not None:
            plan_for_gradients(self, state, scene, sensor, warps)
        return state

    render = planned_render(RBIntegrator)

    def plan(self, scene, sensor=0):
        """The plan for ``scene`` (see ``sh_direct``'s), made on the parameters as they are
        now: where a render rebuilds the state at most every ``rebuild_interval`` renders,
        this call rebuilds it whenever the parameters moved by more than ``rebuild_tolerance``
        since it was built. It is how a frozen optimisation step (``mitsuba_shsampling.freeze``),
        whose replays run no Python, refreshes its sampling state: call it outside the frozen
        function. The state's arrays are made opaque: a rebuilt state's new values are then
        inputs of the same recording, not literals of a new one."""
        self._renders_since_check = self.options.rebuild_interval
        made = plan(self, scene, sensor)
        if not dr.flag(dr.JitFlag.FreezingScope):
            dr.make_opaque(*self.frozen_inputs)
        return made

    def choice(self, scene):
        """The strategy chosen for each material of ``scene`` (see ``sh_direct``)."""
        return self.scenes.get(scene, stale_ok=True).choice

    def render_forward(self, scene, params, sensor=0, seed=0, spp=0):
        self.scenes.get(scene, stale_ok=True)
        return super().render_forward(scene, params, sensor, seed, spp)

    def render_backward(self, scene, params, grad_in, sensor=0, seed=0, spp=0):
        self.scenes.get(scene, stale_ok=True)
        return super().render_backward(scene, params, grad_in, sensor, seed, spp)

    def sample(self, mode: dr.ADMode, scene: mi.Scene, sampler: mi.Sampler, ray: mi.Ray3f,
               δL: mi.Spectrum | None, state_in: mi.Spectrum | None, active: mi.Bool, **kwargs):
        """One path per lane: in ``Primal`` mode its radiance (returned twice: the image and
        the replay's input ``state_in``); in ``Forward``/``Backward`` mode the same path
        again, returning (forward) or propagating (backward, from ``δL``) derivatives
        (:func:`~.path_loop.trace_paths`). See ``ADIntegrator.sample`` in Mitsuba for the
        interface."""
        # As Mitsuba's path: max_depth 0 renders nothing (not even emitters, alpha 0).
        if self.options.max_depth == 0:
            return mi.Spectrum(0.0), mi.Bool(False), [], mi.Spectrum(0.0)
        result, valid_ray, L = trace_paths(mode, scene, self.scenes.get(scene, stale_ok=True), sampler, ray, active,
                                           self.settings, δL=δL, state_in=state_in)
        return result, valid_ray, [], L

    def to_string(self):
        return f"SHPRBIntegrator[{self.options}]"
