"""Specification: the package counts the kernels a piece of work compiled because Dr.Jit's kernel
cache did not hold them, without touching Dr.Jit's kernel history, and the plan's line says so."""

import random

import drjit as dr
import mitsuba as mi
import pytest

from mitsuba_shsampling.integrators.chooser import compiling_note
from mitsuba_shsampling.timing import kernel_time, kernels_compiled

if mi.variant() is None:
    mi.set_variant("llvm_ad_rgb")


def test_a_kernel_new_to_the_cache_is_counted_and_the_same_kernel_again_is_not():
    factor = 1.0 + random.random()  # a literal of the kernel's code: new to every cache
    with kernels_compiled() as compiled:
        dr.eval(dr.arange(mi.Float, 4096) * factor + 0.5)
    assert compiled.kernels == 1
    with kernels_compiled() as again:  # the same code: Dr.Jit has it
        dr.eval(dr.arange(mi.Float, 4096) * factor + 0.5)
    assert again.kernels == 0


def test_counting_leaves_the_kernel_history_and_a_timer_inside_it_alone():
    assert not dr.flag(dr.JitFlag.KernelHistory)
    with kernels_compiled() as compiled:
        assert not dr.flag(dr.JitFlag.KernelHistory)
        _, seconds = kernel_time(lambda: dr.eval(dr.arange(mi.Float, 64) * (2.0 + random.random())))
    assert compiled.kernels == 1 and seconds >= 0
    assert not dr.flag(dr.JitFlag.KernelHistory)


@pytest.mark.parametrize("kernels, said", [(0, None), (1, "compiling 1 kernel new to this machine; Dr.Jit keeps it"),
                                           (3, "compiling 3 kernels new to this machine; Dr.Jit keeps them")])
def test_the_plans_line_says_what_was_compiled_where_anything_was(kernels, said):
    note = compiling_note(kernels)
    assert (note == "") if said is None else (said in note)
