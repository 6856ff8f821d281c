"""Per-scene state and planner shared by every integrator object with the same options.

A user who makes a second integrator object for a scene (a notebook cell run again,
a comparison script, ``mi.load_dict`` inside a loop) pays no second set-up: objects
of one plugin with equal options get one :class:`~.environment.SceneCache` and one
:class:`~.chooser.StrategyChooser`, so the state built and the plan made for a scene
by one of them are the other's. The table keeps the last :data:`SHARED_ENTRIES`
option sets of the process.
"""

from __future__ import annotations

from collections import OrderedDict
from typing import Callable

import mitsuba as mi

from .chooser import StrategyChooser
from .environment import SceneCache

SHARED_ENTRIES = 8
"""Option sets whose state is kept (the least recently used goes first)."""

_shared: "OrderedDict[tuple, tuple[SceneCache, StrategyChooser]]" = OrderedDict()


def shared_planning(options, extra: tuple, build: Callable[[mi.Scene], object],
                    chooser: Callable[[], StrategyChooser]) -> tuple[SceneCache, StrategyChooser]:
    """The (scene cache, planner) of a plugin with ``options`` (a frozen options dataclass;
    ``extra``: anything else its state depends on), made with ``build`` and ``chooser``
    the first time."""
    key = (type(options), options, extra, mi.variant())
    entry = _shared.get(key)
    if entry is None:
        entry = _shared[key] = (SceneCache(build), chooser())
    _shared.move_to_end(key)
    while len(_shared) > SHARED_ENTRIES:
        _shared.popitem(last=False)
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
