"""Specification of the set-up's memory pages (``host_memory``).

The pyramid's short-lived sums are made on ordinary 4 kB pages, the
process's huge-page settings are put back afterwards, and what the passes read for the
whole render is copied into memory of its own (so that neither Dr.Jit's nor the C
library's reuse of freed memory puts it on the sums' pages). Whether Linux then backs that
memory with huge pages is the kernel's business and is not asserted here.
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

