"""Pilot passes: short renders of the integrator with every material forced to a strategy.

Their images measure, in the scene itself, what the quadrature (:mod:`.quadrature`)
leaves out: the variance that every strategy shares (antialiasing, texture edges,
other emitters, deeper vertices) and how far each strategy's prediction is off
(:func:`calibrate`). Their seeds are fixed (:data:`PILOT_SEED`), so the same scene
gives the same images, and the same plan, in every process.

The default plan's pilots are film passes up to :data:`FILM_PILOT_PIXELS` pixels, and
above it camera samples (:func:`camera_sample_pass`): one integrator sample at each of
that many film positions spread over the film, and no film, so that a pilot costs no more
at 1920 x 1080 than at 640 x 400. Timed, the pilots are whole film passes, which also
measure each strategy's cost in the scene (``plan`` ``measure``, and the per-machine
calibration of :mod:`.costs`): the default plan times nothing.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import drjit as dr
import mitsuba as mi
import numpy as np

from ..device_arrays import device_array
from ..frozen import collector_paused, held_inputs
from ..timing import kernel_time
from .strategy import MITSUBA_STRATEGIES, Strategy

PILOT_LANES = 2**17
"""Camera samples per film pilot pass at least (spp is rounded up so that the film gets this many)."""

FILM_PILOT_PIXELS = 2**18
"""Films of at most this many pixels are piloted by film passes; larger ones by camera-sample
passes of this many lanes (:func:`camera_sample_pass`). Not fewer: the pilots' variance is
heavy-tailed where a strategy has rare large samples, and fewer samples mostly miss them. With
2^17 lanes on a 480 x 360 film (172,800 px) the product's variance came out 0.5-0.8 of the
quadrature's in five seeds against 0.7-1.9 from film passes, the plan put one more material on
the product, and it lost at equal time (docs/MEASUREMENTS.md, "The pilots as camera samples on large films")."""

PILOT_REPEATS = 4
"""Timed pilot passes per strategy (interleaved; the fastest counts: whatever else
runs on the machine only ever adds time, and adds it to one pass, not to a strategy)."""

PILOT_IMAGES = 3
"""Pilot passes per strategy when nothing is timed: images only, for the shared
variance and the calibration."""

PILOT_SEED = 0x5EED0000
"""Seed of the first round of pilot passes. The passes of one round share a seed and
the rounds differ: every strategy draws the same sampler dimensions, so within a round
the camera rays, the BSDF samples and the rare paths (a glass block's caustic) are
common to all pilots, and their variance cancels where the pilots are compared."""


LEAN = "lean"
"""Pilot key of the kernel without product code (:meth:`ProductEnvironment.drop_product`)."""

LEAN_STRATEGY = Strategy.ENVIRONMENT
"""What every material runs in the :data:`LEAN` pilot."""


@dataclasses.dataclass(frozen=True)
class Candidate:
    """What one pilot renders with: each material's strategy (registry id -> strategy),
    and whether the kernel leaves the product's code out (the :data:`LEAN` pilot, whose
    materials all run :data:`LEAN_STRATEGY`)."""

    assignment: dict
    lean: bool = False

    @classmethod
    def lean_kernel(cls, materials) -> "Candidate":
        return cls({key: LEAN_STRATEGY for key in materials}, lean=True)


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
    MSE), averaged over the film (from its pilot images, one per round of pilots); a
    camera-sample pass's pixels are its lanes."""
    spp: int = 1
    """Samples per pixel of a pilot pass."""
    film_factor: float = 1.0
    """What ``image_variance`` is per unit variance of one camera sample (the quadrature's
    unit): 1 for camera-sample passes, :func:`film_variance_factor` for film passes."""
    image_variance_error: dict = dataclasses.field(default_factory=dict)
    """Pilot -> the standard error of its ``image_variance`` (:func:`film_variance_and_error`)."""
    pixel_variance: dict = dataclasses.field(default_factory=dict, repr=False)
    """Pilot -> its per-pixel variances (a lane a pixel, float64, on the device): the
    standard error of a difference of pilots (:func:`paired_errors`)."""
    by_material: dict = dataclasses.field(default_factory=dict)
    """Registry id -> strategy -> what the pilots measured on that material's pixels
    (:func:`~.material_pilots.material_differences`)."""
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
    w = np.asarray(rfilter.eval(device_array(mi.Float, x)).numpy(), dtype=np.float64)
    ratio = np.mean(w * w) / (np.mean(w) ** 2 * 2 * radius)  # int w^2 / (int w)^2 on the even grid
    return ratio ** 2 / spp


def camera_sample_pass(scene: mi.Scene, sensor: mi.Sensor, sample: Callable, seed,
                       lanes: int = FILM_PILOT_PIXELS) -> list:
    """One camera sample at each of ``lanes`` film positions, as Mitsuba's
    ``SamplingIntegrator`` takes one (a uniform position in the pixel, then the aperture,
    time and wavelength samples; the ray weighted by the sensor's), through ``sample(scene,
    sampler, ray, active) -> (spectrum, valid)``: per lane its value in the film's channels
    (linear sRGB; one channel in mono variants), a list of arrays, invalid samples 0.

    The positions are the film's pixels in raster order, ``lanes`` of them evenly strided
    where the film has more (1280 x 960: every 4.7th), each pixel as often as it takes where
    it has fewer. So a pass costs the same at every resolution, and develops no film (at
    1280 x 960 a film pass of the same scene costs 6-7x as much; docs/MEASUREMENTS.md). The
    sampler is the sensor's, forked and seeded with ``seed`` for ``lanes`` lanes: the same
    seed draws the same numbers whatever each material runs (common random numbers). One
    recording replays every such pass (a film pass records twice: Mitsuba's sampler holds other
    arrays after its first render)."""
    size = sensor.film().crop_size()
    width = int(size[0])
    sampler = sensor.sampler().fork()
    sampler.set_sample_count(1)
    sampler.set_samples_per_wavefront(1)
    sampler.seed(seed, lanes)
    pixel = pilot_pixels(sensor, lanes)
    position = mi.Vector2f(mi.Float(pixel % width), mi.Float(pixel // width)) + sampler.next_2d()
    aperture = sampler.next_2d() if sensor.needs_aperture_sample() else mi.Point2f(0.5)
    time = mi.Float(sensor.shutter_open())
    if sensor.shutter_open_time() > 0:
        time += sampler.next_1d() * sensor.shutter_open_time()
    wavelength = sampler.next_1d() if mi.is_spectral else mi.Float(0.0)
    ray, weight = sensor.sample_ray_differential(time, wavelength, position / mi.ScalarVector2f(size), aperture)
    spectrum, valid = sample(scene, sampler, ray, mi.Bool(True))
    spectrum = dr.select(valid, mi.unpolarized_spectrum(spectrum) * weight, 0.0)
    if mi.is_spectral:
        # As Mitsuba's films: the mean over the lane's wavelengths of the colour matching
        # functions times the sampled spectrum (normalised so that Y is luminance), then sRGB.
        count = len(spectrum)
        xyz = sum(mi.cie1931_xyz(ray.wavelengths[i]) * spectrum[i] for i in range(count)) \
            * (mi.MI_CIE_Y_NORMALIZATION / count)
        colour = mi.xyz_to_srgb(xyz)
        return [colour.x, colour.y, colour.z]
    return [spectrum[i] for i in range(len(spectrum))]


def pilot_pixels(sensor: mi.Sensor, lanes: int) -> mi.UInt32:
    """The film pixel (raster order over the crop) of each of ``lanes`` pilot lanes: every
    pixel in turn where the film has as many (a film pass), evenly strided where it has more,
    each as often as it takes where it has fewer (:func:`camera_sample_pass`)."""
    size = sensor.film().crop_size()
    pixels = int(size[0]) * int(size[1])
    lane = dr.arange(mi.UInt32, lanes)
    return mi.UInt32(mi.Float64(lane) * (pixels / lanes)) if pixels > lanes else lane % pixels


def film_mean_pixel_variance(images: list) -> float:
    """The film's mean of the report's per-pixel variance
    (:func:`~mitsuba_shsampling.report.metrics.pixel_variance`: unbiased across the K >= 2
    ``images``, channels averaged over the finite ones, 0 where none is) of K pilot images,
    in float64 where the images are: tensors (H, W, C), or lists of C arrays of a
    :func:`camera_sample_pass` (a lane for a pixel).

    Why not in numpy: the images' copies to the host and the numpy passes over them cost
    more than the pilots' kernels at high resolution (1920 x 1440: 5.4 s of the plan's 11.3 s
    of pilots; docs/MEASUREMENTS.md)."""
    return film_variance_and_error(images)[0]


def film_variance_and_error(images: list) -> tuple[float, float]:
    """:func:`film_mean_pixel_variance` and its standard error: the spread of the per-pixel
    variances over the film, over the square root of the number of pixels.

    It says how well the pilots measured the film's variance: where a strategy has rare large
    samples, a few pixels hold much of it (on the studio under studio_small_03 the 10 brightest
    of 172,800 pixels hold 13-40 %). Over eight pilot seeds in six realistic and sphere cells,
    each pilot's film mean scattered by 0.42-1.25x (median 0.83x) this error's mean: a little
    more than the scatter where the pixels' fixed spread counts, a little less where a filter's
    neighbouring pixels share samples (docs/MEASUREMENTS.md, "A calibration weighed by its
    error"). It is itself an estimate from those pixels, so it is low where the rare samples
    were missed altogether."""
    return _mean_and_error(_per_pixel_variance(images))


def _mean_and_error(per_pixel) -> tuple[float, float]:
    """The mean of a float64 array (a lane a pixel) and its standard error over the lanes."""
    pixels = dr.width(per_pixel)
    sums = dr.sum(per_pixel), dr.sum(dr.square(per_pixel))
    dr.eval(*sums)
    total, squares = (float(x.numpy()[0]) for x in sums)
    mean = total / pixels
    spread = max(squares - total * mean, 0.0) / max(pixels - 1, 1)
    return mean, float(np.sqrt(spread / pixels))


def independent_errors(errors: dict) -> Callable[[dict], float]:
    """The standard error of a combination ``sum_n w_n m_n`` of pilots' film variances
    (pilot -> weight), taking each pilot's ``errors[n]`` as independent of the others'."""
    return lambda weights: float(np.sqrt(sum((w * errors.get(name, 0.0)) ** 2 for name, w in weights.items())))


def paired_errors(pixel_variance: dict, scale: float = 1.0) -> Callable[[dict], float]:
    """The standard error of a combination ``sum_n w_n m_n`` of pilots' film variances
    (pilot -> weight), each ``m_n`` the film mean of ``pixel_variance[n]`` over ``scale``:
    the spread over the pixels of the per-pixel combination, over the square root of the
    pixels.

    Why paired: the pilots of a round share their random numbers, so a pixel that a rare
    path (a caustic, a texture edge, an antialiasing sample across a bright edge) makes
    noisy is noisy in every pilot. Their difference, the product's own part of its film,
    is then measured more closely than the pilots' errors taken as independent say: on the
    material studio at 256 x 192, where two thirds of the film's variance is shared, the
    product's calibration is 0.37 +- 1.0 paired, +- 1.65 taken as independent
    (docs/MEASUREMENTS.md, "Each material's difference, measured by the pilots")."""
    def error(weights: dict) -> float:
        terms = [(w, pixel_variance[name]) for name, w in weights.items() if w != 0.0]
        if not terms:
            return 0.0
        return _mean_and_error(sum(w * v for w, v in terms))[1] / scale
    return error


def _per_pixel_variance(images: list):
    """Per pixel (a lane), the unbiased variance across ``images``, channels averaged over the
    finite ones, 0 where none is (float64)."""
    count = len(images)
    channels = [_channels(image) for image in images]
    pixels = dr.width(channels[0][0])
    total, finite = dr.zeros(mi.Float64, pixels), dr.zeros(mi.UInt32, pixels)
    for channel in range(len(channels[0])):
        x = [image[channel] for image in channels]
        mean = sum(x) / count
        ok = dr.all([dr.isfinite(v) for v in x])
        variance = sum(dr.square(v - mean) for v in x) / (count - 1)
        total += dr.select(ok, variance, 0.0)
        finite += dr.select(ok, 1, 0)
    return dr.select(finite > 0, total / mi.Float64(dr.maximum(finite, 1)), 0.0)


def _channels(image) -> list:
    """An image's channels as float64 arrays, a pixel a lane."""
    if isinstance(image, (list, tuple)):
        return [mi.Float64(channel) for channel in image]
    height, width, channels = (int(n) for n in dr.shape(image))
    # Gathered in the image's own precision and widened lane by lane, in the kernel that uses
    # them: a float64 copy of the whole image cost each pilot pass a kernel of its own over
    # fresh memory (8.7 ms of a 45 ms pass at 480 x 360).
    pixel = dr.arange(mi.UInt32, height * width) * channels
    return [mi.Float64(dr.gather(type(image.array), image.array, pixel + channel)) for channel in range(channels)]


def measure_pass_costs(env, candidates: dict, render_pass: Callable[[int], object],
                       repeats: int = PILOT_REPEATS, spp: int = 1, timed: bool = True,
                       film_factor: float = 1.0) -> Pilots:
    """Pass time (s) and image variance per candidate: ``candidates`` maps a name to
    the :class:`Candidate` it runs; ``render_pass(seed)`` renders one pass, waits, and returns its image (or None).
    ``timed``: one warm-up pass per kernel, then ``repeats`` timed rounds, candidates
    interleaved; the fastest time per candidate, as kernel time
    (:func:`~mitsuba_shsampling.timing.kernel_time`). Otherwise ``repeats`` rounds of
    images and no time (``pass_time`` empty). Every round has its own seed
    (:data:`PILOT_SEED`), and each pass's image counts towards its candidate's variance
    (warm-ups included: only their time is compile-bound); ``film_factor``: the images'
    (:attr:`Pilots.film_factor`). ``env`` is left as it was found."""
    table = env.strategies
    saved = {key: table.of(key) for key in table.ids}
    warps = env.warp, env.warp_plain

    def configure(candidate: Candidate):
        env.warp, env.warp_plain = warps
        table.assign(candidate.assignment)
        if candidate.lean:
            env.drop_product()

    times = {name: [] for name in candidates}
    images = {name: [] for name in candidates}
    env.pilot_walks = True
    # bsdf_only's draw is traced only where some pilot runs it (a 1D sample more per slot).
    env.pilot_bsdf_alone = any(s == Strategy.BSDF_ONLY for c in candidates.values() for s in c.assignment.values())
    try:
        # Timed: round 0 compiles each kernel once (the render reuses it) and is not timed.
        for round_ in range(repeats + 1 if timed else repeats):
            for name, candidate in candidates.items():
                configure(candidate)
                if timed:
                    image, elapsed = kernel_time(lambda: render_pass(PILOT_SEED + round_))
                    if round_ > 0:
                        times[name].append(elapsed)
                else:
                    image = render_pass(PILOT_SEED + round_)
                if image is not None:
                    images[name].append(image)
    finally:
        env.warp, env.warp_plain = warps
        env.pilot_walks = env.pilot_bsdf_alone = False
        table.assign(saved)
    # The report's measure of noise (report.metrics): per-pixel variance, channel-averaged.
    per_pixel = {name: _per_pixel_variance(i) for name, i in images.items() if len(i) > 1}
    dr.eval(*per_pixel.values())
    measured = {name: _mean_and_error(v) for name, v in per_pixel.items()}
    return Pilots({name: min(t) for name, t in times.items() if t}, {n: v for n, (v, _) in measured.items()}, spp,
                  film_factor=film_factor, image_variance_error={n: e for n, (_, e) in measured.items()},
                  pixel_variance=per_pixel)


def frozen_pilots(render: Callable[[int, int], object], env, objects: tuple,
                  film_passes: bool = True) -> Callable[[int, int], object]:
    """``render(spp, seed)`` recorded once with ``dr.freeze`` and replayed for every later
    seed and strategy table: pilot passes of one kernel pay its tracing once (a traced
    pass of the product kernel costs several times its execution at pilot size). The
    per-scene state's arrays are inputs of the recording (:func:`~mitsuba_shsampling.frozen.held_inputs`),
    so a new table is read by the replay, and so are ``objects`` (the scene, sensor and
    integrator that ``render`` uses), and so are ``env.emitter_selection`` (a Python string
    that the trace reads: each value is its own recording) and whether it traces
    ``bsdf_only``'s draw. Where recording fails, the
    passes render traced.

    A film pass leaves the sensor's sampler advanced lane by lane, and a recording computes
    what its inputs hold when it returns: that state, which nothing reads (every render seeds
    the sampler again), took a kernel of its own that traced every camera ray again (5-9 ms
    of each 30-40 ms pilot pass at 480 x 360). Each such pass (``film_passes``) therefore ends
    by seeding the sampler for one lane (:func:`settled_samplers`); camera-sample passes draw
    from a fork and leave the sensor's sampler alone."""
    # The recording's closures form a reference cycle inside dr.freeze, which would keep
    # ``render`` (and through it the integrator, its state and the scene) alive until
    # Python's next collection: ``replay.release()`` drops both when the pilots are done.
    target = [render]

    def one_pass(seed, spp, objects, inputs, emitter_selection, draws_bsdf_alone):
        image = target[0](spp, seed)
        if film_passes:
            settled_samplers(objects)
        return image

    frozen, failed = dr.freeze(one_pass), []

    def replay(spp: int, seed: int):
        if failed:
            return render(spp, seed)
        with collector_paused():
            try:
                return frozen(dr.opaque(mi.UInt32, seed), spp, objects, held_inputs(env), env.emitter_selection,
                              env.draws_bsdf_alone)
            except RuntimeError:  # e.g. an integrator whose arrays are out of reach: traced from now on
                failed.append(True)
                return render(spp, seed)

    def release():
        frozen.clear()
        target.clear()

    replay.release = release
    return replay


def settled_samplers(objects: tuple) -> None:
    """Seed the sampler of each sensor among ``objects`` for a single lane: its state then
    costs nothing to compute at the end of a recording (:func:`frozen_pilots`)."""
    for sensor in objects:
        if isinstance(sensor, mi.Sensor):
            sensor.sampler().seed(0, 1)


CALIBRATION_RANGE = (0.5, 4.0)
"""Bounds of a strategy's calibration factor: the pilot images are few (their
variance has its own noise, heavy-tailed where rare paths are), so they correct
the quadrature, but do not replace it."""


def calibrate(pilots: Pilots, measured: dict, model: dict, candidates: dict, variance: dict,
              rest: float, errors: Callable[[dict], float] | None = None) -> None:
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
      Where ``errors`` (the standard error of a combination of the pilots' ``measured``,
      pilot -> weight: :func:`paired_errors`, :func:`independent_errors`) says that part was
      measured loosely (its error follows the pilots it was derived from: :class:`Measured`),
      the factor is drawn towards 1 (:func:`weighed_calibration`).
    """
    environment = [name for name in (LEAN, Strategy.ENVIRONMENT.label) if name in measured]
    pilots.shared_variance, pilots.calibration = 0.0, {}
    if not environment:
        return
    shared, scale = shared_part(measured, environment, model[Strategy.ENVIRONMENT.label])
    pilots.shared_variance = shared.value
    if scale.value != 1.0:
        pilots.calibration = {s: scale.value for s in MITSUBA_STRATEGIES}
    for strategy in (Strategy.PRODUCT, Strategy.PRODUCT_ONLY):
        candidate = candidates.get(strategy.label)
        if candidate is None or strategy.label not in measured:
            continue
        own = sum(variance[k][strategy] for k, s in candidate.assignment.items() if s == strategy)
        others = rest + sum(variance[k][s] for k, s in candidate.assignment.items() if s != strategy)
        if not np.isfinite(own + others) or own <= 1e-3 * model[strategy.label]:
            continue  # the strategy barely shows in its pilot (or cannot be predicted)
        observed = Measured(measured[strategy.label], {strategy.label: 1.0}) - shared - scale * others
        factor = observed.value / own
        if errors:
            factor = weighed_calibration(factor, observed.error(errors) / own)
        pilots.calibration[strategy] = float(np.clip(factor, *CALIBRATION_RANGE))


@dataclasses.dataclass(frozen=True)
class Measured:
    """A figure derived from the pilots' film variances, with its first-order dependence on
    each (pilot -> coefficient), so that its standard error follows the branch that made it."""

    value: float
    weights: dict = dataclasses.field(default_factory=dict)

    def __sub__(self, other: "Measured") -> "Measured":
        weights = dict(self.weights)
        for name, w in other.weights.items():
            weights[name] = weights.get(name, 0.0) - w
        return Measured(self.value - other.value, weights)

    def __mul__(self, k: float) -> "Measured":
        return Measured(self.value * k, {name: w * k for name, w in self.weights.items()})

    def error(self, errors: Callable[[dict], float]) -> float:
        """Standard error, from ``errors``: that of a combination of pilots (pilot -> weight)."""
        return errors(self.weights)


def shared_part(measured: dict, environment: list, model_env: float) -> tuple[Measured, Measured]:
    """``(S, scale)``: the variance every pilot shares, and the factor on the environment
    strategies' variances.

    ``S`` is what the environment pilots (whose quadrature is of Mitsuba's own sampling)
    have beyond the quadrature, at most the least variance any pilot measured: no pilot's
    film can have less than the part they all share, so beyond that bound the environment's
    excess is the quadrature's own shortfall. Where they have less than the quadrature (its
    own noise under a sun) or more than the bound, ``scale`` takes the rest."""
    env = Measured(float(np.mean([measured[n] for n in environment])), {n: 1.0 / len(environment) for n in environment})
    least = min(measured, key=measured.get)
    if env.value - model_env < 0.0:
        shared = Measured(0.0)
    elif env.value - model_env > measured[least]:
        shared = Measured(measured[least], {least: 1.0})
    else:
        shared = env - Measured(model_env)
    if model_env <= 0 or env.value - shared.value == model_env:
        return shared, Measured(1.0)
    scale = (env - shared) * (1.0 / model_env)
    return shared, Measured(float(np.clip(scale.value, *CALIBRATION_RANGE)), scale.weights)


def weighed_calibration(factor: float, error: float) -> float:
    """A calibration factor measured as ``factor`` +- ``error`` (one standard error), weighed
    against the quadrature's own prediction (a factor of 1 +- :data:`CALIBRATION_PRIOR_SD`):
    the mean of the two, each weighed by the inverse of its variance (the posterior mean of a
    normal prior and a normal measurement). A factor measured closely stays as measured; one
    that is mostly the pilots' noise, such as the product's share of a film whose variance is
    mostly shared by every strategy, moves to the quadrature's."""
    prior, measurement = CALIBRATION_PRIOR_SD ** 2, error ** 2
    if not np.isfinite(measurement):
        return 1.0
    return (factor * prior + 1.0 * measurement) / (prior + measurement)


CALIBRATION_PRIOR_SD = 0.25
"""How far a strategy's quadrature is believed off before its pilot is seen: one standard
deviation of its calibration factor. In the 36 plans of the realistic and sphere cells, the
40 product factors of cells whose shared variance is under a tenth of the film's came out
0.50-1.03 (mean 0.93, standard deviation 0.12); the prior is twice as wide, so that the
pilots keep the say wherever they measured anything (docs/MEASUREMENTS.md, "A calibration
weighed by its error")."""
