"""The path-tracing loop of ``sh_path`` and ``sh_prb``: one body, run in three modes.

Written as Mitsuba's ``prb.py`` is. In ``Primal`` mode it gathers each path's radiance
(``sh_path``'s image; ``sh_prb``'s primal pass). In ``Forward`` and ``Backward`` mode
(``sh_prb``'s replay) it draws the same random numbers, so it follows the same paths with
the same environment samples, starts from the primal radiance (``state_in``) and
subtracts each vertex's share as it goes, and propagates derivatives at every vertex:
sampling is detached (directions, pdfs, MIS weights), the values (BSDF, emitters) are
differentiated. Per vertex:

- the emitter hit by the ray that reached it, MIS-weighted against the strategy that
  could have sampled it (the lane's environment strategy for the map, Mitsuba's
  emitter sampling for the others);
- next-event estimation: one sample of the material's environment strategy
  (:func:`~.estimators.product_nee`; the product only at the first
  ``product_depth`` vertices, a mirror's or a window's Dirac bounce not counted) and one of
  Mitsuba's emitter sampling for the other emitters;
- one BSDF sample that continues the path, and Russian roulette as Mitsuba's ``path``.

Random numbers are drawn as Mitsuba's ``path`` and ``prb`` draw them: in every lane still
in the loop, one 2D sample for the emitters, 1D + 2D for the BSDF, 1D for the roulette,
whether or not the lane uses them. At one seed the BSDF-sampled paths of ``path`` and
``sh_path`` are then the same (where the environment is the only emitter), so noise they
share, such as a caustic seen through glass, cancels in a paired comparison instead of
deciding it.
"""

from __future__ import annotations

import dataclasses

import drjit as dr
import mitsuba as mi

from .estimators import emitter_nee, has_emitting_shapes, mis_weight, mitsuba_hit_pdf, product_nee


@dataclasses.dataclass(frozen=True)
class PathSettings:
    """What the loop takes from a plugin's options."""

    max_depth: int
    """Longest path in vertices (``ProductOptions.depth_limit``: -1 made a large number)."""
    rr_depth: int
    """Depth from which Russian roulette runs."""
    product_depth: int
    """Vertices (from the first) whose environment sample may use the product, counted as
    :attr:`through_dirac` says."""
    hide_emitters: bool
    """Emitters seen directly by the camera are not rendered."""
    label: str
    """The loop's name in Dr.Jit's kernels and messages."""
    product_from: int = 0
    """Vertices before this one (counted from 0, the first hit) never use the product
    (``oracle_path``: its oracle at one vertex only)."""
    through_dirac: bool = True
    """A Dirac bounce (a mirror, glass) does not count towards :attr:`product_depth`: what the
    camera sees in a mirror or through a window is a first hit too, as coherent as the
    others and as bright. False: every vertex counts (``oracle_path``, which places its
    oracle at one vertex)."""


# Equal fractions: one environment sample and one BSDF sample per vertex (the power
# heuristic only sees their ratio).
FRACTION = 0.5


@dataclasses.dataclass
class PreviousVertex:
    """What the next vertex needs of the one that sampled the ray reaching it (loop state:
    a dataclass, which Dr.Jit's loops carry field by field)."""

    si: mi.Interaction3f
    bsdf_pdf: mi.Float
    delta: mi.Bool
    env_pdf: mi.Float
    """The ray's pdf under the previous vertex's environment strategy (0 where it hit the scene)."""


def emitter_hit(scene, env, si, active, prev: PreviousVertex, β, visible, differentiable: bool) -> mi.Spectrum:
    """Radiance of the emitter that the ray reaching ``si`` hit, times the path throughput
    ``β``, MIS-weighted against the strategy that could have sampled it: the lane's
    environment strategy for the map, Mitsuba's emitter sampling (traced only where some
    emitter needs it) for the others; weight 1 after a Dirac BSDF sample."""
    emitter = si.emitter(scene, active)
    em_pdf = env.hit_pdf(emitter, prev.env_pdf, mitsuba_hit_pdf(
        scene, si, prev.si, active & ~prev.delta, env.needs_emitter_sampling))
    em_pdf = dr.select(prev.delta, 0.0, em_pdf)
    with dr.resume_grad(when=differentiable):
        return dr.select(visible, β * mis_weight(prev.bsdf_pdf, em_pdf) * emitter.eval(si, visible), 0.0)


def first_vertex() -> PreviousVertex:
    """The camera's 'vertex': a Dirac sample (emitters seen directly get weight 1)."""
    return PreviousVertex(dr.zeros(mi.Interaction3f), mi.Float(1.0), mi.Bool(True), mi.Float(0.0))


def replay_vertex(mode: dr.ADMode, L, δL, Lo, bsdf, ctx, si, wo, active):
    """One vertex's derivatives in a replay pass (``Lo``: what the vertex adds itself,
    differentiable). Returns ``(L, δL)``: the radiance still to be gathered beyond it, and
    (forward mode) the derivative so far."""
    L = L - Lo
    with dr.resume_grad():
        # L now holds what reaches this vertex through the sampled direction, scaled by
        # the detached BSDF value there: give it that value's relative derivative.
        bsdf_val = bsdf.eval(ctx, si, wo, active)
        Lo = Lo + L * dr.relative_grad(bsdf_val)
        if mode == dr.ADMode.Backward:
            dr.backward_from(δL * Lo)
        else:
            δL += dr.forward_to(Lo)
    return L, δL


def russian_roulette(sampler, β, η, depth, rr_depth: int, active):
    """Mitsuba's path roulette: ``(β, survives)``, ``β`` reweighted where it ran."""
    β_max = dr.max(β * dr.square(η))
    rr_active = depth >= rr_depth
    rr_prob = dr.minimum(β_max, 0.95)
    rr_continue = sampler.next_1d(active) < rr_prob
    return dr.select(rr_active, β * dr.rcp(rr_prob), β), (~rr_active | rr_continue) & (β_max != 0)


def next_hit(scene, ray, active, last, occlusion_ends_paths: bool):
    """``(hit, active)``: the new ray intersected where it is spawned, so that the vertex
    that sampled it knows whether it escapes before it evaluates its environment pdf (the
    product's pdf walk, about a fifth of a direct pass's operations, is skipped in every
    packet where no lane escapes: walls, floors, the inside of a room).

    A ray to the path's ``last`` vertex, where nothing is sampled, counts only if it reaches
    an emitter: without emitting shapes, only if it escapes. An occlusion query (which may
    stop at any hit) answers that; the lanes it stops end, the others see a miss."""
    if occlusion_ends_paths:
        hit = scene.ray_intersect_preliminary(ray, coherent=False, active=active & ~last)
        return hit, active & ~scene.ray_test(ray, active & last)
    return scene.ray_intersect_preliminary(ray, coherent=False, active=active), active


@dr.syntax
def trace_paths(mode: dr.ADMode, scene: mi.Scene, env, sampler: mi.Sampler, ray: mi.Ray3f, active: mi.Bool,
                settings: PathSettings, δL: mi.Spectrum | None = None, state_in: mi.Spectrum | None = None):
    """``(result, valid_ray, L)``: in ``Primal`` mode the radiance of each lane's path
    (twice: also the replay's ``state_in``); in ``Forward`` mode its derivative; in
    ``Backward`` mode the derivatives propagated from ``δL`` (result: ``δL``)."""
    primal = mode == dr.ADMode.Primal
    ctx = mi.BSDFContext()
    # Plain locals: inside the loop, dr.syntax would take an attribute read for loop state.
    max_depth, rr_depth, product_depth = settings.max_depth, settings.rr_depth, settings.product_depth
    product_from, through_dirac = settings.product_from, settings.through_dirac
    hide_emitters, label = settings.hide_emitters, f"{settings.label} ({mode.name})"
    occlusion_ends_paths = not has_emitting_shapes(scene)

    ray = mi.Ray3f(dr.detach(ray))
    active = mi.Bool(active)
    # Primal: radiance gathered so far. Replay: radiance still to be gathered further
    # along the path (the primal total, minus each vertex's share).
    L = mi.Spectrum(0.0 if primal else state_in)
    δL = mi.Spectrum(δL if δL is not None else 0.0)
    β, η, depth = mi.Spectrum(1.0), mi.Float(1.0), mi.UInt32(0)
    # The vertex's place as product_depth counts it: its depth, less the Dirac bounces
    # before it where they do not count.
    counted = mi.UInt32(0)
    valid_ray = mi.Bool(not hide_emitters and scene.environment() is not None)
    prev = first_vertex()
    # Camera rays are intersected coherently, as Mitsuba's path traces them.
    hit = scene.ray_intersect_preliminary(ray, coherent=True, active=active)

    while dr.hint(active, max_iterations=max_depth, label=label):
        si = hit.compute_surface_interaction(ray, mi.RayFlags.All, active)
        bsdf = si.bsdf(ray)
        visible = active & ((depth > 0) | (not hide_emitters))
        Le = emitter_hit(scene, env, si, active, prev, β, visible, not primal)
        active_next = active & si.is_valid() & (depth + 1 < max_depth)
        valid_ray |= active & si.is_valid()

        # Next-event estimation; the product only at the first product_depth vertices.
        smooth = active_next & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
        product_lanes = smooth & (counted < product_depth)
        if dr.hint(product_from > 0, mode="scalar"):  # (no comparison traced where it is 0)
            product_lanes &= depth >= product_from
        lobe, use_product = env.lobe(si, product_lanes)
        # The BSDF sample always runs (it continues the path): no lane carries all.
        Lr_env = product_nee(env, scene, sampler.next_2d(active), si, bsdf, ctx, lobe=lobe,
                             use_product=use_product, smooth=smooth, carries_all=False, frac_e=FRACTION,
                             frac_b=FRACTION, differentiable=not primal)
        Lr_em = emitter_nee(env, scene, sampler, si, bsdf, ctx, smooth, FRACTION, FRACTION,
                            differentiable=not primal)

        # The BSDF sample that continues the path (detached).
        bs, bsdf_weight = bsdf.sample(ctx, si, sampler.next_1d(active), sampler.next_2d(active), active_next)
        d = si.to_world(bs.wo)
        delta = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)

        if dr.hint(primal, mode="scalar"):
            L = L + Le + β * Lr_env + β * Lr_em
        else:
            with dr.resume_grad():
                Lo = Le + β * Lr_env + β * Lr_em
            L, δL = replay_vertex(mode, L, δL, Lo, bsdf, ctx, si, bs.wo, active_next)

        ray = si.spawn_ray(d)
        β *= bsdf_weight
        η *= bs.eta
        β, survives = russian_roulette(sampler, β, η, depth, rr_depth, active)
        active = active_next & survives & (bs.pdf > 0)
        depth += 1
        counted += dr.select(delta, mi.UInt32(0), mi.UInt32(1)) if through_dirac else mi.UInt32(1)
        hit, active = next_hit(scene, ray, active, depth + 1 >= max_depth, occlusion_ends_paths)
        prev = PreviousVertex(mi.Interaction3f(si), bs.pdf, delta,
                              env.pdf(lobe, use_product, d, active & smooth & ~delta & ~hit.is_valid()))

    return (L if primal else δL), valid_ray, L
