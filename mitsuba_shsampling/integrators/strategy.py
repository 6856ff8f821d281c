"""The environment strategies a shading point can use, and which one each material runs.

Every smooth lane samples the environment through this package with one of
the strategies of :class:`Strategy`. Which one is a property of the lane's BSDF
instance (its *material*): a :class:`StrategyTable` maps each BSDF's registry
id to a strategy, and the integrators gather it per lane. Lanes of one material
are coherent, so the symbolic branches that run a strategy's walks agree within
SIMD packets, and a packet with no lane of a strategy skips its walks.

The table is device data, not a constant of the traced kernel: assigning other
strategies (the chooser's pilot passes, :mod:`.chooser`) reuses the compiled
kernel.
"""

from __future__ import annotations

import enum

import drjit as dr
import mitsuba as mi
import numpy as np

from ..device_arrays import device_array


class Strategy(enum.IntEnum):
    """How a lane samples the environment (the value is the per-lane code)."""

    ENVIRONMENT = 0
    """The environment alone (MIS-compensated when ``mis_compensation``), one
    sample per ``emitter_samples``, power-heuristic weighted against the BSDF
    samples: the strategy of Mitsuba's ``direct`` on a compensated map, on this
    package's pyramid. No lobe is looked up, no product walk runs."""
    PRODUCT = 1
    """The product of the lane's SH lobe proxy and the (compensated)
    environment, weighted against the BSDF samples by the power heuristic."""
    PRODUCT_ONLY = 2
    """The product with the uncompensated environment carries every sample of
    the lane (``emitter_samples + bsdf_samples``, equally weighted), and no BSDF
    sample runs. Only for BSDFs without a Dirac part, and only in ``sh_direct``
    (a path's BSDF sample always runs, to continue it)."""
    ENVIRONMENT_ONLY = 3
    """The uncompensated environment alone carries every sample of the lane, and
    no BSDF sample runs: Mitsuba's ``direct`` with emitter samples only. Same
    conditions as :attr:`PRODUCT_ONLY`; no product code."""
    BSDF_ONLY = 4
    """The BSDF's own sampling carries every sample of the lane and no environment
    sample runs: Mitsuba's ``direct`` with BSDF samples only (``emitter_samples`` 0),
    the best of Mitsuba's strategies under a uniform or nearly uniform sky, where any
    sampling of the environment only adds noise. Each sample counts the environment
    it sees (a shadow ray towards the map); the other emitters keep Mitsuba's emitter
    sampling, weight 1. Same conditions as :attr:`PRODUCT_ONLY`; no product code."""

    @property
    def label(self) -> str:
        """The name used by the ``strategy`` parameter and in reports."""
        return self.name.lower()

    @property
    def uses_product(self) -> bool:
        return self in (Strategy.PRODUCT, Strategy.PRODUCT_ONLY)

    @property
    def carries_all(self) -> bool:
        """Every sample of the lane is this strategy's (no BSDF sample runs)."""
        return self in (Strategy.PRODUCT_ONLY, Strategy.ENVIRONMENT_ONLY, Strategy.BSDF_ONLY)

    @property
    def fallback(self) -> Strategy:
        """What a material that cannot run this strategy runs instead."""
        return {Strategy.PRODUCT_ONLY: Strategy.PRODUCT, Strategy.PRODUCT: Strategy.ENVIRONMENT,
                Strategy.ENVIRONMENT_ONLY: Strategy.ENVIRONMENT,
                Strategy.BSDF_ONLY: Strategy.ENVIRONMENT}.get(self, Strategy.ENVIRONMENT)


MITSUBA_STRATEGIES = tuple(s for s in Strategy if not s.uses_product)
"""Mitsuba's own strategies, without product code: what the lean kernel runs. The quadrature
predicts them from Mitsuba's own sampling, so the pilots scale them together."""

CARRYING_MITSUBA_STRATEGIES = tuple(s for s in MITSUBA_STRATEGIES if s.carries_all)
"""Mitsuba's own strategies that carry every sample: ``environment_only`` and ``bsdf_only``."""

AUTO = "auto"
"""The ``strategy`` parameter's value that lets :mod:`.chooser` decide per material."""

STRATEGY_NAMES = tuple(s.label for s in Strategy)

ESTIMATE = "estimate"
"""``plan`` value: strategies' costs from the cost model (:mod:`.costs`); no clock decides."""
MEASURE = "measure"
"""``plan`` value: strategies' costs from pilot passes timed in the scene."""
PLAN_MODES = (ESTIMATE, MEASURE)


def strategy_named(name: str) -> Strategy:
    """The :class:`Strategy` of a ``strategy`` parameter value (not ``auto``)."""
    return Strategy[name.upper()]


def parse_strategy(value: str) -> tuple[str, dict[str, str]]:
    """A ``strategy`` parameter value -> (the default for every material, material name ->
    strategy name).

    The value is a comma-separated list: ``name=strategy`` entries set one material's
    strategy (a material is named by its BSDF's id, as the reports name it), and at most
    one bare entry sets the default (``auto`` when there is none): ``"product"``,
    ``"copper=product,ground=environment"`` (the others ``auto``),
    ``"environment,copper=product"``. Raises ``ValueError`` for a malformed list; the
    names are checked against the scene when the plan is made."""
    default, per_material = None, {}
    for entry in (e.strip() for e in value.split(",")):
        name, equals, strategy = (part.strip() for part in entry.partition("="))
        if not equals:
            if default is not None or not entry:
                raise ValueError(f"'{value}' has {'an empty entry' if not entry else 'two defaults'}")
            default = entry
        elif not name or not strategy or name in per_material:
            raise ValueError(f"'{value}': entry '{entry}' must be 'material=strategy', each material once")
        else:
            per_material[name] = strategy
    return default or AUTO, per_material


class MaterialCodes:
    """A small code per material (BSDF registry id -> uint32), as device data gathered per
    lane: changing a code reuses the compiled kernel. Ids outside the table read 0."""

    def __init__(self, ids):
        self.ids = list(ids)
        self._size = max(self.ids, default=0) + 1
        self._codes = np.zeros(self._size, dtype=np.uint32)

    def _set(self, codes: dict[int, int]) -> None:
        for key, code in codes.items():
            if key not in self.ids:
                raise KeyError(f"BSDF registry id {key} is not a material of the table")
            self._codes[key] = code
        # At least two entries, so that the table is always an array in memory and
        # never a literal of the kernel (a literal would make each assignment a new kernel).
        codes = self._codes if self._size > 1 else np.append(self._codes, np.uint32(0))
        self._device = device_array(mi.UInt32, codes)
        dr.make_opaque(self._device)
        # Opaque too: the largest registry id changes with Mitsuba's parallel loading order.
        self._device_size = dr.opaque(mi.UInt32, self._size)

    def _code(self, key: int) -> int:
        return int(self._codes[key]) if key < self._size else 0

    def _lane(self, si: mi.SurfaceInteraction3f, active) -> mi.UInt32:
        bsdf_id = dr.reinterpret_array(mi.UInt32, si.bsdf())
        active = mi.Bool(active) & (bsdf_id < self._device_size)
        return dr.gather(mi.UInt32, self._device, bsdf_id, active)


class StrategyTable(MaterialCodes):
    """Strategy per material: BSDF registry id -> :class:`Strategy` code.

    ``initial`` maps the registry ids of the scene's materials that sample the
    environment (smooth BSDFs) to their first strategy; every other id, and ids
    outside the table, read :attr:`Strategy.ENVIRONMENT` (code 0).
    """

    def __init__(self, initial: dict[int, Strategy]):
        super().__init__(initial)
        self.assign(initial)

    def assign(self, choice: dict[int, Strategy]) -> None:
        """Set the strategy of the materials in ``choice`` (registry id -> strategy)."""
        self._set({key: int(strategy) for key, strategy in choice.items()})

    def of(self, key: int) -> Strategy:
        """The strategy of the material with registry id ``key``."""
        return Strategy(self._code(key))

    def lane(self, si: mi.SurfaceInteraction3f, active: mi.Bool = True) -> mi.UInt32:
        """Per lane: the strategy code of the BSDF at ``si`` (ENVIRONMENT where not ``active``)."""
        return self._lane(si, active)


class MaterialFlags(MaterialCodes):
    """A yes or no per material (BSDF registry id -> bool), in the form of
    :class:`StrategyTable`. Ids outside the table read False."""

    def __init__(self, ids, value: bool):
        super().__init__(ids)
        self.set({key: value for key in self.ids})

    def set(self, flags: dict) -> None:
        """Set the flag of the materials in ``flags`` (registry id -> bool)."""
        self._set({key: int(bool(value)) for key, value in flags.items()})

    def of(self, key: int) -> bool:
        return self._code(key) != 0

    def lane(self, si: mi.SurfaceInteraction3f, active: mi.Bool = True) -> mi.Bool:
        """Per lane: the flag of the BSDF at ``si`` (False where not ``active``)."""
        return self._lane(si, active) != 0
