"""Per-scene state and planner shared by every integrator object with the same options.

A user who makes a second integrator object for a scene (a notebook cell run again,
a comparison script, ``mi.load_dict`` inside a loop) pays no second set-up: objects
of one plugin with equal options share one :class:`~.environment.SceneCache` per scene
they render and one :class:`~.chooser.StrategyChooser`, so the state built and the plan
made for a scene by one of them are the other's. Two such objects on two scenes (a
training and a validation scene, two optimisations in one process) each keep their own
scene's state: they do not rebuild each other's (:class:`SceneSlot`).

The table holds its entries weakly: an entry lives as long as one of its objects
does. A state holds its scene's objects (the emitter, the BSDFs), so a table that
kept it would keep a scene alive after the user dropped it, and with it the scene's
AD graph; a virtual call of a later differentiable render reaches every live
emitter and BSDF and would try to traverse that graph (Dr.Jit refuses: the edges lie
outside the render's ``isolate_grad`` scope). Builds that outlive every object (the
pyramid, the lobe fits, the cosine tables) are kept by their content instead
(:mod:`~mitsuba_shsampling.build_cache`).
"""

from __future__ import annotations

import functools
import gc
import weakref
from typing import Callable

import drjit as dr
import mitsuba as mi

from ..frozen import held_inputs

from .chooser import StrategyChooser
from .emitter_selection import DESIGNS
from .environment import SceneCache, collect_cycles, cycle_collections

class SharedPlanning:
    """The per-scene caches and the planner of one option set; every integrator object of
    that set holds it (which keeps it in the table). ``by_scene`` finds the cache of a scene
    that some object of the set renders (weakly: a cache lives while an object holds it,
    and it holds its scene)."""

    __slots__ = ("build", "by_scene", "chooser", "__weakref__")

    def __init__(self, build: Callable[[mi.Scene], object], chooser: StrategyChooser):
        self.build, self.chooser = build, chooser
        self.by_scene: "weakref.WeakValueDictionary[int, SceneCache]" = weakref.WeakValueDictionary()


class SceneSlot:
    """An integrator object's ``scenes``: the state of the scene it renders, from the cache
    of its option set that holds that scene (another object's, or a new one). The object
    holds its current scene's cache, and nothing more: a scene it moves away from lives on
    only while another object renders it (a state holds its scene's emitters and BSDFs,
    which a later virtual call would trace; see the module docstring)."""

    __slots__ = ("_shared", "_cache")

    def __init__(self, shared: SharedPlanning):
        self._shared, self._cache = shared, None

    def get(self, scene: mi.Scene, stale_ok: bool = False, tolerance: float = 0.0):
        """:meth:`.SceneCache.get` of the cache that holds ``scene``."""
        cache = self._cache
        if cache is None or cache.scene is not scene:
            found = self._shared.by_scene.get(id(scene))
            cache = found if found is not None and found.scene is scene else SceneCache(self._shared.build)
        state = cache.get(scene, stale_ok, tolerance)  # inside a recording: FrozenBeforePlanError for a new one
        # The previous scene's cache goes unless another object holds it.
        self._cache = self._shared.by_scene[id(scene)] = cache
        return state

    def motion(self) -> float:
        """:meth:`.SceneCache.motion` of the scene this object renders."""
        return self._cache.motion()


_shared: "weakref.WeakValueDictionary[tuple, SharedPlanning]" = weakref.WeakValueDictionary()


def shared_planning(options, extra: tuple, build: Callable[[mi.Scene], object],
                    chooser: Callable[[], StrategyChooser]) -> SharedPlanning:
    """The shared scene cache and planner of a plugin with ``options`` (a frozen options
    dataclass; ``extra``: anything else its state depends on), made with ``build`` and
    ``chooser`` where no live object has them. The caller keeps the returned object."""
    key = (type(options), options, extra, mi.variant())
    entry = _shared.get(key)
    if entry is None:
        entry = _shared[key] = SharedPlanning(build, chooser())
    return entry


def forget_shared() -> None:
    """Drop every shared state (tests that need a first set-up)."""
    _shared.clear()


def plan(self, scene: mi.Scene, sensor=0):
    """The plan for ``scene`` (:class:`~.chooser.StrategyChoice`), made now if it was
    not made yet: the per-scene state and, with ``strategy`` ``auto``, each material's
    strategy. None where nothing is planned (no environment map to sample, or every
    strategy set by ``strategy``).

    The ``plan`` method of the plugins that make one (a function, not a mixin: a
    Mitsuba integrator class takes one base).

    It also runs Python's cycle collector: a frozen function (``mitsuba_shsampling.freeze``)
    pauses it, and while it records, the objects of a dropped scene that only the collector
    frees would still be registered with Dr.Jit, whose virtual calls would then find
    instances that are no inputs of the recording. (Not twice: a state built in this call
    ran it before its build.)"""
    collected = cycle_collections()
    prepared(self, scene, sensor)
    if not dr.flag(dr.JitFlag.FreezingScope) and cycle_collections() == collected:
        collect_cycles()
    return self.choice(scene)


class FrozenWithCollectorError(RuntimeError):
    """A ``dr.freeze`` recording reached an integrator while Python's cycle collector runs."""


def prepared(integrator, scene: mi.Scene, sensor=0) -> None:
    """``integrator.prepare_scene`` on the host (state and plan), then the state's arrays
    and objects as the integrator's ``frozen_inputs``.

    Why: Dr.Jit traverses a Python integrator's attributes when a ``dr.freeze``-d
    function takes it as an input (a user's frozen optimisation step), and the state is
    held by plain Python objects that it does not traverse; through this list the
    recording reads the state's arrays as inputs. Inside a recording nothing is
    prepared: the state made before is used as it is (:meth:`.SceneCache.get`)."""
    if dr.flag(dr.JitFlag.FreezingScope):
        if gc.isenabled():
            raise FrozenWithCollectorError(
                f"{type(integrator).__name__}: a dr.freeze recording with Python's cycle collector running "
                "can abort the process (a collection may free arrays made before the recording, which Dr.Jit "
                "cannot record): freeze the function with mitsuba_shsampling.freeze, which pauses the "
                "collector during each call, or call gc.disable() around it")
        integrator.scenes.get(scene)  # the state made before, or FrozenBeforePlanError
        return
    state = integrator.prepare_scene(scene, sensor)
    # Walked on every call, not once per state: a re-plan replaces arrays inside the same state
    # (the strategy table), and a recording must find the current ones.
    integrator.frozen_inputs = held_inputs(state) + [design_marker(state)]


def design_marker(state) -> mi.UInt32:
    """An array whose length says which emitter design (``sh_direct``'s ``emitter_selection``)
    the state runs. The design is a Python string the trace reads, which a recording does not
    see among its inputs (Dr.Jit keys an integrator's attributes by their arrays' layouts, not
    by its plain Python values); an input of another length records anew."""
    return _marker(mi.variant(), getattr(state, "emitter_selection", "each"))


@functools.lru_cache(maxsize=None)
def _marker(variant: str, design: str) -> mi.UInt32:
    """One read-only marker per variant and design, made once (:func:`prepared` runs before
    every pass)."""
    return dr.opaque(mi.UInt32, 0, 1 + DESIGNS.index(design))


def planned_render(base) -> Callable:
    """The ``render`` method of a plugin whose class derives from ``base``: it plans (the
    plugin's ``prepare_scene``) before it renders as ``base`` does. A pilot pass of the
    planner (``StrategyChooser.piloting``) renders as the plugin is set, without planning."""
    def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
        if not self.chooser.piloting:
            prepared(self, scene, sensor)
        return base.render(self, scene, sensor, seed, spp, develop, evaluate)

    return render
