"""Per-scene state and planner shared by every integrator object with the same options.

A user who makes a second integrator object for a scene (a notebook cell run again,
a comparison script, ``mi.load_dict`` inside a loop) pays no second set-up: objects
of one plugin with equal options get one :class:`~.environment.SceneCache` and one
:class:`~.chooser.StrategyChooser`, so the state built and the plan made for a scene
by one of them are the other's.

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

import weakref
from typing import Callable

import mitsuba as mi

from .chooser import StrategyChooser
from .environment import SceneCache

class SharedPlanning:
    """The scene cache and the planner of one option set; every integrator object of
    that set holds it (which keeps it in the table)."""

    __slots__ = ("scenes", "chooser", "__weakref__")

    def __init__(self, scenes: SceneCache, chooser: StrategyChooser):
        self.scenes, self.chooser = scenes, chooser


_shared: "weakref.WeakValueDictionary[tuple, SharedPlanning]" = weakref.WeakValueDictionary()


def shared_planning(options, extra: tuple, build: Callable[[mi.Scene], object],
                    chooser: Callable[[], StrategyChooser]) -> SharedPlanning:
    """The shared scene cache and planner of a plugin with ``options`` (a frozen options
    dataclass; ``extra``: anything else its state depends on), made with ``build`` and
    ``chooser`` where no live object has them. The caller keeps the returned object."""
    key = (type(options), options, extra, mi.variant())
    entry = _shared.get(key)
    if entry is None:
        entry = _shared[key] = SharedPlanning(SceneCache(build), chooser())
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
    Mitsuba integrator class takes one base)."""
    self.prepare_scene(scene, sensor)
    return self.choice(scene)


def planned_render(base) -> Callable:
    """The ``render`` method of a plugin whose class derives from ``base``: it plans (the
    plugin's ``prepare_scene``) before it renders as ``base`` does. A pilot pass of the
    planner (``StrategyChooser.piloting``) renders as the plugin is set, without planning."""
    def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
        if not self.chooser.piloting:
            self.prepare_scene(scene, sensor)
        return base.render(self, scene, sensor, seed, spp, develop, evaluate)

    return render
