"""``oracle_direct``: direct illumination with exact, tabulated product sampling (a reference)."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from ..envmap.pyramid import BLACK_MAP_REASON, EnvPyramid
from ..lobes.fit import luminance
from ..warp.oracle import OracleWarp
from .environment import EnvironmentState, SceneCache
from .estimators import (bsdf_sample_of_emitters, dirac_sample_of_emitters, environment_sample, first_hit,
                         mis_weight, mitsuba_nee)
from .options import OracleOptions, document_parameters


@document_parameters(OracleOptions)
class OracleDirectIntegrator(mi.SamplingIntegrator):
    r"""
    .. _integrator-oracle_direct:

    Oracle product direct illumination (:monosp:`oracle_direct`)
    ------------------------------------------------------------

    .. pluginparameters::

    .. The rows are generated from integrators/options.py (OracleOptions).

    A reference, not a renderer: how far an *ideal* product sampler would
    lower the noise of :monosp:`sh_direct`. At every shading point of a
    smooth BSDF it tabulates the exact product luminance(BSDF value) x
    environment over N x N equal-area cells (the BSDF at each cell's centre,
    times the environment's exact luminance integral over the cell; no
    visibility) and draws environment samples in proportion to it, mixed
    with a share of the environment's own distribution and followed down to
    the environment's finest cells (:class:`~mitsuba_shsampling.warp.oracle.OracleWarp`).
    That costs N^2 BSDF evaluations per shading point and about N^2 / 2 per
    oracle sample (4096 and about 2048 at the default N = 64).

    Oracle and BSDF samples are combined with the power heuristic using
    sample-count fractions, as :monosp:`direct` and :monosp:`sh_direct` do;
    with ``bsdf_samples`` = 0 every sample is an oracle sample, weight 1
    (and delta BSDFs reflect nothing, as in :monosp:`direct`).
    The environment is sampled as it is, never MIS-compensated: the oracle's
    defensive share must reach every lit direction by itself, with no
    partner strategy to cover what compensation drops.

    Other emitters (area, point, ...) use Mitsuba's emitter sampling, the
    environment's share of it left to the oracle. Delta BSDFs, scenes whose
    environment is not an ``envmap`` and scenes without one render as
    :monosp:`direct` does.
    """

    def __init__(self, props: mi.Properties):
        super().__init__(props)
        self.options = options = OracleOptions.from_properties(props)
        self.scenes = SceneCache(lambda scene: OracleEnvironment(scene, options))

    def prepare_scene(self, scene, sensor=0):
        """The per-scene state, built (or rebuilt) on the host before a pass is traced
        (see ``sh_direct``'s ``prepare_scene``)."""
        return self.scenes.get(scene)

    def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
        self.prepare_scene(scene, sensor)
        return super().render(scene, sensor, seed, spp, develop, evaluate)

    def sample(self, scene, sampler, ray, medium=None, active=True):
        env, options = self.scenes.get(scene), self.options
        n_e, n_b, (frac_e, frac_b) = options.emitter_samples, options.bsdf_samples, options.sample_shares
        hit = first_hit(scene, ray, active, options.hide_emitters)
        L, si, bsdf, ctx, smooth = hit.emitted, hit.si, hit.bsdf, hit.ctx, hit.smooth

        # ------------- The oracle's table: the BSDF at every cell centre -------------
        def lobe(d, act):
            return luminance(bsdf.eval(ctx, si, si.to_local(d), act))

        # Without oracle samples the table is not needed: their MIS fraction is 0.
        oracle = smooth if env.warp is not None and n_e > 0 else mi.Bool(False)
        table = env.warp.tabulate(lobe, oracle) if env.warp is not None and n_e > 0 else None

        # ------ Environment: oracle samples; other emitters: Mitsuba's sampling ------
        for _ in range(n_e):
            L += oracle_nee(env, scene, sampler.next_2d(oracle), si, bsdf, ctx, lobe, table, oracle,
                                frac_e, frac_b) / n_e
        for _ in range(n_e):
            L += oracle_emitter_nee(env, scene, sampler, si, bsdf, ctx, oracle, smooth, frac_e, frac_b) / n_e

        # The emitter strategy of a BSDF-sampled direction: the oracle for the
        # environment in oracle lanes (W is the lane's: its pdf costs one BSDF
        # evaluation here), Mitsuba's sampling otherwise.
        def strategy_pdf(emitter, d, act, mitsuba_pdf):
            if table is None:
                return mitsuba_pdf
            by_oracle = oracle & env.is_environment(emitter)
            return dr.select(by_oracle, env.warp.pdf(lobe, table, d, act & by_oracle), mitsuba_pdf)

        # ----------------------------- BSDF sampling -----------------------------
        for _ in range(n_b):
            L += bsdf_sample_of_emitters(scene, hit, sampler.next_1d(hit.active), sampler.next_2d(hit.active),
                                         strategy_pdf, frac_e, frac_b) / n_b

        if n_b == 0:  # as sh_direct: the Dirac components' own sample (estimators.py)
            L += dirac_sample_of_emitters(scene, hit, sampler.next_1d(hit.active), sampler.next_2d(hit.active))

        sees_environment = not options.hide_emitters and scene.environment() is not None
        return L, si.is_valid() | sees_environment, []

    def to_string(self):
        return f"OracleDirectIntegrator[{self.options}]"


class OracleEnvironment(EnvironmentState):
    """Per-scene state of :class:`OracleDirectIntegrator`: the environment state
    (:class:`~.environment.EnvironmentState`) and ``warp``, an
    :class:`~mitsuba_shsampling.warp.oracle.OracleWarp` over the map's own,
    uncompensated pyramid (None when the scene has no usable ``envmap``; every
    lane then uses Mitsuba's emitter sampling). Built from the plugin's checked
    ``options`` (``resolution``, ``defensive_share``).
    """

    def __init__(self, scene: mi.Scene, options: OracleOptions):
        super().__init__(scene)
        self.warp = None
        if not self.reason:
            pyramid = EnvPyramid(self.emitter)
            self.reason = BLACK_MAP_REASON if pyramid.is_black else ""
            if not pyramid.is_black:
                self.warp = OracleWarp(pyramid, options.resolution, options.defensive_share)
                self.needs_emitter_sampling = self.has_other_emitters


# The oracle's per-lane estimators: they read its state (OracleEnvironment), which never calls them.

def oracle_nee(env, scene, u, si, bsdf, ctx, lobe, table, oracle, frac_e, frac_b):
    """One oracle sample of the environment (BSDF value x radiance / pdf),
    power-heuristic weighted against BSDF sampling with the strategies'
    sample-count fractions (weight 1 without BSDF samples)."""
    if env.warp is None:
        return mi.Spectrum(0.0)
    d, pdf = env.warp.sample(lobe, table, u, oracle)
    return environment_sample(scene, si, bsdf, ctx, d, pdf, oracle,
                              lambda bsdf_pdf: mis_weight(pdf * frac_e, bsdf_pdf * frac_b))


def oracle_emitter_nee(env, scene, sampler, si, bsdf, ctx, oracle, smooth, frac_e, frac_b):
    """One sample of Mitsuba's emitter sampling, without the environment's
    share in oracle lanes (that belongs to :func:`oracle_nee`): :func:`~.estimators.mitsuba_nee`."""
    return mitsuba_nee(env, scene, sampler, si, bsdf, ctx, smooth, frac_e, frac_b,
                       oracle if env.warp is not None else False)
