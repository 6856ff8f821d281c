"""What the pilots measure on each material's pixels, and how it enters the plan
(``integrators/material_pilots.py``)."""

import numpy as np
import pytest

import mitsuba as mi

mi.set_variant("llvm_ad_rgb")

from mitsuba_shsampling.device_arrays import device_array  # noqa: E402
from mitsuba_shsampling.integrators import register  # noqa: E402
from mitsuba_shsampling.integrators.chooser import choose_strategies  # noqa: E402
from mitsuba_shsampling.integrators.environment import ProductEnvironment  # noqa: E402
from mitsuba_shsampling.integrators.material_pilots import (MATERIAL_PRIOR_SD, NO_MATERIAL,  # noqa: E402
                                                            MaterialDifference, lane_materials, quadrature_row,
                                                            material_differences, refine,
                                                            weighed_difference)
from mitsuba_shsampling.integrators.options import DirectOptions  # noqa: E402
from mitsuba_shsampling.integrators.pilots import Candidate, Pilots  # noqa: E402
from mitsuba_shsampling.integrators.strategy import Strategy  # noqa: E402
from mitsuba_shsampling.scene_materials import registry_id  # noqa: E402

from test_strategy_choice import PASS_TIME, SUN, floor_scene  # noqa: E402

E, EO, P, PO = Strategy.ENVIRONMENT, Strategy.ENVIRONMENT_ONLY, Strategy.PRODUCT, Strategy.PRODUCT_ONLY


@pytest.fixture(scope="module", autouse=True)
def registered():
    register()


def pilots_of(pixels: dict, film_factor: float = 1.0) -> Pilots:
    return Pilots({}, film_factor=film_factor,
                  pixel_variance={name: device_array(mi.Float64, v) for name, v in pixels.items()})


# ------------------------------------------------------------ measuring

def test_a_materials_difference_is_the_pilots_per_pixel_difference_summed_over_its_pixels():
    """Per material: the environment pilot's per-pixel variance less the product pilot's,
    summed over the pixels whose centre sees it, over the film's pixels and the film factor;
    its error the per-pixel differences' spread over those pixels. A material the product
    pilot left on the environment strategy, and the background, get nothing."""
    rng = np.random.default_rng(3)
    materials = rng.choice(np.array([7, 9, 11, NO_MATERIAL], dtype=np.uint32), size=4000)
    env = rng.gamma(2.0, 1.0, size=4000)
    product = env * np.where(materials == 7, 0.3, 1.0) + rng.normal(0, 0.01, size=4000)
    quadrature = {7: {E: 2.0, P: 1.0}, 9: {E: 1.0, P: 0.9}, 11: {E: 1.0, P: 1.0}}
    candidates = {P.label: Candidate({7: P, 9: P, 11: E})}
    measured = material_differences(pilots_of({E.label: env, P.label: product}, film_factor=0.5),
                                     materials, candidates, quadrature, E.label)
    assert set(measured) == {7, 9} and set(measured[7]) == {P}
    for key in (7, 9):
        mine = materials == key
        d = (env - product)[mine]
        m = measured[key][P]
        assert m.difference == pytest.approx(d.sum() / (4000 * 0.5), rel=1e-12)
        assert m.error == pytest.approx(np.std(d, ddof=1) * np.sqrt(mine.sum()) / (4000 * 0.5), rel=1e-9)
        assert m.environment == pytest.approx(env[mine].sum() / (4000 * 0.5), rel=1e-12)
        assert m.quadrature == quadrature_row(quadrature[key])
    assert measured[7][P].difference > 10 * measured[7][P].error
    assert abs(measured[9][P].difference) < 4 * measured[9][P].error


def test_what_every_strategy_shares_at_a_pixel_cancels_from_the_difference():
    """Pilots of one round share their random numbers: a pixel made noisy by a rare path is
    noisy in both. The difference is then measured far more closely than either pilot."""
    rng = np.random.default_rng(4)
    shared = rng.pareto(1.5, size=20000) * 10.0  # heavy-tailed, the same in both pilots
    env = shared + rng.gamma(2.0, 1.0, size=20000)
    product = shared + 0.5 * rng.gamma(2.0, 1.0, size=20000)
    materials = np.full(20000, 5, dtype=np.uint32)
    measured = material_differences(pilots_of({E.label: env, P.label: product}), materials,
                                    {P.label: Candidate({5: P})}, {5: {E: 1.0, P: 0.5}}, E.label)[5][P]
    alone = np.std(env, ddof=1) / np.sqrt(env.size)
    assert measured.error < 0.1 * alone
    assert measured.difference == pytest.approx(1.0, abs=4 * measured.error)


def test_each_pilot_lane_reads_the_material_its_pixel_centre_sees():
    """A ball on black: the lanes of the pixels on the ball read its BSDF's registry id,
    the others :data:`NO_MATERIAL`; on a film with more pixels than lanes the lanes are
    strided over it as the camera-sample pilots place theirs."""
    scene = mi.load_dict({
        "type": "scene", "env": SUN,
        "sensor": {"type": "perspective", "fov": 30,
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0, -4, 0], target=[0, 0, 0], up=[0, 0, 1]),
                   "film": {"type": "hdrfilm", "width": 24, "height": 16}},
        "ball": {"type": "sphere", "radius": 0.5, "bsdf": {"type": "roughconductor"}}})
    ball = registry_id(scene.shapes()[0].bsdf())
    ids = lane_materials(scene, scene.sensors()[0], 24 * 16).reshape(16, 24)
    assert ids[8, 12] == ball and ids[0, 0] == NO_MATERIAL and ids[15, 23] == NO_MATERIAL
    assert set(np.unique(ids)) == {ball, NO_MATERIAL}
    strided = lane_materials(scene, scene.sensors()[0], 96)
    assert strided.shape == (96,) and np.array_equal(strided, ids.reshape(-1)[(np.arange(96) * 4)])
    # A cropped film's lanes are its window's pixels (positions relative to the crop, as the
    # pilots place their samples).
    cropped = mi.load_dict({
        "type": "perspective", "fov": 30,
        "to_world": mi.ScalarTransform4f().look_at(origin=[0, -4, 0], target=[0, 0, 0], up=[0, 0, 1]),
        "film": {"type": "hdrfilm", "width": 24, "height": 16, "crop_offset_x": 5, "crop_offset_y": 4,
                 "crop_width": 10, "crop_height": 6}})
    assert np.array_equal(lane_materials(scene, cropped, 60).reshape(6, 10), ids[4:10, 5:15])


# ------------------------------------------------------------ weighing

def measurement(difference, error, environment, quadrature):
    return MaterialDifference(difference, error, environment, quadrature_row(quadrature))


def test_a_closely_measured_difference_replaces_the_quadratures():
    """A smaller difference than the quadrature's lowers nothing but the strategy's figure; a
    larger one is the environment strategy's variance that the quadrature missed, and that
    the environment pilot counted as shared: the material's row rises by it and the shared
    part falls by as much. Either way the film's variance under each assignment follows the
    measurement (the decision is the same as if the strategy's figure alone had moved)."""
    quadrature = {1: {E: 1.0, P: 0.8}}
    variance, shared = refine(quadrature, 2.0, {1: {P: measurement(0.1, 1e-6, 1.5, quadrature[1])}}, quadrature)
    assert variance[1] == {E: 1.0, P: pytest.approx(0.9, abs=1e-6)} and shared == 2.0
    variance, shared = refine(quadrature, 2.0, {1: {P: measurement(0.6, 1e-6, 1.5, quadrature[1])}}, quadrature)
    assert variance[1][E] - variance[1][P] == pytest.approx(0.6, abs=1e-6)
    assert variance[1][P] == pytest.approx(0.8, abs=1e-6)
    assert shared + variance[1][E] == pytest.approx(2.0 + 1.0)
    assert quadrature == {1: {E: 1.0, P: 0.8}}  # the input is left as it was


def test_a_loosely_measured_difference_leaves_the_quadratures_nearly_as_it_was():
    quadrature = {1: {E: 1.0, P: 0.8}}
    variance, _ = refine(quadrature, 2.0, {1: {P: measurement(0.6, 100.0, 1.0, quadrature[1])}}, quadrature)
    assert variance[1][E] - variance[1][P] == pytest.approx(0.2, abs=1e-4)


def test_a_measured_difference_moves_the_quadratures_as_far_as_it_can_tell_them_apart():
    """The prior: the quadrature's difference within :data:`MATERIAL_PRIOR_SD` of the
    material's environment variance, or (:data:`MISSED_SHARE` of materials) within all of it.
    A measurement within its noise of the quadrature's leaves it nearly as it was; one far
    from it, by many of its errors, is taken as measured; with no error, as measured. (Figures
    of the plans that set the prior, x 1e3: docs/MEASUREMENTS.md.)"""
    # A small film's loose measurement, 1.3 errors below the quadrature's (a GGX 0.05 sphere
    # under the sun-and-sky map at 128 x 96): the quadrature's figure stands, nearly.
    assert weighed_difference(8.2, MATERIAL_PRIOR_SD * 23.3, 30.4, -3.5, 8.6) == pytest.approx(8.2, rel=0.1)
    # The gold ball, where the quadrature saw nothing and the pilots 2.8 errors' worth: it moves
    # part of the way.
    gold = weighed_difference(-0.074, MATERIAL_PRIOR_SD * 0.569, 5.08, 1.62, 0.6)
    assert 0.1 < gold < 1.62
    assert weighed_difference(0.2, MATERIAL_PRIOR_SD, 4.0, 3.0, 0.01) == pytest.approx(3.0, abs=0.01)
    assert weighed_difference(0.2, MATERIAL_PRIOR_SD, 4.0, 0.25, 0.0) == 0.25
    # Ten of the close part's widths away, and as close: nearly as measured.
    assert weighed_difference(0.2, 0.04, 4.0, 0.6, 0.04) == pytest.approx(0.6, abs=0.02)


def test_a_difference_beyond_the_quadratures_environment_variance_moves_variance_out_of_the_shared_part():
    """The quadrature missed most of a glossy ball's variance under the environment strategy
    (a highlight in a few pixels): the environment pilot had it, and it was taken for
    variance every strategy shares. The pilots' difference puts it back on the material: its
    row rises, the shared part falls by as much (the film's predicted variance under the
    environment strategy stays what the pilot measured), and the product keeps its
    quadrature variance."""
    quadrature = {1: {E: 1.0, P: 1.1, PO: 1.5}, 2: {E: 3.0, P: 2.0}}
    measured = {1: {P: measurement(4.0, 1e-6, 9.0, quadrature[1])}}
    variance, shared = refine(quadrature, 10.0, measured, quadrature)
    assert variance[1][P] == pytest.approx(1.1, abs=1e-5)
    assert variance[1][E] == pytest.approx(5.1, abs=1e-5)
    assert variance[1][PO] == pytest.approx(1.5 + 4.1, abs=1e-5)  # the row rises as a whole
    assert shared == pytest.approx(10.0 - 4.1, abs=1e-5)
    assert shared + variance[1][E] + variance[2][E] == pytest.approx(10.0 + 1.0 + 3.0)
    assert variance[2] == quadrature[2]
    # No further than the shared part: a variance the film did not have is not made up.
    variance, shared = refine(quadrature, 1.0, measured, quadrature)
    assert shared == 0.0 and variance[1][E] == pytest.approx(2.0) and variance[1][P] == 0.0


def test_a_measurement_against_other_quadrature_figures_is_not_used():
    """After a parameter change the material's quadrature row is new: what the pilots measured
    on the old material says nothing about it."""
    old = {1: {E: 1.0, P: 0.8}}
    new = {1: {E: 1.2, P: 0.7}}
    variance, shared = refine(new, 2.0, {1: {P: measurement(0.9, 1e-6, 1.5, old[1])}}, new)
    assert variance == new and shared == 2.0


def test_the_plan_follows_a_materials_measured_difference():
    """A diffuse floor under a tiny sun stays on Mitsuba's environment sampling by the
    quadrature; pilots that measured the product removing most of its variance, closely, put
    it on the product."""
    scene = floor_scene({"type": "diffuse"}, SUN)
    env = ProductEnvironment(scene, DirectOptions(), carry_all=True)
    plain = choose_strategies(env, scene.sensors()[0], 1, 1, render_pass=None, pilots=Pilots(PASS_TIME))
    (material,) = plain.materials
    assert material.strategy == E
    (key,) = env.strategies.ids
    env = ProductEnvironment(scene, DirectOptions(), carry_all=True)
    pilots = Pilots(PASS_TIME, by_material={key: {P: measurement(
        0.9 * material.variance[E], 1e-9, material.variance[E], material.variance)}})
    refined = choose_strategies(env, scene.sensors()[0], 1, 1, render_pass=None, pilots=pilots)
    assert refined.materials[0].strategy == P
    assert refined.materials[0].variance[P] == pytest.approx(0.1 * material.variance[E], rel=1e-3)
