"""What the JIT kernels of a piece of work cost: the one timer of the package.

A pass traced from Python pays its tracing on every call; a pass replayed from a
``dr.freeze`` recording (:mod:`mitsuba_shsampling.frozen`) pays only its kernels.
Both the per-machine calibration of the strategies' costs
(:mod:`mitsuba_shsampling.integrators.costs`) and the sampler benchmarks time the
kernels, so that what they compare is what a replayed pass costs (:func:`kernel_time`).
:func:`kernels_compiled` counts the kernels a piece of work compiled because Dr.Jit's
kernel cache did not hold them (the plan's Info line says it: on a machine's first render,
or with a map of a new resolution, they are most of the set-up).
"""

from __future__ import annotations

import contextlib
import dataclasses
from typing import Callable

import drjit as dr


def kernel_time(run: Callable[[], object]) -> tuple[object, float]:
    """``run()``'s result and the execution time (s) of the JIT kernels it launched
    (``run`` must wait for them). Dr.Jit's kernel history is switched on for the call
    and left as it was found."""
    was_on = dr.flag(dr.JitFlag.KernelHistory)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    dr.kernel_history()  # clears it
    try:
        result = run()
        history = dr.kernel_history()
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, was_on)
    return result, 1e-3 * sum(k["execution_time"] for k in history if k["type"] == dr.KernelType.JIT)


@dataclasses.dataclass
class Compiled:
    """What a :func:`kernels_compiled` block compiled."""

    kernels: int = 0
    """JIT kernels compiled from their code: in neither Dr.Jit's in-memory nor its on-disk kernel cache."""


@contextlib.contextmanager
def kernels_compiled():
    """A block, yielding a :class:`Compiled` that is filled when it ends, from Dr.Jit's launch
    counters (``dr.detail.launch_stats``: launches, kernels loaded from the disk cache, kernels
    compiled). Not from the kernel history, which would give LLVM's seconds too but keeps every
    launch's code: reading it back after a plan took 34 ms (616 launches, 25 MB of IR) of a
    set-up of about a second."""
    result = Compiled()
    before = dr.detail.launch_stats()[2]
    try:
        yield result
    finally:
        result.kernels = dr.detail.launch_stats()[2] - before
