"""Specification of the set-up's memory pages (``host_memory``).

A state's build and a plan run on ordinary 4 kB pages, the process's huge-page settings are
put back afterwards, the memory the set-up freed is handed back when it ends (and only
then: a pass whose state is ready hands nothing back), and what the passes read for the
whole render is copied into memory of its own, with huge pages allowed for that copy (so
that neither Dr.Jit's nor the C library's reuse of freed memory puts it on the set-up's
pages). Whether Linux then backs that memory with huge pages is the kernel's business and
is not asserted here.
"""

from __future__ import annotations

import mmap

import mitsuba as mi
import numpy as np
import pytest

mi.set_variant("llvm_ad_rgb")

from mitsuba_shsampling import build_cache, host_memory  # noqa: E402
from mitsuba_shsampling.device_arrays import device_array  # noqa: E402
from mitsuba_shsampling.envmap import EnvPyramid  # noqa: E402
from mitsuba_shsampling.envmap import pyramid as pyramid_module  # noqa: E402

needs_prctl = pytest.mark.skipif(host_memory.process_thp_disabled() is None,
                                 reason="prctl(PR_GET_THP_DISABLE) is Linux's")


def settings():
    return host_memory.process_thp_disabled(), host_memory.numpy_asks_for_huge_pages()


@pytest.fixture
def user_settings():
    """Restores whatever a test sets as the user's own settings."""
    before = settings()
    yield
    host_memory._put_back(before)


@needs_prctl
@pytest.mark.parametrize("thp_disabled, numpy_huge", [(False, True), (True, False)])
def test_ordinary_pages_turn_huge_pages_off_inside_and_give_the_users_settings_back(user_settings, thp_disabled,
                                                                                      numpy_huge):
    host_memory._put_back((thp_disabled, numpy_huge))
    with host_memory.ordinary_pages():
        assert settings() == (True, False)
        with host_memory.ordinary_pages():
            assert settings() == (True, False)
        assert settings() == (True, False), "an inner block's end leaves the outer block's pages"
    assert settings() == (thp_disabled, numpy_huge)


@needs_prctl
def test_a_failing_block_still_gives_the_settings_back(user_settings):
    host_memory._put_back((False, True))
    with pytest.raises(RuntimeError):
        with host_memory.ordinary_pages():
            raise RuntimeError("a build that fails")
    assert settings() == (False, True)


def test_a_kept_copy_is_the_same_values_read_only_in_a_mapping_of_its_own_that_dr_jit_maps_as_it_is():
    values = np.random.default_rng(1).random(3_000_001)
    kept = host_memory.kept_copy(values)
    assert kept.dtype == values.dtype and np.array_equal(kept, values)
    assert not kept.flags.writeable
    assert kept.ctypes.data % mmap.PAGESIZE == 0, "its own mapping starts a page"
    as_float32 = host_memory.kept_copy(values.astype(np.float32))
    mapped = device_array(mi.Float, as_float32)
    assert mapped.numpy().ctypes.data == as_float32.ctypes.data, "mapped without another copy"


@needs_prctl
def test_a_pyramid_sums_on_ordinary_pages_and_keeps_its_levels_in_kept_copies(monkeypatch, user_settings):
    host_memory._put_back((False, True))
    seen = []
    original = pyramid_module._summed_and_trimmed

    def spied(*args, **kwargs):
        seen.append(settings())
        return original(*args, **kwargs)
    monkeypatch.setattr(pyramid_module, "_summed_and_trimmed", spied)
    monkeypatch.setattr(build_cache, "_in_process_only", True)
    build_cache.clear_in_process()
    image = np.random.default_rng(2).random((64, 128, 3)) + 0.1
    pyramid = EnvPyramid.from_latlong(image, mis_compensation=True)
    assert seen == [(True, False)]
    assert settings() == (False, True)
    for array in (pyramid.buffer, pyramid.records):
        memory = array.numpy()
        assert memory.ctypes.data % mmap.PAGESIZE == 0, "the kept levels are read from a mapping of their own"



@pytest.fixture
def releases(monkeypatch):
    """Counts the hand-backs of freed memory."""
    count = []
    monkeypatch.setattr(host_memory, "release_freed_memory", lambda: count.append(1))
    return count


@needs_prctl
def test_set_up_work_runs_on_ordinary_pages_and_hands_its_memory_back_once_at_the_outermost_end(user_settings,
                                                                                                 releases):
    host_memory._put_back((False, True))
    with host_memory.setup_memory(work=False):  # an integrator's step before a pass
        assert settings() == (False, True), "a scope alone changes no page setting"
        with host_memory.setup_memory():  # the state's build
            assert settings() == (True, False)
        with host_memory.setup_memory():  # the plan
            pass
        assert releases == [], "nothing is handed back before the outermost block ends"
    assert releases == [1]
    assert settings() == (False, True)
    with host_memory.setup_memory():  # work outside any scope: handed back at its own end
        pass
    assert releases == [1, 1]


def test_a_step_without_set_up_work_hands_nothing_back(releases):
    with host_memory.setup_memory(work=False):
        pass
    assert releases == []


def test_a_failing_set_up_still_hands_its_memory_back(releases):
    with pytest.raises(RuntimeError):
        with host_memory.setup_memory():
            raise RuntimeError("a build that fails")
    assert releases == [1]


@needs_prctl
def test_inside_a_block_a_kept_copy_first_touches_its_memory_with_the_users_settings(monkeypatch, user_settings):
    host_memory._put_back((False, True))
    during_copy = []
    original = host_memory._fill

    def spied(out, values):
        during_copy.append(settings())
        original(out, values)
    monkeypatch.setattr(host_memory, "_fill", spied)
    with host_memory.ordinary_pages():
        kept = host_memory.kept_copy(np.arange(10.0))
        assert settings() == (True, False), "the block's pages again after the copy"
    assert during_copy == [(False, True)]
    assert np.array_equal(kept, np.arange(10.0))


def test_handing_freed_memory_back_leaves_live_arrays_as_they_were():
    values = device_array(mi.Float, np.arange(1_000_000, dtype=np.float32))
    host_memory.release_freed_memory()
    assert np.array_equal(values.numpy(), np.arange(1_000_000, dtype=np.float32))


def test_a_plan_runs_its_set_up_on_ordinary_pages_and_hands_its_memory_back_once(monkeypatch, releases, envmaps_dir):
    from mitsuba_shsampling.integrators import chooser as chooser_module
    from mitsuba_shsampling.integrators import sh_direct
    from mitsuba_shsampling.scenes import builtin_scenes, load_scene

    seen = []
    for module, name in ((sh_direct, "ProductEnvironment"), (chooser_module.StrategyChooser, "_choose")):
        original = getattr(module, name)

        def spied(*args, _original=original, **kwargs):
            seen.append(host_memory._DEPTH > 0)
            return _original(*args, **kwargs)
        monkeypatch.setattr(module, name, spied)
    monkeypatch.setattr(build_cache, "_in_process_only", True)
    scene = load_scene(builtin_scenes()["sphere_ggx010"], envmap=str(envmaps_dir / "forest_slope_1k.hdr"), res=16)
    integrator = mi.load_dict({"type": "sh_direct"})
    integrator.plan(scene)
    assert seen == [True, True], "the state's build and the plan"
    assert releases == [1]
    mi.render(scene, integrator=integrator, spp=1)
    assert releases == [1], "a pass on a ready state hands nothing back"
    # A parameter change (an optimisation step): rebuilt and planned again on huge pages.
    params = mi.traverse(scene)
    key = next(k for k in params.keys() if k.endswith("alpha.value"))
    params[key] = 0.3
    params.update()
    integrator.plan(scene)
    assert seen == [True, True, False, False]
    assert releases == [1]
