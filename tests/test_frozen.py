"""Specification of frozen render passes (``mitsuba_shsampling.frozen``).

A frozen pass records the kernels of one ``mi.render`` and replays them. It must
give the image a traced render gives, for Mitsuba's integrators and this
project's; record once, not once per seed; follow a scene whose parameters
change; never record the chooser's pilot passes; and fall back to traced
renders, with a warning, where an integrator cannot be frozen.
"""

import gc
import warnings

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

mi.set_variant("llvm_ad_rgb")

from mitsuba_shsampling.frozen import FrozenPass, held_inputs
from mitsuba_shsampling.integrators import register
from mitsuba_shsampling.scenes import builtin_scenes, load_scene

SPP = 4


@pytest.fixture
def scene(envmaps_dir):
    """A scene of its own for each test (as each method of ``compare`` has). The scenes of
    earlier tests are collected first: a replay records again when the set of BSDFs
    alive in the process changed since its recording (``MethodRenderer.record``)."""
    gc.collect()
    register()
    return load_scene(builtin_scenes()["sphere_ggx010"], envmap=str(envmaps_dir / "forest_slope_1k.hdr"), res=24)


def traced(scene, integrator, seed):
    return np.array(mi.render(scene, integrator=integrator, spp=SPP, seed=seed))


@pytest.mark.parametrize("integrator", [
    {"type": "direct"},
    {"type": "path", "max_depth": 4},
    {"type": "sh_direct"},
    {"type": "sh_direct", "strategy": "product"},
    {"type": "sh_direct", "strategy": "product_only"},
    {"type": "sh_path", "strategy": "product", "max_depth": 4},
    {"type": "sh_prb", "strategy": "product", "max_depth": 4},
    {"type": "oracle_direct", "resolution": 16},
], ids=lambda d: "-".join(str(v) for v in d.values()))
def test_a_replayed_pass_is_the_traced_pass(scene, integrator):
    integrator = mi.load_dict(integrator)
    traced(scene, integrator, 0)  # compiles, builds the state, chooses (as compare's warm-up)
    frozen = FrozenPass(scene, scene.sensors()[0], integrator, SPP)
    for seed in (1, 2, 3):
        np.testing.assert_array_equal(np.array(frozen(seed)), traced(scene, integrator, seed))
    assert frozen.frozen and frozen.failure is None
    assert frozen.recordings == 1  # a new seed replays (opaque), it does not record again


def test_a_changed_parameter_records_again_and_renders_the_new_scene(scene):
    integrator = mi.load_dict({"type": "sh_direct", "strategy": "product"})
    traced(scene, integrator, 0)
    frozen = FrozenPass(scene, scene.sensors()[0], integrator, SPP)
    before = np.array(frozen(1))
    params = mi.traverse(scene)
    key = next(k for k in params.keys() if k.endswith(".data") and dr.width(params[k]) > 1000)
    original = type(params[key])(params[key])
    try:
        params[key] = params[key] * 3.0  # the pyramid and lobes' state is rebuilt from it
        params.update()
        after = np.array(frozen(1))
        np.testing.assert_array_equal(after, traced(scene, integrator, 1))
        assert not np.allclose(after, before)
        assert frozen.recordings == 2
    finally:
        params[key] = original
        params.update()


def test_the_pilot_passes_are_not_recorded(scene):
    integrator = mi.load_dict({"type": "sh_direct"})  # strategy auto: pilots before the first pass
    frozen = FrozenPass(scene, scene.sensors()[0], integrator, SPP)
    np.array(frozen(1))  # chooses (pilots, traced), then records one pass
    assert integrator.choice(scene) is not None
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history()
        np.array(frozen(2))
        replayed = dr.kernel_history()
        traced(scene, integrator, 3)
        one_pass = dr.kernel_history()
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    def jit_kernels(history):
        return [k for k in history if k["type"] == dr.KernelType.JIT]

    # The replay launches about one pass's kernels (it computes the opaque seed apart);
    # recorded pilots (a pass per strategy, several strategies) would multiply them.
    assert 0 < len(jit_kernels(replayed)) < 2 * len(jit_kernels(one_pass))


def test_a_replayed_pilot_pass_runs_one_kernel_over_the_film_the_render_itself(scene):
    """The sampler's state after a pass is nothing the pilots read; left lane by lane, the
    recording would compute it in a second kernel that traces every camera ray again."""
    from mitsuba_shsampling.integrators.pilots import frozen_pilots

    integrator = mi.load_dict({"type": "sh_direct", "strategy": "product"})
    sensor = scene.sensors()[0]
    env = integrator.prepare_scene(scene, sensor)
    replay = frozen_pilots(lambda spp, seed: mi.SamplingIntegrator.render(integrator, scene, sensor, seed, spp),
                           env, (scene, sensor, integrator))
    pixels = int(dr.prod(sensor.film().crop_size()))
    first = [np.array(replay(1, seed)) for seed in (1, 2)]  # (a film pass records twice)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history()
        image = np.array(replay(1, 3))
        history = dr.kernel_history()
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
        replay.release()
    over_the_film = [k for k in history if k["type"] == dr.KernelType.JIT and k["size"] >= pixels
                     and k["operation_count"] > 100]
    assert len(over_the_film) == 1
    assert np.all(np.isfinite(image)) and not np.array_equal(image, first[1])  # a pass of its own seed
    np.testing.assert_allclose(image, traced_pass(scene, integrator, sensor, 3), rtol=1e-5, atol=1e-6)


def traced_pass(scene, integrator, sensor, seed):
    return np.array(mi.SamplingIntegrator.render(integrator, scene, sensor, seed, 1))


class _Holder:
    """Plain object out of the frozen pass's reach (held only inside a closure)."""

    def __init__(self):
        self.gain = dr.opaque(mi.Float, 0.5, 4)


def _register_unreachable_state_integrator():
    holder = _Holder()

    class UnreachableState(mi.SamplingIntegrator):
        def __init__(self, props):
            super().__init__(props)
            self.gain = lambda: holder.gain  # neither an attribute array nor a PyTree

        def sample(self, scene, sampler, ray, medium=None, active=True):
            si = scene.ray_intersect(ray, active)
            value = dr.gather(mi.Float, self.gain(), mi.UInt32(0), active)
            return mi.Spectrum(dr.select(si.is_valid(), value, 0.0)), mi.Bool(True), []

    mi.register_integrator("test_unreachable_state", UnreachableState)


def test_an_integrator_that_cannot_be_frozen_renders_traced_with_a_warning(scene):
    _register_unreachable_state_integrator()
    integrator = mi.load_dict({"type": "test_unreachable_state"})
    traced(scene, integrator, 0)
    frozen = FrozenPass(scene, scene.sensors()[0], integrator, SPP)
    with pytest.warns(RuntimeWarning, match="cannot freeze the render pass"):
        first = np.array(frozen(1))
    assert not frozen.frozen and frozen.failure
    np.testing.assert_array_equal(first, traced(scene, integrator, 1))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # warned once, then quietly traced
        np.testing.assert_array_equal(np.array(frozen(2)), traced(scene, integrator, 2))


def test_the_state_inputs_are_every_array_and_object_it_holds():
    class Plain:
        pass

    inner = Plain()
    inner.table = mi.Float(1, 2, 3)
    inner.items = {"a": [mi.UInt32(4)], "b": (1, "text")}
    outer = Plain()
    outer.inner, outer.again, outer.emitter = inner, inner, mi.load_dict({"type": "constant"})
    found = held_inputs(outer)
    assert len(found) == 3  # each once, host values skipped
    assert any(isinstance(v, mi.Emitter) for v in found)


def test_compares_timed_passes_replay_and_none_records(tmp_path, monkeypatch):
    """In ``compare`` every method's pass is recorded after all the methods' scenes are loaded,
    so no timed pass records (a scene loaded after a recording makes the next replay record)."""
    import json

    from mitsuba_shsampling import cli
    from mitsuba_shsampling.report import rendering

    recorded_while_timed, replayed = [], []
    timed_render = rendering.MethodRenderer.render

    def checked_render(self, spp, seed):
        frozen = self._frozen.get(spp)
        before = frozen.recordings if frozen is not None else None
        result = timed_render(self, spp, seed)
        if frozen is not None:
            replayed.append(self.method.name)
            if frozen.recordings != before:
                recorded_while_timed.append((self.method.name, spp, seed))
        return result

    monkeypatch.setattr(rendering.MethodRenderer, "render", checked_render)
    assert cli.main(["compare", builtin_scenes()["sphere_diffuse"], "--out", str(tmp_path), "--res", "16",
                     "--spp", "2", "--passes", "3", "--ref-spp", "8", "--methods", "direct,direct_misc,sh_direct",
                     "--convergence-max-spp", "0", "--cache-dir", str(tmp_path / "cache"), "--no-progress"]) == 0
    assert recorded_while_timed == []
    assert set(replayed) == {"direct", "direct_misc", "sh_direct"}
    report = json.loads((tmp_path / "report.json").read_text())
    methods = report["scenes"][0]["runs"][0]["methods"]
    assert {name: entry["frozen"] for name, entry in methods.items()} == dict.fromkeys(methods, True)
