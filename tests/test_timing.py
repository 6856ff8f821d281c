"""Specification: the package's timers read Dr.Jit's kernel history, leave it as they found
it, and say what a piece of work spent compiling kernels that Dr.Jit's kernel cache did not hold."""

import random

import drjit as dr
import mitsuba as mi
import pytest

from mitsuba_shsampling.integrators.chooser import COMPILING_NOTED_S, compiling_note
from mitsuba_shsampling.timing import compile_time, kernel_time

if mi.variant() is None:
    mi.set_variant("llvm_ad_rgb")


def a_kernel_no_cache_holds():
    """An array whose kernel is new to every cache: a literal drawn at random is part of its code."""
    return dr.arange(mi.Float, 4096) * (1.0 + random.random()) + 0.5


def test_a_kernel_new_to_the_cache_is_counted_and_the_same_kernel_again_is_not():
    factor = 1.0 + random.random()
    with compile_time() as compiled:
        dr.eval(dr.arange(mi.Float, 4096) * factor + 0.5)
    assert compiled.kernels == 1 and compiled.seconds > 0
    with compile_time() as again:  # the same code: Dr.Jit has it in memory
        dr.eval(dr.arange(mi.Float, 4096) * factor + 0.5)
    assert again.kernels == 0 and again.seconds == 0


def test_the_history_is_switched_off_again_and_a_callers_history_is_left_alone():
    assert not dr.flag(dr.JitFlag.KernelHistory)
    with compile_time():
        assert dr.flag(dr.JitFlag.KernelHistory)
    assert not dr.flag(dr.JitFlag.KernelHistory)

    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history()
        dr.eval(a_kernel_no_cache_holds())
        with compile_time() as compiled:
            dr.eval(a_kernel_no_cache_holds())
        assert compiled.seconds is None and compiled.kernels is None
        # Both launches are still the caller's to read.
        assert len([k for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT]) == 2
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)


def test_kernels_a_kernel_timer_launches_inside_the_block_count_too():
    # kernel_time empties the history as it reads it: what it takes is handed on to the block.
    with compile_time() as compiled:
        _, seconds = kernel_time(lambda: dr.eval(a_kernel_no_cache_holds()))
        dr.eval(a_kernel_no_cache_holds())
    assert seconds >= 0
    assert compiled.kernels == 2 and compiled.seconds > 0
    assert not dr.flag(dr.JitFlag.KernelHistory)


@pytest.mark.parametrize("seconds, said", [(None, False), (0.0, False), (COMPILING_NOTED_S / 2, False), (2.04, True)])
def test_the_plans_info_line_mentions_compilation_that_counts(seconds, said):
    note = compiling_note(seconds)
    assert bool(note) == said
    if said:
        assert "2.0 s of it compiling kernels new to this machine" in note
