"""``oracle_path``: ``sh_path`` with the exact tabulated product at one vertex (a reference)."""

from __future__ import annotations

import warnings

import drjit as dr
import mitsuba as mi

from ..envmap.emitter import EmitterDirections, compensated_copy
from ..envmap.pyramid import BLACK_MAP_REASON, EnvPyramid
from ..lobes.fit import luminance
from ..warp.oracle import OracleTable, OracleWarp
from .environment import EnvironmentState, SceneCache
from .options import OraclePathOptions, document_parameters
from .path_loop import PathSettings, trace_paths


@document_parameters(OraclePathOptions)
class OraclePathIntegrator(mi.SamplingIntegrator):
    r"""
    .. _integrator-oracle_path:

    Oracle product at one path vertex (:monosp:`oracle_path`)
    ---------------------------------------------------------

    .. pluginparameters::

    .. The rows are generated from integrators/options.py (OraclePathOptions).

    A reference, not a renderer: how much variance an *ideal* product sampler
    would still save at one vertex of a path. It is :monosp:`sh_path` with the
    ``environment`` strategy on every material (Mitsuba's envmap sampling,
    MIS-compensated, with the BSDF sample that continues the path), except at
    vertex ``oracle_vertex``, where the environment sample is drawn from the
    exact product luminance(BSDF) x environment tabulated at that vertex
    (:class:`~mitsuba_shsampling.warp.oracle.OracleWarp`, as
    :monosp:`oracle_direct`'s, the map uncompensated and a defensive share of it
    mixed in) and combined with the BSDF sample by the power heuristic. The
    variance against ``oracle_vertex`` 0 (no oracle) is what that vertex could
    still give. It costs N^2 BSDF evaluations at that vertex and about N^2 / 2
    per sample there. Other emitters keep Mitsuba's emitter sampling; scenes
    without an ``envmap`` render as :monosp:`path`.
    """

    def __init__(self, props: mi.Properties):
        super().__init__(props)
        self.options = options = OraclePathOptions.from_properties(props)
        vertex = options.oracle_vertex
        self.settings = PathSettings(max_depth=options.max_depth, rr_depth=options.rr_depth,
                                     product_depth=vertex, product_from=max(vertex - 1, 0), through_dirac=False,
                                     hide_emitters=options.hide_emitters, label="oracle_path")
        self.scenes = SceneCache(lambda scene: OracleAtVertex(scene, options))

    def prepare_scene(self, scene, sensor=0):
        """The per-scene state, built (or rebuilt) on the host before a pass is traced."""
        return self.scenes.get(scene)

    def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
        self.prepare_scene(scene, sensor)
        return super().render(scene, sensor, seed, spp, develop, evaluate)

    def sample(self, scene, sampler, ray, medium=None, active=True):
        L, valid_ray, _ = trace_paths(dr.ADMode.Primal, scene, self.scenes.get(scene), sampler, ray, active,
                                      self.settings)
        return L, valid_ray, []

    def to_string(self):
        return f"OraclePathIntegrator[{self.options}]"


class OracleAtVertex(EnvironmentState):
    """Per-scene state of :class:`OraclePathIntegrator`, with the interface the path loop
    asks of a strategy state (:class:`~.environment.ProductEnvironment`'s ``lobe``,
    ``sample_environment``, ``pdf``): the lanes the loop marks for the product (the
    oracle vertex's) get the oracle, the others Mitsuba's compensated envmap sampling.

    The oracle's "lobe" of a lane is its :class:`~mitsuba_shsampling.warp.oracle.OracleTable`;
    the function it tabulates (the vertex's BSDF) is kept from :meth:`lobe` for the
    ``sample_environment`` and ``pdf`` of the same loop iteration, which trace it again."""

    def __init__(self, scene: mi.Scene, options: OraclePathOptions):
        super().__init__(scene)
        self.warp = self.env_directions = self._bsdf_luminance = None
        if not self.reason:
            pyramid = EnvPyramid(self.emitter)
            self.reason = BLACK_MAP_REASON if pyramid.is_black else ""
        if self.reason:
            if self.emitter is not None:
                warnings.warn(f"oracle_path: {self.reason}; it renders as Mitsuba's path")
            return
        self.warp = OracleWarp(pyramid, options.resolution, options.defensive_share)
        self.env_directions = EmitterDirections(compensated_copy(self.emitter))
        self.active = True
        self.needs_emitter_sampling = self.has_other_emitters

    def lobe(self, si: mi.SurfaceInteraction3f, oracle: mi.Bool):
        """(the oracle's table, the lanes that use it): tabulated only in ``oracle`` lanes."""
        oracle = mi.Bool(oracle)
        if not self.active:
            return OracleTable(mi.Float(1.0), mi.Float(1.0)), oracle & False
        bsdf, ctx = si.bsdf(), mi.BSDFContext()

        def bsdf_luminance(d, act):
            return luminance(bsdf.eval(ctx, si, si.to_local(d), act))
        self._bsdf_luminance = bsdf_luminance
        # (The table's loop runs while some lane is an oracle lane: at other vertices, not at all.)
        return self.warp.tabulate(bsdf_luminance, oracle), oracle

    def sample_environment(self, table, u: mi.Point2f, oracle, carries_all):
        """(direction, pdf): the oracle's in ``oracle`` lanes, the compensated map's elsewhere."""
        return dr.if_stmt(args=(table, u), cond=mi.Bool(oracle),
                          true_fn=lambda t, v: self.warp.sample(self._bsdf_luminance, t, v),
                          false_fn=lambda t, v: self.env_directions.sample(v))

    def pdf(self, table, oracle, d: mi.Vector3f, active: mi.Bool) -> mi.Float:
        """Pdf of world direction ``d`` under the lane's strategy (0 outside ``active``)."""
        if not self.active:
            return mi.Float(0.0)
        active, oracle = mi.Bool(active), mi.Bool(oracle)
        env_pdf = dr.if_stmt(args=(d,), cond=active & ~oracle, true_fn=lambda v: self.env_directions.pdf(v),
                             false_fn=lambda v: mi.Float(0.0))
        oracle_pdf = dr.if_stmt(args=(table, d), cond=active & oracle,
                                true_fn=lambda t, v: self.warp.pdf(self._bsdf_luminance, t, v),
                                false_fn=lambda t, v: mi.Float(0.0))
        return dr.select(oracle, oracle_pdf, env_pdf)
