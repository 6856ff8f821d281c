"""``sh_prb``'s plan for the gradients: the strategies that give the least noisy gradients.

The plan (:mod:`.chooser`) picks each material's strategy for the primal image's
variance at equal time. In an optimisation the gradients are what is estimated, and
their variance can rank the strategies otherwise: on the material studio with seven
material parameters unknown, the plan put every material on ``environment`` while
``product`` everywhere gave gradients of 0.82x (at the start) and 0.91x (at the truth) the
variance (``scripts/bench_gradient_plans.py``, docs/MEASUREMENTS.md). At equal time, over the
image's plan, what this module picks measured 1.09x and 0.94x there, and 1.05x and 0.87x on a
roughness and a texture, within the timing's noise (about 10 %): it is not the default.

With ``plan_for`` ``gradients``, where the scene has parameters with gradients enabled when
the plan is made (an optimisation's unknowns), three candidates are weighed after the plan: the plan itself, every material on ``environment`` and every
material that can on ``product``. Each runs :data:`GRADIENT_PILOTS` pairs of passes at
fixed seeds: a primal pass, then the replay pass with the adjoint of an L2 loss whose
target is the candidates' mean image, so that the loss's gradient is what it is at an
optimum, made of the noise alone (the floor the late loss of an optimisation sits on).
Each candidate's score is its gradients' variance, per unknown over the candidates'
mean variance, times its pass time from the cost model (:mod:`.costs`, no clock: the same
plan in every process). The best candidate is kept while the scene is the same; the
unknowns' own gradients are put back as they were.
"""

from __future__ import annotations

import dataclasses
import time

import drjit as dr
import mitsuba as mi
import numpy as np

from .chooser import apply_choice, pilot_spp
from .costs import cost_model
from .strategy import AUTO, Strategy

GRADIENT_PILOTS = 4
"""Primal and replay passes per candidate (each at the pilots' samples per pixel)."""

GRADIENT_PILOT_SEED = 7_000
"""First seed of the gradient pilots (fixed: the same plan in every process)."""


def differentiable_parameters(scene: mi.Scene) -> dict:
    """Key -> value of every scene parameter whose gradient is enabled."""
    params = mi.traverse(scene)
    values = {}
    for key in params.keys():
        value = params[key]
        if dr.is_diff_v(value) and dr.grad_enabled(value):
            values[key] = value
    return values


def candidates(env) -> dict:
    """Name -> (registry id -> strategy): the plan as assigned, every material on
    ``environment``, every material that can run it on ``product`` (the others on their
    environment strategy). Equal assignments once."""
    ids = env.strategies.ids
    planned = {key: env.strategies.of(key) for key in ids}
    environment = {key: Strategy.ENVIRONMENT if Strategy.ENVIRONMENT in env.allowed(key) else planned[key]
                   for key in ids}
    product = {key: Strategy.PRODUCT if Strategy.PRODUCT in env.allowed(key) else environment[key] for key in ids}
    out = {}
    for name, assignment in (("plan", planned), ("environment", environment), ("product", product)):
        if assignment not in out.values():
            out[name] = assignment
    return out


def predicted_time(env, assignment: dict, shares: dict) -> float:
    """A pass's time with ``assignment``, in lean passes, from the path cost model: the
    product's code where a material runs the product, and each material's extra per its
    share of the film."""
    model = cost_model("path")
    uses_product = any(s.uses_product for s in assignment.values())
    time = 1.0 + (model.product_code if uses_product else 0.0)
    for key, strategy in assignment.items():
        time += shares.get(key, 0.0) * model.extra(strategy, env.samples_from_cosine_table(key),
                                                    env.bsdf_shared.of(key))
    return time


def gradient_variances(integrator, env, scene, sensor, values: dict, assignments: dict, spp: int) -> dict:
    """Name -> key -> (samples, values) gradients of each candidate (:func:`candidates`) at
    the gradient pilots' seeds, with the unknowns' gradients put back afterwards."""
    saved = {key: dr.grad(value) for key, value in values.items()}
    warps = env.warp, env.warp_plain
    params = mi.traverse(scene)
    out = {}
    try:
        for name, assignment in assignments.items():
            env.warp, env.warp_plain = warps
            env.strategies.assign(assignment)
            images = [integrator.render(scene, sensor, seed=GRADIENT_PILOT_SEED + k, spp=spp)
                      for k in range(GRADIENT_PILOTS)]
            mean = sum(images) / GRADIENT_PILOTS
            samples = {key: [] for key in values}
            for k, image in enumerate(images):
                for value in values.values():
                    dr.clear_grad(value)
                grad_in = 2.0 * (image - mean) / dr.prod(dr.shape(image))
                # The replay draws its own samples (as mi.render's seed_grad does): with the image's
                # seed the adjoint would follow the paths whose noise the residual holds.
                integrator.render_backward(scene, params, grad_in, sensor, seed=GRADIENT_PILOT_SEED + GRADIENT_PILOTS + k,
                                           spp=spp)
                for key, value in values.items():
                    samples[key].append(np.asarray(dr.grad(value).numpy(), np.float64).ravel())
            out[name] = {key: np.array(rows) for key, rows in samples.items()}
    finally:
        env.warp, env.warp_plain = warps
        for key, value in values.items():
            dr.set_grad(value, saved[key])
    return out


def choose(variances: dict, times: dict) -> tuple[str | None, dict]:
    """The candidate with the least (variance x time): each unknown's variance (summed over
    its values) over the candidates' mean for that unknown, averaged over the unknowns.
    Returns (name, name -> score); (None, {}) where no unknown's gradient could be read."""
    names = list(variances)
    total = {name: {key: float(np.sum(rows.var(axis=0, ddof=1))) for key, rows in variances[name].items()}
             for name in names}
    # An unknown whose gradients read 0 in every candidate says nothing (a value the scene's
    # parameters hold a copy of, e.g. an envmap's texels, whose own gradient stays with the copy).
    keys = [key for key in total[names[0]] if any(total[name][key] > 0 for name in names)]
    if not keys:
        return None, {}
    scores = {}
    for name in names:
        relative = [total[name][key] / max(np.mean([total[n][key] for n in names]), 1e-300) for key in keys]
        scores[name] = float(np.mean(relative)) * times[name]
    return min(names, key=lambda n: (scores[n], names.index(n))), scores


def plan_for_gradients(integrator, env, scene: mi.Scene, sensor, warps: tuple) -> None:
    """After the plan of a new state of ``scene``: where ``plan_for`` asks for it and the scene
    has unknowns, weigh the candidates (once per scene: a rebuilt state takes the candidate kept
    before) and run the best, reported in ``env.choice.gradient_plan``. ``warps``: the state's
    product warps as built (the plan may have dropped them)."""
    options, chooser = integrator.options, integrator.chooser
    if options.plan_for != "gradients" or options.default_strategy != AUTO or options.material_strategies:
        return
    if env.choice is None or warps[0] is None:
        return  # nothing planned, or no product to weigh
    values = differentiable_parameters(scene)
    if not values:
        return
    env.warp, env.warp_plain = warps
    options_of = candidates(env)
    shares = {key: m.share for m in env.choice.materials for key in env.strategies.ids
              if env.material_name(key) == m.name}
    start = time.perf_counter()
    known = chooser.gradient_choice
    if known is not None and known[0] is scene:
        kept, scores = known[1], dict(known[2])
    else:
        if isinstance(sensor, int):
            sensor = scene.sensors()[sensor]
        chooser.piloting = True
        try:
            variances = gradient_variances(integrator, env, scene, sensor, values, options_of, pilot_spp(sensor))
        finally:
            chooser.piloting = False
        kept, scores = choose(variances, {name: predicted_time(env, a, shares) for name, a in options_of.items()})
        chooser.gradient_choice = (scene, kept, scores)
    if kept is None:  # no gradient read: the image's plan, as planned
        env.warp, env.warp_plain = warps
        apply_choice(env, options_of["plan"], env.choice.lean)
        return
    assignment = options_of.get(kept, options_of["plan"])
    lean = not any(s.uses_product for s in assignment.values())
    apply_choice(env, assignment, lean)
    by_name = {env.material_name(key): strategy for key, strategy in assignment.items()}
    env.choice = dataclasses.replace(
        env.choice, lean=lean, gradient_plan={"kept": kept, "scores": scores, "unknowns": sorted(values)},
        materials=[dataclasses.replace(m, strategy=by_name.get(m.name, m.strategy)) for m in env.choice.materials],
        setup_seconds=env.choice.setup_seconds + time.perf_counter() - start)
    mi.Log(mi.LogLevel.Info, f"{env.plugin}: plan for the gradients of {len(values)} parameter(s): {kept} "
                             f"({', '.join(f'{n} {v:.3g}' for n, v in scores.items())})")
