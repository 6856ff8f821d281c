"""The pieces of a direct-lighting estimator that every integrator here shares.

``sh_direct`` and ``oracle_direct`` differ only in how they sample the
environment; the camera hit, Mitsuba's own emitter sampling of everything
else, the BSDF sample and the MIS weights are the same, and live here once.
Conventions are Mitsuba's ``direct``: one sample per strategy and sample
slot, combined with the power heuristic on sample-count fractions.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import drjit as dr
import mitsuba as mi

from .environment import BSDFDraw


def mis_weight(pdf_a, pdf_b):
    """Mitsuba's power heuristic (``mi.ad.integrators.common.mis_weight``, as its ``prb``
    uses it): 0 where the ratio is not finite, and detached (a weight is a function of
    where the samples fell, which a derivative does not move)."""
    return mi.ad.integrators.common.mis_weight(pdf_a, pdf_b)


def environment_ray_target(d: mi.Vector3f, wavelengths=None) -> mi.SurfaceInteraction3f:
    """An interaction that makes ``envmap.eval`` return the radiance arriving from ``d``, at
    ``wavelengths`` (the lane's, in spectral variants: the emitter evaluates its spectrum
    there; ignored in RGB and mono ones)."""
    si = dr.zeros(mi.SurfaceInteraction3f)
    si.wi = -d
    if wavelengths is not None and mi.is_spectral:
        si.wavelengths = wavelengths
    return si


class FirstHit(NamedTuple):
    """The camera ray's shading point."""

    emitted: mi.Spectrum
    """Radiance of a directly visible emitter (0 with ``hide_emitters``)."""
    si: mi.SurfaceInteraction3f
    bsdf: mi.BSDFPtr
    ctx: mi.BSDFContext
    active: mi.Bool
    """Lanes with a surface hit."""
    smooth: mi.Bool
    """Lanes whose BSDF has a smooth (non-Dirac) component: emitter sampling runs there."""


def first_hit(scene: mi.Scene, ray, active, hide_emitters: bool) -> FirstHit:
    """Intersect the camera ray and collect what the estimators need, as ``direct`` does."""
    ray, active = mi.Ray3f(ray), mi.Bool(active)
    # Camera rays are coherent: Mitsuba's direct traces them in Embree's coherent mode too
    # (without it the pass cost 5-10 % more than direct's at the same operation count).
    si = scene.ray_intersect(ray, mi.RayFlags.All, True, active)
    emitted = mi.Spectrum(0.0)
    if not hide_emitters:
        emitted = si.emitter(scene, active).eval(si, active)
    active &= si.is_valid()
    bsdf = si.bsdf(ray)
    smooth = active & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
    return FirstHit(emitted, si, bsdf, mi.BSDFContext(), active, smooth)


def environment_sample(scene, si, bsdf, ctx, d: mi.Vector3f, pdf: mi.Float, active, weight,
                       differentiable: bool = False) -> mi.Spectrum:
    """The value of one environment sample in direction ``d`` drawn with density ``pdf``:
    BSDF value x radiance x visibility x ``weight(bsdf_pdf)`` / pdf, 0 outside ``active``
    and where ``pdf`` is 0. ``weight`` maps the BSDF's pdf of ``d`` to the sample's MIS
    weight. Every environment strategy of every integrator here ends in this.

    ``differentiable``: the BSDF value and the radiance carry derivatives (``sh_prb``'s
    replay); the direction, its pdf and the MIS weight never do (a sampling decision
    has no counterpart in the detached weight of the BSDF sample that hits the map)."""
    act = mi.Bool(active) & (pdf > 0)
    with dr.resume_grad(when=differentiable):
        bsdf_val, bsdf_pdf = bsdf.eval_pdf(ctx, si, si.to_local(d), act)
        # Where the BSDF reflects nothing (below an opaque surface's horizon) the sample is 0
        # whatever the visibility: no shadow ray. Mitsuba's `direct` traces it first.
        act &= dr.any(bsdf_val != 0.0)
        act &= ~scene.ray_test(si.spawn_ray(d), act)
        radiance = scene.environment().eval(environment_ray_target(d, si.wavelengths), act)
        return dr.select(act, bsdf_val * radiance * (weight(dr.detach(bsdf_pdf)) / pdf), 0.0)


def mitsuba_emitter_sample(scene, sample: mi.Point2f, si, bsdf, ctx, smooth, left_out, frac_e, frac_b,
                           weight_one=False, differentiable: bool = False, selection_share=None) -> mi.Spectrum:
    """One sample of Mitsuba's emitter sampling, power-heuristic weighted
    against BSDF sampling (weight 1 for Dirac emitters and ``weight_one``
    lanes, which run no BSDF sample), in the ``smooth`` lanes.

    ``left_out(emitter) -> mi.Bool``: per lane, the sampled emitter belongs
    to another strategy of the lane (the environment, when a product or oracle
    strategy samples it), so this sample contributes nothing there.

    ``selection_share``: ``sample.x`` draws among emitters whose share of the scene's
    selection this is (:func:`mitsuba_nee`); Mitsuba's pdf is divided by it.

    ``differentiable``: as ``prb``, the sample is drawn without derivatives and the
    emitter's value evaluated again with them (and the BSDF's value with them)."""
    ds, em_weight = scene.sample_emitter_direction(si, sample, True, smooth)
    if selection_share is not None:
        ds.pdf, em_weight = ds.pdf / selection_share, em_weight * selection_share
    act = smooth & (ds.pdf != 0) & ~left_out(ds.emitter)
    with dr.resume_grad(when=differentiable):
        if differentiable:
            em_value = scene.eval_emitter_direction(si, ds, act)
            em_weight = dr.replace_grad(em_weight, em_value * dr.select(ds.pdf != 0, dr.rcp(ds.pdf), 0.0))
        bsdf_val, bsdf_pdf = bsdf.eval_pdf(ctx, si, si.to_local(ds.d), act)
        weight = dr.select(ds.delta | weight_one, 1.0, mis_weight(ds.pdf * frac_e, dr.detach(bsdf_pdf) * frac_b))
        return dr.select(act, bsdf_val * em_weight * weight, 0.0)


def has_emitting_shapes(scene: mi.Scene) -> bool:
    """Some shape of ``scene`` emits (an ``area`` emitter): a ray can then reach an
    emitter without escaping to the environment."""
    return any(mi.has_flag(e.flags(), mi.EmitterFlags.Surface) for e in scene.emitters())


def trace_to_emitters(scene: mi.Scene, ray: mi.Ray3f, active: mi.Bool):
    """(interaction, emitter, lanes that reached one) of a ray traced to find the emitter it hits.

    The surface interaction (normals, uv, partials, a call into the hit shape) is only
    computed where the ray can have reached an emitter: where it escapes to the
    environment, or hit a shape that emits (none is asked in a scene without area
    emitters). Mitsuba's ``direct`` computes it for every BSDF sample; the result is the
    same in the lanes that count (0 is returned elsewhere).

    Without emitting shapes only a ray that escapes reaches an emitter, and which shape
    stops the others does not matter: an occlusion query (``ray_test``, which may stop at
    any hit) replaces the closest-hit search."""
    if has_emitting_shapes(scene):
        hit = scene.ray_intersect_preliminary(ray, coherent=False, active=active)
        # (A null shape pointer, where nothing was hit, answers False.)
        reaches = mi.Bool(active) & (~hit.is_valid() | hit.shape.is_emitter())
    else:
        hit = dr.zeros(mi.PreliminaryIntersection3f)
        hit.t = mi.Float(dr.inf)  # a miss: its interaction is the escaped ray's
        reaches = mi.Bool(active) & ~scene.ray_test(ray, active)
    si = hit.compute_surface_interaction(ray, mi.RayFlags.All, reaches)
    emitter = si.emitter(scene, reaches)
    return si, emitter, reaches & (emitter != None)  # noqa: E711


def mitsuba_hit_pdf(scene: mi.Scene, si: mi.SurfaceInteraction3f, prev_si: mi.Interaction3f, active,
                    needed: bool) -> mi.Float:
    """Mitsuba's emitter-sampling pdf of the emitter that a ray from ``prev_si`` hit at ``si``;
    0, and nothing traced, where it is not ``needed`` (the environment is this package's,
    and no other emitter is sampled by Mitsuba)."""
    if not needed:
        return mi.Float(0.0)
    return scene.pdf_emitter_direction(prev_si, mi.DirectionSample3f(scene, si, prev_si), active)


def bsdf_sample_of_emitters(scene, hit: FirstHit, sample_1, sample_2,
                            strategy_pdf: Callable, frac_e, frac_b, mitsuba_pdf: bool = True) -> mi.Spectrum:
    """One BSDF sample of the emitters it hits, MIS-weighted against the
    lane's emitter strategy.

    ``strategy_pdf(emitter, d, active, mitsuba_pdf) -> mi.Float``: the pdf with
    which the lane's emitter strategy draws direction ``d`` towards the hit
    ``emitter``, given Mitsuba's own emitter-sampling pdf ``mitsuba_pdf``
    (``active``: lanes that hit an emitter by a non-Dirac BSDF sample).
    Without ``mitsuba_pdf`` (no emitter is sampled by Mitsuba) that pdf is 0
    and not traced.
    """
    si, bsdf, active = hit.si, hit.bsdf, hit.active
    bs, bsdf_weight = bsdf.sample(hit.ctx, si, sample_1, sample_2, active)
    act = active & (bs.pdf > 0)
    d = si.to_world(bs.wo)
    si_b, emitter, act = trace_to_emitters(scene, si.spawn_ray(d), act)
    Le = emitter.eval(si_b, act)
    delta = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
    em_pdf = mitsuba_hit_pdf(scene, si_b, si, act & ~delta, mitsuba_pdf)
    pdf_em = strategy_pdf(emitter, d, act & ~delta, em_pdf)
    pdf_em = dr.select(delta | ~hit.smooth, 0.0, pdf_em)
    weight = mis_weight(bs.pdf * frac_b, pdf_em * frac_e)
    return dr.select(act, bsdf_weight * Le * weight, 0.0)


def dirac_sample_of_emitters(scene, hit: FirstHit, sample_1, sample_2) -> mi.Spectrum:
    """One BSDF sample of the Dirac components alone (``BSDFContext.type_mask``), of
    the emitters it hits, with weight 1: no emitter strategy can draw those
    directions. For estimators that run no other BSDF sample (``bsdf_samples``
    0), so that a smooth dielectric, a plastic's coating or a mirror still
    reflect their surroundings; ``bsdf.eval`` (which the emitter samples use)
    leaves the Dirac components out, so the two never count the same light."""
    ctx = mi.BSDFContext()
    ctx.type_mask = mi.BSDFFlags.Delta
    si, bsdf = hit.si, hit.bsdf
    act = hit.active & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Delta)
    bs, bsdf_weight = bsdf.sample(ctx, si, sample_1, sample_2, act)
    act &= bs.pdf > 0
    si_b, emitter, act = trace_to_emitters(scene, si.spawn_ray(si.to_world(bs.wo)), act)
    return dr.select(act, bsdf_weight * emitter.eval(si_b, act), 0.0)


# Per-lane estimators of the per-scene states (environment.py): they call the state
# and its strategies; the state never calls back.

def mitsuba_nee(env, scene, sampler, si, bsdf, ctx, smooth, frac_e, frac_b, sampled_here,
                weight_one=False, differentiable: bool = False) -> mi.Spectrum:
    """One sample of Mitsuba's emitter sampling in the ``smooth`` lanes, without the
    environment where ``env`` (an :class:`~.environment.EnvironmentState`) samples it
    (``sampled_here``: a per-lane mask, or True / False for every lane); not traced at
    all when no lane can use it. ``weight_one`` lanes run no BSDF sample (weight 1);
    ``differentiable``: see :func:`mitsuba_emitter_sample`."""
    if not env.needs_emitter_sampling:
        return mi.Spectrum(0.0)

    def left_out(emitter):
        if sampled_here is False or sampled_here is True:  # every lane alike
            return env.is_environment(emitter) if sampled_here else mi.Bool(False)
        return sampled_here & env.is_environment(emitter)

    u = sampler.next_2d(smooth)
    if sampled_here is True and env.others is not None:
        # Every lane samples the environment elsewhere: draw among the other emitters only
        # (each emitter's pdf divided by their share, in hit_pdf too). Without this, Mitsuba's
        # draw of the environment was a wasted sample: under an envmap and a sun the sun's
        # estimate was 2x or 0, and sh_direct had 1.4x the variance of `direct`'s (which
        # draws one or the other, never nothing).
        u.x = env.others.remap(u.x)
        return mitsuba_emitter_sample(scene, u, si, bsdf, ctx, smooth, left_out, frac_e, frac_b,
                                      weight_one=weight_one, differentiable=differentiable,
                                      selection_share=env.others.share)
    return mitsuba_emitter_sample(scene, u, si, bsdf, ctx, smooth, left_out,
                                  frac_e, frac_b, weight_one=weight_one, differentiable=differentiable)


def product_nee(env, scene, u, si, bsdf, ctx, *, lobe, use_product, smooth, carries_all,
                frac_e: float = 0.5, frac_b: float = 0.5, share: float | None = None,
                u_choice=None, slots=None, alone=None, differentiable: bool = False):
    """One sample of the environment (BSDF value x radiance / pdf) in the ``smooth``
    lanes, with the lane's strategy in ``env`` (a :class:`~.environment.ProductEnvironment`:
    its ``sample_environment``).

    In ``carries_all`` lanes (``env.carries_all``) it is one of the lane's equally
    weighted samples: weight ``share``, its share of the lane's samples (default
    ``frac_e``; a sample drawn in a BSDF sample's slot has ``frac_b``). Elsewhere it
    is power-heuristic weighted against BSDF sampling with the strategies'
    sample-count fractions ``frac_e``, ``frac_b``. ``carries_all`` may be the Python
    value True (inside a branch that only such lanes enter): then only the
    uncompensated walks are traced. ``slots``: how such lanes draw their samples
    (:class:`~.environment.CarriedSlots`), for the balance weights of ``product_only``'s
    lanes; ``u_choice``: a further uniform sample, given in a BSDF sample's slot, with
    which those lanes draw from the BSDF or the product (without it, from the product).
    ``alone``: what the lanes of ``bsdf_only`` draw from the BSDF with
    (:class:`~.environment.BSDFAlone`; None where no lane runs it). ``differentiable``: see
    :func:`environment_sample`."""
    if not env.active:
        return mi.Spectrum(0.0)
    share = frac_e if share is None else share
    smooth = mi.Bool(smooth)
    # (No lane carries all: the state's own strategies, an oracle's too, and nothing of the mixture.)
    bsdf_draw = None if carries_all is False or u_choice is None else BSDFDraw(si, bsdf, ctx, u_choice,
                                                                                slots.bsdf_in_slot)
    # Only what is drawn with (an oracle's sampling takes neither).
    draws = {name: v for name, v in (("bsdf_draw", bsdf_draw), ("alone", alone)) if v is not None}
    # Packets without a smooth lane (sky, delta BSDFs) skip the walks.
    d, pdf_e = dr.if_stmt(args=(lobe, u), cond=smooth,
                          true_fn=lambda c, v: env.sample_environment(c, v, use_product, carries_all, **draws),
                          false_fn=lambda c, v: (mi.Vector3f(0.0, 0.0, 1.0), mi.Float(0.0)))

    def weight(bsdf_pdf):
        if carries_all is False:
            return mis_weight(pdf_e * frac_e, bsdf_pdf * frac_b)
        carried = share * env.carried_weight(lobe, pdf_e, pdf_e, bsdf_pdf, use_product, carries_all, slots)
        if carries_all is True:  # a lane known to carry all: no MIS weight to trace
            return carried
        return dr.select(carries_all, carried, mis_weight(pdf_e * frac_e, bsdf_pdf * frac_b))

    return environment_sample(scene, si, bsdf, ctx, d, pdf_e, smooth, weight, differentiable)


def emitter_nee(env, scene, sampler, si, bsdf, ctx, smooth, frac_e, frac_b, carries_all=False,
                differentiable: bool = False):
    """One sample of Mitsuba's emitter sampling, without the environment's
    share where ``env`` samples it (:func:`product_nee`): :func:`mitsuba_nee`.
    In ``carries_all`` lanes no BSDF sample runs, so its weight is 1."""
    return mitsuba_nee(env, scene, sampler, si, bsdf, ctx, smooth, frac_e, frac_b, env.active,
                       weight_one=carries_all, differentiable=differentiable)


def selected_emitter_nee(env, scene, u: mi.Point2f, si, bsdf, ctx, *, lobe, use_product, smooth, carries_all,
                         frac_e: float, frac_b: float, slots=None, alone=None) -> mi.Spectrum:
    """One sample of one emitter in the ``smooth`` lanes: the emitter drawn as Mitsuba's
    scene draws it (``Scene.sample_emitter``: uniformly, or by the emitters'
    ``sampling_weight``), then the lane's environment strategy in ``env`` where that is
    the environment and the emitter's own sampling elsewhere; one BSDF evaluation and
    one shadow ray a sample (``emitter_selection`` ``one``, :func:`product_nee` plus
    :func:`emitter_nee` being ``each``).

    Each strategy's pdf is its emitter's selection probability times its direction's
    pdf; the BSDF sample's weight uses the same (:meth:`~.environment.ProductEnvironment.hit_pdf`
    with ``selection``). Weights as in :func:`product_nee` (``share`` in ``carries_all``
    lanes, which run no BSDF sample, so 1 for other emitters there) and
    :func:`mitsuba_emitter_sample` (1 for Dirac emitters); ``slots`` as in :func:`product_nee`
    (this is an emitter sample's slot: it draws no BSDF direction); ``alone`` as in
    :func:`product_nee` (the ``bsdf_only`` lanes draw the environment's direction from the BSDF)."""
    smooth = mi.Bool(smooth)
    index, _, u_x = scene.sample_emitter(u.x, smooth)
    to_env = smooth & (index == env.emitter_index)
    to_other = smooth & ~to_env
    # The reprojected component keeps the environment strategy's 2D sample stratified.
    d_env, pdf_direction = dr.if_stmt(
        args=(lobe, mi.Point2f(u_x, u.y)), cond=to_env,
        true_fn=lambda c, v: env.sample_environment(c, v, use_product, carries_all, alone=alone),
        false_fn=lambda c, v: (mi.Vector3f(0.0, 0.0, 1.0), mi.Float(0.0)))
    pdf_env = pdf_direction * env.selection
    # The same sample.x draws the same emitter inside Mitsuba's call; visibility is tested below.
    ds, em_weight = scene.sample_emitter_direction(si, u, False, to_other)
    to_env &= pdf_env > 0
    to_other &= ds.pdf != 0
    d = dr.select(to_env, d_env, ds.d)
    # (Each ray's origin is offset off the surface towards its own direction.)
    ray, env_ray = si.spawn_ray_to(ds.p), si.spawn_ray(d_env)
    ray.o, ray.d = dr.select(to_env, env_ray.o, ray.o), dr.select(to_env, env_ray.d, ray.d)
    ray.maxt = dr.select(to_env, env_ray.maxt, ray.maxt)
    act = to_env | to_other
    bsdf_val, bsdf_pdf = bsdf.eval_pdf(ctx, si, si.to_local(d), act)
    act &= dr.any(bsdf_val != 0.0)
    act &= ~scene.ray_test(ray, act)
    radiance = scene.environment().eval(environment_ray_target(d, si.wavelengths), act & to_env)
    carried = 1.0 if carries_all is False else env.carried_weight(lobe, pdf_env, pdf_direction, bsdf_pdf,
                                                                   use_product, carries_all, slots)
    weight_env = dr.select(carries_all, frac_e * carried,
                           mis_weight(pdf_env * frac_e, bsdf_pdf * frac_b))
    weight_other = dr.select(ds.delta | carries_all, 1.0, mis_weight(ds.pdf * frac_e, bsdf_pdf * frac_b))
    value = dr.select(to_env, radiance * (weight_env / pdf_env), em_weight * weight_other)
    return dr.select(act, bsdf_val * value, 0.0)
