"""Specification of the ``sh_prb`` plugin: path replay backpropagation with the
project's environment strategy.

Gradients are tested statistically on a small scene (a GGX conductor and a GGX
plastic sphere on a diffuse ground with a reflectance texture, under a real
map): K independent passes (different seeds) of ``sh_prb`` and of Mitsuba's
``prb`` give K samples of each parameter's gradient of a fixed scalar loss (a
randomly weighted image mean); texture and texel gradients are summarised by
their dot product with fixed random weights. The means must agree by Welch's
t-test, and be clearly non-zero (so the test cannot pass on two zeros). One
roughness gradient is also checked against central finite differences of
high-spp ``path`` renders, and the replay pass against the primal pass it
replays (a derivative that is exactly the image over the envmap's scale).
"""

import math

import drjit as dr
import mitsuba as mi

import numpy as np
import pytest

mi.set_variant("llvm_ad_rgb")

from test_integrators import assert_unbiased, make_scene  # noqa: E402

import mitsuba_shsampling  # noqa: E402
from mitsuba_shsampling.integrators import PLUGIN_NAMES, register  # noqa: E402
from mitsuba_shsampling.integrators.options import OptionError, PRBOptions  # noqa: E402

RES = 16
SPP = 32
PASSES = 48
MAX_DEPTH = 3
BANDS = 5  # small band count keeps the kernels quick to compile
#: |t| above which two gradient means disagree (5 parameters tested at once).
T_LIMIT = 4.5

CONDUCTOR_ALPHA = "conductor.bsdf.alpha.value"
PLASTIC_ALPHA = "plastic.bsdf.alpha"
TEXTURE = "ground.bsdf.reflectance.data"
ENV_SCALE = "env.scale"
ENV_TEXELS = "env.data"
PARAMETERS = (CONDUCTOR_ALPHA, PLASTIC_ALPHA, TEXTURE, ENV_SCALE, ENV_TEXELS)


@pytest.fixture(scope="module", autouse=True)
def registered():
    register()


def sh_prb(**props):
    return mi.load_dict({"type": "sh_prb", "max_depth": MAX_DEPTH, "max_bands": BANDS} | props)


def gradient_scene(envmaps_dir):
    """Two GGX spheres (conductor alpha 0.3, dark plastic alpha 0.2) on a textured diffuse
    ground under a real studio map, seen from close by."""
    texture = np.random.default_rng(5).uniform(0.2, 0.8, (8, 8, 3)).astype(np.float32)
    return mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 40,
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0, 1.3, 3.2], target=[0, 0.35, 0],
                                                              up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": RES, "height": RES, "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent"}},
        "conductor": {"type": "sphere", "center": [-0.5, 0.45, 0], "radius": 0.45,
                      "bsdf": {"type": "roughconductor", "distribution": "ggx", "alpha": 0.3}},
        "plastic": {"type": "sphere", "center": [0.5, 0.45, 0], "radius": 0.45,
                    "bsdf": {"type": "roughplastic", "distribution": "ggx", "alpha": 0.2,
                             "diffuse_reflectance": {"type": "rgb", "value": [0.04, 0.06, 0.1]}}},
        "ground": {"type": "rectangle", "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], -90).scale(3),
                   "bsdf": {"type": "diffuse",
                            "reflectance": {"type": "bitmap", "bitmap": mi.Bitmap(texture),
                                            "filter_type": "nearest"}}},
        "env": {"type": "envmap", "filename": str(envmaps_dir / "studio_small_03_1k.hdr")},
    })


def image_weights():
    """The fixed random per-pixel weights of the loss."""
    return mi.TensorXf(np.random.default_rng(11).uniform(0.0, 2.0, (RES, RES, 3)).astype(np.float32))


def weighted_loss(image, weights):
    return dr.mean(image * weights, axis=None)


def gradient_samples(scene, integrator, passes=PASSES, spp=SPP, seed=0):
    """(passes, parameters) array: per pass, each parameter's gradient of a fixed
    weighted image mean (of a texture: its dot product with fixed random weights)."""
    params = mi.traverse(scene)
    weights = image_weights()
    rng = np.random.default_rng(12)
    summary_weights = {k: rng.uniform(0.0, 1.0, dr.width(params[k])) if dr.width(params[k]) > 1 else np.ones(1)
                       for k in PARAMETERS}
    for key in PARAMETERS:
        dr.enable_grad(params[key])
    params.update()
    samples = []
    for k in range(-1, passes):
        image = mi.render(scene, params, integrator=integrator, spp=spp,
                          seed=seed + 2 * k + 2, seed_grad=seed + 2 * k + 3)
        dr.backward(weighted_loss(image, weights))
        # The first pass warms up (kernels; Mitsuba's envmap texels get no gradient in the
        # first differentiable pass after grads are enabled, for prb as for sh_prb).
        if k >= 0:
            samples.append([float(np.dot(np.ravel(dr.grad(params[key]).numpy()), summary_weights[key]))
                            for key in PARAMETERS])
        for key in PARAMETERS:
            dr.set_grad(params[key], 0.0)
    return np.array(samples)


def welch_t(a, b):
    se = np.sqrt(a.var(axis=0, ddof=1) / len(a) + b.var(axis=0, ddof=1) / len(b))
    return (a.mean(axis=0) - b.mean(axis=0)) / se


# ------------------------------------------------------------------ plugin and options


def test_sh_prb_is_registered_and_loads_from_a_dict_and_from_xml():
    assert "sh_prb" in PLUGIN_NAMES
    integrator = mi.load_dict({"type": "sh_prb", "max_depth": 4, "rr_depth": 3, "max_bands": 6})
    assert isinstance(integrator, mi.ad.integrators.common.RBIntegrator)
    assert integrator.options == PRBOptions(max_depth=4, rr_depth=3, max_bands=6)
    xml = mi.load_string('<integrator version="3.0.0" type="sh_prb"><integer name="max_depth" value="3"/>'
                         '<boolean name="mis_compensation" value="false"/></integrator>')
    assert "max_depth=3" in str(xml) and "mis_compensation=False" in str(xml)


def test_defaults_are_prbs():
    integrator, prb = mi.load_dict({"type": "sh_prb"}), mi.load_dict({"type": "prb"})
    assert integrator.max_depth == prb.max_depth == 6
    assert integrator.rr_depth == prb.rr_depth == 5


@pytest.mark.parametrize("name, value, requirement", [
    ("max_depth", -2, "must be -1 (infinite) or >= 0"),
    ("max_depth", 8.0, "must be an integer"),
    ("rr_depth", 0, "must be > 0"),
    ("max_bands", 40, "must be in"),
    ("defensive_share", 0.0, "must be in (0, 1]"),
    ("strategy", "product_only", "must be one of"),  # the BSDF sample always runs, as in sh_path
    ("rebuild_tolerance", -0.1, "must be >= 0"),
    ("plan_for", "loss", "must be 'image' or 'gradients'"),
])
def test_a_bad_parameter_raises_an_option_error_naming_sh_prb(name, value, requirement):
    with pytest.raises(OptionError, match=f"sh_prb: parameter '{name}' " + requirement.replace("(", r"\(")
                       .replace(")", r"\)").replace("[", r"\[").replace("]", r"\]")):
        PRBOptions(**{name: value})
    with pytest.raises(RuntimeError, match=f"sh_prb: parameter '{name}'"):
        mi.load_dict({"type": "sh_prb", name: value})


def test_the_docstring_lists_every_parameter_and_shows_xml_and_dict_usage():
    from mitsuba_shsampling.integrators.sh_prb import SHPRBIntegrator

    doc = SHPRBIntegrator.__doc__
    for name in ("max_depth", "rr_depth", "rebuild_interval", "rebuild_tolerance", "strategy", "hide_emitters", "max_bands",
                 "sh_depth", "proxy_depth", "mis_compensation", "defensive_share"):
        assert f"* - {name}" in doc
    assert '<integrator type="sh_prb">' in doc and "'type': 'sh_prb'" in doc


# ------------------------------------------------------------------ primal image


def test_the_primal_image_is_unbiased_against_path():
    scene = make_scene(rotated=True)
    assert_unbiased(scene, sh_prb(max_depth=4), mi.load_dict({"type": "path", "max_depth": 4}))


# ------------------------------------------------------------------ gradients


@pytest.fixture(scope="module")
def gradients(envmaps_dir):
    """Gradient samples of sh_prb and prb, each on its own copy of the scene."""
    return {name: gradient_samples(gradient_scene(envmaps_dir), integrator)
            for name, integrator in (("sh_prb", sh_prb()),
                                     ("prb", mi.load_dict({"type": "prb", "max_depth": MAX_DEPTH})))}


@pytest.mark.parametrize("parameter", PARAMETERS)
def test_gradients_agree_in_expectation_with_prbs(gradients, parameter):
    column = PARAMETERS.index(parameter)
    ours, theirs = gradients["sh_prb"][:, column], gradients["prb"][:, column]
    assert np.all(np.isfinite(ours))
    t = welch_t(ours, theirs)
    assert abs(t) < T_LIMIT, f"{parameter}: sh_prb {ours.mean():.4g} vs prb {theirs.mean():.4g} (t = {t:.1f})"
    # Both are clearly non-zero: the comparison has something to compare.
    for samples in (ours, theirs):
        assert abs(samples.mean()) > 6 * samples.std(ddof=1) / np.sqrt(len(samples))


def test_a_roughness_gradient_matches_finite_differences_of_path_renders(envmaps_dir):
    scene = gradient_scene(envmaps_dir)
    params = mi.traverse(scene)
    weights = image_weights()
    alpha, h = float(params[CONDUCTOR_ALPHA][0]), 0.05

    # Central differences with common random numbers (the same seeds at both ends).
    path = mi.load_dict({"type": "path", "max_depth": MAX_DEPTH})
    losses = []
    for value in (alpha - h, alpha + h):
        params[CONDUCTOR_ALPHA] = value
        params.update()
        images = [mi.render(scene, integrator=path, spp=2048, seed=50 + k) for k in range(4)]
        losses.append(np.array([weighted_loss(image, weights).numpy().item() for image in images]))
    params[CONDUCTOR_ALPHA] = alpha
    params.update()
    differences = (losses[1] - losses[0]) / (2 * h)

    gradient = gradient_samples(scene, sh_prb(), passes=32, spp=64)[:, PARAMETERS.index(CONDUCTOR_ALPHA)]
    se = np.sqrt(gradient.var(ddof=1) / len(gradient) + differences.var(ddof=1) / len(differences))
    z = (gradient.mean() - differences.mean()) / se
    assert abs(z) < 4, f"sh_prb {gradient.mean():.4g} vs finite differences {differences.mean():.4g} (z = {z:.1f})"
    assert abs(differences.mean()) > 6 * se


def test_a_differentiable_render_reuses_the_sampling_state_built_before_it():
    scene = make_scene(materials={"ggx": {"type": "roughconductor", "alpha": 0.2}})
    params = mi.traverse(scene)
    dr.enable_grad(params["ggx.bsdf.alpha.value"])
    dr.enable_grad(params["env.data"])
    params.update()
    integrator = sh_prb(rebuild_interval=1)
    env = integrator.scenes.get(scene)
    for seed in range(2):
        image = mi.render(scene, params, integrator=integrator, spp=4, seed=2 * seed, seed_grad=2 * seed + 1)
        dr.backward(dr.mean(image, axis=None))
    # Gradients enabled on its inputs neither rebuild it in the primal or replay
    # passes nor attach it to the AD graph.
    assert integrator.scenes.get(scene) is env
    assert dr.grad(params["ggx.bsdf.alpha.value"])[0] != 0


def roughen(scene, alpha):
    params = mi.traverse(scene)
    params["ggx.bsdf.alpha.value"] = alpha
    params.update()


def test_changed_parameters_rebuild_the_state_at_most_every_rebuild_interval_renders():
    scene = make_scene(materials={"ggx": {"type": "roughconductor", "alpha": 0.2}})
    integrator = sh_prb(rebuild_interval=3)
    states = []
    for k in range(7):
        roughen(scene, 0.2 + 0.01 * k)  # an optimisation step: new parameter values every render
        mi.render(scene, integrator=integrator, spp=1, seed=k)
        states.append(integrator.scenes.get(scene, stale_ok=True))
    # Built at renders 0, 3 and 6; the renders in between use the state as it was.
    assert [states[k] is states[k - 1] for k in range(1, 7)] == [True, True, False, True, True, False]


@pytest.mark.parametrize("tolerance, alpha, rebuilt", [
    (None, 0.4, True),       # the default tolerance: a roughness doubled
    (0.0, 0.2001, True),     # no tolerance: any change
    (0.05, 0.2001, False),   # 0.05 %: kept
])
def test_with_rebuild_interval_1_every_render_sees_parameters_that_moved_more_than_rebuild_tolerance(
        tolerance, alpha, rebuilt):
    scene = make_scene(materials={"ggx": {"type": "roughconductor", "alpha": 0.2}})
    integrator = sh_prb(rebuild_interval=1, **({} if tolerance is None else {"rebuild_tolerance": tolerance}))
    mi.render(scene, integrator=integrator, spp=1)
    before = integrator.scenes.get(scene, stale_ok=True)
    roughen(scene, alpha)
    mi.render(scene, integrator=integrator, spp=1)
    assert (integrator.scenes.get(scene, stale_ok=True) is not before) == rebuilt


def test_parameters_that_moved_less_than_rebuild_tolerance_keep_the_state():
    """The rebuild follows how far the parameters moved: 2 % keeps the state, at a render's
    check and on plan() alike; once they have moved 25 % from where it was built (not from
    the last check), it is rebuilt."""
    scene = make_scene(materials={"ggx": {"type": "roughconductor", "alpha": 0.2}})
    integrator = sh_prb(rebuild_interval=1, rebuild_tolerance=0.05)
    mi.render(scene, integrator=integrator, spp=1)
    built = integrator.scenes.get(scene, stale_ok=True)
    for alpha in (0.204, 0.208):  # each within 5 % of the 0.2 it was built for
        roughen(scene, alpha)
        mi.render(scene, integrator=integrator, spp=1)
        integrator.plan(scene)
        assert integrator.scenes.get(scene, stale_ok=True) is built
    assert integrator.scenes.motion() == pytest.approx(0.04, rel=1e-3)
    roughen(scene, 0.25)
    integrator.plan(scene)
    assert integrator.scenes.get(scene, stale_ok=True) is not built
    assert integrator.scenes.motion() == 0.0


def test_a_check_that_keeps_the_state_waits_another_rebuild_interval_before_the_next(monkeypatch):
    """Reading the inputs back is a reduction over each changed parameter: every
    ``rebuild_interval`` renders, not every render once the parameters settle."""
    from mitsuba_shsampling.integrators.environment import SceneCache

    scene = make_scene(materials={"ggx": {"type": "roughconductor", "alpha": 0.2}})
    integrator = sh_prb(rebuild_interval=3, rebuild_tolerance=0.5)
    checks, motion = [], SceneCache.motion
    monkeypatch.setattr(SceneCache, "motion", lambda self, *a: checks.append(1) or motion(self, *a))
    for k in range(10):
        roughen(scene, 0.2 + 0.001 * k)  # small steps: the state is kept
        mi.render(scene, integrator=integrator, spp=1, seed=k)
    assert len(checks) == 3  # at renders 3, 6 and 9


def test_the_motion_of_a_texture_is_its_texels_relative_change_and_a_new_transform_is_infinite():
    scene = make_scene(materials={"ggx": {"type": "roughconductor", "alpha": 0.2}})
    integrator = sh_prb()
    integrator.plan(scene)
    params = mi.traverse(scene)
    texels = params["env.data"].numpy()
    params["env.data"] = mi.TensorXf(texels * 1.1)
    params.update()
    assert integrator.scenes.motion() == pytest.approx(0.1, rel=1e-4)
    params["env.to_world"] = mi.ScalarTransform4f().rotate([0, 0, 1], 30)
    params.update()
    assert integrator.scenes.motion() == math.inf


def test_a_stale_state_still_renders_an_unbiased_image():
    scene = make_scene(materials={"ggx": {"type": "roughconductor", "alpha": 0.05},
                                  "diffuse": {"type": "diffuse"}})
    integrator = sh_prb(max_depth=4, rebuild_interval=1000)
    mi.render(scene, integrator=integrator, spp=1)  # the state for alpha 0.05 and the sun map
    state = integrator.scenes.get(scene, stale_ok=True)
    roughen(scene, 0.4)
    params = mi.traverse(scene)
    # The sun moves to the other hemisphere.
    params["env.data"] = mi.TensorXf(params["env.data"].numpy()[::-1].copy())
    params.update()
    assert_unbiased(scene, integrator, mi.load_dict({"type": "path", "max_depth": 4}))
    assert integrator.scenes.get(scene, stale_ok=True) is state


def test_the_replay_follows_the_primal_paths_so_the_scale_derivative_is_the_image_over_the_scale():
    # Every contribution is linear in the envmap's scale: along the same paths, the
    # forward-mode derivative of each pixel is its primal value over the scale.
    scene = make_scene(rotated=True, materials={"ggx": {"type": "roughconductor", "alpha": 0.2},
                                                "diffuse": {"type": "diffuse"}})
    params = mi.traverse(scene)
    params["env.scale"] = 2.0
    params.update()
    integrator = sh_prb(max_depth=4, rr_depth=2)
    image = integrator.render(scene, seed=7, spp=4).numpy()
    dr.enable_grad(params["env.scale"])
    dr.set_grad(params["env.scale"], 1.0)
    derivative = integrator.render_forward(scene, params, seed=7, spp=4).numpy()
    assert image.mean() > 0
    np.testing.assert_allclose(derivative, image / 2.0, rtol=1e-4, atol=1e-6)


# ------------------------------------------------------------ frozen optimisation steps

def optimisation(envmaps_dir, integrator, steps, freeze, refresh_at=()):
    """Adam on the conductor's roughness towards a target rendered by ``path``; the step
    (render, loss, backward) traced or ``dr.freeze``-d. Before the first step and at each of
    ``refresh_at`` the integrator plans on the host (``integrator.plan``). Returns the
    roughness after each step, the frozen function's recordings so far after each step (0s
    when traced) and the sampling state each step rendered with."""
    scene = gradient_scene(envmaps_dir)
    target = mi.render(scene, integrator=mi.load_dict({"type": "path", "max_depth": MAX_DEPTH}), spp=64)
    params = mi.traverse(scene)
    opt = mi.ad.Adam(lr=0.05)
    opt[CONDUCTOR_ALPHA] = mi.Float(0.6)
    params.update(opt)

    def step(scene, params, integrator, seed, target):
        image = mi.render(scene, params, integrator=integrator, spp=4, seed=seed)
        loss = dr.mean(dr.square(image - target), axis=None)
        dr.backward(loss)
        return loss

    run = mitsuba_shsampling.freeze(step) if freeze else step
    integrator.plan(scene)
    trajectory, states, recordings = [], [], []
    for k in range(steps):
        if k in refresh_at:
            integrator.plan(scene)
        dr.eval(run(scene, params, integrator, dr.opaque(mi.UInt32, 2 * k), target))
        states.append(integrator.scenes.get(scene, stale_ok=True))
        recordings.append(run.n_recordings if freeze else 0)
        opt.step()
        opt[CONDUCTOR_ALPHA] = dr.clip(opt[CONDUCTOR_ALPHA], 0.01, 1.0)
        params.update(opt)
        trajectory.append(float(opt[CONDUCTOR_ALPHA][0]))
    return np.array(trajectory), recordings, states


def test_a_frozen_optimisation_step_replays_the_traced_steps_trajectory(envmaps_dir):
    """Planned before the loop, the step records once (Dr.Jit's second recording makes the
    changed literals opaque) and replays the traced step's arithmetic: its sampling state
    stays the one planned, as the traced step's does within rebuild_interval."""
    traced, _, _ = optimisation(envmaps_dir, sh_prb(rebuild_interval=1000), 8, freeze=False)
    frozen, recordings, states = optimisation(envmaps_dir, sh_prb(rebuild_interval=1000), 8, freeze=True)
    assert recordings[-1] <= 2
    assert traced[-1] < 0.55  # it moved
    np.testing.assert_allclose(frozen, traced, rtol=1e-4)
    assert all(state is states[0] for state in states)


def test_planning_again_outside_the_frozen_step_rebuilds_its_state_and_records_again(envmaps_dir):
    frozen, recordings, states = optimisation(envmaps_dir, sh_prb(), 6, freeze=True, refresh_at=(3,))
    assert states[0] is states[1] is states[2]  # a replay runs no Python: nothing is rebuilt
    assert states[3] is not states[2] and states[3] is states[5]
    assert recordings[2] == recordings[1] and recordings[3] > recordings[2]  # a new state is recorded again
    assert frozen[-1] < 0.6


def test_frozen_steps_of_two_objects_with_equal_options_on_two_scenes_replay_without_rebuilding(envmaps_dir):
    """Two optimisations in one process (equal options, two scenes), their frozen steps in
    turn: each replays its own scene's state (before, the second plan took the first's
    place, and the first scene's next frozen step was a FrozenBeforePlanError)."""
    scenes = [gradient_scene(envmaps_dir), gradient_scene(envmaps_dir)]
    integrators = [sh_prb(), sh_prb()]

    @mitsuba_shsampling.freeze
    def step(scene, integrator, seed):
        return mi.render(scene, integrator=integrator, spp=1, seed=seed)

    for integrator, scene in zip(integrators, scenes):
        integrator.plan(scene)
    states = [integrator.scenes.get(scene, stale_ok=True) for integrator, scene in zip(integrators, scenes)]
    assert states[0] is not states[1]
    for k in range(3):
        for integrator, scene, state in zip(integrators, scenes, states):
            dr.eval(step(scene, integrator, dr.opaque(mi.UInt32, k)))
            assert integrator.scenes.get(scene, stale_ok=True) is state


def test_a_plan_for_the_gradients_weighs_the_candidates_on_the_unknowns_and_leaves_their_gradients_as_they_were(
        envmaps_dir):
    """plan_for gradients: after the image's plan, the plan itself, every material on
    environment and every material on product are weighed by the unknowns' gradient
    variance x predicted time; the candidate kept runs, is reported, and the unknown's own
    gradient is what it was before."""
    scene = gradient_scene(envmaps_dir)
    params = mi.traverse(scene)
    alpha = mi.Float(params[CONDUCTOR_ALPHA])
    dr.enable_grad(alpha)
    params[CONDUCTOR_ALPHA] = alpha
    params.update()
    dr.set_grad(alpha, 0.25)
    integrator = sh_prb(plan_for="gradients")
    choice = integrator.plan(scene)
    plan = choice.gradient_plan
    assert plan["unknowns"] == [CONDUCTOR_ALPHA]
    assert set(plan["scores"]) <= {"plan", "environment", "product"} and len(plan["scores"]) >= 2
    assert plan["kept"] == min(plan["scores"], key=plan["scores"].get)
    assert all(np.isfinite(v) and v > 0 for v in plan["scores"].values())
    assert "for the gradients" in choice.summary()
    assert dr.grad(alpha)[0] == pytest.approx(0.25)
    uses_product = any(m.strategy.uses_product for m in choice.materials)
    assert uses_product == (plan["kept"] == "product" or (plan["kept"] == "plan" and not choice.lean))


def test_after_a_plan_for_the_gradients_the_optimisers_unknowns_still_get_their_gradients(envmaps_dir):
    """The gradient pilots must leave the scene wired to the optimiser's values: an envmap's
    texels (which the emitter copies) and a roughness still receive nonzero gradients from the
    next step. (Taking the unknowns out of the scene and putting them back cut that wire: the
    texels' gradients were 0 from then on.)"""
    scene = gradient_scene(envmaps_dir)
    params = mi.traverse(scene)
    texels = next(k for k in params.keys() if k.endswith(".data") and "EnvironmentMap" in params.properties[k][2].class_name())
    opt = mi.ad.Adam(lr=0.0, params={CONDUCTOR_ALPHA: params[CONDUCTOR_ALPHA], texels: params[texels]})
    params.update(opt)
    integrator = sh_prb(plan_for="gradients")
    assert integrator.plan(scene).gradient_plan["unknowns"] == sorted([CONDUCTOR_ALPHA, texels])
    image = mi.render(scene, params, integrator=integrator, spp=4, seed=3)
    dr.backward(dr.mean(dr.square(image), axis=None))
    for key in (CONDUCTOR_ALPHA, texels):
        grad = np.asarray(dr.grad(opt[key]).numpy())
        assert np.all(np.isfinite(grad)) and np.abs(grad).sum() > 0, key


def test_the_image_plan_is_the_default_and_a_scene_without_unknowns_gets_no_plan_for_the_gradients(envmaps_dir):
    scene = gradient_scene(envmaps_dir)
    assert sh_prb().options.plan_for == "image"
    assert sh_prb().plan(scene).gradient_plan == {}
    assert sh_prb(plan_for="gradients").plan(scene).gradient_plan == {}  # no parameter has a gradient


def first_frozen_render_error(freeze, scene, integrator):
    """The chain of errors (outermost first) that a one-pass render frozen by ``freeze`` raises."""
    @freeze
    def step(scene, integrator, seed):
        return mi.render(scene, integrator=integrator, spp=1, seed=seed)

    with pytest.raises(RuntimeError) as caught:
        step(scene, integrator, dr.opaque(mi.UInt32, 0))
    chain, error = [], caught.value
    while error is not None:
        chain.append(error)
        error = error.__cause__
    return chain


def test_a_frozen_step_before_any_plan_is_a_clear_error(envmaps_dir):
    from mitsuba_shsampling.integrators.environment import FrozenBeforePlanError

    chain = first_frozen_render_error(mitsuba_shsampling.freeze, gradient_scene(envmaps_dir), sh_prb())
    assert any(isinstance(e, FrozenBeforePlanError) and "integrator.plan(scene)" in str(e) for e in chain)


def test_dr_freeze_with_the_cycle_collector_running_is_a_clear_error_not_an_abort(envmaps_dir):
    from mitsuba_shsampling.integrators.sharing import FrozenWithCollectorError

    scene = gradient_scene(envmaps_dir)
    integrator = sh_prb()
    integrator.plan(scene)
    chain = first_frozen_render_error(dr.freeze, scene, integrator)
    assert any(isinstance(e, FrozenWithCollectorError) and "mitsuba_shsampling.freeze" in str(e) for e in chain)
