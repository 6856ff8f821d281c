"""What the JIT kernels of a piece of work cost: the one timer of the package.

A pass traced from Python pays its tracing on every call; a pass replayed from a
``dr.freeze`` recording (:mod:`mitsuba_shsampling.frozen`) pays only its kernels.
Both the per-machine calibration of the strategies' costs
(:mod:`mitsuba_shsampling.integrators.costs`) and the sampler benchmarks time the
kernels, so that what they compare is what a replayed pass costs.
"""

from __future__ import annotations

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
