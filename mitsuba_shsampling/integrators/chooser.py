"""Choosing each material's environment strategy before the first pass (``strategy`` ``auto``).

What is minimised is the image's expected error at equal time: the per-pixel
variance summed over the film, times the time of a pass,

    J = (V_rest + sum_m V_m(s_m)) * (P_env + sum_m a_m * dP(s_m)),

over one strategy s_m per material m (a BSDF instance with a product lobe),
with

- ``V_m(s)``: the variance that the environment estimator of strategy ``s``
  adds to the film, summed over the shading points of material ``m``. It is
  computed at the camera's first hits (:func:`camera_frames`, a stratified grid
  over the film) from the estimator's second moment, by importance-sampled
  quadrature over directions (:func:`frame_variances`): the integrand is the
  BSDF value x radiance x *visibility* (a shadow ray per direction), so occluded
  skies and windows count as they will in the render.
- ``V_rest``: the same for the smooth materials without a choice (they run
  :attr:`Strategy.ENVIRONMENT`), plus ``S``, the variance that no environment
  strategy changes: antialiasing and texture edges, other emitters, Dirac
  paths, a path tracer's deeper vertices. It is what the pilot images'
  variance (:func:`measure_pass_costs`), converted to the quadrature's units
  (:func:`film_variance_factor`), has beyond the quadrature's prediction for
  the same passes. Without it the choice is optimistic wherever that shared
  variance dominates a pixel: a strategy that halves a quarter of the
  variance buys less than its time. The product pilots' images also scale
  each product strategy's quadrature variances to what they measured
  (:func:`calibrate`).
- ``P_env`` and ``dP(s)``: the pass time with every material on the
  environment strategy, and the extra time per pixel of material ``m`` on
  strategy ``s``. Both are measured in the scene itself by short pilot passes
  of the integrator with every material forced to each strategy, interleaved
  (:func:`measure_pass_costs`); the table of strategies is device data, so the
  pilots and the render share one compiled kernel.
- ``a_m``: the share of the film's pixels that material ``m`` covers.

J is minimised by coordinate descent over the materials (a handful of
strategies, a few sweeps). Where another assignment (one material's strategy changed)
is predicted within :data:`CONFIRM_MARGIN` of the best, the close ones are timed
as wholes by further pilots and their measured times decide
(:func:`confirm_by_timing`). What is predicted is direct lighting at the
camera's first hits; in a path tracer the deeper vertices share the choice.
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Callable

import drjit as dr
import mitsuba as mi
import numpy as np

from ..report.metrics import pixel_variance
from .estimators import environment_ray_target, mis_weight
from .strategy import Strategy

FRAMES = 4096
"""Camera shading points at most (a stratified grid over the film)."""

DIRECTIONS = 64
"""Quadrature directions per shading point."""

PILOT_LANES = 2**17
"""Camera samples per pilot pass (spp is rounded up so that the film gets at least this many)."""

PILOT_REPEATS = 4
"""Timed pilot passes per strategy (interleaved; the fastest counts: whatever else
runs on the machine only ever adds time, and adds it to one pass, not to a strategy)."""

PILOT_SEED = 0x5EED0000
"""Seed of the first round of pilot passes. The passes of one round share a seed and
the rounds differ: every strategy draws the same sampler dimensions, so within a round
the camera rays, the BSDF samples and the rare paths (a glass block's caustic) are
common to all pilots, and their variance cancels where the pilots are compared."""

REQUIRED_GAIN = 1.15
"""A product strategy must be predicted to beat the lean kernel by this factor at
equal time. The lean kernel is, per material, exactly one of Mitsuba's own
strategies at Mitsuba's cost; a prediction's error is the scatter of the pilots'
times and images: on the realistic scenes the measured gain was 0.85-1.15x the
predicted one where no rare path decided it, and the default job measured 0.78
where 1.09 was predicted (1.05 was the bar then)."""

CONFIRM_MARGIN = 1.15
"""Assignments predicted within this factor of the best one's error at equal time are
timed as wholes before the choice (:func:`confirm_by_timing`): the per-material times
are differences of pilot times, and where a material's share of the pass is small
their noise can flip a near tie."""

CONFIRM_RIVALS = 3
"""At most this many rivals (one material's strategy changed each) are timed."""


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


@dataclasses.dataclass
class StrategyChoice:
    """The outcome of :func:`choose_strategies`, for reports."""

    materials: list
    pass_time: dict
    """Pilot -> pass time (s): each strategy with every material that can run it on it,
    and :data:`LEAN`, the kernel without product code; ``confirm 0`` (the model's pick)
    and ``confirm 1`` ... (its close rivals) where :func:`confirm_by_timing` ran."""
    predicted_gain: float
    """Predicted equal-time efficiency of the choice over the lean kernel (every
    material on its best environment strategy, no product code: Mitsuba's
    ``direct`` with or without emitter samples only, per material): image
    variance ratio x pass-time ratio; 1 when lean."""
    lean: bool
    """No material runs a product strategy, and the product's code is not traced."""
    seconds: float
    """Time the choice took (frames, quadrature, pilots), spent once per scene."""
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

    def as_dict(self) -> dict:
        return {"predicted_gain": self.predicted_gain, "lean": self.lean, "seconds": self.seconds,
                "cosine_tables": list(self.cosine_tables),
                "pass_time_s": dict(self.pass_time), "shared_variance": self.shared_variance,
                "calibration": {s.label: f for s, f in (self.pilots.calibration if self.pilots else {}).items()},
                "pilot_variance": {k: {"predicted": p, "measured": m} for k, (p, m) in self.pilot_variance.items()},
                "materials": [{"name": m.name, "strategy": m.strategy.label, "share": m.share,
                               "predicted_gain": m.predicted_gain,
                               "variance": {s.label: v for s, v in m.variance.items()}}
                              for m in self.materials]}

    def summary(self) -> str:
        return summary_of(self.as_dict())


def summary_of(choice: dict) -> str:
    """One line from :meth:`StrategyChoice.as_dict` (also as a report stores it)."""
    parts = [f"{m['name']}: {m['strategy']}" + (f" (variance /{m['predicted_gain']:.2f})"
                                                if m["strategy"].startswith("product") else "")
             for m in choice["materials"] if m["share"] > 0]
    head = ("no product strategy pays: environment strategies only, without product code" if choice["lean"]
            else f"predicted x{choice['predicted_gain']:.2f} at equal time over environment strategies only")
    environment = choice.get("pilot_variance", {}).get(Strategy.ENVIRONMENT.label)
    if environment and environment["measured"] > 0:
        shared = min(choice["shared_variance"] / environment["measured"], 1.0)
        head += f" ({shared:.0%} of the film's variance shared by every strategy)"
    return f"{head}; " + ", ".join(parts)


# ----------------------------------------------------------------- shading points

def camera_frames(scene: mi.Scene, sensor: mi.Sensor, count: int = FRAMES):
    """The camera's first hits at a stratified grid of film positions (at most
    ``count``, at most one per pixel): ``(si, bsdf, total)`` with only the hits on
    smooth BSDFs kept, and ``total`` the number of film positions traced."""
    size = sensor.film().crop_size()
    width, height = int(size[0]), int(size[1])
    aspect = width / height
    nx = max(1, min(width, int(round(math.sqrt(count * aspect)))))
    ny = max(1, min(height, int(round(count / nx))))
    ix, iy = np.meshgrid((np.arange(nx) + 0.5) / nx, (np.arange(ny) + 0.5) / ny)
    position = mi.Point2f(ix.ravel().astype(np.float32), iy.ravel().astype(np.float32))
    ray, _ = sensor.sample_ray(0.0, 0.5, position, mi.Point2f(0.5))
    si = scene.ray_intersect(ray)
    bsdf = si.bsdf(ray)
    smooth = si.is_valid() & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
    keep = mi.UInt32(np.flatnonzero(np.broadcast_to(smooth.numpy(), (nx * ny,))).astype(np.uint32))
    return dr.gather(mi.SurfaceInteraction3f, si, keep), dr.gather(mi.BSDFPtr, bsdf, keep), nx * ny


def frame_variances(env, si: mi.SurfaceInteraction3f, bsdf: mi.BSDFPtr, n_e: int, n_b: int,
                    directions: int = DIRECTIONS, seed: int = 0, cosine_tables: bool = True) -> np.ndarray:
    """Variance of the environment estimator at each shading point, per strategy.

    With ``cosine_tables`` False the product of every lobe is its SH walk's, the cosine
    lobes' included (else theirs is their table's, where the product has tables).

    Returns an array (points, 4), indexed by :class:`Strategy`: the variance
    (averaged over the colour channels, as the report's MSE is) of one lane's
    environment estimate with ``n_e`` strategy samples and ``n_b`` BSDF samples
    (power heuristic on sample-count fractions), or with ``n_e + n_b`` strategy
    samples for the strategies that carry every sample. NaN where no product is
    built. At points without a product lobe the product strategies are what such
    a lane runs: the environment alone. Visibility counts: the integrand is
    BSDF x radiance x a shadow ray's verdict, per channel.

    The integrals E[w^2 f^2 / p] and E[w f] are estimated with ``directions``
    samples per point from an equal mixture of the BSDF's sampling, the two
    environment strategies and the two products (so that the sun, the lobe and
    the BSDF's own peak are all found), with the balance heuristic over it.
    """
    columns_out = len(Strategy)
    points = dr.width(si)
    if points == 0:
        return np.zeros((0, columns_out))
    lanes = points * directions
    index = dr.arange(mi.UInt32, lanes)
    frame = index // directions
    component = index % 5
    si = dr.gather(mi.SurfaceInteraction3f, si, frame)
    bsdf = dr.gather(mi.BSDFPtr, bsdf, frame)
    rng = mi.PCG32(lanes, seed)
    u0, u = rng.next_float32(), mi.Point2f(rng.next_float32(), rng.next_float32())

    ctx = mi.BSDFContext()
    product = env.warp is not None
    plain = env.warp_plain is not None
    if product:
        coeffs, proxy, has_lobe = env.lobes.coefficients_and_proxy(si, env.pyramid.grid_from_world, True,
                                                                   env.cosine_tables and cosine_tables)
    else:
        coeffs, proxy, has_lobe = None, None, mi.Bool(False)

    # One direction per lane, from the component its index selects. Lanes without
    # a lobe draw their "product" components from the compensated environment.
    bs, _ = bsdf.sample(ctx, si, u0, u, component == 0)
    d_env, _ = env.env_directions.sample(u)
    d_plain_env, _ = env.env_plain.sample(u)
    d = dr.select(component == 0, si.to_world(bs.wo), dr.select(component == 4, d_plain_env, d_env))
    if product:
        d_product, _ = env.warp.sample(coeffs, u, proxy)
        d = dr.select((component == 2) & has_lobe, d_product, d)
    if plain:
        d_plain, _ = env.warp_plain.sample(coeffs, u, proxy)
        d = dr.select((component == 3) & has_lobe, d_plain, d)

    wo = si.to_local(d)
    value, p_bsdf = bsdf.eval_pdf(ctx, si, wo)
    radiance = env.emitter.eval(environment_ray_target(d))
    visible = ~env.scene.ray_test(si.spawn_ray(d))
    # Per colour channel: the report's MSE averages the channels' squared errors
    # (report.metrics), and a strategy can be good in luminance and poor in blue
    # (a sun-following strategy in the shadow of a blue sky).
    channels = [dr.select(visible, value[c] * radiance[c], 0.0) for c in range(len(value))]
    p_env = env.env_directions.pdf(d)
    p_plain_env = env.env_plain.pdf(d)
    p_product = dr.select(has_lobe, env.warp.pdf(coeffs, d, proxy), 0.0) if product else mi.Float(0.0)
    p_plain = dr.select(has_lobe, env.warp_plain.pdf(coeffs, d, proxy), 0.0) if plain else mi.Float(0.0)
    mixture = 0.2 * (p_bsdf + p_env + p_plain_env + dr.select(has_lobe, p_product, p_env)
                     + dr.select(has_lobe & plain, p_plain, p_env))
    dr.eval(channels, mixture, p_bsdf, p_env, p_plain_env, p_product, p_plain, has_lobe)

    # The moments, per shading point, in float64 on the host. Each strategy's variance
    # is estimated as the mean of (Y - I)^2 p / q, Y = w f / p its sample's value and
    # I its mean: centred, so that an estimator with a large mean and a small variance
    # (a sun that the strategy follows closely) does not lose it to cancellation in
    # E[Y^2] - I^2.
    def per_point(x):
        return np.broadcast_to(np.asarray(x.numpy(), dtype=np.float64), (lanes,)).reshape(points, directions)

    channels, q = [per_point(f) for f in channels], per_point(mixture)
    p_bsdf, p_env, p_plain_env = per_point(p_bsdf), per_point(p_env), per_point(p_plain_env)
    p_product, p_plain = per_point(p_product), per_point(p_plain)
    lobed = per_point(mi.Float(has_lobe))[:, 0] > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        channels = [np.where(q > 0, f, 0.0) for f in channels]
        inv_q = np.where(q > 0, 1.0 / q, 0.0)

        def one_sample_variance(weighted, pdf):
            """Variance of weighted(d) / pdf(d), d ~ pdf: (Y - I)^2 over the pdf's support."""
            mean = np.mean(weighted * inv_q, axis=1, keepdims=True)
            value = np.where(pdf > 0, weighted / pdf, 0.0)
            return np.mean(np.where(pdf > 0, (value - mean) ** 2 * pdf * inv_q, 0.0), axis=1)

        def mis_variance(pdf):
            frac_e, frac_b = n_e / (n_e + n_b), n_b / (n_e + n_b)
            a2, b2 = (frac_e * pdf) ** 2, (frac_b * p_bsdf) ** 2
            w = np.where(pdf > 0, a2 / (a2 + b2), 0.0) if n_b else np.where(pdf > 0, 1.0, 0.0)
            w_b = np.where(p_bsdf > 0, 1.0 - w, 0.0)

            def channel(f):
                var = one_sample_variance(w * f, pdf) / n_e if n_e else 0.0
                return var + (one_sample_variance(w_b * f, p_bsdf) / n_b if n_b else 0.0)
            return np.mean([channel(f) for f in channels], axis=0)

        def alone_variance(pdf):
            return np.mean([one_sample_variance(f, pdf) for f in channels], axis=0) / (n_e + n_b)

        result = np.full((points, len(Strategy)), np.nan)
        result[:, Strategy.ENVIRONMENT] = mis_variance(p_env)
        result[:, Strategy.ENVIRONMENT_ONLY] = alone_variance(p_plain_env)
        # A lane of a product material without a lobe (its back side, where the BSDF is
        # black) samples the environment alone (ProductEnvironment.sample_environment).
        if product:
            result[:, Strategy.PRODUCT] = np.where(lobed, mis_variance(p_product), result[:, Strategy.ENVIRONMENT])
        if plain:
            result[:, Strategy.PRODUCT_ONLY] = np.where(lobed, alone_variance(p_plain),
                                                        result[:, Strategy.ENVIRONMENT_ONLY])
    return result


# ----------------------------------------------------------------- pass costs

LEAN = "lean"
"""Pilot key of the kernel without product code (:meth:`ProductEnvironment.drop_product`)."""

LEAN_STRATEGY = Strategy.ENVIRONMENT
"""What every material runs in the :data:`LEAN` pilot."""


def cosine_pilot(strategy: Strategy) -> str:
    """Pilot key of ``strategy`` on the materials with a clamped-cosine lobe alone (the
    others on the environment strategy): with the pilot of ``strategy`` on every
    material, it tells the cosine tables' cost from the SH walk's."""
    return f"{strategy.label} (cosine lobes)"


@dataclasses.dataclass
class Pilots:
    """What the pilot passes measured."""

    pass_time: dict
    """Pilot -> pass time (s): the kernels' execution time, the fastest of the timed passes."""
    image_variance: dict = dataclasses.field(default_factory=dict)
    """Pilot -> per-pixel variance of one pilot pass (channel-averaged, as the report's
    MSE), averaged over the film (from its pilot images, one per round of pilots)."""
    spp: int = 1
    """Samples per pixel of a pilot pass."""
    shared_variance: float | None = None
    """``S`` once derived (:func:`calibrate`); kept when the scene's parameters change
    and only the quadrature is redone."""
    calibration: dict = dataclasses.field(default_factory=dict)
    """Strategy -> factor on its quadrature variances that makes its pilot's prediction
    match the pilot's images (:func:`calibrate`); 1 where missing."""


def film_variance_factor(film: mi.Film, spp: int) -> float:
    """Variance of a developed pixel per unit variance of one camera sample, at ``spp``.

    A pixel is the filter-weighted mean sum w f / sum w of the samples around it
    (``spp`` per pixel area), so its variance is sigma^2 int w^2 / (spp (int w)^2):
    1 / spp for the box filter, about 1 / (3.1 spp) for the Gaussian. Mitsuba's
    filters are separable, so the 2D ratio is the square of the 1D one."""
    rfilter = film.rfilter()
    radius = float(rfilter.radius())
    x = np.linspace(-radius, radius, 4097)
    w = np.asarray(rfilter.eval(mi.Float(x.astype(np.float32))).numpy(), dtype=np.float64)
    ratio = np.mean(w * w) / (np.mean(w) ** 2 * 2 * radius)  # int w^2 / (int w)^2 on the even grid
    return ratio ** 2 / spp


def kernel_time(run: Callable[[], object]) -> tuple[object, float]:
    """``run()``'s result and the execution time (s) of the JIT kernels it launched
    (``run`` waits for them). That is a pass's time as the render replays it from a
    ``dr.freeze`` recording (``mitsuba_shsampling.frozen``): a pilot pass is traced
    each time, and the tracing, which weighs more for the larger product kernel
    (docs/MEASUREMENTS.md, "Frozen passes"), is no part of a replayed pass."""
    was_on = dr.flag(dr.JitFlag.KernelHistory)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    dr.kernel_history()  # clears it
    try:
        result = run()
        history = dr.kernel_history()
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, was_on)
    return result, 1e-3 * sum(k["execution_time"] for k in history if k["type"] == dr.KernelType.JIT)


def measure_pass_costs(env, candidates: dict, render_pass: Callable[[int], object],
                       repeats: int = PILOT_REPEATS, spp: int = 1) -> Pilots:
    """Pass time (s) and image variance per candidate: ``candidates`` maps a name to
    the assignment (registry id -> strategy) it runs with, or to :data:`LEAN` for
    the kernel without product code (every material on the environment strategy);
    ``render_pass(seed)`` renders one pass, waits, and returns its image (or None).
    One warm-up pass per kernel, then ``repeats`` timed rounds, candidates
    interleaved; the fastest time per candidate, as kernel time
    (:func:`kernel_time`). Every round has its own seed (:data:`PILOT_SEED`), and
    each pass's image counts towards its candidate's variance (warm-ups included:
    only their time is compile-bound). ``env`` is left as it was found."""
    table = env.strategies
    saved = {key: table.of(key) for key in table.ids}
    warps = env.warp, env.warp_plain

    def configure(assignment):
        env.warp, env.warp_plain = warps
        if assignment == LEAN:
            table.assign({key: LEAN_STRATEGY for key in table.ids})
            env.drop_product()
        else:
            table.assign(assignment)

    times = {name: [] for name in candidates}
    images = {name: [] for name in candidates}
    env.pilot_walks = True
    try:
        for round_ in range(repeats + 1):  # round 0 compiles each kernel once (the render reuses it)
            for name, assignment in candidates.items():
                configure(assignment)
                image, elapsed = kernel_time(lambda: render_pass(PILOT_SEED + round_))
                if round_ > 0:
                    times[name].append(elapsed)
                if image is not None:
                    images[name].append(np.asarray(image, dtype=np.float64))
    finally:
        env.warp, env.warp_plain = warps
        env.pilot_walks = False
        table.assign(saved)
    # The report's measure of noise (report.metrics): per-pixel variance, channel-averaged.
    variance = {name: float(np.mean(pixel_variance(np.stack(i)))) for name, i in images.items() if len(i) > 1}
    return Pilots({name: min(t) for name, t in times.items()}, variance, spp)


CALIBRATION_RANGE = (0.5, 4.0)
"""Bounds of a strategy's calibration factor: the pilot images are few (their
variance has its own noise, heavy-tailed where rare paths are), so they correct
the quadrature, but do not replace it."""


def calibrate(pilots: Pilots, measured: dict, model: dict, candidates: dict, variance: dict,
              rest: float) -> None:
    """Set ``pilots.shared_variance`` and ``pilots.calibration`` from the pilots' film
    variances (``measured``, quadrature units) against the quadrature's (``model``).

    - ``S``: what the pilots without the product (the environment strategy, whose
      quadrature is of Mitsuba's own sampling) have beyond the quadrature, at most
      the least variance any pilot measured. Where they have less (the quadrature's
      own noise under a sun), or more than that bound, the environment strategies'
      variances are scaled to them instead.
    - Each product strategy's pilot (every material that can run it on it, the
      others on the environment strategy) then fixes a factor on that strategy's
      variances: the pilot's measured variance, less ``S`` and the other
      materials' part, over the quadrature's part, within :data:`CALIBRATION_RANGE`.
    """
    environment = [name for name in (LEAN, Strategy.ENVIRONMENT.label) if name in measured]
    pilots.shared_variance, pilots.calibration = 0.0, {}
    if not environment:
        return
    measured_env = float(np.mean([measured[name] for name in environment]))
    model_env = model[Strategy.ENVIRONMENT.label]
    # No pilot's film can have less variance than the part they all share: beyond the
    # least of them, the environment's excess is the quadrature's own shortfall.
    pilots.shared_variance = float(np.clip(measured_env - model_env, 0.0, min(measured.values())))
    if measured_env - pilots.shared_variance != model_env and model_env > 0:
        scale = float(np.clip((measured_env - pilots.shared_variance) / model_env, *CALIBRATION_RANGE))
        pilots.calibration = {Strategy.ENVIRONMENT: scale, Strategy.ENVIRONMENT_ONLY: scale}
    environment_scale = pilots.calibration.get(Strategy.ENVIRONMENT, 1.0)
    for strategy in (Strategy.PRODUCT, Strategy.PRODUCT_ONLY):
        assignment = candidates.get(strategy.label)
        if assignment is None or strategy.label not in measured:
            continue
        own = sum(variance[k][strategy] for k, s in assignment.items() if s == strategy)
        others = rest + sum(variance[k][s] for k, s in assignment.items() if s != strategy)
        if not np.isfinite(own + others) or own <= 1e-3 * model[strategy.label]:
            continue  # the strategy barely shows in its pilot (or cannot be predicted)
        observed = measured[strategy.label] - pilots.shared_variance - others * environment_scale
        pilots.calibration[strategy] = float(np.clip(observed / own, *CALIBRATION_RANGE))


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
    strategy."""
    choice = {m: Strategy.ENVIRONMENT for m in variance}

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


def choose_strategies(env, sensor: mi.Sensor, n_e: int, n_b: int, render_pass: Callable[[int, int], object],
                      pilots: Pilots | None = None) -> StrategyChoice:
    """Choose and assign (``env.strategies``) a strategy for every material; when no
    product strategy pays for the time its code costs every lane, drop the
    product altogether (:meth:`ProductEnvironment.drop_product`).

    ``render_pass(spp, seed)`` renders one pass of the integrator as it is
    configured and returns its image; ``pilots`` (as an earlier choice measured
    them) skips the pilot passes. Pilots without images leave the shared
    variance ``S`` at 0. Without a product to choose, pilots run only where the
    quadrature prefers ``environment_only`` for some material: its time decides
    whether that pays (it costs more than ``environment``).
    """
    start = time.perf_counter()
    table = env.strategies
    si, bsdf, total = camera_frames(env.scene, sensor)
    variances = frame_variances(env, si, bsdf, n_e, n_b)
    keys = np.broadcast_to(dr.reinterpret_array(mi.UInt32, bsdf).numpy(), (dr.width(si),)) \
        if dr.width(si) else np.zeros(0, dtype=np.uint32)
    if env.cosine_tables:
        variances = choose_cosine_sampling(env, variances, frame_variances(env, si, bsdf, n_e, n_b, cosine_tables=False),
                                           keys)

    materials = list(table.ids)
    allowed = {key: env.allowed(key) for key in materials}
    variance, share = {}, {}
    for key in materials:
        rows = variances[keys == key]
        share[key] = len(rows) / total
        variance[key] = {s: (float(np.sum(rows[:, s])) / total if len(rows) else 0.0) for s in allowed[key]}
    rest_rows = variances[~np.isin(keys, materials)]
    rest = float(np.sum(rest_rows[:, Strategy.ENVIRONMENT])) / total if len(rest_rows) else 0.0

    # The lean kernel: the environment strategies only, no product code.
    cheap = (Strategy.ENVIRONMENT, Strategy.ENVIRONMENT_ONLY)

    def best_environment_strategies(variance):
        return {k: min((s for s in allowed[k] if s in cheap), key=lambda s: (variance[k][s], s)) for k in materials}

    lean_choice = best_environment_strategies(variance)
    product_possible = any(s.uses_product for k in materials for s in allowed[k])
    # The two environment strategies do not cost the same: environment_only draws a second
    # map sample and traces a second shadow ray where the other traces the BSDF sample's
    # occlusion query, 4-25 % of a pass (docs/MEASUREMENTS.md, "environment_only's time").
    # Where the quadrature prefers it for some material, a pilot measures what it costs.
    alone_capable = [k for k in materials if Strategy.ENVIRONMENT_ONLY in allowed[k]]
    alone_wanted = any(s == Strategy.ENVIRONMENT_ONLY for s in lean_choice.values())

    choice, lean, gain, shared, fit, confirmed = lean_choice, True, 1.0, 0.0, {}, {}
    if product_possible or alone_wanted:
        # Cosine lobes take the product from tables, at a fraction of the SH walk's cost: where
        # both kinds could run a product strategy, a pilot with the cosine lobes alone on it
        # tells the two costs apart.
        cosine = {k for k in materials if env.samples_from_cosine_table(k)}
        candidates = {LEAN: LEAN, Strategy.ENVIRONMENT.label: {k: Strategy.ENVIRONMENT for k in materials}}
        if alone_wanted:
            candidates[Strategy.ENVIRONMENT_ONLY.label] = {
                k: Strategy.ENVIRONMENT_ONLY if k in alone_capable else Strategy.ENVIRONMENT for k in materials}
        for strategy in (Strategy.PRODUCT, Strategy.PRODUCT_ONLY):
            capable = [k for k in materials if strategy in allowed[k]]
            if capable:
                candidates[strategy.label] = {k: strategy if k in capable else Strategy.ENVIRONMENT
                                              for k in materials}
            if any(k in cosine for k in capable) and any(k not in cosine for k in capable):
                candidates[cosine_pilot(strategy)] = {k: strategy if k in capable and k in cosine
                                                      else Strategy.ENVIRONMENT for k in materials}
        fresh = pilots is None  # (pilots of an earlier choice: the scene's parameters changed)
        if fresh:
            film = sensor.film().crop_size()
            spp = max(1, math.ceil(PILOT_LANES / (int(film[0]) * int(film[1]))))
            pilots = measure_pass_costs(env, candidates, lambda seed: render_pass(spp, seed), spp=spp)
        # The model's film variance of each pilot, against its images.
        model = {name: rest + sum(variance[k][LEAN_STRATEGY if a == LEAN else a[k]] for k in materials)
                 for name, a in candidates.items()}
        factor = film_variance_factor(sensor.film(), pilots.spp)
        measured = {name: v / factor for name, v in pilots.image_variance.items() if name in model}
        if pilots.shared_variance is None:
            calibrate(pilots, measured, model, candidates, variance, rest)
        shared = pilots.shared_variance
        fit = {name: (model[name] + shared, measured[name]) for name in measured}
        variance = {k: {s: v * pilots.calibration.get(s, 1.0) for s, v in row.items()} for k, row in variance.items()}
        rest *= pilots.calibration.get(Strategy.ENVIRONMENT, 1.0)

        pass_time = pilots.pass_time
        base = pass_time[Strategy.ENVIRONMENT.label]
        extra = {k: {s: 0.0 for s in cheap} for k in materials}

        def set_extra(strategy, kinds, times):
            # Extra pass time per unit of film share of the materials of each kind switched to
            # ``strategy`` (the pilots' times: before, then with each kind added in turn).
            for kind, before, after in zip(kinds, times, times[1:]):
                switched = sum(share[k] for k in kind)
                per_share = max(after - before, 0.0) / switched if switched > 0 else 0.0
                for k in kind:
                    extra[k][strategy] = per_share

        if Strategy.ENVIRONMENT_ONLY.label in pass_time:  # else (pilots of an earlier choice) as before: no extra
            set_extra(Strategy.ENVIRONMENT_ONLY, [alone_capable], [base, pass_time[Strategy.ENVIRONMENT_ONLY.label]])
        for strategy in (Strategy.PRODUCT, Strategy.PRODUCT_ONLY):
            if strategy.label not in pass_time:
                continue
            capable = [k for k in materials if strategy in allowed[k]]
            # Per kind of lobe where a pilot told the kinds apart, else one figure for all.
            if cosine_pilot(strategy) in pass_time:
                set_extra(strategy, [[k for k in capable if k in cosine], [k for k in capable if k not in cosine]],
                          [base, pass_time[cosine_pilot(strategy)], pass_time[strategy.label]])
            else:
                set_extra(strategy, [capable], [base, pass_time[strategy.label]])
        # Materials no camera ray sees give no evidence: they keep their lean choice.
        seen = {k: v for k, v in variance.items() if share[k] > 0}
        # The lean kernel's choice, calibrated and timed: environment_only only where it pays.
        seen_cheap = {k: {s: v for s, v in row.items() if s in cheap} for k, row in seen.items()}
        lean_seen, _ = minimise_error_at_equal_time(seen_cheap, rest + shared, share, pass_time[LEAN], extra)
        lean_choice = {**best_environment_strategies(variance), **lean_seen}
        error_lean = predicted_error(lean_choice, variance, rest + shared, share, pass_time[LEAN], extra)
        choice = lean_choice
        if product_possible:
            full_choice, error_full = minimise_error_at_equal_time(seen, rest + shared, share, base, extra)
            if fresh:
                def time_assignments(assignments):
                    whole = {name: {**lean_choice, **a} for name, a in assignments.items()}
                    times = measure_pass_costs(env, whole, lambda seed: render_pass(spp, seed), spp=spp).pass_time
                    confirmed.update(times)  # reported with the pilots' times
                    return times

                full_choice = confirm_by_timing(full_choice, seen, rest + shared, share, base, extra,
                                                time_assignments)
                error_full = predicted_error(full_choice, seen, rest + shared, share, base, extra)
            if error_full * REQUIRED_GAIN < error_lean and any(s.uses_product for s in full_choice.values()):
                choice, lean, gain = {**lean_choice, **full_choice}, False, error_lean / error_full
    table.assign(choice)
    if lean and env.warp is not None:
        env.drop_product()
    if not any(s.carries_all for s in choice.values()):
        env.carry_all = False  # no lane skips its BSDF sample: the branch is not traced either

    report = []
    for key in materials:
        s, v = choice[key], variance[key]
        reference = v[lean_choice[key]]
        report.append(MaterialChoice(env.material_name(key), s, share[key], dict(v),
                                     reference / v[s] if v[s] > 0 else 1.0))
    return StrategyChoice(report, {**(pilots.pass_time if pilots else {}), **confirmed}, gain, lean,
                          time.perf_counter() - start, shared, fit, pilots,
                          sorted(env.material_name(k) for k in env.lobes.tabled_ids) if env.cosine_tables else [])


class StrategyChooser:
    """An integrator's chooser: runs :func:`choose_strategies` before the first pass of
    each scene state whose ``strategy`` is ``auto``. The pilots (pass times and the
    shared variance) are measured once per scene and reused when only its
    parameters change (an optimisation loop rebuilds the state at every step)."""

    def __init__(self, emitter_samples: int, bsdf_samples: int):
        self.n_e, self.n_b = emitter_samples, bsdf_samples
        self._scene, self._pilots = None, None
        #: A pilot pass is running. Mitsuba's ``render``, called by a pilot from inside the
        #: integrator's Python ``render``, dispatches to that ``render`` again: the
        #: integrator must then render as configured, without choosing (a nested choice
        #: would see the pilot's configuration, and the pilots would not run what they time).
        self.piloting = False

    def prepare(self, integrator: mi.SamplingIntegrator, env, scene: mi.Scene, sensor):
        """:meth:`before_render` for a plugin derived from ``mi.SamplingIntegrator``
        (``sh_direct``, ``sh_path``): its pilots render through Mitsuba's
        ``SamplingIntegrator.render``, past the plugin's own. Returns ``env``."""
        self.before_render(env, scene, sensor, lambda spp, seed: mi.SamplingIntegrator.render(
            integrator, scene, sensor, seed, spp))
        return env

    def before_render(self, env, scene: mi.Scene, sensor, render: Callable) -> None:
        """Choose for ``env`` if it awaits a choice. ``render(spp, seed)`` returns one
        pass's image with the integrator as it is (the pilots)."""
        if not env.awaits_choice:
            return
        if isinstance(sensor, int):
            sensor = scene.sensors()[sensor]

        def render_pass(spp: int, seed: int):
            image = render(spp, seed)
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
            env.choice = choose_strategies(env, sensor, self.n_e, self.n_b, render_pass, known)
        finally:
            self.piloting = False
            sampler.set_sample_count(sample_count)
        self._scene, self._pilots = scene, env.choice.pilots
