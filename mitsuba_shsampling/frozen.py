"""Render passes without re-tracing: ``dr.freeze`` around ``mi.render``.

A pass traced from Python pays its tracing on every call, and the product
kernel's tracing most: at 128 px and 16 spp about half of a pass's wall time
(docs/MEASUREMENTS.md, "Frozen passes"), 6-14 % at 480 x 360. A
:class:`FrozenPass` records the kernels of its first call and replays them on
later calls, for this project's integrators and Mitsuba's alike, so that
timing compares kernels with kernels.

How a pass is frozen (Dr.Jit's ``freeze`` rules, ``docs/freeze.rst``):

- The seed is an opaque ``UInt32``: a new seed replays instead of recording again.
- A replay runs no Python. The integrator's host-side work (``prepare_scene(scene,
  sensor)``: the per-scene state, the strategy choice and its pilot passes) runs
  before every call, outside the frozen function: the pilots are never
  recorded, and a scene whose parameters changed gets its new state before the
  replay reads it.
- The state object is an input compared by identity: a new one (rebuilt after
  a parameter change) records again, because the traced code depends on
  decisions taken in Python (which strategies exist, which branches are traced).
- Dr.Jit traverses PyTrees and Mitsuba objects, not the plain classes that hold
  this project's per-scene state: :func:`held_inputs` hands their arrays and
  Mitsuba objects over as inputs.
- Python's cycle collector is paused during a call: a cycle collected while a
  pass records could free arrays made before the recording, which Dr.Jit cannot
  record (the process aborts: ``enqueue_host_func(): this function cannot be
  recorded``). Garbage waits until the call returns.
- Fallback: when recording fails (an integrator whose arrays are out of reach,
  e.g. a user's plugin), a warning names the reason and the pass renders
  unfrozen from then on (:attr:`FrozenPass.frozen` is False). Images are the
  same either way (``tests/test_frozen.py``).
"""

from __future__ import annotations

import contextlib
import dataclasses
import gc
import warnings

import drjit as dr
import mitsuba as mi


@contextlib.contextmanager
def collector_paused():
    """Python's cycle collector off for the block (as it was after): a collection during a
    ``dr.freeze`` recording can free arrays made before it, which Dr.Jit cannot record."""
    collecting = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if collecting:
            gc.enable()


def held_inputs(state) -> list:
    """Every Dr.Jit array and Mitsuba object reachable from ``state`` through
    containers, dataclasses and plain objects' attributes (each once; a scene is
    left out: it is an input of the pass already)."""
    found, seen = [], set()

    def walk(value):
        if value is None or isinstance(value, (bool, int, float, str, bytes, type)) or id(value) in seen:
            return
        seen.add(id(value))
        if dr.is_array_v(value):
            found.append(value)
        elif isinstance(value, mi.Object):
            if not isinstance(value, mi.Scene):
                found.append(value)
        elif isinstance(value, (list, tuple, set, frozenset)):
            for item in value:
                walk(item)
        elif isinstance(value, dict):
            for item in value.values():
                walk(item)
        elif dataclasses.is_dataclass(value):
            for field in dataclasses.fields(value):
                walk(getattr(value, field.name, None))
        else:
            for item in getattr(value, "__dict__", {}).values():
                walk(item)
            for name in getattr(type(value), "__slots__", ()):
                walk(getattr(value, name, None))

    walk(state)
    return found


def _render(scene, sensor, integrator, seed, spp, state, inputs):
    """The function frozen: one pass. ``state`` and ``inputs`` are read by the
    integrator through its own attributes; they are arguments so that Dr.Jit
    compares the state's identity and traverses its arrays."""
    return mi.render(scene, sensor=sensor, integrator=integrator, spp=spp, seed=seed)


class FrozenPass:
    """Passes of one (scene, sensor, integrator, spp), recorded once and replayed.

    ``FrozenPass(scene, sensor, integrator, spp)(seed)`` returns the image as
    ``mi.render(scene, sensor=sensor, integrator=integrator, spp=spp, seed=seed)``
    would. With ``enabled=False`` it is exactly that call. The first call records; on a
    scene that has not rendered yet the second records once more (the first render sets
    up state, e.g. the sampler's, that the second finds changed), so ``compare`` renders
    each method once traced before it records.
    """

    def __init__(self, scene: mi.Scene, sensor, integrator: mi.Integrator, spp: int, enabled: bool = True):
        self.scene, self.sensor, self.integrator, self.spp = scene, sensor, integrator, int(spp)
        self.frozen = enabled
        self.failure: str | None = None
        # spp is a Python int: each value is its own recording (the kernels bake it in).
        self._function = dr.freeze(_render) if enabled else None

    @property
    def recordings(self) -> int:
        """How many times the pass was recorded (0 when not frozen)."""
        return self._function.n_recordings if self._function is not None else 0

    def __call__(self, seed: int) -> mi.TensorXf:
        prepare = getattr(self.integrator, "prepare_scene", None)
        state = prepare(self.scene, self.sensor) if prepare is not None else None
        if self.frozen:
            with collector_paused():
                try:
                    return self._function(self.scene, self.sensor, self.integrator, dr.opaque(mi.UInt32, seed),
                                          self.spp, state, held_inputs(state))
                except RuntimeError as err:
                    while err.__cause__ is not None:  # the innermost error says why
                        err = err.__cause__
                    self.frozen, self.failure = False, (str(err).strip().splitlines() or [type(err).__name__])[0]
                    warnings.warn(f"{type(self.integrator).__name__}: cannot freeze the render pass "
                                  f"({self.failure}); rendering unfrozen", RuntimeWarning, stacklevel=2)
        return mi.render(self.scene, sensor=self.sensor, integrator=self.integrator, spp=self.spp, seed=seed)


class Frozen:
    """``dr.freeze(function, **options)`` with Python's cycle collector paused during each
    call (a recording or a replay): what :func:`freeze` returns. ``n_recordings`` and
    the frozen function's other attributes are the wrapped one's."""

    def __init__(self, function, **options):
        self._frozen = dr.freeze(function, **options)

    def __call__(self, *args, **kwargs):
        with collector_paused():
            return self._frozen(*args, **kwargs)

    def __getattr__(self, name):
        return getattr(self._frozen, name)


def freeze(function=None, **options):
    """``dr.freeze`` for functions that render with this package's integrators (a frozen
    optimisation step of ``sh_prb``, a frozen preview of ``sh_direct``): the same
    recording and replay, with Python's cycle collector paused during each call.

    Why: a collection during a recording can free an array made before it, which Dr.Jit
    cannot record (the process aborts); a pass of these integrators leaves such cycles
    behind. The integrators refuse a recording while the collector runs, with an error
    that names this function. Call ``integrator.plan(scene)`` before the first call and
    again, outside the frozen function, to refresh the sampling state as parameters move
    (a replay runs no Python, so it renders with the state it was recorded with, which
    keeps images and gradients unbiased). Use as ``freeze(step)`` or ``@freeze``."""
    if function is None:
        return lambda f: Frozen(f, **options)
    return Frozen(function, **options)
