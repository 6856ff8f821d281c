"""The comparison report, typed: what ``report.json`` holds, how it is written and read.

``compare`` measures into these dataclasses (the statistics themselves are those of
:mod:`.metrics`) and writes them with :func:`serialise`; everything that reads a report (the
verdict, the HTML page, the CLI summary, the sweep aggregate, ``scripts/results_table.py``)
reads these types back through :func:`load_report`. The two sit side by side so that the
file and the types cannot drift apart, and the loader is the one place that knows older
formats:

- a pass entry with its MSE statistics at its own level instead of under ``error`` (reports
  from before the expected error);
- ``bias_ok``, a bool, instead of the ``bias`` test;
- ``tail_worse_than_baseline`` as a bool instead of the list of the worse tail statistics;
- a per-material ``variance_ratio`` (now ``error_ratio``: the breakdown ranks by squared error);
- a verdict row without ``family`` (from before the multi-bounce family: direct lighting).

JSON has no NaN, so a non-finite float is written as null (every one has a note in the report
saying where it came from). Reading, null is NaN in a field typed ``float`` and None in one
typed ``... | None`` (not measured, or no value, e.g. a ratio against a missing baseline). A
key the file lacks (an older report, or a hand-written one in a test) reads as if it were
null: NaN for a float, None for anything else, that is "unknown". Keys the types do not have
(a newer report's) are ignored.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import os
import types
import typing

import numpy as np

from . import DEFAULT_CACHE_DIR
from .methods import DIRECT
from .metrics import BiasTest, ErrorStats, TailStats


# Settings -----------------------------------------------------------------------------------

@dataclasses.dataclass
class CompareSettings:
    """Settings of one ``compare`` run (the CLI options)."""

    out: str = "report"
    res: int = 256
    """Image width; the default job's (``cli.COMPARE_RES``, see its comment there)."""
    spp: int = 8
    passes: int = 32
    ref_spp: int = 1024
    samplers: tuple[str, ...] = ("independent",)
    methods: tuple[str, ...] | None = None
    envmap: str | None = None
    max_depth: int = 2
    seed: int = 0
    convergence_max_spp: int | None = None  # None: 4 x spp; 0 disables the sweep
    cache_dir: str = DEFAULT_CACHE_DIR
    progress: bool = True
    freeze: bool = True  # passes replay a dr.freeze recording (report/rendering.py)


# One method ---------------------------------------------------------------------------------

@dataclasses.dataclass
class PassResult:
    """K passes of one method at one sample count (equal samples or equal time).

    :param time_s: median wall time of a warm pass (s); ``times_s`` every pass's.
    :param efficiency: 1 / (expected MSE x ``time_s``).
    :param files: report-relative paths of the first pass (``first_pass`` EXR, ``first_pass_png``)
        and of the mean of all passes (``mean`` EXR); every pass enters the statistics, only these
        are kept as images.
    :param tail_worse_than_baseline: the tail statistics worse than the family baseline's
        (``direct`` or ``path``) at the same kind of comparison (:func:`.metrics.tail_worse`).
    :param budget_method, time_budget_s: the method whose time per pass set the equal-time
        budget, and that budget (s).
    """

    spp: int
    time_s: float
    times_s: list[float]
    efficiency: float
    error: ErrorStats
    tail: TailStats
    bias: BiasTest
    seeds: list[int]
    files: dict[str, str] = dataclasses.field(default_factory=dict)
    tail_worse_than_baseline: list[str] = dataclasses.field(default_factory=list)
    mse_ratio_vs_baseline: float | None = None
    efficiency_ratio_vs_baseline: float | None = None
    budget_method: str | None = None
    time_budget_s: float | None = None


@dataclasses.dataclass
class ConvergencePoint:
    """One render of the convergence sweep; ``file`` its EXR (report-relative)."""

    spp: int
    time_s: float
    mse: float
    rel_mse: float
    file: str | None = None


@dataclasses.dataclass
class MethodResult:
    """One method of one scene and sampler.

    :param integrator: its ``mi.load_dict`` description (:attr:`.methods.Method.integrator`).
    :param compile_time_s: the first render's time over a warm pass's (s), after the set-up.
    :param setup_time_s: the plugin's set-up before its first pass (per-scene state and
        plan, s); 0 for Mitsuba's integrators; None in reports from before it was timed.
    :param equal_time: None until the equal-time phase measured it.
    :param oracle: a reference row (:attr:`.methods.Method.oracle`), not a contender.
    :param strategy_choice: what ``strategy`` ``auto`` chose before the first pass
        (:meth:`~mitsuba_shsampling.integrators.chooser.StrategyChoice.as_dict`), for the
        project's integrators; None otherwise.
    :param frozen: its timed passes replayed a ``dr.freeze`` recording (False: recording
        failed and they were traced; None: freezing off, or a report from before it).
    """

    label: str
    family: str
    rays_per_sample: int
    integrator: dict
    scene_params: dict
    compile_time_s: float | None
    equal_spp: PassResult
    equal_time: PassResult | None = None
    convergence: list[ConvergencePoint] = dataclasses.field(default_factory=list)
    oracle: bool = False
    strategy_choice: dict | None = None
    frozen: bool | None = None
    setup_time_s: float | None = None


# One run (scene x sampler) and one scene --------------------------------------------------------

@dataclasses.dataclass
class MaterialEntry:
    """One material's row of the per-material breakdown (:mod:`.materials`).

    :param name: the BSDF's id in the scene, or the ids of the shapes that use it.
    :param plugin: Mitsuba's class name of the BSDF (``RoughConductor``, ``BumpMap``, ...).
    :param pixel_share: fraction of the image's pixels whose centre sees it.
    :param error_ratio: method -> {"equal_spp": r, "equal_time": r}: the method's expected
        squared error summed over these pixels, over the best Mitsuba strategy's.
    :param best_mitsuba: {"equal_spp": name, "equal_time": name} of that strategy.
    :param error_ratio_interval: method -> {"equal_spp": [low, high], "equal_time": ...}: the
        paired bootstrap interval of each error ratio (None in reports from before it).
    :param error_share: method -> share of the method's equal-sample image error on these pixels.
    :param strategy: method -> {"strategy": name, "predicted_gain": variance of the material's
        best environment strategy over the chosen one's}, for methods that chose per material.
    """

    name: str
    plugin: str
    pixel_share: float
    error_ratio: dict[str, dict[str, float | None]]
    best_mitsuba: dict[str, str | None]
    error_share: dict[str, float | None]
    strategy: dict[str, dict] = dataclasses.field(default_factory=dict)
    error_ratio_interval: dict[str, dict[str, list[float]]] | None = None


@dataclasses.dataclass
class ErrorMaps:
    """The false-colour per-pixel maps of a run (equal samples).

    :param files: method -> {"variance": png, "rel_error": png} (report-relative; the EXR of
        each beside it).
    :param scale: kind -> [low, high], the log colour scale every method's map of that kind shares.

    In the file the scales are one more entry of the method mapping, under :data:`SCALE_KEY`.
    """

    files: dict[str, dict[str, str]]
    scale: dict[str, list[float]]

    SCALE_KEY: typing.ClassVar[str] = "_scale"

    def to_json(self) -> dict:
        return {**self.files, self.SCALE_KEY: self.scale}

    @classmethod
    def from_json(cls, data: dict) -> ErrorMaps:
        return cls(files={k: v for k, v in data.items() if k != cls.SCALE_KEY},
                   scale=_decode(dict[str, list[float]], data.get(cls.SCALE_KEY)) or {})


@dataclasses.dataclass
class RunResult:
    """One scene with one sampler.

    :param methods: method name -> result, in report order.
    :param crop: [x, y, size] of the zoomed crop shown for every method (None without methods).
    :param materials: family -> the per-material rows.
    :param sampler_plugin, film_size: what actually rendered, read back from the sensor.
    """

    sampler: str
    methods: dict[str, MethodResult]
    maps: ErrorMaps
    crop: list[int] | None
    convergence_plot: str | None
    materials: dict[str, list[MaterialEntry]]
    sampler_plugin: str | None
    film_size: list[int] | None


@dataclasses.dataclass
class ReferenceEntry:
    """The ``path`` reference of one family of a scene.

    :param cache_file: its entry in the reference cache; ``cached``: reused from there.
    :param file, png: its EXR and PNG in the report (report-relative).
    :param mean_variance: the reference's own noise, its per-pixel variance averaged over the
        image (NaN: no finite pixel).
    :param integrator: what rendered it, as a user reads it (``path, max_depth 2``).
    """

    spp: int
    chunks: int
    cache_file: str
    cached: bool
    render_time_s: float
    file: str
    png: str
    mean_variance: float
    integrator: str


@dataclasses.dataclass
class EnvmapEntry:
    """The environment map's file name (``--envmap``, else the scene's) and its thumbnail."""

    name: str
    png: str


@dataclasses.dataclass
class SamplerFigure:
    """Warped sample points over their target (an illustration of the samplers)."""

    caption: str
    png: str


@dataclasses.dataclass
class SceneResult:
    """One scene: its references per family and one run per sampler.

    :param scene: its name in the report (:func:`.compare.scene_labels`), also its folder.
    :param exposure: of every PNG of the scene (:func:`.compare.exposure`).
    """

    scene: str
    path: str
    has_envmap: bool
    envmap: EnvmapEntry | None
    notes: list[str]
    exposure: float
    references: dict[str, ReferenceEntry]
    runs: list[RunResult]
    sampler_figures: list[SamplerFigure]


# The verdict --------------------------------------------------------------------------------

@dataclasses.dataclass
class VerdictCell:
    """One comparison kind of one verdict row (:mod:`.verdict`).

    ``ratio`` is ``numerator``'s quantity over ``denominator``'s: MSE at equal samples (< 1:
    the numerator wins), efficiency at equal time (> 1: the numerator wins);
    [``low``, ``high``] its bootstrap interval. All three are NaN (``n/a`` in the report) when
    the ratio has no finite value: a zero MSE (an all-black environment renders every pixel
    exactly) or a non-finite one (every pixel of a pass non-finite).
    ``winner`` is first of all the contenders by point estimate; [``winner_low``,
    ``winner_high``] the interval of its ratio to the ``runner_up``'s (None and NaN in reports
    from before them, and with a single contender).
    """

    quantity: str
    winner: str
    winner_is_project: bool
    numerator: str
    denominator: str
    ratio: float
    low: float
    high: float
    runner_up: str | None = None
    winner_low: float = math.nan
    winner_high: float = math.nan

    @property
    def decided(self) -> bool:
        """The interval excludes 1: the data decide between numerator and denominator."""
        return math.isfinite(self.low) and math.isfinite(self.high) and not (self.low <= 1.0 <= self.high)

    @property
    def winner_decided(self) -> bool:
        """The interval of the winner over the runner-up excludes 1: it is first of all."""
        finite = math.isfinite(self.winner_low) and math.isfinite(self.winner_high)
        return finite and not (self.winner_low <= 1.0 <= self.winner_high)

    @property
    def numerator_better(self) -> bool:
        """The interval says the numerator is the better of the two (below 1 for an MSE ratio,
        above 1 for an efficiency ratio)."""
        return self.decided and (self.high < 1 if self.quantity == "MSE" else self.low > 1)


@dataclasses.dataclass
class VerdictOther:
    """Another project row of a verdict row: its method, plugin configuration and cells."""

    method: str
    configuration: str
    equal_spp: VerdictCell
    equal_time: VerdictCell
    time_normalised: VerdictCell | None = None

    def contests(self) -> list[tuple[str, VerdictCell]]:
        """(title, cell) of each kind the row holds, in the order reports show them."""
        return _contests(self)


@dataclasses.dataclass
class VerdictRow:
    """One scene, sampler and family. ``configuration`` is how a user writes the first line's
    project method (None when no project method ran); ``others`` the project's other rows."""

    scene: str
    sampler: str
    family: str
    equal_spp: VerdictCell
    equal_time: VerdictCell
    caveats: list[str]
    configuration: str | None = None
    others: list[VerdictOther] = dataclasses.field(default_factory=list)
    #: Efficiency of the equal-sample passes (:mod:`.verdict`); None in reports from before it.
    time_normalised: VerdictCell | None = None

    def contests(self) -> list[tuple[str, VerdictCell]]:
        """(title, cell) of each kind the row holds, in the order reports show them."""
        return _contests(self)


#: The titles of the verdict's kinds (:mod:`.verdict`), in the order reports show them.
CONTEST_TITLES = {"equal_spp": "equal samples", "equal_time": "equal time",
                  "time_normalised": "equal time, from the equal-sample passes"}


def _contests(row) -> list[tuple[str, VerdictCell]]:
    return [(title, getattr(row, kind)) for kind, title in CONTEST_TITLES.items()
            if getattr(row, kind) is not None]


# The report ---------------------------------------------------------------------------------

@dataclasses.dataclass
class Report:
    """A whole ``compare`` run, as ``report.json`` holds it.

    :param machine, variant, versions: where it ran (:func:`.compare.environment_info`).
    :param verdict: one row per scene x sampler x family (:func:`.verdict.verdict`).
    """

    machine: dict
    variant: str
    versions: dict
    settings: CompareSettings
    scenes: list[SceneResult]
    total_time_s: float
    verdict: list[VerdictRow] = dataclasses.field(default_factory=list)


# Writing ------------------------------------------------------------------------------------

def serialise(value):
    """JSON form of a report or any part of it: dataclasses as objects (in field order), tuples
    as lists, NumPy scalars as Python ones, non-finite floats as None.

    Every NaN has a note in the report saying where it came from (:mod:`.metrics`), so the
    JSON stays strict (``allow_nan=False``) and no ``nan`` is printed silently.
    """
    if hasattr(value, "to_json"):
        return serialise(value.to_json())
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: serialise(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, dict):
        return {k: serialise(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [serialise(v) for v in value]
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.bool_):
        return bool(value)
    return value


def write_report(path: str, report: Report) -> None:
    """Write ``report`` as strict JSON to ``path``."""
    with open(path, "w") as f:
        json.dump(serialise(report), f, indent=2, allow_nan=False)


# Reading ------------------------------------------------------------------------------------

#: The tail statistics of a report that recorded only whether any was worse.
UNNAMED_TAIL = "a tail statistic worse than the baseline's (an older report: which one is not recorded)"


def _upgrade_pass(data: dict) -> dict:
    if not isinstance(data.get("error"), dict):
        data = {**data, "error": data}
    data = dict(data)
    if isinstance(data.get("bias_ok"), bool) and not isinstance(data.get("bias"), dict):
        data["bias"] = {"flagged": not data["bias_ok"]}
    if isinstance(data.get("tail_worse_than_baseline"), bool):
        data["tail_worse_than_baseline"] = [UNNAMED_TAIL] if data["tail_worse_than_baseline"] else []
    return data


def _upgrade_material(data: dict) -> dict:
    if "error_ratio" not in data and "variance_ratio" in data:
        return {**data, "error_ratio": data["variance_ratio"]}
    return data


def _upgrade_verdict_row(data: dict) -> dict:
    return data if "family" in data else {**data, "family": DIRECT}


#: Older formats, upgraded to the current one before a dataclass is read (module docstring).
_UPGRADES = {PassResult: _upgrade_pass, MaterialEntry: _upgrade_material, VerdictRow: _upgrade_verdict_row}


@functools.cache
def _field_types(cls) -> dict[str, typing.Any]:
    hints = typing.get_type_hints(cls)
    return {f.name: hints[f.name] for f in dataclasses.fields(cls) if f.init}


def _decode(tp, value):
    """``value`` (parsed JSON, None for a missing key) as type ``tp`` (module docstring)."""
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        (inner,) = [a for a in args if a is not type(None)]
        return None if value is None else _decode(inner, value)
    if tp is float:
        return float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else math.nan
    if tp in (int, str, bool):
        return value if isinstance(value, tp) else None
    if hasattr(tp, "from_json"):
        return tp.from_json(value) if isinstance(value, dict) else None
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            return None
        value = _UPGRADES.get(tp, lambda d: d)(value)
        return tp(**{name: _decode(ftype, value.get(name)) for name, ftype in _field_types(tp).items()})
    if origin in (list, tuple):
        if not isinstance(value, list):
            return None
        items = [_decode(args[0], v) for v in value]
        return items if origin is list else tuple(items)
    if origin is dict:
        return {k: _decode(args[1], v) for k, v in value.items()} if isinstance(value, dict) else None
    return value  # a free-form dict (machine, versions, integrator): as written


def load_report(source: str | os.PathLike | dict | Report) -> Report:
    """The typed report of a ``report.json`` file, of its parsed dict, or ``source`` itself if it
    is one already; older formats are upgraded and missing keys read as unknown (module docstring)."""
    if isinstance(source, Report):
        return source
    if not isinstance(source, dict):
        with open(source) as f:
            source = json.load(f)
    return _decode(Report, source)
