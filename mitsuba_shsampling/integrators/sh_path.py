"""``sh_path``: a path tracer with SH product sampling for environment NEE."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from .chooser import StrategyChooser
from .environment import ProductEnvironment
from .options import PathOptions, document_parameters
from .path_loop import PathSettings, trace_paths
from .sharing import SceneSlot, plan, planned_render, shared_planning


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
    the first ``product_depth`` vertices of a path (the first hits, by default,
    those seen in a mirror or through glass included: a Dirac bounce is not
    counted); deeper vertices sample the environment alone. It is combined with
    BSDF sampling by the power heuristic; the product pdf of each BSDF-sampled
    direction is evaluated at the vertex that sampled it and carried to the
    next one (one float of loop state). Other emitters keep Mitsuba's emitter
    sampling; without an ``envmap`` nothing is built and it runs like
    :monosp:`path`.
    """

    def __init__(self, props: mi.Properties):
        super().__init__(props)
        self.options = options = PathOptions.from_properties(props)
        self.settings = PathSettings(max_depth=options.depth_limit, rr_depth=options.rr_depth,
                                     product_depth=options.product_depth_limit,
                                     hide_emitters=options.hide_emitters, label="sh_path")
        # One environment sample and one BSDF sample per vertex.
        self.shared = shared_planning(
            options, (), lambda scene: ProductEnvironment(scene, options),
            lambda: StrategyChooser(1, 1, "path", options.plan, options.plan_file))
        self.scenes, self.chooser = SceneSlot(self.shared), self.shared.chooser

    def prepare_scene(self, scene, sensor=0):
        """The host-side work before a pass: state and choice (see ``sh_direct``'s)."""
        return self.chooser.prepare(self, self.scenes.get(scene), scene, sensor)

    render = planned_render(mi.SamplingIntegrator)
    plan = plan

    def choice(self, scene):
        """The strategy chosen for each material of ``scene`` (see ``sh_direct``)."""
        return self.scenes.get(scene).choice

    def sample(self, scene, sampler, ray, medium=None, active=True):
        # As Mitsuba's path: max_depth 0 renders nothing (not even emitters, alpha 0).
        if self.options.max_depth == 0:
            return mi.Spectrum(0.0), mi.Bool(False), []
        L, valid_ray, _ = trace_paths(dr.ADMode.Primal, scene, self.scenes.get(scene), sampler, ray, active,
                                      self.settings)
        return L, valid_ray, []

    def to_string(self):
        return f"SHPathIntegrator[{self.options}]"
