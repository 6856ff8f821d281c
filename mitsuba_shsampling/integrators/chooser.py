"""The plan: each material's environment strategy, chosen before the first pass (``strategy`` ``auto``).

What is minimised is the image's expected error at equal time: the per-pixel
variance summed over the film, times the time of a pass,

    J = (V_rest + sum_m V_m(s_m)) * (P_env + sum_m a_m * dP(s_m)),

over one strategy s_m per material m (a BSDF instance with a product lobe),
with

- ``V_m(s)``: the variance that the environment estimator of strategy ``s``
  adds to the film, summed over the shading points of material ``m``, by
  quadrature at the camera's first hits, visibility included (:mod:`.quadrature`).
- ``V_rest``: the same for the smooth materials without a choice, plus ``S``, the
  variance that no environment strategy changes (antialiasing and texture edges,
  other emitters, Dirac paths, a path tracer's deeper vertices): what the pilot
  images have beyond the quadrature's prediction (:mod:`.pilots`). The product
  pilots' images also scale each product strategy's predictions to what they
  measured, and on each material's own pixels measure how much variance the
  strategy removes there, which is weighed against the quadrature's figure
  (:mod:`.material_pilots`: the quadrature can miss a highlight that a few pixels
  hold). Pilot seeds are fixed, and what the pilots give is rounded to
  :data:`SIGNIFICANT_DIGITS`: the same scene gives the same figures in every process.
- ``P_env`` and ``dP(s)``: the pass time with every material on the environment
  strategy, and the extra time per unit film share of material ``m`` on strategy
  ``s``, from the cost model (:mod:`.costs`): with ``plan`` ``estimate`` (the
  default) this machine's calibration or the shipped model, so that no clock
  decides the plan; with ``plan`` ``measure`` timed pilot passes in the scene,
  where the close rivals of the best assignment are also timed as wholes
  (:func:`confirm_by_timing`).
- ``a_m``: the share of the film's camera samples that see material ``m``.

J is minimised by coordinate descent over the materials (:func:`minimise_error_at_equal_time`).
When no product strategy beats the lean kernel (every material on one of
Mitsuba's own strategies, no product code traced) by :data:`REQUIRED_GAIN`, the
lean kernel runs. What is predicted is direct lighting at the camera's first
hits; in a path tracer the deeper vertices share the choice.

A plan can be forced per material (``strategy`` ``"copper=product,ground=environment"``),
saved and loaded (``plan_file``, :mod:`.plan_file`), and is logged once per scene state
through Mitsuba's logger (Info).
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Callable

import drjit as dr
import mitsuba as mi
import numpy as np

from ..timing import kernels_compiled
from .costs import CostModel, cost_model
from .emitter_selection import SELECTION_REQUIRED_GAIN, price_emitter_selection, selection_summary
from .pilots import (FILM_PILOT_PIXELS, LEAN, PILOT_IMAGES, PILOT_LANES, Candidate, Pilots, calibrate,
                     camera_sample_pass, cosine_pilot, film_variance_factor, frozen_pilots, measure_pass_costs,
                     paired_errors, pilot_pixels)
from .material_pilots import lane_materials, material_differences, refine
from .pilot_frames import PILOT_FRAMES, PILOT_FRAMES_SEED, PixelDensity
from .quadrature import PRODUCT_ONLY_SHARED, camera_frames_at, frame_variances, grid_positions
from . import plan_file
from .strategy import CARRYING_MITSUBA_STRATEGIES, ESTIMATE, MEASURE, MITSUBA_STRATEGIES, Strategy, strategy_named

REQUIRED_GAIN = 1.05
"""A product strategy must be predicted to beat the lean kernel by this factor at
equal time. The lean kernel is, per material, exactly one of Mitsuba's own
strategies at Mitsuba's cost; the margin covers the scatter of the cost model's pass
times. It was 1.15 until the best product plan of every lean plan was measured against
it (``product_candidate``; docs/MEASUREMENTS.md, "The product's required gain"): over the
realistic cells of ``sh_direct`` and ``sh_path`` and the sphere cells near the bar, the six
plans predicted between 1.05 and 1.15 gained 0.90-1.24x at equal time when forced (five of
six above 1.1), while the two plans it over-predicted most (the sunsky map's small sun:
predicted 1.20 and 1.28, measured 0.82 and 1.02) were above 1.15, out of this margin's reach."""

CONFIRM_MARGIN = 1.15
"""``plan`` ``measure``: assignments predicted within this factor of the best one's
error at equal time are timed as wholes before the choice (:func:`confirm_by_timing`):
the per-material times are differences of pilot times, and where a material's share of
the pass is small their noise can flip a near tie."""

CONFIRM_RIVALS = 3
"""At most this many rivals (one material's strategy changed each) are timed."""

SIGNIFICANT_DIGITS = 3
"""What the pilot images give (the shared variance, the calibration factors) is rounded
to this many digits: the film's atomic splats leave differences of ~1e-7 between
processes, and a plan must not follow them."""

FRAME_FIGURE_DIGITS = 6
"""The figures summed with the pilots' frames (:func:`with_pilot_frames`) are rounded to this
many digits: every frame's weight carries the pilots' per-pixel variances through the
density's normalisation, and with them the last bits of the films' atomic splats (figures
that differed by up to 2e-11 between processes). Six digits keep what the quadrature says
and drop that."""


@dataclasses.dataclass
class MaterialChoice:
    """The choice for one material."""

    name: str
    """The BSDF's id in the scene."""
    strategy: Strategy
    share: float
    """Share of the film's camera samples that see it."""
    variance: dict
    """Strategy -> predicted variance it adds to the film (squared error per colour channel
    and camera sample, averaged over the channels and the film; calibrated by the pilots
    where they ran)."""
    predicted_gain: float
    """Predicted variance of the material's best environment strategy over that of the
    chosen one, at equal samples (1 where an environment strategy is chosen)."""
    forced: bool = False
    """The user set this material's strategy (``strategy`` ``"name=..."``)."""


@dataclasses.dataclass
class StrategyChoice:
    """The plan: what :func:`choose_strategies` chose (or a plan file held), for reports."""

    materials: list
    pass_time: dict
    """``plan`` ``measure``: pilot -> pass time (s), each strategy with every material
    that can run it on it, and :data:`~.pilots.LEAN` (the kernel without product code).
    Empty with ``plan`` ``estimate``."""
    predicted_gain: float
    """Predicted equal-time efficiency of the choice over the lean kernel (every
    material on its best environment strategy, no product code: Mitsuba's
    ``direct`` with or without emitter samples only, per material): image
    variance ratio x pass-time ratio; 1 when lean."""
    lean: bool
    """No material runs a product strategy, and the product's code is not traced."""
    seconds: float
    """Time the choice took (frames, quadrature, pilots)."""
    shared_variance: float = 0.0
    """``S``: the film's variance that no environment strategy changes (quadrature units:
    squared error per colour channel and camera sample, averaged over the channels and
    the film), from the pilot images."""
    pilot_variance: dict = dataclasses.field(default_factory=dict)
    """Pilot -> (predicted, measured) film variance of its passes (quadrature units): how well
    the quadrature, before calibration and with ``S``, matches the pilot images (the
    environment pilots by construction)."""
    pilots: "Pilots | None" = None
    """What the pilots measured, reused when the scene's parameters change."""
    cosine_tables: list = dataclasses.field(default_factory=list)
    """Materials with a cosine lobe whose product is sampled from the cosine tables (the
    others with one walk their SH lobe: :func:`choose_cosine_sampling`)."""
    bsdf_shares: list = dataclasses.field(default_factory=list)
    """Materials whose ``product_only`` gives the BSDF its share (``bsdf_defensive_share``:
    where the quadrature predicts less variance with it, :func:`predict`)."""
    mode: str = ESTIMATE
    """How the plan was made: ``estimate`` (the cost model), ``measure`` (timed pilots in
    the scene), ``file`` (loaded from ``plan_file``) or ``kept`` (made by an earlier process
    for the same scene content, options and cost model, and read from the cache folder)."""
    costs: dict = dataclasses.field(default_factory=dict)
    """The cost model the plan was weighed with (:meth:`CostModel.as_dict`)."""
    setup_seconds: float = 0.0
    """Set-up before the first pass: the per-scene state's build and the plan."""
    kernels_compiled: int = 0
    """Kernels the set-up (the state's build and the plan) compiled because Dr.Jit's kernel cache
    did not hold them: on a machine's first render, or with a map of a resolution or materials
    it has not rendered, most of the set-up (:func:`~mitsuba_shsampling.timing.kernels_compiled`)."""
    confirmation_time: dict = dataclasses.field(default_factory=dict)
    """``plan`` ``measure``, where :func:`confirm_by_timing` ran: ``confirm 0`` (the model's
    pick), ``confirm 1`` ... (its close rivals) -> pass time (s) of each, timed as a whole."""
    gradient_plan: dict = dataclasses.field(default_factory=dict)
    """``sh_prb``'s plan for the gradients (:mod:`.gradient_plan`): the candidate kept and each
    candidate's score (relative gradient variance x predicted pass time); empty where none ran."""
    emitter_selection: dict = dataclasses.field(default_factory=dict)
    """``sh_direct``'s ``emitter_selection`` ``auto`` in a scene with other emitters: the
    design chosen and what it was weighed with (:class:`~.emitter_selection.SelectionPrice`
    as a dict); empty elsewhere."""
    product_candidate: dict = dataclasses.field(default_factory=dict)
    """The best assignment with the product allowed, where it runs a product strategy, chosen
    or not: its ``predicted_gain`` at equal time over the lean kernel, the ``required_gain`` it
    was held to (:data:`REQUIRED_GAIN`) and its ``strategies`` (material name -> label), so that
    a lean plan says by how much the product missed; empty where that assignment has no product
    strategy (or no material can run one)."""

    def as_dict(self) -> dict:
        return {"predicted_gain": self.predicted_gain, "lean": self.lean, "seconds": self.seconds,
                "mode": self.mode, "setup_seconds": self.setup_seconds, "kernels_compiled": self.kernels_compiled,
                "costs": dict(self.costs),
                "cosine_tables": list(self.cosine_tables), "bsdf_shares": list(self.bsdf_shares),
                "pass_time_s": dict(self.pass_time), "confirmation_time_s": dict(self.confirmation_time),
                "emitter_selection": dict(self.emitter_selection),
                "gradient_plan": dict(self.gradient_plan),
                "product_candidate": dict(self.product_candidate),
                "shared_variance": self.shared_variance,
                "calibration": {s.label: f for s, f in (self.pilots.calibration if self.pilots else {}).items()},
                "pilot_variance": {k: {"predicted": p, "measured": m} for k, (p, m) in self.pilot_variance.items()},
                "materials": [{"name": m.name, "strategy": m.strategy.label, "share": m.share,
                               "predicted_gain": m.predicted_gain, "forced": m.forced,
                               "variance": {s.label: v for s, v in m.variance.items()}}
                              for m in self.materials]}

    def summary(self) -> str:
        return summary_of(self.as_dict())

    def assignment(self) -> dict:
        """Material name -> strategy label: what a plan file keeps."""
        return {m.name: m.strategy.label for m in self.materials}


def compiling_note(kernels: int) -> str:
    """What the plan's Info line (and ``render``'s) adds about the kernels the set-up compiled,
    :attr:`StrategyChoice.kernels_compiled` (nothing where none)."""
    if kernels <= 0:
        return ""
    return (f", compiling {kernels} kernel{'s' if kernels > 1 else ''} new to this machine; Dr.Jit keeps "
            f"{'them' if kernels > 1 else 'it'} for the next time")


def summary_of(choice: dict) -> str:
    """One line from :meth:`StrategyChoice.as_dict` (also as a report stores it). Materials
    are listed by name: their registry order follows Mitsuba's parallel scene loading, and the
    same plan should read the same in every process."""
    shared = set(choice.get("bsdf_shares", []))
    parts = [f"{m['name']}: {m['strategy']}" + (" with the BSDF's share" if m["name"] in shared else "")
             + (" (forced)" if m.get("forced") else "")
             + (f" (variance /{m['predicted_gain']:.2f})" if m["strategy"].startswith("product")
                and not m.get("forced") else "")
             for m in sorted(choice["materials"], key=lambda m: m["name"]) if m["share"] > 0]
    candidate = choice.get("product_candidate", {})
    missed = (f" (the best product plan: predicted x{candidate['predicted_gain']:.2f}, "
              f"{candidate.get('required_gain', REQUIRED_GAIN):.2f} required)" if candidate else "")
    head = ("no product strategy pays: environment strategies only, without product code" + missed
            if choice["lean"] else f"predicted x{choice['predicted_gain']:.2f} at equal time over environment "
                                   "strategies only")
    environment = choice.get("pilot_variance", {}).get(Strategy.ENVIRONMENT.label)
    if environment and environment["measured"] > 0:
        shared = min(choice["shared_variance"] / environment["measured"], 1.0)
        head += f" ({shared:.0%} of the film's variance shared by every strategy)"
    selection = selection_summary(choice.get("emitter_selection", {}))
    gradients = choice.get("gradient_plan", {})
    if gradients:
        head = (f"for the gradients: {gradients['kept']} (variance x time: "
                + ", ".join(f"{name} {score:.3g}" for name, score in gradients["scores"].items()) + "); " + head)
    return f"{head}; " + ", ".join(parts) + (f"; {selection}" if selection else "")


def rounded(x: float, digits: int = SIGNIFICANT_DIGITS) -> float:
    """``x`` to ``digits`` significant digits (0 and non-finite values as they are)."""
    if x == 0 or not math.isfinite(x):
        return x
    return round(x, digits - 1 - int(math.floor(math.log10(abs(x)))))


# ----------------------------------------------------------------- the choice

def predicted_error(choice: dict, variance: dict, rest: float, share: dict, base_time: float,
                    extra_time: dict) -> float:
    """(rest + sum V) x (base + sum share x extra) of one assignment (see
    :func:`minimise_error_at_equal_time` for the arguments)."""
    v = rest + sum(variance[m][s] for m, s in choice.items())
    t = base_time + sum(share[m] * extra_time[m][s] for m, s in choice.items())
    return v * t


def confirm_by_timing(best: dict, variance: dict, rest: float, share: dict, base_time: float,
                      extra_time: dict, time_assignments: Callable[[dict], dict]) -> dict:
    """The assignment of least error at equal time among ``best`` and its close rivals, with
    each one's pass time measured as a whole.

    Rivals change one material's strategy; those predicted within :data:`CONFIRM_MARGIN`
    of ``best`` (at most :data:`CONFIRM_RIVALS`, the closest) are timed together with it by
    ``time_assignments(name -> assignment)`` (returning name -> pass time), and the error
    is their variance (the model's) times that time. Without a close rival nothing runs."""
    limit = CONFIRM_MARGIN * predicted_error(best, variance, rest, share, base_time, extra_time)
    rivals = []
    for m, chosen in best.items():
        for s in variance[m]:
            if s == chosen or s not in extra_time[m] or not np.isfinite(variance[m][s]):
                continue
            rival = {**best, m: s}
            error = predicted_error(rival, variance, rest, share, base_time, extra_time)
            if error <= limit:
                rivals.append((error, rival))
    if not rivals:
        return best
    rivals = [rival for _, rival in sorted(rivals, key=lambda r: r[0])[:CONFIRM_RIVALS]]
    assignments = {f"confirm {i}": a for i, a in enumerate([best] + rivals)}
    times = time_assignments(assignments)
    errors = {name: (rest + sum(variance[m][s] for m, s in a.items())) * times[name]
              for name, a in assignments.items()}
    return assignments[min(errors, key=errors.get)]


def minimise_error_at_equal_time(variance: dict, rest: float, share: dict, base_time: float,
                                 extra_time: dict, sweeps: int = 8) -> dict:
    """Strategy per material minimising (rest + sum V) x (base + sum share x extra).

    ``variance[m][s]``: material m's variance on strategy s (NaN or missing: not
    possible); ``share[m]``: its share of the film; ``extra_time[m][s]``: extra pass
    time per unit share of material m on strategy s (0 for the environment strategy;
    missing: not possible). Coordinate descent from every material on the environment
    strategy (a material that cannot run it, one forced to another: on its first)."""
    choice = {m: Strategy.ENVIRONMENT if Strategy.ENVIRONMENT in row else next(iter(row))
              for m, row in variance.items()}

    def cost(choice):
        return predicted_error(choice, variance, rest, share, base_time, extra_time)

    for _ in range(sweeps):
        changed = False
        for m in variance:
            options = [s for s in variance[m] if s in extra_time[m] and np.isfinite(variance[m][s])]
            best = min(options, key=lambda s: (cost({**choice, m: s}), s != choice[m]))
            if best != choice[m]:
                choice[m], changed = best, True
        if not changed:
            break
    return choice, cost(choice)


def choose_cosine_sampling(env, tabled: np.ndarray, walked: np.ndarray, keys: np.ndarray) -> np.ndarray:
    """Per material with a cosine lobe, sample its product from the cosine tables or by its SH
    walk, whichever the quadrature predicts the less variance for (its best product strategy;
    the tables on a tie: they cost less). Sets :meth:`SceneLobes.sample_from_tables` and
    returns the frames' variances (``tabled`` and ``walked``: :func:`frame_variances` with and
    without the tables) with each material's rows from its choice.

    Visibility decides it: without it the tables follow max(n . w, 0) x L exactly and win
    everywhere; inside a room, the SH walk's looser distribution can reach the openings more
    often than the tables' close one (docs/MEASUREMENTS.md, "Cosine tables")."""
    products = [int(s) for s in (Strategy.PRODUCT, Strategy.PRODUCT_ONLY)]
    chosen, out = set(), tabled.copy()
    for key in env.lobes.cosine_ids:
        rows = keys == key
        with np.errstate(invalid="ignore"):
            best = [np.nanmin(np.sum(v[rows][:, products], axis=0)) if rows.any() else 0.0 for v in (tabled, walked)]
        if not best[1] < best[0]:
            chosen.add(key)
        else:
            out[rows] = walked[rows]
    env.lobes.sample_from_tables(chosen)
    return out




# ----------------------------------------------------------------- the plan, step by step

@dataclasses.dataclass
class Predictions:
    """The quadrature's figures per material (registry id), in its units (squared error
    per colour channel and camera sample, averaged over the channels and the film)."""

    materials: list
    allowed: dict
    """Id -> the strategies it may run (a forced material: its own alone)."""
    variance: dict
    """Id -> strategy -> variance it adds to the film."""
    share: dict
    """Id -> share of the film's camera samples that see it."""
    rest: float
    """The variance of the smooth materials outside the table (environment strategy)."""
    smooth_share: float = 1.0
    """Share of the film's camera samples that hit a smooth BSDF (they sample emitters)."""
    rows: "FrameRows | None" = None
    """The shading points the figures were summed from."""
    bsdf_shared: set = dataclasses.field(default_factory=set)
    """The materials whose ``product_only`` gives the BSDF its share."""

    def best_environment_strategies(self, variance: dict) -> dict:
        """Each material's least-variance strategy among Mitsuba's own (the lean kernel's;
        a material forced to a product strategy keeps it)."""
        return {k: min((s for s in self.allowed[k] if s in MITSUBA_STRATEGIES), key=lambda s: (variance[k][s], s),
                       default=None) or self.allowed[k][0] for k in self.materials}


@dataclasses.dataclass
class FrameRows:
    """The quadrature's shading points, from which a :class:`Predictions`' figures are summed."""

    variances: np.ndarray
    """(points, columns): :func:`~.quadrature.frame_variances` of each point (each cosine
    lobe's by the sampling its material was given)."""
    keys: np.ndarray
    """Registry id of each point's BSDF."""
    x: np.ndarray
    y: np.ndarray
    """Each point's film position."""
    grid_positions: int
    """The grid's film positions, those that hit no smooth BSDF included."""
    grid_rows: int
    """How many of the points (the first ones) are the grid's; the rest were drawn where the
    pilots' pixels are noisiest (:func:`with_pilot_frames`)."""
    dirac_weight: np.ndarray
    """Each point's weight on the film beside its film position's: the square of the Dirac
    bounces' throughput before it (:class:`~.quadrature.CameraFrames`; 1 at a first hit)."""


def predict(env, sensor: mi.Sensor, n_e: int, n_b: int, forced: dict) -> Predictions:
    """Quadrature at the camera's first hits (:mod:`.quadrature`), per material of
    ``env``'s strategy table; ``forced``: registry id -> the strategy the user set. Decides
    which cosine lobes sample from their tables and which materials' ``product_only`` gives
    the BSDF its share (``env`` is set so)."""
    x, y = grid_positions(sensor)
    si, bsdf, kept, dirac_weight = camera_frames_at(env.scene, sensor, x, y, env.frame_dirac_bounces)
    variances = frame_variances(env, si, bsdf, n_e, n_b)
    keys = frame_keys(si, bsdf)
    cosine_frames = np.flatnonzero(np.isin(keys, list(env.lobes.cosine_ids))) if env.cosine_tables else []
    if len(cosine_frames):
        # The cosine lobes' SH walks at their own frames (as they were in the call over all):
        # the same kernel with no lobe read from the tables (device data), not another traced
        # without the tables' code (0.8 s of a cold plan's compiling).
        tabled = set(env.lobes.tabled_ids)
        env.lobes.sample_from_tables(set())
        try:
            walked = variances.copy()
            walked[cosine_frames] = frame_variances(env, si, bsdf, n_e, n_b, frames=cosine_frames)
        finally:
            env.lobes.sample_from_tables(tabled)
        variances = choose_cosine_sampling(env, variances, walked, keys)
    rows = FrameRows(variances, keys, x[kept], y[kept], len(x), len(keys), dirac_weight)
    p = summed_predictions(env, rows, dirac_weight / len(x), forced, None)
    env.share_bsdf(p.bsdf_shared)
    return p


def frame_keys(si: mi.SurfaceInteraction3f, bsdf: mi.BSDFPtr) -> np.ndarray:
    """The registry id of each shading point's BSDF."""
    if not dr.width(si):
        return np.zeros(0, dtype=np.uint32)
    return np.broadcast_to(dr.reinterpret_array(mi.UInt32, bsdf).numpy(), (dr.width(si),))


def summed_predictions(env, rows: FrameRows, weights: np.ndarray, forced: dict,
                       bsdf_shared: set | None) -> Predictions:
    """Each material's figures: its points' variances, each times its ``weights`` (a film mean:
    1 / grid positions on the grid alone), summed. ``bsdf_shared``: the materials whose
    ``product_only`` gives the BSDF its share; None decides it (where that is predicted to
    lower the variance)."""
    materials = list(env.strategies.ids)
    allowed = {key: [forced[key]] if key in forced else env.allowed(key) for key in materials}
    variance, share, shared = {}, {}, set()
    for key in materials:
        mine = rows.keys == key
        values, w = rows.variances[mine], weights[mine]
        share[key] = float(np.count_nonzero(mine[:rows.grid_rows])) / rows.grid_positions
        strategies = set(allowed[key]) | set(env.allowed(key))
        variance[key] = {s: float(np.sum(values[:, s] * w)) for s in strategies}
        # product_only gives the BSDF its share where that is predicted to lower the variance
        # (a lobe proxy that misses part of the BSDF), not where the product alone is close to
        # exact: the share's floor, b / (1 - b) of the squared mean, then dominates.
        with_share = float(np.sum(values[:, PRODUCT_ONLY_SHARED] * w))
        if Strategy.PRODUCT_ONLY in strategies and env.bsdf_share > 0 and (
                with_share < variance[key][Strategy.PRODUCT_ONLY] if bsdf_shared is None else key in bsdf_shared):
            variance[key][Strategy.PRODUCT_ONLY] = with_share
            shared.add(key)
    rest_rows = ~np.isin(rows.keys, materials)
    rest = float(np.sum(rows.variances[rest_rows, Strategy.ENVIRONMENT] * weights[rest_rows]))
    smooth = rows.grid_rows / rows.grid_positions if rows.grid_positions else 0.0
    return Predictions(materials, allowed, variance, share, rest, smooth, rows=rows, bsdf_shared=shared)


def with_pilot_frames(env, sensor: mi.Sensor, p: Predictions, pilots: Pilots, n_e: int, n_b: int,
                      forced: dict) -> Predictions:
    """``p`` summed again with :data:`~.pilot_frames.PILOT_FRAMES` more shading points, drawn
    where the pilots' pixels are noisiest (:mod:`.pilot_frames`), every point weighed by the
    balance heuristic over the grid's density and theirs. ``p`` where the pilots kept no
    per-pixel variances. The grid's decisions (cosine tables, the BSDF's share) stand: the
    pilots ran with them. Figures to :data:`FRAME_FIGURE_DIGITS` digits."""
    density = pilot_density(sensor, pilots)
    if density is None or p.rows is None:
        return p
    x, y = density.positions(PILOT_FRAMES)
    si, bsdf, kept, dirac_weight = camera_frames_at(env.scene, sensor, x, y, env.frame_dirac_bounces)
    extra = frame_variances(env, si, bsdf, n_e, n_b, seed=PILOT_FRAMES_SEED)
    grid = p.rows
    rows = FrameRows(np.concatenate([grid.variances, extra]), np.concatenate([grid.keys, frame_keys(si, bsdf)]),
                     np.concatenate([grid.x, x[kept]]), np.concatenate([grid.y, y[kept]]), grid.grid_positions,
                     grid.grid_rows, np.concatenate([grid.dirac_weight, dirac_weight]))
    weights = density.frame_weights(rows.x, rows.y, grid.grid_positions, len(x)) * rows.dirac_weight
    summed = summed_predictions(env, rows, weights, forced, p.bsdf_shared)
    return dataclasses.replace(summed, rest=rounded(summed.rest, FRAME_FIGURE_DIGITS), variance={
        k: {s: rounded(v, FRAME_FIGURE_DIGITS) for s, v in row.items()} for k, row in summed.variance.items()})


def pilot_density(sensor: mi.Sensor, pilots: Pilots) -> PixelDensity | None:
    """The pilots' per-pixel variance, summed over the pilots, as a density over the film
    (None where they kept none)."""
    if not pilots.pixel_variance:
        return None
    total = np.asarray(sum(pilots.pixel_variance.values()).numpy(), dtype=np.float64)  # summed on the device
    size = sensor.film().crop_size()
    lanes = pilot_pixels(sensor, len(total)).numpy()
    return PixelDensity.from_lanes(int(size[0]), int(size[1]), np.asarray(lanes, dtype=np.int64), total)


def pilot_candidates(env, p: Predictions, lean_choice: dict, timed: bool, alone: tuple | None = None) -> dict:
    """Pilot name -> :class:`~.pilots.Candidate` (each material's strategy; the lean kernel).

    Images need the environment strategy (for ``S``) and each product strategy on every
    material that can run it (for its calibration). Timed pilots also run the lean kernel,
    ``environment_only`` and ``bsdf_only`` where the quadrature prefers them for some material, and, where
    cosine lobes and SH lobes could both run a product strategy, that strategy on the
    cosine lobes alone, which tells the tables' cost from the SH walk's. ``alone``: the
    strategies that carry every sample to pilot when timed (default: those of ``lean_choice``)."""
    environment = {k: Strategy.ENVIRONMENT for k in p.materials}
    candidates = {LEAN: Candidate.lean_kernel(p.materials)} if timed else {}
    candidates[Strategy.ENVIRONMENT.label] = Candidate(environment)
    wanted = set(lean_choice.values()) if alone is None else set(alone)
    for strategy in CARRYING_MITSUBA_STRATEGIES:
        if timed and strategy in wanted:
            candidates[strategy.label] = Candidate({**environment, **{k: strategy for k in p.materials
                                                                      if strategy in env.allowed(k)}})
    cosine = {k for k in p.materials if env.samples_from_cosine_table(k)}
    for strategy in (Strategy.PRODUCT, Strategy.PRODUCT_ONLY):
        capable = [k for k in p.materials if strategy in env.allowed(k)]
        if capable:
            candidates[strategy.label] = Candidate({**environment, **{k: strategy for k in capable}})
        if timed and any(k in cosine for k in capable) and any(k not in cosine for k in capable):
            candidates[cosine_pilot(strategy)] = Candidate({**environment,
                                                            **{k: strategy for k in capable if k in cosine}})
    return candidates


def run_pilots(env, sensor: mi.Sensor, candidates: dict, render_pass: Callable, timed: bool,
               film_factor: float | None) -> Pilots:
    """The pilot passes of ``candidates``, at least :data:`~.pilots.PILOT_LANES` camera samples
    each; ``film_factor``: :func:`choose_strategies`'s."""
    spp = pilot_spp(sensor)
    factor = film_variance_factor(sensor.film(), spp) if film_factor is None else film_factor
    if timed:
        return measure_pass_costs(env, candidates, lambda seed: render_pass(spp, seed), spp=spp, film_factor=factor)
    return measure_pass_costs(env, candidates, lambda seed: render_pass(spp, seed), spp=spp, repeats=PILOT_IMAGES,
                              timed=False, film_factor=factor)


def pilot_spp(sensor: mi.Sensor) -> int:
    """Samples per pixel of a pilot pass: at least :data:`~.pilots.PILOT_LANES` camera samples."""
    film = sensor.film().crop_size()
    return max(1, math.ceil(PILOT_LANES / (int(film[0]) * int(film[1]))))


def priced_emitter_selection(env, sensor: mi.Sensor, p: Predictions, pass_time: float, costs: CostModel | None,
                             pilots: Pilots | None, render_pass: Callable) -> dict:
    """``emitter_selection`` ``auto`` where the scene has other emitters: both designs priced
    for the plan as applied (:func:`~.emitter_selection.price_emitter_selection`), the better
    one set; what was weighed, as a dict (empty where there is nothing to price)."""
    if not (env.prices_emitter_selection and env.active and env.has_other_emitters):
        return {}
    lean_seconds = pilots.pass_time.get(LEAN) if costs is None and pilots is not None else None
    model = costs if costs is not None else cost_model("direct")
    return price_emitter_selection(env, render_pass, pilot_spp(sensor), pass_time, model.emitter_sample,
                                   p.smooth_share, SELECTION_REQUIRED_GAIN, rounded, lean_seconds).as_dict()


def calibrated(p: Predictions, pilots: Pilots, candidates: dict):
    """``(variance, rest, shared, fit)``: the predictions scaled to what the pilot images
    measured (:func:`~.pilots.calibrate`, rounded to :data:`SIGNIFICANT_DIGITS`), the
    shared variance ``S`` and, per pilot, (predicted, measured) film variance."""
    model = {name: p.rest + sum(p.variance[k][c.assignment[k]] for k in p.materials)
             for name, c in candidates.items()}
    measured = {name: v / pilots.film_factor for name, v in pilots.image_variance.items() if name in model}
    # Pilots without images (given pass times alone) have no error to weigh by.
    errors = paired_errors(pilots.pixel_variance, pilots.film_factor) if pilots.pixel_variance else None
    if pilots.shared_variance is None:
        calibrate(pilots, measured, model, candidates, p.variance, p.rest, errors)
        pilots.shared_variance = rounded(pilots.shared_variance)
        pilots.calibration = {s: rounded(f) for s, f in pilots.calibration.items()}
    fit = {name: (model[name] + pilots.shared_variance, measured[name]) for name in measured}
    variance = {k: {s: v * pilots.calibration.get(s, 1.0) for s, v in row.items()} for k, row in p.variance.items()}
    variance, shared = refine(variance, pilots.shared_variance, pilots.by_material, p.variance)
    return variance, p.rest * pilots.calibration.get(Strategy.ENVIRONMENT, 1.0), shared, fit


def measured_by_material(env, sensor: mi.Sensor, pilots: Pilots, candidates: dict, p: Predictions) -> dict:
    """What the pilots measured on each material's pixels (:mod:`.material_pilots`), rounded
    to :data:`SIGNIFICANT_DIGITS` as every figure from the pilots is."""
    environment = next((n for n in (Strategy.ENVIRONMENT.label, LEAN) if n in pilots.pixel_variance), None)
    if environment is None:
        return {}
    lanes = dr.width(pilots.pixel_variance[environment])
    by_material = material_differences(pilots, lane_materials(env.scene, sensor, lanes, env.frame_dirac_bounces),
                                       candidates, p.variance, environment)
    return {k: {s: dataclasses.replace(m, difference=rounded(m.difference), error=rounded(m.error),
                                       environment=rounded(m.environment)) for s, m in row.items()}
            for k, row in by_material.items()}


def pilot_shares(env, p: Predictions) -> dict:
    """The film shares that the timed pilots switch (:meth:`CostModel.from_pass_times`)."""
    def share(keys):
        return sum(p.share[k] for k in keys)

    shares = {alone.label: share(k for k in p.materials if alone in env.allowed(k))
              for alone in CARRYING_MITSUBA_STRATEGIES}
    for strategy in (Strategy.PRODUCT, Strategy.PRODUCT_ONLY):
        capable = [k for k in p.materials if strategy in env.allowed(k)]
        tabled = [k for k in capable if env.samples_from_cosine_table(k)]
        shares[strategy.label] = (share(tabled), share(k for k in capable if k not in tabled))
    return shares


def pass_times(model: CostModel, env, materials: list) -> tuple[float, float, dict]:
    """(lean pass, pass with product code, extra[id][strategy] per unit film share), in lean passes."""
    extra = {k: {s: model.extra(s, env.samples_from_cosine_table(k), env.bsdf_shared.of(k)) for s in Strategy}
             for k in materials}
    return 1.0, 1.0 + model.product_code, extra


def apply_choice(env, choice: dict, lean: bool) -> None:
    """Give each material (registry id) its strategy; leave the product's code out of
    the kernel where ``lean``, and the branch of the strategies that carry every sample
    where no material runs one."""
    env.strategies.assign(choice)
    if lean and env.warp is not None:
        env.drop_product()
    if not any(s.carries_all for s in choice.values()):
        env.carry_all = False


def choose_strategies(env, sensor: mi.Sensor, n_e: int, n_b: int, render_pass: Callable[[int, int], object],
                      pilots: Pilots | None = None, costs: CostModel | None = None,
                      forced: dict | None = None, film_factor: float | None = None) -> StrategyChoice:
    """Choose and assign (``env.strategies``) a strategy for every material; when no
    product strategy pays for the time its code costs every lane, drop the
    product altogether (:meth:`ProductEnvironment.drop_product`).

    ``render_pass(spp, seed)`` renders one pass of the integrator as it is configured
    and returns its image. ``costs``: the cost model (``plan`` ``estimate``); None times
    the pilots in the scene (``plan`` ``measure``). ``pilots`` (as an earlier choice
    measured them) skips the pilot passes; pilots without images leave the shared
    variance ``S`` at 0. ``forced``: registry id -> the strategy the user set for it.
    ``film_factor``: what ``render_pass``'s images' pixel variance is per unit variance of a
    camera sample: 1 for camera-sample passes (:func:`~.pilots.camera_sample_pass`); None for
    film passes (:func:`~.pilots.film_variance_factor` of the sensor's film).
    Without a product to choose, pilots run only where the quadrature prefers
    ``environment_only`` for some material.
    """
    start = time.perf_counter()
    forced = forced or {}
    p = predict(env, sensor, n_e, n_b, forced)
    lean_choice = p.best_environment_strategies(p.variance)
    product_possible = any(s.uses_product for k in p.materials for s in p.allowed[k])
    product_forced = any(s.uses_product for s in forced.values())
    alone_wanted = any(s.carries_all for s in lean_choice.values())
    timed = costs is None
    choice, lean, gain, shared, fit, confirmed = lean_choice, not product_forced, 1.0, 0.0, {}, {}
    candidate = {}
    planned_time = 1.0  # in lean passes
    if product_possible or alone_wanted:
        candidates = pilot_candidates(env, p, lean_choice, timed)
        fresh = pilots is None  # (pilots of an earlier choice: the scene's parameters changed)
        if fresh:
            pilots = run_pilots(env, sensor, candidates, render_pass, timed, film_factor)
        p = with_pilot_frames(env, sensor, p, pilots, n_e, n_b, forced)
        if fresh:
            pilots.by_material = measured_by_material(env, sensor, pilots, candidates, p)
        variance, rest, shared, fit = calibrated(p, pilots, candidates)
        if timed:
            costs = CostModel.from_pass_times(pilots.pass_time, pilot_shares(env, p), "measured in the scene")
        lean_time, base, extra = pass_times(costs, env, p.materials)
        # Materials no camera ray sees give no evidence: they keep their lean choice.
        seen = {k: v for k, v in variance.items() if p.share[k] > 0}
        seen_allowed = {k: {s: v[s] for s in p.allowed[k]} for k, v in seen.items()}
        seen_lean = {k: {s: v for s, v in row.items() if not s.uses_product} or row for k, row in seen_allowed.items()}
        lean_seen, _ = minimise_error_at_equal_time(seen_lean, rest + shared, p.share, lean_time, extra)
        lean_choice = {**p.best_environment_strategies(variance), **lean_seen}
        error_lean = predicted_error(lean_choice, variance, rest + shared, p.share,
                                     base if product_forced else lean_time, extra)
        choice = lean_choice
        if product_possible:
            full_choice, error_full = minimise_error_at_equal_time(seen_allowed, rest + shared, p.share, base, extra)
            if timed and fresh:
                full_choice = confirm_by_timing(full_choice, seen_allowed, rest + shared, p.share, base, extra,
                                                confirmation_timer(env, lean_choice, render_pass, pilots.spp, confirmed))
                error_full = predicted_error(full_choice, seen_allowed, rest + shared, p.share, base, extra)
            pays = error_full * REQUIRED_GAIN < error_lean
            if any(s.uses_product for s in full_choice.values()):
                candidate = {"predicted_gain": error_lean / error_full, "required_gain": REQUIRED_GAIN,
                             "strategies": {env.material_name(k): s.label for k, s in full_choice.items()}}
                if pays or product_forced:
                    choice, lean, gain = {**lean_choice, **full_choice}, False, error_lean / error_full
        planned_time = (lean_time if lean else base) + sum(p.share[m] * extra[m][choice[m]] for m in p.materials)
    apply_choice(env, choice, lean)
    selection = priced_emitter_selection(env, sensor, p, planned_time, None if timed else costs, pilots, render_pass)
    return StrategyChoice(
        materials=materials_report(env, p, choice, lean_choice,
                                   variance if product_possible or alone_wanted else p.variance, forced),
        pass_time=dict(pilots.pass_time if pilots else {}), confirmation_time=confirmed, predicted_gain=gain,
        lean=lean,
        seconds=time.perf_counter() - start, shared_variance=shared, pilot_variance=fit, pilots=pilots,
        cosine_tables=sorted(env.material_name(k) for k in env.lobes.tabled_ids) if env.cosine_tables else [],
        bsdf_shares=shared_names(env), mode=MEASURE if timed else ESTIMATE, costs=costs.as_dict() if costs is not None else {},
        emitter_selection=selection, product_candidate=candidate)


def confirmation_timer(env, lean_choice: dict, render_pass: Callable, spp: int, confirmed: dict) -> Callable:
    """``time_assignments`` of :func:`confirm_by_timing`: the rivals timed as wholes (each
    with the lean choice's strategies for the materials it leaves out); their times are
    also reported with the pilots' (``confirmed``)."""
    def time_assignments(assignments):
        whole = {name: Candidate({**lean_choice, **a}) for name, a in assignments.items()}
        times = measure_pass_costs(env, whole, lambda seed: render_pass(spp, seed), spp=spp).pass_time
        confirmed.update(times)
        return times
    return time_assignments


def materials_report(env, p: Predictions, choice: dict, lean_choice: dict, variance: dict,
                     forced: dict) -> list:
    """A :class:`MaterialChoice` per material: its strategy and predicted gain over its lean choice."""
    report = []
    for key in p.materials:
        s, v = choice[key], variance[key]
        reference = v[lean_choice[key]]
        report.append(MaterialChoice(env.material_name(key), s, p.share[key], dict(v),
                                     reference / v[s] if v[s] > 0 else 1.0, key in forced))
    return report


def shared_names(env) -> list:
    """The materials on ``product_only`` that give the BSDF its share (their lobes walked in
    SH), by name; none where the option is 0."""
    if env.bsdf_share <= 0:
        return []
    return sorted(env.material_name(k) for k in env.strategies.ids if env.bsdf_shared.of(k)
                  and env.strategies.of(k) == Strategy.PRODUCT_ONLY and not env.samples_from_cosine_table(k))


def stored_choice(env, stored: dict, mode: str = "file") -> StrategyChoice:
    """Apply a plan read from a file (:func:`.plan_file.load`) to ``env``; its
    :class:`StrategyChoice` (``mode`` ``file``, or ``kept`` for a plan from the cache
    folder), with the predictions the file holds. It runs what the file says: the same
    strategies, the same kernel (lean only where no material runs a product)."""
    choice = stored["strategies"]
    lean = stored["lean"] and not any(s.uses_product for s in choice.values())
    if env.lobes is not None and env.cosine_tables:
        env.lobes.sample_from_tables({key for key in env.lobes.cosine_ids
                                      if env.material_name(key) in set(stored["cosine_tables"])})
    env.share_bsdf({key for key in env.strategies.ids if env.material_name(key) in set(stored["bsdf_shares"])})
    apply_choice(env, choice, lean)
    plan = stored["plan"]
    selection = plan.get("emitter_selection", {})
    if selection and env.prices_emitter_selection:
        env.emitter_selection = selection["design"]
    shown = {m["name"]: m for m in plan.get("materials", [])}
    materials = []
    for key, strategy in choice.items():
        name = env.material_name(key)
        row = shown.get(name, {})
        variance = {strategy_named(label): v for label, v in row.get("variance", {}).items()}
        materials.append(MaterialChoice(name, strategy, row.get("share", 0.0), variance,
                                        row.get("predicted_gain", 1.0), row.get("forced", False)))
    pilot_variance = {k: (v["predicted"], v["measured"]) for k, v in plan.get("pilot_variance", {}).items()}
    return StrategyChoice(materials=materials, pass_time=plan.get("pass_time_s", {}),
                          predicted_gain=plan.get("predicted_gain", 1.0), lean=lean, seconds=0.0,
                          shared_variance=plan.get("shared_variance", 0.0), pilot_variance=pilot_variance,
                          cosine_tables=sorted(stored["cosine_tables"]), bsdf_shares=shared_names(env), mode=mode,
                          costs=plan.get("costs", {}),
                          emitter_selection=selection if env.prices_emitter_selection else {},
                          product_candidate=plan.get("product_candidate", {}))


# ----------------------------------------------------------------- the integrators' planner

class StrategyChooser:
    """An integrator's planner: before the first pass of each scene state whose
    ``strategy`` is ``auto`` (or names materials), it loads the plan from ``plan_file``
    or makes one (:func:`choose_strategies`), saves it where asked, and logs it.

    ``kind`` (``direct`` or ``path``) picks the cost model (:func:`~.costs.cost_model`);
    ``plan`` is ``estimate`` (the cost model) or ``measure`` (timed pilots in the scene;
    the plan is then also kept in the cache folder, keyed by the scene's content, and
    reused like FFTW's wisdom). The pilots (their images and, measured, their times) are
    made once per scene and reused when only its parameters change (an optimisation loop
    rebuilds the state at every step)."""

    def __init__(self, emitter_samples: int, bsdf_samples: int, kind: str = "direct", plan: str = ESTIMATE,
                 plan_file: str = ""):
        self.n_e, self.n_b = emitter_samples, bsdf_samples
        self.kind, self.mode, self.plan_file = kind, plan, plan_file
        self._scene, self._pilots = None, None
        #: A pilot pass is running. Mitsuba's ``render``, called by a pilot from inside the
        #: integrator's Python ``render``, dispatches to that ``render`` again: the
        #: integrator must then render as configured, without choosing (a nested choice
        #: would see the pilot's configuration, and the pilots would not run what they time).
        self.piloting = False
        #: ``sh_prb``'s plan for the gradients (:mod:`.gradient_plan`): (scene, the candidate
        #: kept, its scores), reused by the states rebuilt for the same scene.
        self.gradient_choice = None

    def prepare(self, integrator: mi.SamplingIntegrator, env, scene: mi.Scene, sensor):
        """:meth:`before_render` for a plugin derived from ``mi.SamplingIntegrator``
        (``sh_direct``, ``sh_path``): its timed pilots render through Mitsuba's
        ``SamplingIntegrator.render``, past the plugin's own. Returns ``env``."""
        self.before_render(env, scene, sensor, lambda spp, seed: mi.SamplingIntegrator.render(
            integrator, scene, sensor, seed, spp), integrator,
            lambda scene, sampler, ray, active: integrator.sample(scene, sampler, ray, None, active)[:2])
        return env

    def before_render(self, env, scene: mi.Scene, sensor, render: Callable, integrator=None,
                      sample: Callable | None = None) -> None:
        """Plan for ``env`` if it awaits a plan. ``render(spp, seed)`` returns one
        pass's image with ``integrator`` as it is (timed pilots); ``sample(scene, sampler,
        ray, active) -> (spectrum, valid)`` is its sample of one camera ray (the default
        plan's pilots: :func:`~.pilots.camera_sample_pass`; None: film passes too)."""
        if not env.awaits_choice:
            return
        if isinstance(sensor, int):
            sensor = scene.sensors()[sensor]
        start = time.perf_counter()
        if self.plan_file:
            file, key = self.plan_file, env.options_key
        else:
            # Kept in the cache folder by the scene's content: a measured plan (FFTW's wisdom),
            # and an estimated one with the cost model it was weighed with (a new calibration
            # plans again). The same plan, without its pilots and quadrature (0.8-1.1 s on
            # the studio), in every later process that renders the same scene.
            key = env.options_key if self.mode == MEASURE else f"{env.options_key}; {cost_model(self.kind).key}"
            file = plan_file.wisdom_path(scene, sensor, key)
        with kernels_compiled() as compiled:
            stored = plan_file.load(file, env, key) if file else None
            if stored is not None:
                env.choice = stored_choice(env, stored, "file" if self.plan_file else "kept")
            else:
                env.choice = self._choose(env, scene, sensor, render, integrator, sample)
                if file:
                    plan_file.save(file, env.choice, key)
        env.choice.setup_seconds = env.build_seconds + time.perf_counter() - start
        env.choice.kernels_compiled = getattr(env, "kernels_compiled", 0) + compiled.kernels
        mi.Log(mi.LogLevel.Info, f"{env.plugin}: plan ({env.choice.mode}, set-up {env.choice.setup_seconds:.2f} s"
                                 f"{compiling_note(env.choice.kernels_compiled)}): {env.choice.summary()}")

    def _choose(self, env, scene, sensor, render, integrator, sample) -> StrategyChoice:
        # Untimed pilots differ only in the strategy table, which is device data: one recording
        # replays them all (pilots.frozen_pilots); on a large film they are camera samples.
        # Timed pilots include the lean kernel, another trace: they render film passes traced.
        size = sensor.film().crop_size()
        samples = self.mode == ESTIMATE and sample is not None and int(size[0]) * int(size[1]) > FILM_PILOT_PIXELS
        if samples:
            render = lambda spp, seed: camera_sample_pass(scene, sensor, sample, seed)  # noqa: E731
        replay = frozen_pilots(render, env, (scene, sensor, integrator), film_passes=not samples) \
            if self.mode == ESTIMATE else render

        def render_pass(spp: int, seed: int):
            image = replay(spp, seed)
            dr.eval(image)
            dr.sync_thread()
            return image

        known = self._pilots if self._scene is scene else None
        # A pilot render sets the sensor's sampler to its own sample count: the render that
        # follows with spp=0 must get the scene's count back.
        sampler = sensor.sampler()
        sample_count = sampler.sample_count()
        self.piloting = True
        try:
            choice = choose_strategies(env, sensor, self.n_e, self.n_b, render_pass, known,
                                       None if self.mode == MEASURE else cost_model(self.kind), env.forced,
                                       1.0 if samples else None)
        finally:
            self.piloting = False
            sampler.set_sample_count(sample_count)
            if replay is not render:
                replay.release()
        self._scene, self._pilots = scene, choice.pilots
        return choice
