"""``product_only`` gives the BSDF a share b of its samples (its BSDF samples' slots draw
from the BSDF or the product, and every sample gets the balance weight over the slots):
those slots' samples follow their pdf, the renders are unbiased, and the brightest pixel
stays near ``direct``'s.

Without a BSDF sample in the lane, the product alone covered a lit direction only by
the lobe proxy and the environment's defensive share; where the proxy misses part of
the BSDF (a rough coating's grazing peak), a sample there was worth BSDF / (share x
environment pdf): the rough plastic sphere under potsdamer_platz had a brightest pixel
6.6x ``direct``'s over 4 M samples. The BSDF share ``bsdf_defensive_share`` bounds
those samples by the BSDF sample's weight x radiance / b.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

mi.set_variant("llvm_ad_rgb")

from mitsuba import chi2  # noqa: E402
from leaf_chi2 import LeafAlignedChiSquareTest  # noqa: E402
from test_integrators import MATERIALS, assert_unbiased, make_scene  # noqa: E402

from mitsuba_shsampling.integrators import register  # noqa: E402
from mitsuba_shsampling.integrators.environment import BSDFDraw  # noqa: E402
from mitsuba_shsampling.integrators.strategy import Strategy  # noqa: E402
from mitsuba_shsampling.scenes import builtin_scenes, load_scene  # noqa: E402

from conftest import ENVMAPS_DIR  # noqa: E402
from test_plan import forget_shared  # noqa: E402

register()

COATED = {"type": "roughplastic", "distribution": "ggx", "alpha": 0.1,
          "diffuse_reflectance": {"type": "rgb", "value": [0.08, 0.2, 0.55]}}


@pytest.fixture(scope="module")
def coated_sphere():
    """The coated sphere under the sun map, on ``product_only``, and a shading point seen
    at a grazing angle (where the coating's peak is sharpest)."""
    scene = make_scene(materials={"coated": COATED})
    integrator = mi.load_dict({"type": "sh_direct", "strategy": "product_only"})
    env = integrator.scenes.get(scene)
    # The ray passes the sphere (centre (-1.35, -0.45, 0), radius 0.4) near its rim.
    ray = mi.Ray3f(mi.Point3f(-1.35 + 0.36, -4.0, 0.05), mi.Vector3f(0.0, 1.0, 0.0))
    si = scene.ray_intersect(ray)
    assert si.is_valid()[0] and abs(si.wi.z[0]) < 0.5
    return scene, env, si, si.bsdf(ray)


def test_only_sh_walked_lobes_on_product_only_trace_the_mixture(coated_sphere):
    _, env, _, _ = coated_sphere
    assert env.bsdf_share == pytest.approx(0.1)
    assert all(env.strategies.of(key) == Strategy.PRODUCT_ONLY for key in env.strategies.ids
               if env.material_name(key) == "coated")
    assert env.draws_bsdf


def test_a_bsdf_samples_slot_draws_from_the_bsdf_so_that_it_has_its_share_of_the_lanes_samples(coated_sphere):
    _, env, _, _ = coated_sphere
    assert env.carried_slots(0.5, 0.5).bsdf_in_slot == pytest.approx(0.2)
    assert env.carried_slots(0.75, 0.25).bsdf_in_slot == pytest.approx(0.4)
    assert env.carried_slots(0.95, 0.05).bsdf_in_slot == 1.0  # all it can


def test_chi2_a_bsdf_samples_slot_follows_its_pdf(coated_sphere):
    """The slot draws from (1 - t) product + t BSDF."""
    _, env, si, bsdf = coated_sphere
    pyramid, share, ctx = env.pyramid, env.carried_slots(0.5, 0.5).bsdf_in_slot, mi.BSDFContext()

    def point(width: int):
        """The shading point in ``width`` lanes, with its lobe."""
        lanes = dr.zeros(mi.UInt32, width)
        si_n, bsdf_n = dr.gather(mi.SurfaceInteraction3f, si, lanes), dr.gather(mi.BSDFPtr, bsdf, lanes)
        lobe, use_product = env.lobe(si_n, mi.Bool(True))
        assert dr.all(use_product)
        return si_n, bsdf_n, lobe, use_product

    def sample(u):
        si_n, bsdf_n, lobe, use_product = point(dr.width(u))
        draw = BSDFDraw(si_n, bsdf_n, ctx, u.x, share)
        d, pdf = env.sample_environment(lobe, mi.Point2f(u.y, u.z), use_product, True, draw)
        # A failed BSDF draw (below the horizon) returns pdf 0: the mixture's density
        # then integrates to less than 1, as the estimator counts it.
        return pyramid.grid_from_world(d), dr.select(pdf > 0, 1.0, 0.0)

    def pdf(d_grid):
        si_n, bsdf_n, lobe, _ = point(dr.width(d_grid))
        d = pyramid.world_from_grid(d_grid)
        product = env.warp_plain.pdf(lobe.coeffs, d, lobe.proxy)
        return (1.0 - share) * product + share * bsdf_n.pdf(ctx, si_n, si_n.to_local(d))

    test = LeafAlignedChiSquareTest(domain=chi2.SphericalDomain(), sample_func=sample, pdf_func=pdf,
                                    sample_dim=3, sample_count=1_000_000, res=2 << env.warp_plain.depth, seed=4)
    assert test.run(0.01), test.messages


@pytest.mark.parametrize("emitter_selection, sun_light", [("each", False), ("one", False), ("one", True)])
def test_product_only_with_its_bsdf_share_is_unbiased(emitter_selection, sun_light):
    """With ``one``, an emitter sample draws the environment with its selection probability
    (1/2 beside the area light; 2/7 with a sun and the light weighted 0.5 and 2), which enters the
    balance over the slots."""
    materials = {"coated": COATED, **{k: MATERIALS[k] for k in ("ggx", "principled", "blend", "diffuse")}}
    scene = make_scene(materials=materials, area_light=True, sun_light=sun_light)
    sh = mi.load_dict({"type": "sh_direct", "max_bands": 5, "strategy": "product_only",
                       "emitter_selection": emitter_selection})
    assert_unbiased(scene, sh, mi.load_dict({"type": "path", "max_depth": 2}))


def brightest_pixel(scene, integrator, passes: int) -> float:
    """The brightest pixel (luminance) over ``passes`` passes at fixed seeds."""
    brightest = 0.0
    for seed in range(passes):
        image = mi.render(scene, integrator=integrator, seed=seed).numpy()
        assert np.all(np.isfinite(image))
        brightest = max(brightest, float(np.max(image @ np.array([0.2126, 0.7152, 0.0722]))))
    return brightest


def test_the_coated_sphere_under_a_city_map_has_no_firefly_on_product_only():
    """The specification of the share (issue 46): 2 M samples, 3x ``direct``'s brightest
    pixel at most (the report's tail flag); without the share the same samples exceed it."""
    scene = load_scene(builtin_scenes()["sphere_roughplastic"], envmap=str(ENVMAPS_DIR / "potsdamer_platz_1k.hdr"),
                       res=256, spp=4)
    brightest = {name: brightest_pixel(scene, mi.load_dict(desc), passes=8) for name, desc in {
        "direct": {"type": "direct"},
        "product_only": {"type": "sh_direct", "strategy": "product_only"},
        "without the share": {"type": "sh_direct", "strategy": "product_only", "bsdf_defensive_share": 0.0},
    }.items()}
    assert brightest["product_only"] <= 3.0 * brightest["direct"], brightest
    assert brightest["without the share"] > 3.0 * brightest["direct"], brightest


def test_the_plan_gives_the_share_where_it_lowers_the_predicted_variance_and_a_plan_file_keeps_it(tmp_path):
    """The share costs a variance floor of about b / (1 - b) of the squared mean where the
    product alone is close to exact (a copper ball under a studio's softboxes: 1.8x the
    variance); the plan weighs it per material with the quadrature, which samples the
    BSDF's peak too. A forced ``product_only`` (no plan) shares everywhere."""
    scene = load_scene(builtin_scenes()["sphere_roughplastic"], envmap=str(ENVMAPS_DIR / "potsdamer_platz_1k.hdr"),
                       res=64, spp=4)
    plan_file = str(tmp_path / "plan.json")
    # The sphere on product_only (the plan weighs its share all the same), the ground planned.
    options = {"type": "sh_direct", "plan_file": plan_file, "strategy": "material=product_only"}
    planned = mi.load_dict(options)
    choice = planned.plan(scene)
    by_name = {m.name: m for m in choice.materials}
    assert choice.bsdf_shares == ["material"]  # the coated sphere; the diffuse ground's lobe is exact
    assert "material: product_only with the BSDF's share" in choice.summary()
    env = planned.scenes.get(scene)
    keys = {env.material_name(k): k for k in env.strategies.ids}
    assert env.bsdf_shared.of(keys["material"]) and not env.bsdf_shared.of(keys["ground"])
    assert by_name["material"].variance[Strategy.PRODUCT_ONLY] > 0

    forget_shared()  # a new process, as far as the plans are concerned
    loaded = mi.load_dict(options)
    assert loaded.plan(scene).mode == "file"
    env = loaded.scenes.get(scene)
    assert env.bsdf_shared.of(keys["material"]) and not env.bsdf_shared.of(keys["ground"])

    forced = mi.load_dict({"type": "sh_direct", "strategy": "product_only"}).scenes.get(scene)
    assert all(forced.bsdf_shared.of(k) for k in forced.strategies.ids)
