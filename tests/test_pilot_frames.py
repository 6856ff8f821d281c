"""Quadrature frames drawn where the pilots' pixels are noisiest (``integrators/pilot_frames.py``)."""

import numpy as np
import pytest

from mitsuba_shsampling.integrators.pilot_frames import PixelDensity

WIDTH, HEIGHT = 64, 48


def grid(count: int) -> tuple[np.ndarray, np.ndarray]:
    """A stratified grid of film positions, as the quadrature's (one per 2 x 2 pixels here)."""
    nx, ny = int(np.sqrt(count * WIDTH / HEIGHT)), None
    ny = count // nx
    x, y = np.meshgrid((np.arange(nx) + 0.5) / nx, (np.arange(ny) + 0.5) / ny)
    return x.ravel(), y.ravel()


def spiky(pixels: np.ndarray) -> np.ndarray:
    """1 everywhere, and 3,000 in three pixels that the grid does not visit."""
    value = np.ones(len(pixels))
    value[np.isin(pixels, [4 * WIDTH + 6, 20 * WIDTH + 32, 40 * WIDTH + 60])] = 3000.0
    return value


def film_mean_estimate(density: PixelDensity, drawn: int, grid_count: int = WIDTH * HEIGHT // 4) -> float:
    gx, gy = grid(grid_count)
    dx, dy = density.positions(drawn)
    x, y = np.concatenate([gx, dx]), np.concatenate([gy, dy])
    weights = density.frame_weights(x, y, len(gx), drawn)
    return float(np.sum(spiky(density.pixels_at(x, y)) * weights))


def test_frames_drawn_from_the_pilots_density_find_what_the_grid_misses():
    """With a density proportional to the function (pilots that saw where it is large), the
    balance-weighted frames of both sets give the film's mean; the grid alone misses it by
    most of it."""
    pixels = np.arange(WIDTH * HEIGHT)
    truth = spiky(pixels).mean()
    density = PixelDensity.from_lanes(WIDTH, HEIGHT, pixels, spiky(pixels))
    gx, gy = grid(WIDTH * HEIGHT // 4)
    grid_alone = spiky(density.pixels_at(gx, gy)).mean()
    assert grid_alone < 0.3 * truth
    assert film_mean_estimate(density, 256) == pytest.approx(truth, rel=0.02)


def test_a_density_blind_to_the_function_leaves_the_grids_estimate_nearly_as_it_was():
    """Pilots that saw nothing where the function is large: the drawn frames weigh little
    there and the estimate is about the grid's, not an over-correction (balance heuristic)."""
    pixels = np.arange(WIDTH * HEIGHT)
    elsewhere = np.where(pixels < 100, 1.0, 1e-6)
    density = PixelDensity.from_lanes(WIDTH, HEIGHT, pixels, elsewhere)
    gx, gy = grid(WIDTH * HEIGHT // 4)
    grid_alone = spiky(density.pixels_at(gx, gy)).mean()
    assert film_mean_estimate(density, 256) == pytest.approx(grid_alone, rel=0.05)


def test_each_lane_gets_frames_in_proportion_to_its_mass():
    pixels = np.arange(WIDTH * HEIGHT)
    weights = np.zeros(len(pixels))
    weights[[10, 500, 2000]] = [1.0, 2.0, 5.0]
    density = PixelDensity.from_lanes(WIDTH, HEIGHT, pixels, weights)
    x, y = density.positions(800)
    drawn = density.pixels_at(x, y)
    assert [np.count_nonzero(drawn == p) for p in (10, 500, 2000)] == [100, 200, 500]
    assert len({(a, b) for a, b in zip(x, y)}) == 800  # each frame at its own point of the pixel


def test_fewer_lanes_than_pixels_spread_each_lanes_mass_over_its_run_of_pixels():
    """Camera-sample pilots stride their lanes over a larger film: a lane stands for the
    pixels up to the next lane's, and the density over the film still integrates to one."""
    pixels = WIDTH * HEIGHT
    lanes = 1000
    lane_pixels = np.floor(np.arange(lanes) * (pixels / lanes)).astype(np.int64)
    weights = np.random.default_rng(1).gamma(0.5, size=lanes)
    density = PixelDensity.from_lanes(WIDTH, HEIGHT, lane_pixels, weights)
    ratio = density.ratio(np.arange(pixels))
    assert ratio.mean() == pytest.approx(1.0, rel=1e-12)
    # Each pixel's density follows its lane's per-pixel variance, however long the lane's run.
    lane_of_pixel = np.searchsorted(lane_pixels, np.arange(pixels), side="right") - 1
    assert ratio == pytest.approx(weights[lane_of_pixel] * pixels / np.sum(weights[lane_of_pixel]), rel=1e-9)
    x, y = density.positions(4000)
    assert np.all((x >= 0) & (x < 1) & (y >= 0) & (y < 1))
    drawn = density.pixels_at(x, y)
    lane = np.searchsorted(lane_pixels, drawn, side="right") - 1
    assert np.all(weights[lane] > 0)


def test_pilots_without_a_positive_finite_variance_give_no_density():
    pixels = np.arange(WIDTH * HEIGHT)
    assert PixelDensity.from_lanes(WIDTH, HEIGHT, pixels, np.zeros(len(pixels))) is None
    assert PixelDensity.from_lanes(WIDTH, HEIGHT, pixels, np.full(len(pixels), np.nan)) is None


def test_the_frames_are_the_same_in_every_call():
    pixels = np.arange(WIDTH * HEIGHT)
    weights = np.random.default_rng(2).gamma(0.3, size=len(pixels))
    first = PixelDensity.from_lanes(WIDTH, HEIGHT, pixels, weights).positions(512)
    second = PixelDensity.from_lanes(WIDTH, HEIGHT, pixels, weights.copy()).positions(512)
    assert all(np.array_equal(a, b) for a, b in zip(first, second))


# ------------------------------------------------------------ in the plan

BALL_FILM = 64


@pytest.fixture(scope="module")
def small_ball():
    """A GGX 0.05 ball, 1.4 % of a 64 x 64 film, on a diffuse floor under a half-degree sun:
    nearly all of the ball's variance is in the one or two pixels of the sun's reflection."""
    import mitsuba as mi

    mi.set_variant("llvm_ad_rgb")
    from mitsuba_shsampling.integrators import register
    from test_strategy_choice import SUN

    register()
    return mi.load_dict({
        "type": "scene", "env": SUN,
        "sensor": {"type": "perspective", "fov": 30,
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0, -3, 3], target=[0, 0, 0], up=[0, 0, 1]),
                   "film": {"type": "hdrfilm", "width": BALL_FILM, "height": BALL_FILM, "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent"}},
        "floor": {"type": "rectangle", "to_world": mi.ScalarTransform4f().scale(10), "bsdf": {"type": "diffuse"}},
        "ball": {"type": "sphere", "center": [0, 0, 0.15], "radius": 0.15,
                 "bsdf": {"type": "roughconductor", "distribution": "ggx", "alpha": 0.05}}})


def ball_variances(scene, env, ball, points_per_side: int) -> np.ndarray:
    """Per film pixel, the ball's variance per strategy (0 elsewhere), from a quadrature at
    ``points_per_side``^2 points of every pixel."""
    import drjit as dr
    import mitsuba as mi

    from mitsuba_shsampling.integrators.quadrature import camera_frames_at, frame_variances

    k = (np.arange(points_per_side) + 0.5) / points_per_side
    pixel = np.arange(BALL_FILM * BALL_FILM)
    x = ((pixel % BALL_FILM)[:, None, None] + k[None, :, None] + 0 * k[None, None, :]) / BALL_FILM
    y = ((pixel // BALL_FILM)[:, None, None] + 0 * k[None, :, None] + k[None, None, :]) / BALL_FILM
    si, bsdf, kept, _ = camera_frames_at(scene, scene.sensors()[0], x.ravel(), y.ravel())
    rows = frame_variances(env, si, bsdf, 1, 1, seed=9)
    rows[np.asarray(dr.reinterpret_array(mi.UInt32, bsdf).numpy()) != ball] = 0.0
    per_point = np.zeros((x.size, rows.shape[1]))
    per_point[kept] = np.nan_to_num(rows)
    return per_point.reshape(BALL_FILM * BALL_FILM, -1, rows.shape[1]).mean(axis=1)


def pilots_that_saw_the_highlight(scene, env, ball):
    import mitsuba as mi

    from mitsuba_shsampling.device_arrays import device_array
    from mitsuba_shsampling.integrators.pilots import Pilots

    return Pilots({}, pixel_variance={"environment": device_array(mi.Float64, ball_variances(scene, env, ball, 1)[:, 0])})


def test_the_plan_finds_a_suns_highlight_on_a_small_ball_that_its_grid_misses(small_ball):
    """The quadrature's grid does not visit the ball's highlight. Pilots that saw those pixels
    bring the ball's figures, for the environment strategy and the product alike, to a dense
    quadrature's (16 points a pixel)."""
    from mitsuba_shsampling.integrators.chooser import predict, with_pilot_frames
    from mitsuba_shsampling.integrators.environment import ProductEnvironment
    from mitsuba_shsampling.integrators.options import DirectOptions
    from mitsuba_shsampling.integrators.strategy import Strategy

    env = ProductEnvironment(small_ball, DirectOptions(), carry_all=True)
    sensor = small_ball.sensors()[0]
    grid = predict(env, sensor, 1, 1, {})
    ball = min(grid.materials, key=grid.share.get)
    dense = ball_variances(small_ball, env, ball, 4).mean(axis=0)
    refined = with_pilot_frames(env, sensor, grid, pilots_that_saw_the_highlight(small_ball, env, ball), 1, 1, {})
    for strategy in (Strategy.ENVIRONMENT, Strategy.PRODUCT):
        assert grid.variance[ball][strategy] < 0.7 * dense[strategy]
        assert refined.variance[ball][strategy] == pytest.approx(dense[strategy], rel=0.25)
    assert refined.share == grid.share


def test_the_chooser_weighs_its_materials_with_the_frames_its_pilots_point_to(small_ball):
    """The plan reports (and chooses by) the figures summed with the pilots' frames, not the
    grid's, whenever its pilots kept per-pixel variances."""
    from mitsuba_shsampling.integrators.chooser import choose_strategies, predict, with_pilot_frames
    from mitsuba_shsampling.integrators.environment import ProductEnvironment
    from mitsuba_shsampling.integrators.options import DirectOptions
    from mitsuba_shsampling.integrators.strategy import Strategy
    from test_strategy_choice import PASS_TIME

    sensor = small_ball.sensors()[0]
    env = ProductEnvironment(small_ball, DirectOptions(), carry_all=True)
    grid = predict(env, sensor, 1, 1, {})
    ball = min(grid.materials, key=grid.share.get)
    pilots = pilots_that_saw_the_highlight(small_ball, env, ball)
    refined = with_pilot_frames(env, sensor, grid, pilots, 1, 1, {})
    pilots.pass_time = dict(PASS_TIME)  # pass times as timed pilots give them (``plan`` ``measure``)
    env = ProductEnvironment(small_ball, DirectOptions(), carry_all=True)
    choice = choose_strategies(env, sensor, 1, 1, render_pass=None, pilots=pilots)
    (reported,) = [m for m in choice.materials if m.share == grid.share[ball]]
    assert reported.variance[Strategy.ENVIRONMENT] == pytest.approx(refined.variance[ball][Strategy.ENVIRONMENT],
                                                                    rel=1e-9)
    assert reported.variance[Strategy.ENVIRONMENT] > 1.5 * grid.variance[ball][Strategy.ENVIRONMENT]


def test_pilots_that_differ_in_their_last_bits_give_the_same_figures(small_ball):
    """Film passes splat with atomics, so two processes' pilots differ in their last bits; the
    figures summed with their frames must not (the same scene gives the same plan and figures)."""
    import mitsuba as mi

    from mitsuba_shsampling.device_arrays import device_array
    from mitsuba_shsampling.integrators.chooser import predict, with_pilot_frames
    from mitsuba_shsampling.integrators.environment import ProductEnvironment
    from mitsuba_shsampling.integrators.options import DirectOptions
    from mitsuba_shsampling.integrators.pilots import Pilots

    env = ProductEnvironment(small_ball, DirectOptions(), carry_all=True)
    sensor = small_ball.sensors()[0]
    grid = predict(env, sensor, 1, 1, {})
    ball = min(grid.materials, key=grid.share.get)
    seen = ball_variances(small_ball, env, ball, 1)[:, 0] + 1e-3
    jitter = 1.0 + 1e-12 * np.random.default_rng(3).standard_normal(len(seen))
    figures = [with_pilot_frames(env, sensor, grid, Pilots({}, pixel_variance={"environment": device_array(
        mi.Float64, values)}), 1, 1, {}) for values in (seen, seen * jitter)]
    assert figures[0].variance == figures[1].variance and figures[0].rest == figures[1].rest
