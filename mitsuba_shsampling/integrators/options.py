"""Plugin parameters of ``sh_direct``, ``sh_path``, ``sh_prb`` and ``oracle_direct``: defaults,
limits, validation, documentation.

One frozen dataclass per plugin (:class:`DirectOptions`, :class:`PathOptions`,
both extending :class:`ProductOptions`, the options of the product strategy;
:class:`PRBOptions`, extending :class:`PathOptions`; :class:`OracleOptions`,
:class:`OraclePathOptions`),
all extending :class:`PluginOptions`.
Each field carries its documentation; the plugins' RST parameter tables are
generated from it (:func:`document_parameters`), so code, checks and docs
cannot disagree. Limits come from the modules that impose them: the SH basis
(:data:`~mitsuba_shsampling.sh.basis.MAX_ORDER`), the lobe proxies
(:data:`~mitsuba_shsampling.lobes.scene_lobes.DIFFUSE_BANDS`), the warp
hierarchy (:data:`~mitsuba_shsampling.warp.hierarchy.MAX_DEPTH`), the
product warp (:func:`~mitsuba_shsampling.warp.product.check_defensive_share`) and the
oracle (:func:`~mitsuba_shsampling.warp.oracle.check_resolution`).

Conventions follow Mitsuba's own integrators: integer and boolean parameters
must have exactly that type (an ``<integer>`` in XML, a Python ``int`` in a
dict; ``"8"``, ``8.0`` or ``True`` for an integer are errors; a float
parameter also takes an integer, as Mitsuba's do), ``max_depth``
is -1 (infinite) or >= 0 (0 renders nothing, 1 only directly visible
emitters), ``rr_depth`` > 0. Unknown parameter names are reported by
Mitsuba's parser ("unreferenced property"), as for any plugin.

``compare`` and other callers validate values the same way, e.g.
``PathOptions(max_depth=args.max_depth)`` raises :class:`OptionError`.
"""

from __future__ import annotations

import dataclasses
import warnings
from typing import ClassVar

from ..lobes.scene_lobes import DEFAULT_MAX_BANDS, DIFFUSE_BANDS, MAX_BANDS, check_max_bands
from ..warp.hierarchy import MAX_DEPTH
from ..warp.oracle import (DEFAULT_RESOLUTION as DEFAULT_ORACLE_RESOLUTION,
                           MAX_RESOLUTION as MAX_ORACLE_RESOLUTION, check_resolution)
from ..warp.product import DEFAULT_DEFENSIVE_SHARE, DEFAULT_PROXY_DEPTH, SH_DEPTH_WITH_PROXY, check_defensive_share
from .strategy import AUTO, ESTIMATE, PLAN_MODES, STRATEGY_NAMES, Strategy, parse_strategy

#: Band counts the lobe proxies support (:func:`~..lobes.scene_lobes.check_max_bands`).
MIN_BANDS = DIFFUSE_BANDS

# sh_prb's state is rebuilt at most every 64 renders: a build of the material studio's lobe
# table (3.5 s idle, 4-7 s on a busy machine) every 16 steps made an optimisation at 96 px and
# 4 spp take 1.3-1.5x as long per step, while a state 64 steps old converged as well
# (scripts/optimise_prb.py, since replaced by scripts/bench_inverse.py; docs/MEASUREMENTS.md, "sh_prb's state rebuilds").
DEFAULT_REBUILD_INTERVAL = 64

# A state built for parameters within 5 % (relative L2, per parameter) of the current ones is
# kept: chosen before measuring, as a change that moves a lobe's width or a map's texels by a
# few per cent, which changes a sampling density's variance by about as little.
DEFAULT_REBUILD_TOLERANCE = 0.05

DEFAULT_SH_DEPTH = SH_DEPTH_WITH_PROXY

# The BSDF's share in product_only's mixture: the environment's own share in the product's
# (DEFAULT_DEFENSIVE_SHARE), for the same reason on the other factor, chosen before it was
# measured (docs/MEASUREMENTS.md, "A BSDF share in product_only").
DEFAULT_BSDF_DEFENSIVE_SHARE = 0.1


class OptionError(ValueError):
    """A plugin parameter of the wrong type or out of range; the message is one line
    naming the plugin, the parameter, what it must be and what it got."""


def sample_shares(emitter_samples: int, bsdf_samples: int) -> tuple[float, float]:
    """The shares of a lane's samples that are emitter and BSDF samples: the sample-count
    fractions with which ``direct`` (and every direct-illumination estimator here) weighs
    its strategies in the power heuristic."""
    total = emitter_samples + bsdf_samples
    return emitter_samples / total, bsdf_samples / total


def _doc(text: str) -> dict:
    return {"doc": text}


def _emitter_samples_field(what: str):
    """``emitter_samples`` of the direct-illumination plugins: ``what`` says what they draw."""
    return dataclasses.field(default=1, metadata=_doc(
        f"{what}; also the number of Mitsuba emitter samples for any other emitters."))


def _bsdf_samples_field(more: str):
    """``bsdf_samples`` of the direct-illumination plugins, ``more`` appended to its documentation."""
    return dataclasses.field(default=1, metadata=_doc(f"BSDF samples per shading point{more}."))


_ARTICLES = {int: "an integer", bool: "a boolean", float: "a float", str: "a string"}
#: Mitsuba's names of property types, for messages.
_TYPE_NAMES = {bool: "boolean", int: "integer", float: "float", str: "string"}


@dataclasses.dataclass(frozen=True)
class PluginOptions:
    """What every plugin's options share: exact types, range checks, one-line errors,
    reading from ``mi.Properties``. Subclasses add the fields and ``_check_ranges``."""

    #: Plugin name used in messages (set by the subclasses).
    PLUGIN: ClassVar[str] = "sh_*"
    #: Parameters of the plugin docstring's XML and Python example (:func:`document_parameters`).
    EXAMPLE: ClassVar[dict] = {}

    def __post_init__(self) -> None:
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            # Exact types (that of the default): bool is a subclass of int, and True
            # for an integer is a mistake.
            expected = type(field.default)
            if expected is float and type(value) is int:
                object.__setattr__(self, field.name, float(value))
            elif type(value) is not expected:
                self._fail(field.name, f"must be {_ARTICLES[expected]}", value)
        self._check_ranges()

    def _check_ranges(self) -> None:
        pass

    def _fail(self, name: str, requirement: str, value) -> None:
        kind = _TYPE_NAMES.get(type(value), type(value).__name__)
        raise OptionError(f"{self.PLUGIN}: parameter '{name}' {requirement}, got {kind} {value!r}")

    @property
    def sample_shares(self) -> tuple[float, float]:
        """(emitter, BSDF) shares of a lane's samples (of the plugins with sample counts)."""
        return sample_shares(self.emitter_samples, self.bsdf_samples)

    def _check_sample_counts(self) -> None:
        """``emitter_samples`` and ``bsdf_samples`` (of the plugins that have them): >= 0, not both 0."""
        for name in ("emitter_samples", "bsdf_samples"):
            if getattr(self, name) < 0:
                self._fail(name, "must be >= 0", getattr(self, name))
        if self.emitter_samples + self.bsdf_samples == 0:
            raise OptionError(f"{self.PLUGIN}: parameters 'emitter_samples' and 'bsdf_samples' "
                              "must be >= 0 and not both 0, got 0 and 0")

    def _check_oracle(self) -> None:
        """``resolution`` and ``defensive_share`` (of the oracle references)."""
        try:
            check_resolution(self.resolution)
        except ValueError:
            self._fail("resolution", f"must be a power of two in [2, {MAX_ORACLE_RESOLUTION}]", self.resolution)
        try:
            check_defensive_share(self.defensive_share)
        except ValueError:
            self._fail("defensive_share", "must be in (0, 1]", self.defensive_share)

    @classmethod
    def from_properties(cls, props):
        """Options from a plugin's ``mi.Properties``: the parameters it sets, defaults
        for the others. Reading a property marks it as used, so Mitsuba still reports
        misspelled names."""
        names = [f.name for f in dataclasses.fields(cls)]
        return cls(**{name: props.get(name) for name in names if name in props})


@dataclasses.dataclass(frozen=True)
class ProductOptions(PluginOptions):
    """Options of the SH product strategy, common to both plugins."""

    hide_emitters: bool = dataclasses.field(default=False, metadata=_doc(
        "Hide directly visible emitters."))
    strategy: str = dataclasses.field(default=AUTO, metadata=_doc(
        "How each material samples the environment (one value for every material, or a "
        "comma-separated list of ``material=value`` entries naming materials by their BSDF's id, "
        "with at most one bare value for the others, e.g. ``copper=product,ground=environment``): "
        "``environment`` (the environment alone, "
        "MIS-compensated, with the BSDF samples: Mitsuba's ``direct`` with ``mis_compensation`` "
        "on this package's pyramid, no lobe and no product walk), ``product`` (the SH lobe x "
        "environment product with the BSDF samples, under MIS), ``product_only`` (``sh_direct`` "
        "only: the product with the uncompensated map carries every sample and no BSDF sample "
        "runs, for BSDFs without a Dirac part; the others use ``product``), ``environment_only`` "
        "(``sh_direct`` only: the uncompensated environment alone carries every sample), "
        "``bsdf_only`` (``sh_direct`` only: the BSDF's sampling carries every sample, Mitsuba's "
        "``direct`` with BSDF samples only, the best strategy under a uniform sky; both for "
        "BSDFs without a Dirac part, the others use ``environment``), or ``auto``: before "
        "the first pass each material gets the strategy that minimises the predicted image error "
        "at equal time, from the variance of each strategy at the camera's first hits and the "
        "strategies' costs (see ``plan`` and integrators/chooser.py). Materials without a product lobe "
        "(transmissive BSDFs) use the environment strategies only."))
    plan: str = dataclasses.field(default=ESTIMATE, metadata=_doc(
        "Where ``auto`` takes the strategies' costs from: ``estimate``, a cost model (this "
        "machine's calibration, ``python -m mitsuba_shsampling calibrate``, else the shipped "
        "one), so that the same scene and options give the same plan, and the same image at "
        "the same seed, in every process; or ``measure``, pilot passes timed in the scene (a "
        "plan that can differ from run to run; kept in the cache folder by the scene's content "
        "and reused, as FFTW keeps its wisdom)."))
    plan_file: str = dataclasses.field(default="", metadata=_doc(
        "A JSON file for the plan: loaded when it holds a plan for this scene's materials and "
        "these options, else made and written there (empty: none)."))
    max_bands: int = dataclasses.field(default=DEFAULT_MAX_BANDS, metadata=_doc(
        f"Cap on the SH band count of the lobe proxies ({MIN_BANDS}..{MAX_BANDS}); the scene's "
        "band count follows its sharpest lobe, and sharper lobes are widened to what the cap "
        "represents (BSDF sampling under MIS takes over)."))
    sh_depth: int = dataclasses.field(default=DEFAULT_SH_DEPTH, metadata=_doc(
        f"Levels of the product hierarchy that use analytic SH cell integrals (1..{MAX_DEPTH}, "
        "or -1: from the band count, 2^k >= 4 n); below them the closed-form proxy takes over "
        "down to ``proxy_depth``, then the environment alone."))
    proxy_depth: int = dataclasses.field(default=DEFAULT_PROXY_DEPTH, metadata=_doc(
        "Levels of the product hierarchy, counted from the root, down to which the children are "
        "weighted by the lobe proxy in closed form (its fitted exponent, not widened to the band "
        f"limit) times the environment (0..{MAX_DEPTH}); the levels "
        "between ``sh_depth`` and this use it, deeper ones follow the environment alone. A value "
        "not above ``sh_depth`` switches it off."))
    mis_compensation: bool = dataclasses.field(default=True, metadata=_doc(
        "Product-sample against the environment minus its mean radiance (clamped at 0), "
        "leaving the smooth part to BSDF sampling, as Mitsuba's ``envmap`` option of the "
        "same name does. It leaves holes that only BSDF sampling covers, so ``sh_direct`` "
        "switches it off (with a warning) when ``bsdf_samples`` is 0; in ``sh_path`` the BSDF "
        "sample that continues every path covers them."))
    defensive_share: float = dataclasses.field(default=DEFAULT_DEFENSIVE_SHARE, metadata=_doc(
        "Share e of the environment's own distribution in the product strategy, which samples "
        "(1 - e) product + e environment. It keeps the strategy's pdf positive wherever the map "
        "is lit, so a clamped or inexact lobe never leaves lit directions to BSDF sampling alone "
        "(whose rare hits on a bright light are fireflies). In (0, 1]."))

    #: Values of ``strategy`` this plugin accepts.
    STRATEGIES: ClassVar[tuple] = (AUTO,) + STRATEGY_NAMES

    def _check_ranges(self) -> None:
        one_of = "must be one of " + ", ".join(f"'{s}'" for s in self.STRATEGIES)
        try:
            default, per_material = parse_strategy(self.strategy)
        except ValueError as err:
            self._fail("strategy", f"{one_of}, or a list 'material=strategy,...' ({err})", self.strategy)
        for value in [default, *per_material.values()]:
            if value not in self.STRATEGIES:
                self._fail("strategy", one_of + (" (in every entry)" if per_material else ""), self.strategy)
        if self.plan not in PLAN_MODES:
            self._fail("plan", "must be one of " + ", ".join(f"'{m}'" for m in PLAN_MODES), self.plan)
        try:
            check_max_bands(self.max_bands)
        except ValueError:
            self._fail("max_bands", f"must be in [{MIN_BANDS}, {MAX_BANDS}]", self.max_bands)
        if not (self.sh_depth == -1 or 1 <= self.sh_depth <= MAX_DEPTH):
            self._fail("sh_depth", f"must be in [1, {MAX_DEPTH}] or -1 (automatic)", self.sh_depth)
        if not 0 <= self.proxy_depth <= MAX_DEPTH:
            self._fail("proxy_depth", f"must be in [0, {MAX_DEPTH}]", self.proxy_depth)
        try:
            check_defensive_share(self.defensive_share)
        except ValueError:
            self._fail("defensive_share", "must be in (0, 1]", self.defensive_share)

    @property
    def default_strategy(self) -> str:
        """``strategy``'s value for the materials it does not name (``auto`` by default)."""
        return parse_strategy(self.strategy)[0]

    @property
    def material_strategies(self) -> dict[str, str]:
        """Material name -> the strategy ``strategy`` sets for it."""
        return parse_strategy(self.strategy)[1]

    @property
    def plan_key(self) -> str:
        """What a stored plan must have been made with: every option but the plan's own."""
        return repr(dataclasses.replace(self, plan=ESTIMATE, plan_file=""))

    @property
    def warp_sh_depth(self) -> int | None:
        """``sh_depth`` as :class:`~mitsuba_shsampling.warp.product.ProductWarp` takes it
        (None: automatic)."""
        return None if self.sh_depth == -1 else self.sh_depth

    @property
    def warp_proxy_depth(self) -> int | None:
        """``proxy_depth`` as :class:`~mitsuba_shsampling.warp.product.ProductWarp` takes it
        (None: no closed-form proxy levels)."""
        return self.proxy_depth or None


@dataclasses.dataclass(frozen=True)
class DirectOptions(ProductOptions):
    """Parameters of ``sh_direct``."""

    PLUGIN: ClassVar[str] = "sh_direct"

    EXAMPLE: ClassVar[dict] = {"emitter_samples": 1, "bsdf_samples": 1, "strategy": "auto"}

    emitter_samples: int = _emitter_samples_field(
        "Environment samples per shading point, drawn from the product of the BSDF lobe "
        "(in spherical harmonics, rotated per shading point) and the environment map")
    bsdf_samples: int = _bsdf_samples_field("")
    emitter_selection: str = dataclasses.field(default="auto", metadata=_doc(
        "Where the scene has emitters besides the environment: ``each``, every emitter sample "
        "is one sample of the environment (the material's strategy) plus one of Mitsuba's "
        "emitter sampling for the others, two shadow rays; ``one``, an emitter drawn as "
        "Mitsuba's ``direct`` draws it (uniformly, or by the emitters' ``sampling_weight``), "
        "then one sample of it, with the material's strategy where it is the environment: "
        "one shadow ray; or ``auto``, the one of the two the plan prices better (each's "
        "variance from pilot images, its time from the cost model; ``each`` where no plan is "
        "made: every material's ``strategy`` set). The same estimator in a scene lit by its "
        "environment alone."))

    bsdf_defensive_share: float = dataclasses.field(default=DEFAULT_BSDF_DEFENSIVE_SHARE, metadata=_doc(
        "Share b of the BSDF's own sampling in ``product_only``, which draws each sample from "
        "(1 - b) product + b BSDF. Where the lobe proxy misses part of the BSDF (the grazing "
        "peak of a rough coating), no BSDF sample runs in that strategy to find it: this share "
        "bounds its samples' values there (by the BSDF sample's weight times the radiance / b). "
        "In [0, 1); 0 switches it off."))

    #: Values of ``emitter_selection``.
    EMITTER_SELECTIONS: ClassVar[tuple] = ("auto", "each", "one")

    def _check_ranges(self) -> None:
        super()._check_ranges()
        self._check_sample_counts()
        if not 0.0 <= self.bsdf_defensive_share < 1.0:
            self._fail("bsdf_defensive_share", "must be in [0, 1)", self.bsdf_defensive_share)
        if self.emitter_selection not in self.EMITTER_SELECTIONS:
            self._fail("emitter_selection", "must be one of "
                       + ", ".join(f"'{v}'" for v in self.EMITTER_SELECTIONS), self.emitter_selection)
        # The strategies that carry every sample take the BSDF samples' slots; without any, the
        # others are what they would be with them, but bsdf_only would silently become the environment.
        if self.bsdf_samples == 0 and Strategy.BSDF_ONLY.label in [self.default_strategy,
                                                                   *self.material_strategies.values()]:
            self._fail("strategy", "can only be 'bsdf_only' with 'bsdf_samples' > 0 (Mitsuba's direct with "
                       "'emitter_samples' 0 draws from the BSDF alone)", self.strategy)

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.mis_compensation and self.bsdf_samples == 0:
            # The compensated environment is 0 wherever the map is darker than
            # its mean: without BSDF samples nothing would reach those directions.
            warnings.warn(f"{self.PLUGIN}: 'mis_compensation' is switched off because 'bsdf_samples' "
                          "is 0 (only BSDF sampling covers the directions it leaves out)", stacklevel=3)
            object.__setattr__(self, "mis_compensation", False)


@dataclasses.dataclass(frozen=True)
class PathOptions(ProductOptions):
    """Parameters of ``sh_path``."""

    PLUGIN: ClassVar[str] = "sh_path"
    EXAMPLE: ClassVar[dict] = {"max_depth": 8}
    # The BSDF sample continues the path, so it always runs.
    STRATEGIES: ClassVar[tuple] = (AUTO, Strategy.ENVIRONMENT.label, Strategy.PRODUCT.label)

    max_depth: int = dataclasses.field(default=-1, metadata=_doc(
        "Longest path, in vertices after the camera (-1: infinite). As in Mitsuba's "
        "``path``: 0 renders nothing, 1 only directly visible emitters, 2 direct lighting."))
    rr_depth: int = dataclasses.field(default=5, metadata=_doc(
        "Path depth at which Russian roulette starts (> 0)."))
    product_depth: int = dataclasses.field(default=1, metadata=_doc(
        "Vertices of a path, from the camera's first hit (1), at which a material's product "
        "strategy runs (-1: every vertex); deeper vertices sample the environment alone "
        "(MIS-compensated). Deeper vertices carry less of the image and their packets mix "
        "materials, so the product's walks cost them as much for less: on the interior under "
        "forest_slope the product at every vertex gave 1.53x ``path``'s efficiency, at the "
        "first hits only 1.64x (docs/MEASUREMENTS.md, \"The product at a path's first hits\"). "
        "A Dirac bounce (a mirror, glass) is not counted: what the camera sees in a mirror or "
        "through a window is a first hit too (the studio with a mirror panel under "
        "forest_slope: 1.12x the efficiency of counting it)."))

    @property
    def depth_limit(self) -> int:
        """``max_depth`` as the integrators' loop compares it with a vertex's depth (-1: no limit)."""
        return self.max_depth if self.max_depth >= 0 else 0xFFFFFFFF

    @property
    def product_depth_limit(self) -> int:
        """``product_depth`` as the loop compares it with a vertex's depth (-1: no limit)."""
        return self.product_depth if self.product_depth >= 0 else 0xFFFFFFFF

    def _check_ranges(self) -> None:
        super()._check_ranges()
        if self.max_depth < -1:
            self._fail("max_depth", "must be -1 (infinite) or >= 0", self.max_depth)
        if self.rr_depth <= 0:
            self._fail("rr_depth", "must be > 0", self.rr_depth)
        if self.product_depth == 0 or self.product_depth < -1:
            self._fail("product_depth", "must be -1 (every vertex) or >= 1", self.product_depth)


@dataclasses.dataclass(frozen=True)
class PRBOptions(PathOptions):
    """Parameters of ``sh_prb``: those of Mitsuba's ``prb`` (its default ``max_depth``)
    and the product strategy's."""

    PLUGIN: ClassVar[str] = "sh_prb"
    EXAMPLE: ClassVar[dict] = {"max_depth": 6}

    max_depth: int = dataclasses.field(default=6, metadata=_doc(
        "Longest path, in vertices after the camera (-1: infinite). As in Mitsuba's "
        "``prb``: 0 renders nothing, 1 only directly visible emitters, 2 direct lighting."))
    rebuild_interval: int = dataclasses.field(default=DEFAULT_REBUILD_INTERVAL, metadata=_doc(
        "Renders (primal passes) at least between two builds of the sampling state (pyramid, "
        "lobe table) while an optimisation changes its inputs (>= 1; 1: rebuilt whenever they "
        "changed, as ``sh_path`` does). In between, the state of older parameters still gives "
        "unbiased images and gradients (it is only a sampling density, MIS-combined with the "
        "BSDF sample that always runs), at some variance; a build of the material studio's lobe "
        "table takes seconds, many render passes' time."))
    rebuild_tolerance: float = dataclasses.field(default=DEFAULT_REBUILD_TOLERANCE, metadata=_doc(
        "How far the state's inputs must have moved for a rebuild: the largest relative change "
        "|x - x_built| / |x_built| of one parameter (all its values together: a texture's texels, "
        "a roughness) since the state was built. Where they moved less, the state is kept, at "
        "the interval's end and on ``integrator.plan(scene)`` alike, and checked again at the "
        "next render or plan: late in an optimisation, when the parameters settle, nothing is "
        "rebuilt. A changed transform or flag always rebuilds. >= 0; 0: any change rebuilds."))

    plan_for: str = dataclasses.field(default="image", metadata=_doc(
        "What the plan (``strategy`` ``auto``) minimises: ``image`` (default), the primal image's "
        "variance at equal time, as ``sh_path``'s; ``gradients``, the variance of the gradients of "
        "the parameters whose gradients are enabled when the plan is made (an optimisation's "
        "unknowns): the plan, every material on ``environment`` and every material on ``product`` "
        "weighed by a few primal and replay passes at fixed seeds, 1.5-3.5 s once per scene "
        "(integrators/gradient_plan.py). Measured on three inverse problems at equal time it was "
        "0.87-1.09x ``image``'s plan (scripts/bench_gradient_plans.py), so it is not "
        "the default. A strategy set by ``strategy`` is kept as set."))

    def _check_ranges(self) -> None:
        super()._check_ranges()
        if self.plan_for not in ("image", "gradients"):
            self._fail("plan_for", "must be 'image' or 'gradients'", self.plan_for)
        if self.rebuild_interval < 1:
            self._fail("rebuild_interval", "must be >= 1", self.rebuild_interval)
        if not self.rebuild_tolerance >= 0.0:
            self._fail("rebuild_tolerance", "must be >= 0", self.rebuild_tolerance)


@dataclasses.dataclass(frozen=True)
class OracleOptions(PluginOptions):
    """Parameters of ``oracle_direct``."""

    PLUGIN: ClassVar[str] = "oracle_direct"

    EXAMPLE: ClassVar[dict] = {"emitter_samples": 1, "bsdf_samples": 1, "resolution": 64}

    emitter_samples: int = _emitter_samples_field(
        "Oracle samples of the environment per shading point, drawn from the exact BSDF x "
        "environment product tabulated at the shading point")
    bsdf_samples: int = _bsdf_samples_field("; with 0 every environment sample is an oracle sample (weight 1)")
    resolution: int = dataclasses.field(default=DEFAULT_ORACLE_RESOLUTION, metadata=_doc(
        f"Cells per side N of the table (a power of two in [2, {MAX_ORACLE_RESOLUTION}], capped at "
        "the environment pyramid's finest level): the BSDF is evaluated at the centres of the "
        "N x N equal-area cells, N^2 evaluations per shading point and about N^2 / 2 more per "
        "oracle sample."))
    defensive_share: float = dataclasses.field(default=DEFAULT_DEFENSIVE_SHARE, metadata=_doc(
        "Share e of the environment's own distribution in the oracle, which samples "
        "(1 - e) tabulated product + e environment, so that every lit direction has a positive pdf "
        "however coarse the table. In (0, 1]."))
    hide_emitters: bool = dataclasses.field(default=False, metadata=_doc(
        "Hide directly visible emitters."))

    def _check_ranges(self) -> None:
        self._check_sample_counts()
        self._check_oracle()


@dataclasses.dataclass(frozen=True)
class OraclePathOptions(PluginOptions):
    """Parameters of ``oracle_path``."""

    PLUGIN: ClassVar[str] = "oracle_path"

    EXAMPLE: ClassVar[dict] = {"max_depth": 4, "oracle_vertex": 2, "resolution": 32}

    max_depth: int = dataclasses.field(default=4, metadata=_doc(
        "Longest path, in vertices after the camera, as in Mitsuba's ``path`` (>= 2)."))
    rr_depth: int = dataclasses.field(default=5, metadata=_doc(
        "Path depth at which Russian roulette starts (> 0)."))
    oracle_vertex: int = dataclasses.field(default=1, metadata=_doc(
        "The one vertex of a path (1: the camera's first hit) whose environment sample is the "
        "oracle's; every other vertex samples the environment alone (MIS-compensated), as "
        "``sh_path``'s ``environment`` strategy does (0: no vertex: that strategy everywhere)."))
    resolution: int = dataclasses.field(default=32, metadata=_doc(
        f"Cells per side N of the oracle's table (a power of two in [2, {MAX_ORACLE_RESOLUTION}]): N^2 BSDF "
        "evaluations per oracle vertex and about N^2 / 2 per oracle sample."))
    defensive_share: float = dataclasses.field(default=DEFAULT_DEFENSIVE_SHARE, metadata=_doc(
        "Share e of the environment's own distribution in the oracle (as ``oracle_direct``'s). In (0, 1]."))
    hide_emitters: bool = dataclasses.field(default=False, metadata=_doc(
        "Hide directly visible emitters."))

    def _check_ranges(self) -> None:
        if self.max_depth < 2:
            self._fail("max_depth", "must be >= 2 (the oracle samples at a vertex)", self.max_depth)
        if self.rr_depth <= 0:
            self._fail("rr_depth", "must be > 0", self.rr_depth)
        if not 0 <= self.oracle_vertex < self.max_depth:
            self._fail("oracle_vertex", f"must be in [0, max_depth - 1 = {self.max_depth - 1}]", self.oracle_vertex)
        self._check_oracle()


def parameter_table(options_cls: type[PluginOptions], indent: str = "") -> str:
    """The RST ``pluginparameters`` rows of a plugin: name, type, documentation, default."""
    rows = []
    for field in sorted(dataclasses.fields(options_cls), key=_documentation_order(options_cls)):
        kind = type(field.default).__name__
        default = str(field.default).lower() if kind == "bool" else field.default
        rows += [f"{indent} * - {field.name}",
                 f"{indent}   - |{kind}|",
                 f"{indent}   - {field.metadata['doc']} (Default: {default})"]
    return "\n".join(rows)


def _documentation_order(options_cls):
    """Plugin-specific parameters first (as Mitsuba's docs list them), then the shared ones."""
    shared = [f.name for f in dataclasses.fields(ProductOptions)]
    own = [f.name for f in dataclasses.fields(options_cls) if f.name not in shared]
    order = own + shared
    return lambda field: order.index(field.name)


def usage_example(options_cls: type[PluginOptions], indent: str = "") -> str:
    """The RST ``tabs`` of a plugin's docstring: ``options_cls.EXAMPLE`` in XML and as a
    Python dict, written from one place so that the two cannot disagree."""
    def xml_value(value):
        return str(value).lower() if isinstance(value, bool) else value

    example = options_cls.EXAMPLE
    properties = [f'{indent}            <{_TYPE_NAMES[type(v)]} name="{k}" value="{xml_value(v)}"/>'
                  for k, v in example.items()]
    python = ", ".join([f"'type': '{options_cls.PLUGIN}'"] + [f"'{k}': {v!r}" for k, v in example.items()])
    return "\n".join([f"{indent}.. tabs::", f"{indent}    .. code-tab:: xml", "",
                      f'{indent}        <integrator type="{options_cls.PLUGIN}">', *properties,
                      f"{indent}        </integrator>", "", f"{indent}    .. code-tab:: python", "",
                      f"{indent}        {python}", ""])


def document_parameters(options_cls: type[PluginOptions]):
    """Class decorator: put the parameter rows of ``options_cls`` right after the
    ``.. pluginparameters::`` line of the class docstring, and its usage example
    (:func:`usage_example`) at the end."""
    def decorate(cls):
        lines = cls.__doc__.rstrip().split("\n")
        at = next(i for i, line in enumerate(lines) if line.strip() == ".. pluginparameters::")
        indent = lines[at][:len(lines[at]) - len(lines[at].lstrip())]
        lines[at + 1:at + 1] = ["", parameter_table(options_cls, indent)]
        cls.__doc__ = "\n".join(lines + ["", usage_example(options_cls, indent)])
        return cls
    return decorate
