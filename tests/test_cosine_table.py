"""Specification of the cosine tables (``mitsuba_shsampling.warp.cosine_table``): the
product of a clamped cosine and the environment for diffuse lobes, one table per normal bin.

What must hold: samples follow the pdf the sampler returns (chi-square, and the pdf walk
gives back the sampled pdf); the pdf integrates to one and never falls below the defensive
share of the environment's own (so every lit direction stays reachable whatever the
lane's normal); the bins put the world's axes at their centres; and in the product warp,
lanes of a diffuse lobe take the table while the others keep their SH walk.
"""

from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

mi.set_variant("llvm_ad_rgb")

from mitsuba import chi2  # noqa: E402

from mitsuba_shsampling.envmap import EnvPyramid  # noqa: E402
from mitsuba_shsampling.envmap.synthetic import sun_sky_latlong  # noqa: E402
from mitsuba_shsampling.lobes import SceneLobes  # noqa: E402
from mitsuba_shsampling.lobes.scene_lobes import is_cosine_lobe  # noqa: E402
from mitsuba_shsampling.warp.cosine_table import (NORMAL_BINS, TABLE_DEPTH, CosineTable, bin_normals,  # noqa: E402
                                                  mixture_tables, normal_bin)
from mitsuba_shsampling.warp.product import ProductWarp  # noqa: E402
from mitsuba_shsampling.warp.proxy_lobe import ProxyLobe  # noqa: E402

from leaf_chi2 import LeafAlignedChiSquareTest
# The product warp's specification holds the maps these tests sample (its fixtures, shared).
from test_product import REAL_MAP, real_pyramid, sun_pyramid, uniform_samples  # noqa: F401

SHARE = 0.1


def unit(v) -> list[float]:
    v = np.asarray(v, dtype=np.float64)
    return (v / np.linalg.norm(v)).tolist()


def random_normals(count: int, seed: int) -> mi.Vector3f:
    n = np.random.default_rng(seed).normal(size=(count, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return mi.Vector3f(*(mi.Float(c.astype(np.float32)) for c in n.T))


#: World normals of the chi-square cases: up (a bin's centre), tilted, and on a bin edge.
CHI2_NORMALS = {"up": (0.0, 1.0, 0.0), "tilted": (0.5, 0.3, -0.8), "bin_edge": (1.0, 1.0 / NORMAL_BINS, 0.2)}


@pytest.mark.parametrize("pyramid_name", ["real_pyramid", "sun_pyramid"])
@pytest.mark.parametrize("normal", sorted(CHI2_NORMALS))
def test_chi2_samples_follow_own_pdf(request, pyramid_name, normal):
    pyramid = request.getfixturevalue(pyramid_name)
    table = CosineTable(pyramid, SHARE)
    n = pyramid.grid_from_world(mi.Vector3f(*unit(CHI2_NORMALS[normal])))
    test = LeafAlignedChiSquareTest(
        domain=chi2.SphericalDomain(),
        sample_func=lambda u: pyramid.grid_from_world(table.sample(n, u)[0]),
        pdf_func=lambda d: table.pdf(n, pyramid.world_from_grid(d)),
        sample_dim=2, sample_count=1_000_000, res=2 << pyramid.depth, seed=3)
    assert test.run(0.01), test.messages


def test_sample_returns_the_pdf_that_pdf_evaluates(sun_pyramid):
    table = CosineTable(sun_pyramid, SHARE)
    count = 1 << 15
    normals = random_normals(count, seed=1)
    d, pdf = table.sample(normals, uniform_samples(count))
    again = table.pdf(normals, d).numpy()
    pdf = pdf.numpy()
    assert np.all(np.isfinite(pdf)) and np.all(pdf > 0)
    assert np.max(np.abs(again - pdf) / pdf) <= 1e-3


def test_pdf_integrates_to_one_for_any_normal(real_pyramid):
    table = CosineTable(real_pyramid, SHARE)
    directions = mi.warp.square_to_uniform_sphere(uniform_samples(1 << 21, seed=2))
    for normal in ([0, 1, 0], [0.3, -0.9, 0.1], [-1, 0, 0]):
        integral = 4 * math.pi * float(np.mean(table.pdf(mi.Vector3f(*unit(normal)), directions).numpy()))
        assert integral == pytest.approx(1.0, abs=0.01)


def test_pdf_is_never_below_the_defensive_share_of_the_environments(sun_pyramid):
    """Even a lane whose own normal is off its bin's, or faces away from every light,
    reaches every lit direction: q >= e p_env."""
    table = CosineTable(sun_pyramid, SHARE)
    environment = ProductWarp(sun_pyramid, defensive_share=1.0)
    count = 1 << 14
    normals = random_normals(count, seed=3)
    d = mi.warp.square_to_uniform_sphere(uniform_samples(count, seed=4))
    pdf_env = environment.pdf([mi.Float(1.0)] + [mi.Float(0.0)] * 3, d).numpy()
    pdf = table.pdf(normals, d).numpy()
    assert np.all(pdf >= SHARE * pdf_env * (1.0 - 1e-4))


def test_tables_are_the_cosine_weighted_environment_mixed_with_the_environment():
    """At the table's finest level W = (1 - e) T / sum T + e E / sum E, T the sum over the four
    finer cells of their integral times the cosine at their centre; 0 where the map is dark."""
    rng = np.random.default_rng(5)
    n_cells, fine = 1 << TABLE_DEPTH, 2 << TABLE_DEPTH
    env = rng.random((fine, fine)) * (rng.random((fine, fine)) > 0.3)
    env[:2] = 0.0  # a dark band: both finer rows of the cells there
    table = mixture_tables(env, np.array([[0.0, 0.0, 1.0]]), SHARE)[0]
    z = -1.0 + (np.arange(fine) + 0.5) * (2.0 / fine)
    lit = (env * np.maximum(z, 0.0)[:, None]).reshape(n_cells, 2, n_cells, 2).sum(axis=(1, 3))
    coarse = env.reshape(n_cells, 2, n_cells, 2).sum(axis=(1, 3))
    assert np.allclose(table, (1 - SHARE) * lit / lit.sum() + SHARE * coarse / coarse.sum())
    assert table.sum() == pytest.approx(1.0)
    assert np.all(table[0] == 0)


def test_a_cell_astride_the_horizon_keeps_product_weight():
    """A horizontal normal whose horizon runs through the centres of one column of level-6
    cells (cosine 0 there): those cells keep the product weight of their lit halves."""
    n_cells, fine = 1 << TABLE_DEPTH, 2 << TABLE_DEPTH
    column = n_cells // 3
    horizon = 2.0 * math.pi * (column + 0.5) / n_cells
    normal = np.array([[math.cos(horizon - math.pi / 2), math.sin(horizon - math.pi / 2), 0.0]])
    table = mixture_tables(np.ones((fine, fine)), normal, SHARE)[0]
    environment_alone = SHARE / n_cells**2
    middle = slice(n_cells // 4, 3 * n_cells // 4)  # |z| < 1/2, away from the poles
    assert np.all(table[middle, column] > 1.2 * environment_alone)  # at its centre alone: exactly 1x


def test_the_world_axes_are_bin_centres_and_every_centre_is_in_its_own_bin():
    centres = bin_normals()
    assert len(centres) == 6 * NORMAL_BINS**2
    bins = normal_bin(mi.Vector3f(*(mi.Float(c.astype(np.float32)) for c in centres.T))).numpy()
    assert np.array_equal(bins, np.arange(len(centres)))
    for axis in np.vstack([np.eye(3), -np.eye(3)]):
        index = int(normal_bin(mi.Vector3f(*axis.tolist())).numpy()[0])
        assert np.allclose(centres[index], axis)


def test_nearby_normals_share_a_bin_within_its_angular_radius():
    normals = random_normals(1 << 14, seed=6)
    bins = normal_bin(normals).numpy()
    n = np.stack([c.numpy() for c in (normals.x, normals.y, normals.z)], axis=1)
    angle = np.degrees(np.arccos(np.clip(np.sum(n * bin_normals()[bins], axis=1), -1, 1)))
    assert angle.max() < 10.0


def test_the_product_warp_samples_diffuse_lanes_from_the_table_and_the_others_by_their_walk(sun_pyramid):
    """Mixed lanes: pdf(sample) is the returned pdf in each, and a diffuse lane's density is
    the table's (the SH coefficients of those lanes are not even read)."""
    warp = ProductWarp(sun_pyramid, cosine_tables=True)
    count = 1 << 14
    normals = random_normals(count, seed=7)
    cosine_only = mi.Bool(np.arange(count) % 2 == 0)
    proxy = ProxyLobe(normals, mi.Float(1.0), normals, mi.Float(0.0), mi.Float(1.0), cosine_only)
    coeffs = [dr.select(cosine_only, dr.nan, mi.Float(1.0))] + [mi.Float(0.0)] * 3
    d, pdf = warp.sample(coeffs, uniform_samples(count), proxy)
    again = warp.pdf(coeffs, d, proxy).numpy()
    table = warp.cosine_table.pdf(normals, d).numpy()
    pdf, even = pdf.numpy(), np.arange(count) % 2 == 0
    assert np.all(np.isfinite(pdf)) and np.all(pdf > 0)
    assert np.max(np.abs(again - pdf) / pdf) <= 1e-3
    assert np.allclose(pdf[even], table[even], rtol=1e-3)
    assert not np.allclose(pdf[~even], table[~even], rtol=1e-2)


def test_a_pyramid_too_shallow_for_the_tables_keeps_every_lane_on_its_walk():
    shallow = EnvPyramid.from_latlong(sun_sky_latlong(16, 32), max_depth=TABLE_DEPTH - 1)
    assert ProductWarp(shallow, cosine_tables=True).cosine_table is None
    with pytest.raises(ValueError, match="levels deep"):
        CosineTable(shallow, SHARE)


# ------------------------------------------------------------- which lobes are cosines

COSINE_LOBES = {
    "diffuse": {"type": "diffuse"},
    "twosided_diffuse": {"type": "twosided", "bsdf": {"type": "diffuse"}},
    "blend_of_diffuse": {"type": "blendbsdf", "weight": 0.3, "bsdf_0": {"type": "diffuse"},
                         "bsdf_1": {"type": "diffuse", "reflectance": 0.2}},
    "bumpmapped_diffuse": {"type": "bumpmap", "arbitrary": {"type": "checkerboard"}, "bsdf": {"type": "diffuse"}},
}
OTHER_LOBES = {
    "roughplastic": {"type": "roughplastic"},
    "roughconductor": {"type": "roughconductor", "alpha": 0.3},
    "principled": {"type": "principled"},
    "blend_diffuse_conductor": {"type": "blendbsdf", "weight": 0.3, "bsdf_0": {"type": "diffuse"},
                                "bsdf_1": {"type": "roughconductor"}},
    "dielectric": {"type": "dielectric"},
}


@pytest.mark.parametrize("name", sorted(COSINE_LOBES))
def test_diffuse_bsdfs_and_their_wrappers_have_a_cosine_lobe(name):
    assert is_cosine_lobe(mi.load_dict(COSINE_LOBES[name]))


@pytest.mark.parametrize("name", sorted(OTHER_LOBES))
def test_glossy_and_transmissive_bsdfs_have_no_cosine_lobe(name):
    assert not is_cosine_lobe(mi.load_dict(OTHER_LOBES[name]))


def test_lanes_of_a_diffuse_material_are_marked_and_get_no_sh_coefficients():
    scene = mi.load_dict({
        "type": "scene",
        "floor": {"type": "rectangle", "bsdf": {"type": "diffuse"}},
        "ball": {"type": "sphere", "center": [0, 0, 2], "radius": 0.5,
                 "bsdf": {"type": "roughconductor", "alpha": 0.2}}})
    lobes = SceneLobes(scene)
    assert lobes.has_cosine_lobes
    # Rays straight down from above the floor's edge (floor) and onto the ball (ball).
    origins = mi.Point3f(mi.Float([0.9, 0.0]), mi.Float([0.0, 0.0]), mi.Float([5.0, 5.0]))
    si = scene.ray_intersect(mi.Ray3f(origins, mi.Vector3f(0, 0, -1)))
    coeffs, proxy, use_product = lobes.coefficients_and_proxy(si, lambda v: v, True, cosine_tables=True)
    assert use_product.numpy().tolist() == [True, True]
    assert proxy.cosine_only.numpy().tolist() == [True, False]
    f00 = coeffs.coefficients(1)[0].numpy()
    assert float(abs(f00[0])) == 0.0 and float(f00[1]) > 0.0
    _, without, _ = lobes.coefficients_and_proxy(si, lambda v: v, True)
    assert without.cosine_only is False or not np.any(without.cosine_only.numpy())


# ------------------------------------------------------------------ in the integrators

@pytest.mark.parametrize("strategy", ["product", "product_only"])
def test_where_every_product_lane_is_diffuse_no_sh_code_is_traced_and_renders_stay_unbiased(strategy):
    """A diffuse sphere on a diffuse plane, the product forced: the lanes' lobes are the
    constant cosine_only, with no SH coefficients, and sh_direct matches path."""
    from mitsuba_shsampling.integrators import register
    from test_integrators import MATERIALS, assert_unbiased, make_scene

    register()
    scene = make_scene(materials={"diffuse": MATERIALS["diffuse"]})
    integrator = mi.load_dict({"type": "sh_direct", "strategy": strategy})
    env = integrator.scenes.get(scene)
    si = scene.ray_intersect(scene.sensors()[0].sample_ray(0.0, 0.5, mi.Point2f(0.5, 0.5), mi.Point2f(0.5))[0])
    lobe, use_product = env.lobe(si, True)
    assert bool(use_product.numpy()[0]) and lobe.proxy.cosine_only is True and lobe.coeffs == []
    assert_unbiased(scene, integrator, mi.load_dict({"type": "path", "max_depth": 2}))


def test_a_scene_of_diffuse_and_glossy_product_lanes_is_unbiased():
    """The tables' lanes and the SH walk's lanes in one kernel (both strategies forced in turn)."""
    from mitsuba_shsampling.integrators import register
    from test_integrators import MATERIALS, assert_unbiased, make_scene

    register()
    scene = make_scene(materials={k: MATERIALS[k] for k in ("diffuse", "ggx", "blend")})
    for strategy in ("product", "product_only"):
        integrator = mi.load_dict({"type": "sh_direct", "strategy": strategy})
        assert integrator.scenes.get(scene).cosine_tables
        assert_unbiased(scene, integrator, mi.load_dict({"type": "path", "max_depth": 2}))


def test_each_diffuse_material_takes_the_tables_unless_its_sh_walk_is_predicted_less_noisy():
    """The quadrature with and without the tables, per material: the tables unless the SH walk's
    best product strategy has less variance (visibility can favour the looser walk)."""
    from mitsuba_shsampling.integrators.chooser import choose_cosine_sampling
    from mitsuba_shsampling.integrators.environment import ProductEnvironment
    from mitsuba_shsampling.integrators.options import DirectOptions
    from mitsuba_shsampling.integrators.strategy import Strategy
    from mitsuba_shsampling.scene_materials import registry_id

    scene = mi.load_dict({
        "type": "scene", "env": {"type": "envmap", "filename": REAL_MAP},
        "wall": {"type": "rectangle", "bsdf": {"type": "diffuse"}},
        "floor": {"type": "disk", "bsdf": {"type": "diffuse", "reflectance": 0.3}},
        "ball": {"type": "sphere", "bsdf": {"type": "roughconductor"}}})
    env = ProductEnvironment(scene, DirectOptions(), carry_all=True)
    ids = {shape.id(): registry_id(shape.bsdf()) for shape in scene.shapes()}
    wall, floor = ids["wall"], ids["floor"]
    assert env.lobes.tabled_ids == env.lobes.cosine_ids == {wall, floor}
    keys = np.array([wall, wall, floor, floor])
    tabled = np.full((4, len(Strategy)), 1.0)
    walked = tabled.copy()
    walked[keys == floor, Strategy.PRODUCT_ONLY] = 0.5  # the floor's SH walk is predicted better
    tabled[keys == wall, Strategy.PRODUCT] = 0.6        # the wall's tables are
    variances = choose_cosine_sampling(env, tabled, walked, keys)
    assert env.lobes.tabled_ids == {wall}
    assert np.array_equal(variances[keys == floor], walked[keys == floor])
    assert np.array_equal(variances[keys == wall], tabled[keys == wall])
    assert env.samples_from_cosine_table(wall) and not env.samples_from_cosine_table(floor)


def test_where_no_diffuse_material_runs_a_product_no_table_code_is_traced():
    """A glossy sphere on the product, the diffuse plane on the environment: the lanes' lobes
    say cosine_only False as a constant, so the product warp traces its SH walk alone."""
    from mitsuba_shsampling.integrators import register
    from mitsuba_shsampling.integrators.strategy import Strategy
    from test_integrators import MATERIALS, make_scene

    register()
    scene = make_scene(materials={"ggx": MATERIALS["ggx"]})
    env = mi.load_dict({"type": "sh_direct", "strategy": "product"}).scenes.get(scene)
    assert env.cosine_tables
    env.strategies.assign({key: Strategy.ENVIRONMENT if key in env.lobes.cosine_ids else Strategy.PRODUCT
                           for key in env.strategies.ids})
    si = scene.ray_intersect(scene.sensors()[0].sample_ray(0.0, 0.5, mi.Point2f(0.5, 0.5), mi.Point2f(0.5))[0])
    lobe, _ = env.lobe(si, True)
    assert lobe.proxy.cosine_only is False and len(lobe.coeffs.coefficients()) > 0
