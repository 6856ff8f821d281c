"""Specification: with ``emitter_selection`` ``auto`` (the default), ``sh_direct``'s plan prices
each emitter sample as two samples (``each``: the environment's and one of the other lights')
or one (``one``: an emitter drawn as Mitsuba's ``direct`` draws it), with the variance of pilot
images of its own plan under both and the pass time of the cost model, and runs the better."""

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

mi.set_variant("llvm_ad_rgb")

from test_integrators import MATERIALS, make_scene  # noqa: E402

import mitsuba_shsampling  # noqa: E402
from mitsuba_shsampling.integrators.chooser import rounded  # noqa: E402
from mitsuba_shsampling.integrators.emitter_selection import (SELECTION_REQUIRED_GAIN,  # noqa: E402
                                                               price_emitter_selection)
from mitsuba_shsampling.integrators.sharing import forget_shared  # noqa: E402

BANDS = 5


def lit_scene():
    return make_scene(rotated=True, area_light=True, sun_light=True,
                      materials={k: MATERIALS[k] for k in ("ggx", "diffuse", "roughplastic")})


def test_auto_keeps_each_where_one_emitter_a_sample_is_noisier_than_its_time_saves_and_says_so():
    forget_shared()
    scene = lit_scene()
    integrator = mi.load_dict({"type": "sh_direct", "max_bands": BANDS})
    choice = integrator.plan(scene)
    priced = choice.emitter_selection
    assert priced["design"] == "each"
    assert integrator.scenes.get(scene).emitter_selection == "each"
    # A sun, an area light and the map drawn one at a time: more variance (never less, by the
    # module's algebra), here more than the shorter pass makes up for.
    assert priced["variance"]["one"] > priced["variance"]["each"]
    # One shadow ray less a sample: a shorter pass, priced by the cost model.
    assert priced["pass_time"]["one"] < priced["pass_time"]["each"]
    assert "other emitters: each" in choice.summary()


def test_a_scene_lit_by_its_environment_alone_prices_nothing():
    forget_shared()
    scene = make_scene(materials={k: MATERIALS[k] for k in ("ggx", "diffuse")})
    choice = mi.load_dict({"type": "sh_direct", "max_bands": BANDS}).plan(scene)
    assert choice.emitter_selection == {}
    assert "other emitters" not in choice.summary()


def test_a_kept_plan_runs_the_design_it_was_made_with(tmp_path):
    forget_shared()
    path = str(tmp_path / "plan.json")
    scene = lit_scene()
    made = mi.load_dict({"type": "sh_direct", "max_bands": BANDS, "plan_file": path}).plan(scene)
    forget_shared()
    integrator = mi.load_dict({"type": "sh_direct", "max_bands": BANDS, "plan_file": path})
    loaded = integrator.plan(scene)
    assert loaded.mode == "file"
    assert loaded.emitter_selection == made.emitter_selection
    assert integrator.scenes.get(scene).emitter_selection == made.emitter_selection["design"]


class FakeEnvironment:
    emitter_selection = "each"


def fake_render(noise: dict):
    """``render_pass(spp, seed)`` whose images have the given per-pixel standard deviation per
    design (what ``env.emitter_selection`` says when it is called)."""
    env = FakeEnvironment()

    def render_pass(spp, seed):
        rng = np.random.default_rng(seed * 7 + len(env.emitter_selection))
        values = 1.0 + noise[env.emitter_selection] * rng.standard_normal((64, 64, 3))
        return mi.TensorXf(values.astype(np.float32))

    return env, render_pass


@pytest.mark.parametrize("one_noise, expected", [(1.0, "one"), (1.3, "each"), (3.0, "each")])
def test_one_runs_only_where_its_variance_times_its_time_wins_by_the_required_gain(one_noise, expected):
    # Pass times from the cost model: 'each' 1.0 lean passes, 'one' 1 - 0.4 x 0.9 = 0.64. With
    # the same variance 'one' wins (0.64 < 1 / 1.15); at 1.3x the standard deviation (1.69x the
    # variance: 1.08 > 1) and at 3x 'each' does.
    env, render_pass = fake_render({"each": 1.0, "one": one_noise})
    priced = price_emitter_selection(env, render_pass, spp=1, pass_time=1.0, sample_time=0.4, smooth_share=0.9,
                                     required_gain=SELECTION_REQUIRED_GAIN, rounded=rounded)
    assert priced.design == expected and env.emitter_selection == expected
    assert priced.pass_time == pytest.approx({"each": 1.0, "one": 0.64})
    assert priced.variance["one"] == pytest.approx(one_noise ** 2 * priced.variance["each"], rel=0.1)


def test_the_pilots_of_both_designs_are_rendered_with_the_design_set_and_the_setting_restored_before_the_choice():
    env, inner = fake_render({"each": 1.0, "one": 2.0})
    seen = []

    def render_pass(spp, seed):
        seen.append((env.emitter_selection, seed))
        return inner(spp, seed)

    price_emitter_selection(env, render_pass, 1, 1.0, 0.1, 1.0, SELECTION_REQUIRED_GAIN, rounded)
    designs = [d for d, _ in seen]
    assert designs.count("each") == designs.count("one") >= 2
    # The same seeds for both designs, round by round.
    assert [s for d, s in seen if d == "each"] == [s for d, s in seen if d == "one"]


def test_emitter_selection_takes_auto_each_and_one_and_refuses_others():
    for value in ("auto", "each", "one"):
        mi.load_dict({"type": "sh_direct", "emitter_selection": value})
    with pytest.raises(RuntimeError, match="emitter_selection"):
        mi.load_dict({"type": "sh_direct", "emitter_selection": "both"})


def test_a_frozen_render_records_again_for_another_design():
    """The design is read when a pass is traced: a replay must not keep the old one."""
    forget_shared()
    scene = lit_scene()
    integrator = mi.load_dict({"type": "sh_direct", "max_bands": BANDS})
    integrator.plan(scene)

    @mitsuba_shsampling.freeze
    def render(scene, integrator, seed):
        return mi.render(scene, integrator=integrator, spp=4, seed=seed)

    each = [render(scene, integrator, dr.opaque(mi.UInt32, 7)).numpy() for _ in range(2)]
    recordings = render.n_recordings
    integrator.scenes.get(scene).emitter_selection = "one"
    integrator.plan(scene)  # hands the state's inputs to the next call
    one = render(scene, integrator, dr.opaque(mi.UInt32, 7)).numpy()
    assert render.n_recordings > recordings
    assert not np.allclose(one, each[0])
    traced = mi.render(scene, integrator=integrator, spp=4, seed=7).numpy()
    np.testing.assert_allclose(one, traced, rtol=1e-5, atol=1e-6)
