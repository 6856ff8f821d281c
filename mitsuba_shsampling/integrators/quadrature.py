"""The variance of each environment strategy at the camera's first hits, by quadrature.

The chooser (:mod:`.chooser`) weighs these predictions against the strategies'
costs. For every shading point the camera sees (:func:`camera_frames`, a
stratified grid over the film; for the path plugins the first rough hit behind
mirrors and glass, :func:`rough_hits`) the second moment of each strategy's one-sample
estimator is integrated over directions by importance-sampled quadrature
(:func:`frame_variances`): the integrand is the BSDF value x radiance x
*visibility* (a shadow ray per direction), so occluded skies and windows count
as they will in the render. Fixed seeds: the same scene gives the same figures
in every process.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import drjit as dr
import mitsuba as mi
import numpy as np

from ..device_arrays import device_array
from .estimators import environment_ray_target
from .options import sample_shares
from .strategy import Strategy

PCG32_DEFAULT_STREAM = 0xDA3E39CB94B95BDB
"""Dr.Jit's ``PCG32`` stream (``initseq``) when none is given."""

FRAMES = 4096
"""Camera shading points at most (a stratified grid over the film)."""

DIRECTIONS = 64
"""Quadrature directions per shading point."""

PRODUCT_ONLY_SHARED = len(Strategy)
"""Column of :func:`frame_variances` after the strategies': ``product_only`` with the BSDF's
share (``bsdf_defensive_share``; the plan gives it where it predicts less variance,
:func:`~.chooser.predict`)."""


def grid_positions(sensor: mi.Sensor, count: int = FRAMES) -> tuple[np.ndarray, np.ndarray]:
    """A stratified grid of film positions (``x``, ``y`` in [0, 1]^2 over the crop window), at
    most ``count`` and at most one per pixel, in raster order."""
    size = sensor.film().crop_size()
    width, height = int(size[0]), int(size[1])
    aspect = width / height
    nx = max(1, min(width, int(round(math.sqrt(count * aspect)))))
    ny = max(1, min(height, int(round(count / nx))))
    ix, iy = np.meshgrid((np.arange(nx) + 0.5) / nx, (np.arange(ny) + 0.5) / ny)
    return ix.ravel(), iy.ravel()


FRAME_SEED = 0x5EED0001
"""Seed of the random numbers that pick a Dirac BSDF's lobe (reflection or refraction) per frame."""


class CameraFrames(NamedTuple):
    """The shading points of :func:`camera_frames_at`."""

    si: mi.SurfaceInteraction3f
    bsdf: mi.BSDFPtr
    kept: np.ndarray
    """Indices of the film positions whose point was kept (a smooth BSDF)."""
    dirac_weight: np.ndarray
    """Per kept point, what one unit of variance there is on the film: the square of the Dirac
    bounces' throughput before it (the mean over the colour channels), 1 at a first hit."""


def rough_hits(scene: mi.Scene, sensor: mi.Sensor, position: mi.Point2f, dirac_bounces: int = 0):
    """``(si, bsdf, throughput)`` of the rays through film positions ``position`` ([0, 1]^2 over
    the crop): their first hit, or with ``dirac_bounces`` the first hit that is not on a Dirac-only
    BSDF (a mirror, glass) behind up to that many such bounces, each drawn by the BSDF's own
    sampling (fixed random numbers: :data:`FRAME_SEED`), and the bounces' throughput (1 at a
    first hit). Lazy: the caller evaluates what it needs in one kernel."""
    ray, _ = sensor.sample_ray(0.0, 0.5, position, mi.Point2f(0.5))
    si = scene.ray_intersect(ray)
    bsdf = si.bsdf(ray)
    throughput = mi.Spectrum(1.0)
    if dirac_bounces:
        ctx, lanes = mi.BSDFContext(), dr.width(position)
        rng = mi.PCG32(lanes, dr.opaque(mi.UInt64, FRAME_SEED))
        for _ in range(dirac_bounces):
            dirac = si.is_valid() & ~mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
            bs, value = bsdf.sample(ctx, si, rng.next_float32(), mi.Point2f(rng.next_float32(), rng.next_float32()),
                                    dirac)
            onwards = dirac & (bs.pdf > 0) & mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
            ray = dr.select(onwards, si.spawn_ray(si.to_world(bs.wo)), ray)
            beyond = scene.ray_intersect(ray, onwards)
            si = dr.select(onwards, beyond, si)
            bsdf = dr.select(onwards, beyond.bsdf(ray), bsdf)
            throughput = dr.select(onwards, throughput * mi.unpolarized_spectrum(value), throughput)
    return si, bsdf, throughput


def camera_frames_at(scene: mi.Scene, sensor: mi.Sensor, x: np.ndarray, y: np.ndarray,
                     dirac_bounces: int = 0) -> CameraFrames:
    """The shading points the camera sees at film positions ``(x, y)``, only those on smooth BSDFs
    kept: the first hits, or with ``dirac_bounces`` the first rough hit behind up to that many
    Dirac bounces (what a path integrator that does not count them product-samples as a first
    hit: ``integrators/path_loop.py``), each bounce drawn by the BSDF's own sampling."""
    position = mi.Point2f(device_array(mi.Float, np.asarray(x, dtype=np.float32)),
                          device_array(mi.Float, np.asarray(y, dtype=np.float32)))
    si, bsdf, throughput = rough_hits(scene, sensor, position, dirac_bounces)
    smooth = si.is_valid() & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
    weight = dr.mean(dr.square(throughput), axis=0) + dr.zeros(mi.Float, dr.width(position)) if dirac_bounces \
        else None
    # One kernel for the whole interaction: a gather from unevaluated fields evaluates
    # each field alone, each in a kernel of its own that traces the rays again (some 30
    # kernels, 1.6 s of a cold plan's compiling on the material studio).
    dr.eval(si, bsdf, smooth, *([weight] if weight is not None else []))
    kept = np.flatnonzero(np.broadcast_to(smooth.numpy(), (len(x),)))
    index = device_array(mi.UInt32, kept)
    weight = np.ones(len(kept)) if weight is None else np.asarray(weight.numpy(), dtype=np.float64)[kept]
    return CameraFrames(dr.gather(mi.SurfaceInteraction3f, si, index), dr.gather(mi.BSDFPtr, bsdf, index), kept,
                        weight)


def camera_frames(scene: mi.Scene, sensor: mi.Sensor, count: int = FRAMES):
    """The camera's first hits at a stratified grid of film positions (:func:`grid_positions`):
    ``(si, bsdf, total)`` with only the hits on smooth BSDFs kept, and ``total`` the number of
    film positions traced."""
    x, y = grid_positions(sensor, count)
    frames = camera_frames_at(scene, sensor, x, y)
    return frames.si, frames.bsdf, len(x)


def frame_variances(env, si: mi.SurfaceInteraction3f, bsdf: mi.BSDFPtr, n_e: int, n_b: int,
                    directions: int = DIRECTIONS, seed: int = 0, frames: np.ndarray | None = None) -> np.ndarray:
    """Variance of the environment estimator at each shading point, per strategy.

    The product of a cosine lobe is its table's where the lobes say so
    (:meth:`~..lobes.scene_lobes.SceneLobes.sample_from_tables`), else its SH walk's.

    Returns an array (points, 6), indexed by :class:`Strategy` and :data:`PRODUCT_ONLY_SHARED`: the variance
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

    ``frames``: the rows of ``si`` to estimate (default: all); each draws the random numbers
    it draws in the call over all of them, so a subset's rows are that call's rows.
    """
    if frames is None:
        frames = np.arange(dr.width(si))
    if len(frames) == 0:
        return np.zeros((0, len(Strategy) + 1))
    samples = mixture_samples(env, si, bsdf, directions, seed, device_array(mi.UInt32, frames.astype(np.uint32)))
    return strategy_variances(samples, n_e, n_b, env.warp is not None, env.warp_plain is not None)


def mixture_samples(env, si: mi.SurfaceInteraction3f, bsdf: mi.BSDFPtr, directions: int, seed: int,
                    frames: mi.UInt32) -> dict:
    """``directions`` directions per shading point (the rows ``frames`` of ``si``) from the
    equal mixture of :func:`frame_variances`, on the device; returns, as float64 device arrays
    of a block of ``directions`` lanes per point, the integrand per channel (``channels``), the
    mixture's pdf (``q``) and each strategy's pdf, whether each lane's point has a product lobe
    (``lobed``), and ``directions``. A lane's random numbers and mixture component are those of
    its place among every row's lanes (``row * directions + k``), whichever rows are asked."""
    lanes = dr.width(frames) * directions
    index = dr.arange(mi.UInt32, lanes)
    frame = dr.gather(mi.UInt32, frames, index // directions)
    lane = frame * directions + index % directions
    component = lane % 5
    si = dr.gather(mi.SurfaceInteraction3f, si, frame)
    bsdf = dr.gather(mi.BSDFPtr, bsdf, frame)
    # PCG32 adds arange(lanes) to both its state and its stream: offset each lane to its own place.
    offset = mi.UInt64(lane) - mi.UInt64(index)
    # The seed is opaque: a literal would make each seed's kernel a kernel of its own to compile.
    rng = mi.PCG32(lanes, dr.opaque(mi.UInt64, seed) + offset, mi.UInt64(PCG32_DEFAULT_STREAM) + offset)
    u0, u = rng.next_float32(), mi.Point2f(rng.next_float32(), rng.next_float32())

    ctx = mi.BSDFContext()
    product = env.warp is not None
    plain = env.warp_plain is not None
    if product:
        coeffs, proxy, has_lobe = env.lobes.coefficients_and_proxy(si, env.pyramid.grid_from_world, True,
                                                                   env.cosine_tables)
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
    radiance = env.emitter.eval(environment_ray_target(d, si.wavelengths))
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
    # With the BSDF's share, product_only draws from its mixture with the BSDF where its lobe
    # is walked in SH (ProductEnvironment.sample_environment): the pdf of its lane's samples
    # is that mixture's (the balance over its slots).
    p_shared = p_plain
    if plain and env.bsdf_share > 0:
        cosine = mi.Bool(proxy.cosine_only) if proxy is not None else mi.Bool(False)
        p_shared = dr.select(has_lobe & ~cosine, (1.0 - env.bsdf_share) * p_plain + env.bsdf_share * p_bsdf, p_plain)

    def lane_values(x):  # float64 on every lane (a literal 0 included)
        return mi.Float64(x) + dr.zeros(mi.Float64, lanes)

    samples = {"channels": [lane_values(f) for f in channels], "q": lane_values(mixture), "bsdf": lane_values(p_bsdf),
               "environment": lane_values(p_env), "environment_only": lane_values(p_plain_env),
               "product": lane_values(p_product), "product_only": lane_values(p_plain),
               "product_only_shared": lane_values(p_shared), "lobed": mi.Bool(has_lobe) | dr.zeros(mi.Bool, lanes),
               "directions": directions}
    dr.eval(samples["channels"], *(v for k, v in samples.items() if k not in ("channels", "directions")))
    return samples


def strategy_variances(samples: dict, n_e: int, n_b: int, product: bool, plain: bool) -> np.ndarray:
    """Each strategy's variance per point (:func:`frame_variances`) from the
    :func:`mixture_samples`, in float64 on the device (a block of ``directions`` lanes per
    point); returned on the host as (points, 6), the columns of :func:`frame_variances`.

    Each strategy's variance is estimated as the mean of (Y - I)^2 p / q, Y = w f / p
    its sample's value and I its mean: centred, so that an estimator with a large
    mean and a small variance (a sun that the strategy follows closely) does not lose
    it to cancellation in E[Y^2] - I^2."""
    q, p_bsdf, directions = samples["q"], samples["bsdf"], samples["directions"]
    points = dr.width(q) // directions
    point = dr.arange(mi.UInt32, dr.width(q)) // directions
    lit = q > 0
    channels = [dr.select(lit, f, 0.0) for f in samples["channels"]]
    inv_q = dr.select(lit, 1.0 / q, 0.0)

    def point_mean(x):  # the mean of each point's block, on its lanes
        return dr.gather(mi.Float64, dr.block_sum(x, directions) / directions, point)

    def one_sample_variance(weighted, pdf):
        """Variance of weighted(d) / pdf(d), d ~ pdf: (Y - I)^2 over the pdf's support (per point)."""
        mean = point_mean(weighted * inv_q)
        value = dr.select(pdf > 0, weighted / pdf, 0.0)
        return dr.block_sum(dr.select(pdf > 0, dr.square(value - mean) * pdf * inv_q, 0.0), directions) / directions

    def mis_variance(pdf):
        frac_e, frac_b = sample_shares(n_e, n_b)
        a2, b2 = dr.square(frac_e * pdf), dr.square(frac_b * p_bsdf)
        w = dr.select(pdf > 0, a2 / (a2 + b2), 0.0) if n_b else dr.select(pdf > 0, 1.0, 0.0)
        w_b = dr.select(p_bsdf > 0, 1.0 - w, 0.0)

        def channel(f):
            var = one_sample_variance(w * f, pdf) / n_e if n_e else 0.0
            return var + (one_sample_variance(w_b * f, p_bsdf) / n_b if n_b else 0.0)
        return sum(channel(f) for f in channels) / len(channels)

    def alone_variance(pdf):
        return sum(one_sample_variance(f, pdf) for f in channels) / (len(channels) * (n_e + n_b))

    columns = {Strategy.ENVIRONMENT: mis_variance(samples["environment"]),
               Strategy.ENVIRONMENT_ONLY: alone_variance(samples["environment_only"]),
               Strategy.BSDF_ONLY: alone_variance(p_bsdf)}
    # A lane of a product material without a lobe (its back side, where the BSDF is
    # black) samples the environment alone (ProductEnvironment.sample_environment).
    lobed = dr.block_sum(mi.Float64(samples["lobed"]), directions) > 0
    if product:
        columns[Strategy.PRODUCT] = dr.select(lobed, mis_variance(samples["product"]), columns[Strategy.ENVIRONMENT])
    if plain:
        alone = columns[Strategy.ENVIRONMENT_ONLY]
        columns[Strategy.PRODUCT_ONLY] = dr.select(lobed, alone_variance(samples["product_only"]), alone)
        columns[PRODUCT_ONLY_SHARED] = dr.select(lobed, alone_variance(samples["product_only_shared"]), alone)
    dr.eval(*columns.values())
    result = np.full((points, len(Strategy) + 1), np.nan)
    for column, values in columns.items():
        result[:, column] = np.broadcast_to(np.asarray(values.numpy(), dtype=np.float64), (points,))
    return result
