"""What the JIT kernels of a piece of work cost: the package's timers.

A pass traced from Python pays its tracing on every call; a pass replayed from a
``dr.freeze`` recording (:mod:`mitsuba_shsampling.frozen`) pays only its kernels.
Both the per-machine calibration of the strategies' costs
(:mod:`mitsuba_shsampling.integrators.costs`) and the sampler benchmarks time the
kernels, so that what they compare is what a replayed pass costs
(:func:`kernel_time`). :func:`compile_time` gives what a piece of work spent compiling
kernels that Dr.Jit's kernel cache did not hold (the plan's Info line says it: on a
machine's first render, or a map of a new resolution, most of the set-up).

Both read Dr.Jit's kernel history, which :func:`dr.kernel_history` empties as it returns
it: :func:`kernel_time` passes what it takes on to an open :func:`compile_time` block.
"""

from __future__ import annotations

import contextlib
import dataclasses
from typing import Callable

import drjit as dr

_OPEN_BLOCKS: list[list] = []
"""The launches that each open :func:`compile_time` block has seen taken from the history."""


def _taken_history() -> list:
    """``dr.kernel_history()`` (which empties it), also handed to the open compile-time blocks."""
    history = dr.kernel_history()
    for seen in _OPEN_BLOCKS:
        seen.extend(history)
    return history


def kernel_time(run: Callable[[], object]) -> tuple[object, float]:
    """``run()``'s result and the execution time (s) of the JIT kernels it launched
    (``run`` must wait for them). Dr.Jit's kernel history is switched on for the call
    and left as it was found."""
    was_on = dr.flag(dr.JitFlag.KernelHistory)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    _taken_history()  # clears it
    try:
        result = run()
        history = _taken_history()
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, was_on)
    return result, 1e-3 * sum(k["execution_time"] for k in history if k["type"] == dr.KernelType.JIT)


@dataclasses.dataclass
class CompileTime:
    """What a :func:`compile_time` block compiled: ``seconds`` of LLVM (or of the CUDA driver) on
    the JIT kernels that were not in Dr.Jit's kernel cache, and how many (``kernels``); None
    where the block could not see it (the kernel history was on already: it is the caller's)."""

    seconds: float | None = None
    kernels: int | None = None


@contextlib.contextmanager
def compile_time():
    """A block in which Dr.Jit's kernel history is on (where it was off), yielding a
    :class:`CompileTime` that is filled when the block ends. Where the history was on already
    it is left alone (a user's, or an enclosing block's) and the figures stay None."""
    result = CompileTime()
    if dr.flag(dr.JitFlag.KernelHistory):
        yield result
        return
    seen: list = []
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    dr.kernel_history()  # empty while the flag was off; cleared all the same
    _OPEN_BLOCKS.append(seen)
    try:
        yield result
    finally:
        seen.extend(dr.kernel_history())
        _OPEN_BLOCKS.remove(seen)
        dr.set_flag(dr.JitFlag.KernelHistory, False)
        compiled = [k for k in seen if k["type"] == dr.KernelType.JIT and not k.get("cache_hit", True)]
        result.seconds = 1e-3 * sum(float(k.get("backend_time", 0.0)) for k in compiled)
        result.kernels = len(compiled)
