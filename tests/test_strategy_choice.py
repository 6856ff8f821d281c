"""Specification of the per-material choice of the environment strategy (``strategy`` ``auto``).

The chooser predicts each strategy's variance at the camera's first hits by
quadrature (visibility included) and weighs it against the strategies' costs (a
cost model; timed pilot passes with ``plan`` ``measure``). On
synthetic cases the answer is known; the predictions must agree with the
variance measured in renders; a scene that mixes strategies stays unbiased;
and where no product strategy pays, no product code is traced.
"""

import warnings

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

mi.set_variant("llvm_ad_rgb")

from mitsuba_shsampling.envmap.synthetic import envmap_emitter, sun_sky_latlong, window_latlong  # noqa: E402
from mitsuba_shsampling.integrators import register  # noqa: E402
from mitsuba_shsampling.integrators.chooser import (choose_strategies, confirm_by_timing,  # noqa: E402
                                                    minimise_error_at_equal_time)
from mitsuba_shsampling.integrators import pilots as pilots_module  # noqa: E402
from mitsuba_shsampling.integrators import chooser as chooser_module  # noqa: E402
from mitsuba_shsampling.integrators.pilots import (FILM_PILOT_PIXELS, LEAN, Candidate, Pilots, calibrate,  # noqa: E402
                                                   camera_sample_pass, cosine_pilot, film_mean_pixel_variance,
                                                   film_variance_and_error, film_variance_factor,
                                                   independent_errors, measure_pass_costs, paired_errors,
                                                   weighed_calibration)
from mitsuba_shsampling.integrators.quadrature import camera_frames, frame_variances  # noqa: E402
from mitsuba_shsampling.integrators.environment import ProductEnvironment  # noqa: E402
from mitsuba_shsampling.integrators.options import DirectOptions, OptionError, PathOptions  # noqa: E402
from mitsuba_shsampling.integrators.strategy import Strategy  # noqa: E402
from mitsuba_shsampling.report.metrics import pixel_variance  # noqa: E402

from test_integrators import MATERIALS, assert_unbiased, make_scene  # noqa: E402


E, EO, P, PO = Strategy.ENVIRONMENT, Strategy.ENVIRONMENT_ONLY, Strategy.PRODUCT, Strategy.PRODUCT_ONLY
BO = Strategy.BSDF_ONLY

#: Pilot pass times of a scene filled by one material: the product's code costs every
#: lane 7 %, its walks another 20-30 % (the proportions measured on the material studio).
PASS_TIME = {LEAN: 1.0, E.label: 1.07, P.label: 1.3, PO.label: 1.35}

#: Light from above the floor (envmap +Y is the scene's +Z here: see ``floor_scene``).
SUN = envmap_emitter(sun_sky_latlong(256, 512, sun_direction=(0.4, 0.5, 0.75), sun_radius_deg=0.5,
                                     sun_radiance=1e5))
WINDOW = envmap_emitter(window_latlong(128, 256, direction=(0.3, 0.5, 0.8)))
#: A lone disk light on black: two map samples beat one map and one BSDF sample on a diffuse floor.
DISK = envmap_emitter(sun_sky_latlong(128, 256, sun_direction=(0.3, 0.8, 0.5), sun_radius_deg=12.0,
                                      sun_radiance=50.0, sky_radiance=0.0))
#: A uniform sky, as Mitsuba's ``constant`` emitter: the BSDF's own sampling is the best strategy.
UNIFORM = {"type": "constant", "radiance": {"type": "rgb", "value": [0.8, 0.9, 1.0]}}


@pytest.fixture(scope="module", autouse=True)
def registered():
    register()


def floor_scene(bsdf: dict, emitter, rfilter: str = "box", size: int = 32) -> mi.Scene:
    """A floor filling the view from above at 45 degrees, lit by ``emitter`` alone (no
    edge in the frame: pixels across an edge add an antialiasing variance that every
    strategy shares and the quadrature leaves out)."""
    return mi.load_dict({
        "type": "scene", "env": emitter,
        "sensor": {"type": "perspective", "fov": 30,
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0, -3, 3], target=[0, 0, 0], up=[0, 0, 1]),
                   "film": {"type": "hdrfilm", "width": size, "height": size, "rfilter": {"type": rfilter}},
                   "sampler": {"type": "independent"}},
        "floor": {"type": "rectangle", "to_world": mi.ScalarTransform4f().scale(10), "bsdf": bsdf}})


def chosen(bsdf: dict, emitter) -> tuple[Strategy, dict]:
    scene = floor_scene(bsdf, emitter)
    env = ProductEnvironment(scene, DirectOptions(), carry_all=True)
    choice = choose_strategies(env, scene.sensors()[0], 1, 1, render_pass=None, pilots=Pilots(PASS_TIME))
    (material,) = choice.materials
    return material.strategy, material.variance


# ------------------------------------------------------------ known answers

def test_a_diffuse_lobe_under_a_tiny_sun_keeps_mitsubas_compensated_environment_sampling():
    """The compensated map puts nearly every sample on the sun, which carries nearly all
    the light; the cosine-sampled BSDF sample covers the sky. The product adds nothing a
    diffuse lobe could, and costs time."""
    strategy, variance = chosen({"type": "diffuse"}, SUN)
    assert strategy == E
    assert variance[P] > 0.9 * variance[E]


def test_a_glossy_lobe_under_a_broad_bright_window_gets_the_product():
    strategy, variance = chosen({"type": "roughconductor", "distribution": "ggx", "alpha": 0.2}, WINDOW)
    assert strategy == P
    assert variance[P] < 0.6 * min(variance[E], variance[BO])


@pytest.mark.parametrize("alpha", [0.1, 0.03])
def test_a_lobe_much_narrower_than_the_window_gives_every_sample_to_the_bsdf(alpha):
    """The BSDF's own sampling follows a sharp lobe closely, and the window's radiance barely
    varies across it: bsdf_only (Mitsuba's BSDF sampling alone) beats the product, whose SH
    proxy is a blurred copy of the lobe (predictions checked against renders in
    test_predicted_variance_ratios_match_the_rendered_ones)."""
    strategy, variance = chosen({"type": "roughconductor", "distribution": "ggx", "alpha": alpha}, WINDOW)
    assert strategy == BO
    assert variance[BO] < 0.75 * min(variance[E], variance[P], variance[PO])


def test_a_diffuse_lobe_under_a_broad_window_gives_every_sample_to_the_product():
    """Cosine x window is what the product follows; a BSDF sample would waste half the budget."""
    strategy, variance = chosen({"type": "diffuse"}, WINDOW)
    assert strategy == PO
    assert variance[PO] < 0.5 * min(variance[E], variance[P])


def test_a_material_also_seen_from_its_back_keeps_its_product_strategies():
    """Where the camera sees a product material's back (a one-sided BSDF, black there) a
    lane has no lobe and samples the environment alone: the product strategies are
    predicted as that, not left unknown (an unknown once ruled them out for the
    material and, through the pilots' calibration, for the whole scene)."""
    scene = mi.load_dict({
        "type": "scene", "env": WINDOW,
        "sensor": {"type": "perspective", "fov": 40,
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0, -3, 3], target=[0, 0, 0], up=[0, 0, 1]),
                   "film": {"type": "hdrfilm", "width": 32, "height": 32, "rfilter": {"type": "box"}}},
        "floor": {"type": "rectangle", "to_world": mi.ScalarTransform4f().scale(10), "bsdf": {"type": "ref", "id": "paint"}},
        "paint": {"type": "diffuse"},
        "card": {"type": "rectangle", "bsdf": {"type": "ref", "id": "paint"},  # its back faces the camera
                 "to_world": mi.ScalarTransform4f().translate([0, 0, 0.5]).rotate([1, 0, 0], -135)}})
    env = ProductEnvironment(scene, DirectOptions(), carry_all=True)
    si, bsdf, _ = camera_frames(scene, scene.sensors()[0])
    variances = frame_variances(env, si, bsdf, 1, 1)
    back = si.wi.z.numpy() < 0
    assert back.any() and (~back).any()
    assert np.all(np.isfinite(variances[:, [E, P, EO, PO]]))
    assert np.array_equal(variances[back, P], variances[back, E])
    assert np.array_equal(variances[back, PO], variances[back, EO])
    choice = choose_strategies(env, scene.sensors()[0], 1, 1, render_pass=None, pilots=Pilots(PASS_TIME))
    assert choice.materials[0].strategy == PO


def test_a_dirac_part_rules_out_the_strategies_without_a_bsdf_sample():
    _, variance = chosen({"type": "plastic"}, WINDOW)
    assert set(variance) == {E, P}


def test_the_coordinate_descent_pays_for_time_only_where_the_variance_drops_enough():
    variance = {"big_glossy": {E: 10.0, P: 3.0}, "small_diffuse": {E: 1.0, P: 0.97}}
    share = {"big_glossy": 0.5, "small_diffuse": 0.5}
    extra_time = {m: {E: 0.0, P: 0.4} for m in variance}
    choice, error = minimise_error_at_equal_time(variance, 0.0, share, base_time=1.0, extra_time=extra_time)
    assert choice == {"big_glossy": P, "small_diffuse": E}
    assert error == pytest.approx((3.0 + 1.0) * (1.0 + 0.2))


def test_the_descent_starts_a_material_forced_off_the_environment_on_its_own_strategy():
    """Whatever the materials' order: a forced material listed after the others once made
    the descent price them with it on the environment, a strategy its row does not have."""
    variance = {"glossy": {E: 4.0, P: 1.0}, "forced": {P: 2.0}}
    share = {"glossy": 0.5, "forced": 0.5}
    extra = {"glossy": {E: 0.0, P: 0.4}, "forced": {P: 0.4}}
    choice, _ = minimise_error_at_equal_time(variance, 0.0, share, base_time=1.0, extra_time=extra)
    assert choice == {"glossy": P, "forced": P}


def test_a_near_tie_is_settled_by_timing_the_rival_assignments_as_wholes():
    """The per-material times are differences of pilot times; where the model puts two
    assignments within a few per cent, both are timed whole and the measured time decides."""
    variance = {"glossy": {E: 4.0, P: 1.0, PO: 1.02}, "ground": {E: 1.0, P: 0.9}}
    share = {"glossy": 0.2, "ground": 0.8}
    extra = {"glossy": {E: 0.0, P: 0.5, PO: 0.25}, "ground": {E: 0.0, P: 1.0}}
    best, _ = minimise_error_at_equal_time(variance, 0.0, share, base_time=1.0, extra_time=extra)
    assert best == {"glossy": PO, "ground": E}  # the model's pick: the cheaper per-share time
    timed = []

    def time_assignments(assignments):
        timed.append(assignments)
        return {name: 1.25 if a["glossy"] == PO else 1.1 for name, a in assignments.items()}

    confirmed = confirm_by_timing(best, variance, 0.0, share, 1.0, extra, time_assignments)
    assert confirmed == {"glossy": P, "ground": E}
    (assignments,) = timed
    assert list(assignments.values())[0] == best and {"glossy": P, "ground": E} in assignments.values()
    # A clear winner is not timed again.
    far = {"glossy": {E: 4.0, P: 1.0, PO: 3.0}, "ground": {E: 1.0, P: 0.95}}
    best, _ = minimise_error_at_equal_time(far, 0.0, share, base_time=1.0, extra_time=extra)
    assert confirm_by_timing(best, far, 0.0, share, 1.0, extra, lambda a: pytest.fail("timed")) == best


def test_a_lobe_sampled_from_the_cheap_cosine_tables_takes_the_product_where_the_sh_walk_would_not_pay():
    """The same variances; the diffuse material's product costs what its tables cost, the
    glossy one's what its SH walk costs (each per unit of film share)."""
    variance = {"glossy": {E: 10.0, P: 3.0}, "diffuse": {E: 1.0, P: 0.8}}
    share = {"glossy": 0.2, "diffuse": 0.8}
    one_cost = {m: {E: 0.0, P: 0.4} for m in variance}
    choice, _ = minimise_error_at_equal_time(variance, 0.0, share, base_time=1.0, extra_time=one_cost)
    assert choice == {"glossy": P, "diffuse": E}
    per_kind = {"glossy": {E: 0.0, P: 0.4}, "diffuse": {E: 0.0, P: 0.05}}
    choice, error = minimise_error_at_equal_time(variance, 0.0, share, base_time=1.0, extra_time=per_kind)
    assert choice == {"glossy": P, "diffuse": P}
    assert error == pytest.approx((3.0 + 0.8) * (1.0 + 0.2 * 0.4 + 0.8 * 0.05))


def test_environment_only_is_chosen_where_its_measured_time_pays_and_not_elsewhere():
    """Under a lone disk light on black, two map samples halve the diffuse floor's variance
    against one map sample and one BSDF sample. environment_only does not cost what
    environment costs (a second map sample and shadow ray instead of the BSDF sample's
    occlusion query: 4-25 % of a pass measured), so its pilot's time decides: it is kept
    when it costs a little more, dropped when it costs three times the pass."""
    scene = floor_scene({"type": "diffuse"}, DISK)
    products_never_pay = {P.label: 50.0, PO.label: 50.0}

    def lean_choice(environment_only_time):
        env = ProductEnvironment(scene, DirectOptions(), carry_all=True)
        pilots = Pilots({**PASS_TIME, **products_never_pay, EO.label: environment_only_time})
        choice = choose_strategies(env, scene.sensors()[0], 1, 1, render_pass=None, pilots=pilots)
        assert choice.lean
        (material,) = choice.materials
        assert material.variance[EO] < 0.6 * material.variance[E]
        return material.strategy

    assert lean_choice(1.3) == EO
    assert lean_choice(3.0) == E


@pytest.mark.parametrize("bsdf", [{"type": "diffuse"}, {"type": "roughconductor", "alpha": 0.3}],
                         ids=["diffuse", "glossy"])
def test_under_a_uniform_sky_every_sample_goes_to_the_bsdfs_own_sampling(bsdf):
    """Under a constant emitter the BSDF's sampling is the best of Mitsuba's strategies (a
    diffuse floor's samples are then exact but for visibility): bsdf_only, predicted below
    half the environment strategy's variance, with the products never paying."""
    strategy, variance = chosen(bsdf, UNIFORM)
    assert strategy == BO
    assert variance[BO] < 0.5 * variance[E] and variance[BO] < variance[EO]
    # And in renders. (Not as a ratio to the prediction: under a uniform sky every strategy's
    # variance is small beside what the pixels' footprints add, which the quadrature leaves out.)
    scene = floor_scene(bsdf, UNIFORM)

    def rendered(strategy):
        integrator = mi.load_dict({"type": "sh_direct", "strategy": strategy.label})
        images = np.stack([np.array(mi.render(scene, integrator=integrator, spp=16, seed=k)) for k in range(16)])
        return pixel_variance(images).mean()

    assert rendered(BO) < 0.5 * rendered(E)


def test_a_pilot_runs_environment_only_where_the_quadrature_prefers_it():
    """The same floor with no pilots given: one pilot pass puts it on environment_only,
    and that pilot's time enters the choice."""
    scene = floor_scene({"type": "diffuse"}, DISK)
    env = ProductEnvironment(scene, DirectOptions(), carry_all=True)
    (key,) = env.strategies.ids
    ran = []
    choice = choose_strategies(env, scene.sensors()[0], 1, 1,
                               render_pass=lambda spp, seed: ran.append(env.strategies.of(key)))
    assert EO in ran
    assert EO.label in choice.pass_time


def test_materials_where_nothing_pays_leave_the_product_out_of_the_kernel():
    scene = floor_scene({"type": "diffuse"}, SUN)
    env = ProductEnvironment(scene, DirectOptions(), carry_all=True)
    choice = choose_strategies(env, scene.sensors()[0], 1, 1, render_pass=None, pilots=Pilots(PASS_TIME))
    assert choice.lean and env.warp is None and env.warp_plain is None
    assert choice.predicted_gain == 1.0


def test_a_lean_plan_says_by_how_much_the_best_product_plan_missed_the_required_gain(monkeypatch):
    """The best assignment with a product strategy is kept beside the choice, taken or not, so
    that a user reads why a plan stayed lean; where no assignment with the product is the best
    (a diffuse floor under a tiny sun) there is none to show."""
    from mitsuba_shsampling.integrators import chooser
    scene = floor_scene({"type": "roughconductor", "distribution": "ggx", "alpha": 0.2}, WINDOW)
    env = ProductEnvironment(scene, DirectOptions(), carry_all=True)
    taken = choose_strategies(env, scene.sensors()[0], 1, 1, render_pass=None, pilots=Pilots(PASS_TIME))
    candidate = taken.product_candidate
    assert not taken.lean and candidate["predicted_gain"] == taken.predicted_gain > chooser.REQUIRED_GAIN
    assert candidate["required_gain"] == chooser.REQUIRED_GAIN
    assert candidate["strategies"] == taken.assignment()
    assert "required" not in taken.summary()

    monkeypatch.setattr(chooser, "REQUIRED_GAIN", 2 * taken.predicted_gain)
    env = ProductEnvironment(scene, DirectOptions(), carry_all=True)
    missed = choose_strategies(env, scene.sensors()[0], 1, 1, render_pass=None, pilots=Pilots(PASS_TIME))
    assert missed.lean and missed.product_candidate == dict(candidate, required_gain=2 * taken.predicted_gain)
    assert (f"the best product plan: predicted x{candidate['predicted_gain']:.2f}, "
            f"{2 * taken.predicted_gain:.2f} required" in missed.summary())

    scene = floor_scene({"type": "diffuse"}, SUN)
    env = ProductEnvironment(scene, DirectOptions(), carry_all=True)
    none = choose_strategies(env, scene.sensors()[0], 1, 1, render_pass=None, pilots=Pilots(PASS_TIME))
    assert none.lean and none.product_candidate == {} and "required" not in none.summary()


# ------------------------------------------------------------ predictions against renders

def test_the_quadratures_camera_hits_are_traced_in_one_kernel():
    """A gather from an interaction whose fields are not evaluated evaluates each field in
    a kernel of its own, each tracing the rays again: some 30 kernels to compile on a
    new scene (1.6 s of the material studio's cold plan). One kernel traces them all, one
    keeps the hits on smooth BSDFs."""
    scene = floor_scene({"type": "diffuse"}, envmap_emitter(window_latlong(32, 16)))
    with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
        dr.kernel_history()
        si, bsdf, total = camera_frames(scene, scene.sensors()[0], count=256)
        dr.eval(si, bsdf)
        kernels = [k for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT]
    assert dr.width(si) == total == 256  # the floor fills the view
    assert len(kernels) == 2


@pytest.mark.parametrize("case", ["diffuse_sun", "glossy_window", "diffuse_window"])
def test_predicted_variance_ratios_match_the_rendered_ones(case):
    """Per strategy, the variance over the environment strategy's: the prediction
    (quadrature at the camera's first hits) against the per-pixel variance of 32
    renders, within a factor 1.5. Both are estimates of second moments, whose own
    spread under a 1e5 sun is tens of per cent; the choice needs the ordering.
    (bsdf_only is left out under the sun: its rare hits on a 0.5-degree disc of 1e5 make
    32 renders' variance a draw from a heavy tail.)"""
    bsdf, emitter, strategies = {
        "diffuse_sun": ({"type": "diffuse"}, SUN, (P, PO)),
        "glossy_window": ({"type": "roughconductor", "alpha": 0.1}, WINDOW, (P, PO, EO, BO)),
        "diffuse_window": ({"type": "diffuse"}, WINDOW, (P, PO, EO, BO))}[case]
    scene = floor_scene(bsdf, emitter)
    env = ProductEnvironment(scene, DirectOptions(), carry_all=True)
    si, bsdf_ptr, _ = camera_frames(scene, scene.sensors()[0])
    predicted = np.nanmean(frame_variances(env, si, bsdf_ptr, 1, 1, directions=1024), axis=0)

    def rendered(strategy):
        integrator = mi.load_dict({"type": "sh_direct", "strategy": strategy.label})
        images = np.stack([np.array(mi.render(scene, integrator=integrator, spp=16, seed=k)) for k in range(32)])
        return pixel_variance(images).mean()

    measured_env = rendered(E)
    for strategy in strategies:
        measured, expected = rendered(strategy) / measured_env, predicted[strategy] / predicted[E]
        assert abs(np.log(measured / expected)) < np.log(1.5), (strategy.label, measured, expected)


def test_predicted_variances_are_averaged_over_colour_channels_as_the_reports_mse():
    """The report's MSE averages the channels' squared errors (report.metrics), so the
    prediction does too: a sky of blue alone has a third of the grey sky's variance
    (in luminance it would have 0.07^2 of it, and a strategy that is poor in the blue
    sky of a sunny map would look good)."""
    image = window_latlong(64, 128, direction=(0.3, 0.5, 0.8))
    variances = []
    for tint in ([1.0, 1.0, 1.0], [0.0, 0.0, 1.0]):
        scene = floor_scene({"type": "roughconductor", "alpha": 0.2}, envmap_emitter(image * np.float32(tint)))
        env = ProductEnvironment(scene, DirectOptions(), carry_all=True)
        si, bsdf_ptr, _ = camera_frames(scene, scene.sensors()[0], count=256)
        variances.append(np.mean(frame_variances(env, si, bsdf_ptr, 1, 1), axis=0))
    grey, blue = variances
    assert np.allclose(blue / grey, 1 / 3, rtol=1e-3), blue / grey


# ------------------------------------------------------------ the pilots and the shared variance

def test_the_pilots_measure_the_reports_per_pixel_variance_where_the_images_are():
    """The film's mean of report.metrics.pixel_variance (unbiased across the passes, channels
    averaged over the finite ones, 0 where none is), computed on the device images."""
    rng = np.random.default_rng(0)
    images = (rng.random((3, 17, 23, 3)) * 5).astype(np.float32)
    images[0, 3, 4, 1] = np.nan        # one channel of a pixel lost
    images[1, 5, 6, :] = np.inf        # a whole pixel lost
    images[2, 7, 8, 0] = -np.inf
    expected = float(np.mean(pixel_variance(images.astype(np.float64))))
    assert film_mean_pixel_variance([mi.TensorXf(i) for i in images]) == pytest.approx(expected, rel=1e-12)


def test_the_pilots_film_variance_comes_with_its_standard_error_over_the_pixels():
    """The error is the per-pixel variances' spread over the square root of the pixels: a
    film whose variance sits in a few pixels is measured more loosely than one that spreads
    the same variance evenly."""
    rng = np.random.default_rng(1)
    even = rng.normal(size=(3, 40, 50, 3))
    spiky = even * np.where(rng.random((40, 50, 1)) < 0.01, 10.0, 1.0)
    for images in (even, spiky):
        per_pixel = pixel_variance(images)
        mean, error = film_variance_and_error([mi.TensorXf(i.astype(np.float32)) for i in images])
        assert mean == pytest.approx(np.mean(per_pixel), rel=1e-6)
        assert error == pytest.approx(np.std(per_pixel, ddof=1) / np.sqrt(per_pixel.size), rel=1e-5)
    relative = [film_variance_and_error([mi.TensorXf(i.astype(np.float32)) for i in images])
                for images in (even, spiky)]
    assert relative[1][1] / relative[1][0] > 3 * relative[0][1] / relative[0][0]


#: A diffuse floor whose albedo alternates 400 times across the view: within a pixel the
#: texture varies more than the lighting estimate does.
FINE_CHECKER = {"type": "diffuse", "reflectance": {"type": "checkerboard", "color0": 0.05, "color1": 0.9,
                                                   "to_uv": mi.ScalarTransform4f().scale([400, 400, 1])}}


@pytest.mark.parametrize("rfilter, expected", [("box", 1.0), ("tent", 4 / 9), ("gaussian", 0.319)])
def test_a_pixels_variance_is_the_samples_over_the_filters_effective_sample_count(rfilter, expected):
    """sum w f / sum w over spp samples a pixel: sigma^2 (int w^2 / (int w)^2)^2 / spp."""
    film = mi.load_dict({"type": "hdrfilm", "width": 8, "height": 8, "rfilter": {"type": rfilter}})
    assert film_variance_factor(film, 4) == pytest.approx(expected / 4, rel=2e-3)


@pytest.mark.parametrize("rfilter", ["box", "gaussian"])
def test_the_pilots_run_what_they_time_and_their_images_confirm_the_quadrature(rfilter):
    """Without texture edges or other light, each pilot's film variance (its images'
    per-pixel variance over the filter's factor) is what the quadrature predicts,
    for every strategy, and nothing is shared. (A pilot re-enters the integrator's
    render through Mitsuba's; it once ran the choice again there, and the
    product_only pilot ran the product.)"""
    scene = floor_scene({"type": "diffuse"}, WINDOW, rfilter, size=96)
    measured = mi.load_dict({"type": "sh_direct", "plan": "measure", "plan_file": ""})
    mi.render(scene, integrator=measured, spp=1)
    assert set(measured.choice(scene).pilot_variance) == {LEAN, E.label, P.label, PO.label}
    # The default plan runs the same pilots for their images alone (no lean kernel: it
    # would be one more kernel to trace, and only its time told it apart).
    integrator = mi.load_dict({"type": "sh_direct"})
    mi.render(scene, integrator=integrator, spp=1)
    choice = integrator.choice(scene)
    assert set(choice.pilot_variance) == {E.label, P.label, PO.label}
    for name, (predicted, measured) in choice.pilot_variance.items():
        assert measured == pytest.approx(predicted, rel=0.15), name
    assert choice.shared_variance < 0.05 * choice.pilot_variance[E.label][1]
    assert choice.pilot_variance[PO.label][1] < 0.5 * choice.pilot_variance[P.label][1]
    # So the pilots leave the quadrature's variances nearly as they were.
    assert all(0.85 < factor < 1.15 for factor in choice.pilots.calibration.values())
    # And on the floor's own pixels (all of them) each product pilot measured the variance it
    # removes as the quadrature predicted it.
    (by_strategy,) = choice.pilots.by_material.values()
    assert set(by_strategy) == {P, PO}
    for strategy, m in by_strategy.items():
        row = dict(m.quadrature)
        predicted = row[E.label] - row[strategy.label]
        assert m.difference == pytest.approx(predicted, rel=0.15, abs=3 * m.error), strategy


def test_the_pilots_scale_a_strategys_predicted_variance_to_what_its_images_measured():
    """Pilot images that show the product at twice the quadrature's variance (and the
    environment as predicted, nothing shared) double the product's predicted variances."""
    variance = {1: {E: 4.0, P: 1.0}, 2: {E: 2.0, P: 2.0}}
    candidates = {E.label: Candidate({1: E, 2: E}), P.label: Candidate({1: P, 2: E})}
    model = {E.label: 0.5 + 6.0, P.label: 0.5 + 1.0 + 2.0}
    pilots = Pilots({}, spp=1)
    calibrate(pilots, {E.label: 6.5, P.label: 0.5 + 2.0 * 1.0 + 2.0}, model, candidates, variance, rest=0.5)
    assert pilots.shared_variance == 0.0 and pilots.calibration == {P: pytest.approx(2.0)}
    # A film that measures more than the environment's quadrature: the excess is shared.
    calibrate(pilots, {E.label: 9.5, P.label: 3.0 + 0.5 + 1.0 + 2.0}, model, candidates, variance, rest=0.5)
    assert pilots.shared_variance == pytest.approx(3.0) and pilots.calibration == {P: pytest.approx(1.0)}
    # ... but never more than the least any pilot measured: the rest is the environment's own.
    calibrate(pilots, {E.label: 9.5, P.label: 2.5}, model, candidates, variance, rest=0.5)
    assert pilots.shared_variance == pytest.approx(2.5)
    assert pilots.calibration[E] == pytest.approx((9.5 - 2.5) / 6.5) == pilots.calibration[EO]


def test_a_calibration_factor_is_weighed_against_the_quadrature_by_how_closely_it_was_measured():
    """A factor measured closely stays as measured; one within the pilots' noise moves to the
    quadrature's 1; halfway where the measurement's error equals the prior's."""
    sd = pilots_module.CALIBRATION_PRIOR_SD
    assert weighed_calibration(2.0, 1e-4) == pytest.approx(2.0, abs=1e-5)
    assert weighed_calibration(0.3, 100 * sd) == pytest.approx(1.0, abs=1e-3)
    assert weighed_calibration(0.5, sd) == pytest.approx(0.75)
    assert weighed_calibration(0.5, float("inf")) == 1.0


def test_a_product_pilot_lost_in_shared_variance_leaves_the_quadrature_as_it_was():
    """The product's part of its pilot is what is left after ``S`` and the other materials':
    where the films' errors are as large as that part, the factor is (nearly) 1, not what the
    noise made of it; where they are small, the pilots' factor stands."""
    variance = {1: {E: 4.0, P: 1.0}, 2: {E: 2.0, P: 2.0}}
    candidates = {E.label: Candidate({1: E, 2: E}), P.label: Candidate({1: P, 2: E})}
    model = {E.label: 0.5 + 6.0, P.label: 0.5 + 1.0 + 2.0}
    measured = {E.label: 9.5, P.label: 3.0 + 0.5 + 0.4 * 1.0 + 2.0}  # S = 3, the product at 0.4x
    pilots = Pilots({}, spp=1)
    calibrate(pilots, measured, model, candidates, variance, rest=0.5,
              errors=independent_errors({E.label: 1e-3, P.label: 1e-3}))
    assert pilots.calibration[P] == pytest.approx(0.5, abs=0.01)  # 0.4, within CALIBRATION_RANGE
    calibrate(pilots, measured, model, candidates, variance, rest=0.5,
              errors=independent_errors({E.label: 2.0, P.label: 1.0}))
    assert 0.95 < pilots.calibration[P] < 1.0


#: A floor in four large tiles: an image whose mean a partial cover of the film would miss.
COARSE_CHECKER = {"type": "diffuse", "reflectance": {"type": "checkerboard", "color0": 0.05, "color1": 0.9,
                                                     "to_uv": mi.ScalarTransform4f().scale([2, 2, 1])}}


@pytest.mark.parametrize("size, lanes", [(64, 1024), (16, 4096)])
def test_a_camera_sample_pass_estimates_the_films_mean_at_any_resolution(size, lanes):
    """The default plan's pilots are camera samples, not films: the integrator's sample of one
    camera ray at each of ``lanes`` film positions, strided over a film with more pixels,
    repeated over one with fewer. Their mean is the image's (a box filter's film is the mean
    of its pixels), and the lanes' values are in the film's channels."""
    scene = floor_scene(COARSE_CHECKER, WINDOW, size=size)
    sensor = scene.sensors()[0]
    direct = mi.load_dict({"type": "direct"})
    image = np.asarray(mi.render(scene, integrator=direct, spp=256, seed=1), dtype=np.float64)

    def sample(scene, sampler, ray, active):
        return direct.sample(scene, sampler, ray, None, active)[:2]

    passes = [np.stack([np.asarray(c, dtype=np.float64) for c in camera_sample_pass(scene, sensor, sample, seed,
                                                                                   lanes)], axis=-1)
              for seed in range(64)]
    assert passes[0].shape == (lanes, 3)
    per_channel = np.mean(passes, axis=(0, 1))
    assert per_channel == pytest.approx(image.reshape(-1, 3).mean(axis=0), rel=0.02)


@pytest.fixture
def camera_passes(monkeypatch):
    """The seeds of the camera-sample passes the chooser traces (a replayed pass runs no Python)."""
    seeds, camera_sample_pass = [], chooser_module.camera_sample_pass

    def camera_pass(*args, **kwargs):
        seeds.append(args[3])
        return camera_sample_pass(*args, **kwargs)

    monkeypatch.setattr(chooser_module, "camera_sample_pass", camera_pass)
    return seeds


@pytest.mark.parametrize("size", [32, 520])
def test_the_default_plan_pilots_a_large_film_by_camera_samples_one_recording_replayed(monkeypatch, camera_passes,
                                                                                        size):
    """A film of at most FILM_PILOT_PIXELS pixels is piloted by film passes (the statistics
    the realistic scenes' plans were measured with); a larger one by camera-sample passes of
    as many lanes, which cost the same at any resolution, all replaying one dr.freeze
    recording, and whose variances confirm the quadrature as the film passes' do."""
    recordings, freeze = [], pilots_module.dr.freeze

    def counted(function, **kwargs):
        frozen = freeze(function, **kwargs)

        def call(*args, **kw):
            result = frozen(*args, **kw)
            recordings.append(frozen.n_recordings)
            return result
        call.clear = frozen.clear
        return call

    monkeypatch.setattr(pilots_module.dr, "freeze", counted)
    scene = floor_scene({"type": "diffuse"}, WINDOW, size=size)
    choice = mi.load_dict({"type": "sh_direct", "plan_file": ""}).plan(scene)
    assert len(choice.pilot_variance) == 3 and len(recordings) == 9
    if size * size <= FILM_PILOT_PIXELS:
        assert camera_passes == []
        return
    assert len(camera_passes) == 1 and set(recordings) == {1}  # traced once, replayed by every pass
    for name, (predicted, measured) in choice.pilot_variance.items():
        assert measured == pytest.approx(predicted, rel=0.15), name


@pytest.mark.parametrize("plugin", ["sh_path", "sh_prb"])
def test_the_path_plugins_pilot_a_large_film_by_camera_samples_as_well(camera_passes, plugin):
    """Each plugin gives the pilots its own sample of a camera ray (``sh_prb``'s in primal mode)."""
    scene = floor_scene({"type": "diffuse"}, WINDOW, size=520)
    choice = mi.load_dict({"type": plugin, "max_depth": 2, "plan_file": ""}).plan(scene)
    assert camera_passes and set(choice.pilot_variance) == {E.label, P.label}
    for name, (predicted, measured) in choice.pilot_variance.items():
        assert measured == pytest.approx(predicted, rel=0.15), name


def test_the_quadrature_of_some_frames_is_their_rows_of_the_quadrature_of_all():
    """The chooser's second quadrature (the cosine lobes walked) runs at the cosine
    materials' frames alone: each frame draws what it drew among all, so the plan is the
    one the quadrature over every frame makes, bit for bit."""
    scene = floor_scene({"type": "roughplastic", "alpha": 0.2}, WINDOW)
    env = ProductEnvironment(scene, DirectOptions(), carry_all=True)
    si, bsdf, _ = camera_frames(scene, scene.sensors()[0])
    every = frame_variances(env, si, bsdf, 1, 1)
    some = np.arange(3, dr.width(si), 7)
    assert np.array_equal(frame_variances(env, si, bsdf, 1, 1, frames=some), every[some], equal_nan=True)


def test_the_pilots_of_one_round_share_a_seed_and_the_rounds_differ():
    """Common random numbers: what the strategies share cancels where pilots are compared."""
    scene = floor_scene({"type": "diffuse"}, WINDOW)
    env = ProductEnvironment(scene, DirectOptions(), carry_all=True)
    (key,) = env.strategies.ids
    seeds = []
    pilots = measure_pass_costs(env, {LEAN: Candidate.lean_kernel([key]), E.label: Candidate({key: E}),
                                      P.label: Candidate({key: P})},
                                lambda seed: seeds.append(seed), repeats=3)
    rounds = [seeds[i:i + 3] for i in range(0, len(seeds), 3)]
    assert len(rounds) == 4 and all(len(set(r)) == 1 for r in rounds) and len({r[0] for r in rounds}) == 4
    assert set(pilots.pass_time) == {LEAN, E.label, P.label} and pilots.image_variance == {}
    assert env.warp is not None and env.strategies.of(key) == P  # left as it was found


def test_a_pilot_pass_is_timed_by_its_kernels_not_by_its_tracing():
    """The render replays frozen passes (no tracing), so the pilots, traced each time,
    count only the kernels' execution time: positive, and less than the wall time."""
    import time

    from mitsuba_shsampling.timing import kernel_time
    scene = floor_scene({"type": "diffuse"}, WINDOW, size=64)
    integrator = mi.load_dict({"type": "sh_direct", "strategy": "product"})
    mi.render(scene, integrator=integrator, spp=4)  # compiles

    def one_pass():
        image = mi.render(scene, integrator=integrator, spp=4, seed=1)
        dr.eval(image)
        dr.sync_thread()
        return image

    start = time.perf_counter()
    image, seconds = kernel_time(one_pass)
    wall = time.perf_counter() - start
    assert 0.0 < seconds < wall
    np.testing.assert_array_equal(np.array(image), np.array(mi.render(scene, integrator=integrator, spp=4, seed=1)))
    assert not dr.flag(dr.JitFlag.KernelHistory)  # left as it was


def test_the_render_after_the_choice_runs_the_chosen_strategy():
    scene = floor_scene({"type": "diffuse"}, WINDOW)
    chosen_automatically = mi.load_dict({"type": "sh_direct"})
    forced = mi.load_dict({"type": "sh_direct", "strategy": "product_only"})
    image = np.array(mi.render(scene, integrator=chosen_automatically, spp=16, seed=3))
    assert [m.strategy for m in chosen_automatically.choice(scene).materials] == [PO]
    assert np.array_equal(image, np.array(mi.render(scene, integrator=forced, spp=16, seed=3)))


def test_variance_every_strategy_shares_is_measured_and_weighs_against_the_product():
    """Under the window a plain diffuse floor gives every sample to the product (above);
    on a fine checkerboard the texture's variance within each pixel is most of the
    film's, which the product cannot reduce: its time no longer pays."""
    scene = floor_scene(FINE_CHECKER, WINDOW, size=96)
    integrator = mi.load_dict({"type": "sh_direct"})
    mi.render(scene, integrator=integrator, spp=1)
    choice = integrator.choice(scene)
    predicted, measured = choice.pilot_variance[E.label]
    assert choice.shared_variance > 0.5 * measured
    assert measured == pytest.approx(predicted, rel=0.15)
    (material,) = choice.materials
    assert material.variance[PO] < 0.5 * material.variance[E]  # the lighting estimate alone would pay
    assert choice.lean and material.strategy in (E, EO)


# ------------------------------------------------------------ end to end

def test_a_scene_whose_materials_run_different_strategies_is_unbiased():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        scene = make_scene(materials={k: MATERIALS[k] for k in ("ggx", "diffuse", "roughplastic", "blend")},
                           area_light=True)
        # Forced (so no chooser overrides the table) to a strategy that keeps every branch traced.
        sh = mi.load_dict({"type": "sh_direct", "max_bands": 5, "strategy": "product_only"})
        env = sh.scenes.get(scene)
    keys = env.strategies.ids
    mix = [E, EO, P, PO]
    env.strategies.assign({key: next(s for s in mix[i % 4:] + mix if s in env.allowed(key))
                           for i, key in enumerate(keys)})
    assert len({env.strategies.of(k) for k in keys}) >= 3
    assert_unbiased(scene, sh, mi.load_dict({"type": "path", "max_depth": 2}))


def test_auto_chooses_before_the_first_pass_and_reports_every_material(monkeypatch, tmp_path):
    monkeypatch.setenv("SHSAMPLING_CACHE_DIR", str(tmp_path))  # planned here, not read from another test's plan
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        scene = make_scene(materials={k: MATERIALS[k] for k in ("ggx", "diffuse")})
    sh = mi.load_dict({"type": "sh_direct", "max_bands": 5})
    assert sh.choice(scene) is None
    image = np.array(mi.render(scene, integrator=sh, spp=4))
    assert np.all(np.isfinite(image))
    choice = sh.choice(scene)
    names = {m.name for m in choice.materials}
    assert {"ggx", "diffuse", "plane"} <= names
    assert "at equal time" in choice.summary() or "no product strategy pays" in choice.summary()
    # Listed by name, whatever order the scene's objects were registered in.
    listed = [part.split(":")[0] for part in choice.summary().split("; ", 1)[1].split(", ")]
    assert listed == sorted(listed) and {"ggx", "diffuse", "plane"} <= set(listed)
    # By default no clock enters the plan: the costs are the cost model's.
    assert choice.mode == "estimate" and choice.pass_time == {} and choice.costs["product_walk"] > 0


def test_a_measured_plan_times_every_strategy_and_prices_the_cosine_tables_apart(monkeypatch, tmp_path):
    # A cache folder of its own: a measured plan of the same scene kept by another test
    # would be reused as wisdom instead of measured.
    monkeypatch.setenv("SHSAMPLING_CACHE_DIR", str(tmp_path))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        scene = make_scene(materials={k: MATERIALS[k] for k in ("ggx", "diffuse")})
    sh = mi.load_dict({"type": "sh_direct", "max_bands": 5, "plan": "measure"})
    choice = sh.plan(scene)
    assert choice.mode == "measure" and set(choice.pass_time) >= {LEAN, E.label, P.label}
    # A diffuse and a glossy lobe: a pilot with the diffuse one alone on the product
    # prices the cosine tables apart from the SH walk.
    assert {cosine_pilot(P), cosine_pilot(PO)} <= set(choice.pass_time)
    assert choice.costs["source"] == "measured in the scene"
    # The pilots' times are the pilots' only: rivals timed as wholes are kept apart.
    assert set(choice.pass_time) <= {LEAN, *(s.label for s in Strategy), cosine_pilot(P), cosine_pilot(PO)}
    assert all(name.startswith("confirm ") for name in choice.confirmation_time)


@pytest.mark.parametrize("name", ["sh_direct", "sh_path"])
def test_the_pilot_passes_leave_the_scenes_sample_count_as_it_was(name):
    """A render with spp=0 uses the sensor's sample count, which the pilots must not change."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        scene = make_scene(materials={k: MATERIALS[k] for k in ("ggx", "diffuse")})
    sampler = scene.sensors()[0].sampler()
    sampler.set_sample_count(3)
    integrator = mi.load_dict({"type": name, "max_bands": 5})
    mi.render(scene, integrator=integrator)
    assert integrator.choice(scene) is not None
    assert sampler.sample_count() == 3


def test_sh_path_unbiased_with_its_automatic_choice():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        scene = make_scene(rotated=True, materials={k: MATERIALS[k] for k in ("ggx", "diffuse", "blend")})
    assert_unbiased(scene, mi.load_dict({"type": "sh_path", "max_depth": 3, "max_bands": 5}),
                    mi.load_dict({"type": "path", "max_depth": 3}))


# ------------------------------------------------------------ the parameter

@pytest.mark.parametrize("value", ["auto", "environment", "environment_only", "bsdf_only", "product", "product_only"])
def test_sh_direct_accepts_auto_and_every_strategy(value):
    assert DirectOptions(strategy=value).strategy == value


@pytest.mark.parametrize("value", ["bsdf_only", "product,glossy=bsdf_only"])
def test_bsdf_only_without_bsdf_samples_is_refused_rather_than_run_as_the_environment(value):
    with pytest.raises(OptionError, match="'bsdf_only' with 'bsdf_samples' > 0"):
        DirectOptions(strategy=value, bsdf_samples=0, mis_compensation=False)
    assert DirectOptions(strategy="product_only", bsdf_samples=0, mis_compensation=False).bsdf_samples == 0


@pytest.mark.parametrize("value", ["Product", "mis", "", 1])
def test_other_strategy_values_are_refused_with_the_list_of_valid_ones(value):
    with pytest.raises(OptionError, match="strategy"):
        DirectOptions(strategy=value)


@pytest.mark.parametrize("value", ["product_only", "environment_only", "bsdf_only"])
def test_sh_path_refuses_strategies_that_skip_the_bsdf_sample_it_continues_with(value):
    with pytest.raises(OptionError, match="'strategy' must be one of 'auto', 'environment', 'product'"):
        PathOptions(strategy=value)
