"""Specification of the coverage invariant of the SH integrators.

In every lane, the strategies that run cover every direction where
BSDF x radiance > 0: the product strategy's pdf is positive wherever the map
is lit, and lanes without a product lobe (frame-perturbing wrappers, unfitted
BSDFs) are covered by Mitsuba's own emitter sampling. Checked here by Monte
Carlo quadrature of the direct-lighting integrand at thousands of random
shading points under a map with a small, very bright sun, on every BSDF a
user can write (wrappers included), and end to end: product-only sampling is
unbiased, and the brightest pixel over many samples is that of Mitsuba's
``direct``, not a firefly.
"""

import warnings

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

mi.set_variant("llvm_ad_rgb")

from mitsuba_shsampling.envmap.synthetic import envmap_emitter, sun_sky_latlong  # noqa: E402
from mitsuba_shsampling.integrators import register  # noqa: E402
from mitsuba_shsampling.integrators.environment import ProductEnvironment  # noqa: E402
from mitsuba_shsampling.integrators.options import ProductOptions  # noqa: E402
from mitsuba_shsampling.scenes import load_scene, unit_scene_path  # noqa: E402

from test_integrators import assert_unbiased, make_scene, MATERIALS  # noqa: E402


@pytest.fixture(scope="module", autouse=True)
def registered():
    register()


def bump_texture(size=64):
    """A smooth height field / normal map with strong slopes (tangent-space normals in [0,1])."""
    y, x = np.mgrid[0:size, 0:size] / size
    height = 0.5 + 0.5 * np.sin(6 * np.pi * x) * np.cos(4 * np.pi * y)
    nx, ny = 0.6 * np.cos(6 * np.pi * x), 0.6 * np.sin(4 * np.pi * y)
    normal = np.stack([nx, ny, np.ones_like(nx)], axis=-1)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    return (mi.Bitmap(height[..., None].astype(np.float32)),
            mi.Bitmap((0.5 * normal + 0.5).astype(np.float32)))


HEIGHT, NORMALS = bump_texture()

BSDFS = {
    "ggx_0.05": {"type": "roughconductor", "distribution": "ggx", "alpha": 0.05},
    "ggx_0.1": {"type": "roughconductor", "distribution": "ggx", "alpha": 0.1},
    "ggx_0.2": {"type": "roughconductor", "distribution": "ggx", "alpha": 0.2},
    "ggx_0.5": {"type": "roughconductor", "distribution": "ggx", "alpha": 0.5},
    "beckmann_0.3": {"type": "roughconductor", "distribution": "beckmann", "alpha": 0.3},
    "roughplastic": {"type": "roughplastic", "distribution": "ggx", "alpha": 0.1},
    "principled": {"type": "principled", "roughness": 0.3, "metallic": 0.7},
    "diffuse": {"type": "diffuse"},
    "blendbsdf": {"type": "blendbsdf", "weight": 0.3, "bsdf_0": {"type": "diffuse"},
                  "bsdf_1": {"type": "roughconductor", "alpha": 0.08}},
    "twosided": {"type": "twosided", "bsdf": {"type": "roughconductor", "alpha": 0.12}},
    "anisotropic": {"type": "roughconductor", "distribution": "ggx", "alpha_u": 0.05, "alpha_v": 0.3},
    "roughdielectric": {"type": "roughdielectric", "distribution": "ggx", "alpha": 0.2},
    "bumpmap": {"type": "bumpmap", "scale": 0.5,
                "arbitrary": {"type": "bitmap", "bitmap": HEIGHT, "raw": True},
                "bsdf": {"type": "roughconductor", "alpha": 0.1}},
    "normalmap": {"type": "normalmap",
                  "normalmap": {"type": "bitmap", "bitmap": NORMALS, "raw": True},
                  "bsdf": {"type": "roughconductor", "alpha": 0.1}},
}


def hard_sun_emitter():
    """A 0.5-degree sun 1e5 times brighter than the sky, under a tilted to_world."""
    image = sun_sky_latlong(256, 512, sun_direction=(0.5, 0.4, -0.6), sun_radius_deg=0.5,
                            sun_radiance=1e5)
    to_world = mi.ScalarTransform4f().rotate(list(np.array([0.2, 1.0, 0.3]) / np.linalg.norm([0.2, 1.0, 0.3])), 25.0)
    return envmap_emitter(image, to_world=to_world)


def luminance(spectrum) -> mi.Float:
    return mi.luminance(spectrum) if dr.size_v(spectrum) == 3 else spectrum[0]


def uncovered_share(bsdf: dict, points: int = 4096, seed: int = 0,
                    product_only_lanes: bool = False) -> tuple[float, float]:
    """Share of the integral of BSDF x radiance (luminance, no visibility) over
    random shading points of a sphere that falls where the environment strategy
    of the lane (the product's pdf, or the environment alone's where the BSDF has
    no product lobe) is 0. Returns (share, fraction of lanes with a product lobe).
    With ``product_only_lanes``, the scene's pyramid is MIS-compensated and only
    the lanes that give every sample to the product (no BSDF sample) count:
    their strategy, the uncompensated product, must cover everything alone.

    The integral is estimated with one environment sample and one BSDF sample
    per point, balance-weighted: every direction where the integrand is > 0 is
    reachable by one of the two (BSDF sampling covers the BSDF's support).
    """
    scene = mi.load_dict({"type": "scene", "env": hard_sun_emitter(),
                          "ball": {"type": "sphere", "radius": 1.0, "bsdf": bsdf}})
    # Every scene BSDF goes through the same classification as in the integrators.
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        env = ProductEnvironment(scene, ProductOptions(max_bands=8, sh_depth=3,
                                                       mis_compensation=product_only_lanes),
                                 plain_product=product_only_lanes)
    emitter = scene.environment()
    rng = np.random.default_rng(seed)
    # Rays towards the sphere from random directions: shading points all over it,
    # viewed at every elevation.
    origin = rng.normal(size=(points, 3))
    origin = 4.0 * origin / np.linalg.norm(origin, axis=1, keepdims=True)
    target = rng.uniform(-0.9, 0.9, size=(points, 3))
    ray = mi.Ray3f(mi.Point3f(origin.T.astype(np.float32)),
                   mi.Vector3f(dr.normalize(mi.Vector3f((target - origin).T.astype(np.float32)))))
    si = scene.ray_intersect(ray)
    hit = si.is_valid()
    bsdf_ptr = si.bsdf(ray)
    ctx = mi.BSDFContext()
    smooth = hit & mi.has_flag(bsdf_ptr.flags(), mi.BSDFFlags.Smooth)
    lobe, use_product = env.lobe(si, smooth)
    if product_only_lanes:
        all_hits = hit.numpy().copy()
        hit &= env.product_carries_all(si, bsdf_ptr, use_product)
        use_product &= hit
        product_only_fraction = float(np.mean(np.broadcast_to(hit.numpy(), (points,))[all_hits]))
    sampler = rng.random((5, points)).astype(np.float32)

    def covering_pdf(d):
        assert env.active and not env.needs_emitter_sampling  # the environment is this package's alone
        if product_only_lanes:
            return dr.select(use_product, env.warp_plain.pdf(lobe.coeffs, d, lobe.proxy), 0.0)
        return env.pdf(lobe, use_product, d, smooth)

    def integrand_and_pdfs(d):
        wo = si.to_local(d)
        f = luminance(bsdf_ptr.eval(ctx, si, wo, hit))
        target = dr.zeros(mi.SurfaceInteraction3f)
        target.wi = -d
        radiance = luminance(emitter.eval(target, hit))
        ds = mi.DirectionSample3f(scene, dr.zeros(mi.SurfaceInteraction3f), si)
        ds.d = d
        return f * radiance, emitter.pdf_direction(si, ds, hit), bsdf_ptr.pdf(ctx, si, wo, hit)

    ds, _ = emitter.sample_direction(si, mi.Point2f(sampler[0], sampler[1]), hit)
    bs, _ = bsdf_ptr.sample(ctx, si, mi.Float(sampler[2]), mi.Point2f(sampler[3], sampler[4]), hit)
    total, hole = 0.0, 0.0
    for d, ok in ((ds.d, hit & (ds.pdf > 0)), (si.to_world(bs.wo), hit & (bs.pdf > 0))):
        g, p_env, p_bsdf = integrand_and_pdfs(d)
        weight = dr.select(ok & (g > 0), g / (p_env + p_bsdf), 0.0).numpy().astype(np.float64)
        uncovered = (covering_pdf(d).numpy() <= 0) | ~np.isfinite(covering_pdf(d).numpy())
        total += weight.sum()
        hole += weight[uncovered].sum()
    assert total > 0, "the test's quadrature found no light"
    if product_only_lanes:
        return hole / total, product_only_fraction
    lanes = np.broadcast_to(use_product.numpy(), (points,))
    return hole / total, float(np.mean(lanes[hit.numpy()]))


#: BSDFs without a product lobe: their lanes sample the environment alone.
NO_PRODUCT_LOBE = ("bumpmap", "normalmap", "anisotropic", "roughdielectric")


@pytest.mark.parametrize("name", list(BSDFS))
def test_no_lit_direction_is_left_to_bsdf_sampling_alone(name):
    share, product_lanes = uncovered_share(BSDFS[name])
    assert share < 1e-6, f"{name}: {share:.2e} of BSDF x radiance falls where the environment strategy has pdf 0"
    if name in NO_PRODUCT_LOBE:
        assert product_lanes == 0.0  # covered by the environment alone instead
    else:
        assert product_lanes > 0.5


@pytest.mark.parametrize("name", ["diffuse", "ggx_0.5", "beckmann_0.3"])
def test_lanes_without_a_bsdf_sample_are_covered_by_the_uncompensated_product(name):
    share, product_only = uncovered_share(BSDFS[name], product_only_lanes=True)
    assert product_only > 0.5, "the check needs product-only lanes"
    assert share < 1e-6


def test_rough_lobes_give_every_sample_to_the_product_and_sharp_ones_do_not():
    def product_only_fraction(bsdf):
        scene = mi.load_dict({"type": "scene", "env": hard_sun_emitter(),
                              "ball": {"type": "sphere", "bsdf": bsdf}})
        env = ProductEnvironment(scene, ProductOptions(max_bands=8, sh_depth=3), plain_product=True)
        ray = mi.Ray3f(mi.Point3f(0, 0, 4), mi.Vector3f(0, 0, -1))
        si = scene.ray_intersect(ray)
        bsdf_ptr = si.bsdf(ray)
        _, use_product = env.lobe(si, si.is_valid())
        return bool(env.product_carries_all(si, bsdf_ptr, use_product)[0])
    assert product_only_fraction(BSDFS["diffuse"])
    assert not product_only_fraction(BSDFS["ggx_0.05"])
    assert not product_only_fraction({"type": "blendbsdf", "weight": 0.5, "bsdf_0": {"type": "diffuse"},
                                      "bsdf_1": {"type": "conductor"}})  # a Dirac part needs BSDF samples


def test_no_lane_goes_product_only_unless_the_uncompensated_product_was_built():
    scene = mi.load_dict({"type": "scene", "env": hard_sun_emitter(),
                          "ball": {"type": "sphere", "bsdf": BSDFS["diffuse"]}})
    env = ProductEnvironment(scene, ProductOptions(max_bands=8, sh_depth=3, mis_compensation=True))
    assert env.warp_plain is None
    si = scene.ray_intersect(mi.Ray3f(mi.Point3f(0, 0, 4), mi.Vector3f(0, 0, -1)))
    _, use_product = env.lobe(si, si.is_valid())
    assert env.product_carries_all(si, si.bsdf(), use_product) is False


def test_frame_perturbing_wrappers_fall_back_to_the_environment_alone_with_a_warning():
    scene = mi.load_dict({"type": "scene", "env": hard_sun_emitter(),
                          "ball": {"type": "sphere", "bsdf": BSDFS["bumpmap"]},
                          "floor": {"type": "rectangle", "bsdf": {"type": "diffuse"}}})
    with pytest.warns(UserWarning, match="perturbs the shading frame"):
        env = ProductEnvironment(scene, ProductOptions(max_bands=8, sh_depth=3))
    assert env.active and env.env_warp is not None
    # The environment is sampled by this package in every lane; Mitsuba's emitter
    # sampling has nothing left to do in a scene without other emitters.
    assert not env.needs_emitter_sampling


# ------------------------------------------------------------ end to end

WRAPPED = {"bumpmap": BSDFS["bumpmap"], "normalmap": BSDFS["normalmap"], "ggx": MATERIALS["ggx"],
           "anisotropic": BSDFS["anisotropic"], "roughdielectric": BSDFS["roughdielectric"]}


@pytest.mark.parametrize("integrator", [
    {"type": "sh_direct", "max_bands": 5},
    {"type": "sh_path", "max_bands": 5, "max_depth": 3},
])
def test_bsdfs_without_a_product_lobe_are_unbiased_with_the_environment_alone(integrator):
    """bumpmap, normalmap, anisotropic and transmissive lobes beside a product-sampled GGX."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        scene = make_scene(materials=WRAPPED)
        sh = mi.load_dict(integrator)
        sh.scenes.get(scene)
    depth = integrator.get("max_depth", 2)
    assert_unbiased(scene, sh, mi.load_dict({"type": "path", "max_depth": depth}))


def test_product_only_sampling_is_unbiased_on_a_hard_sun_map():
    with pytest.warns(UserWarning, match="mis_compensation' is switched off"):
        sh = mi.load_dict({"type": "sh_direct", "max_bands": 5, "emitter_samples": 2, "bsdf_samples": 0})
    scene = make_scene(materials={k: MATERIALS[k] for k in ("ggx", "diffuse", "roughplastic", "blend")})
    assert_unbiased(scene, sh, mi.load_dict({"type": "path", "max_depth": 2}))


def test_product_only_sampling_is_unbiased_on_the_glossy_unit_scene():
    with pytest.warns(UserWarning, match="mis_compensation' is switched off"):
        sh = mi.load_dict({"type": "sh_direct", "emitter_samples": 2, "bsdf_samples": 0})
    scene = load_scene(unit_scene_path(), res=24)
    assert_unbiased(scene, sh, mi.load_dict({"type": "path", "max_depth": 2}))


def test_brightest_pixel_over_ten_million_samples_is_no_firefly():
    """Same seeds, 1024 x 1024 x 10 spp = 10.5 M camera samples per method."""
    scene = load_scene(unit_scene_path(), res=1024)
    brightest = {}
    for name in ("direct", "sh_direct"):
        image = mi.render(scene, integrator=mi.load_dict({"type": name}), spp=10, seed=7).numpy()
        assert np.all(np.isfinite(image))
        brightest[name] = float(np.max(np.tensordot(image, [0.2126, 0.7152, 0.0722], axes=([2], [0]))))
    assert brightest["sh_direct"] <= 3.0 * brightest["direct"], brightest


def test_giving_every_sample_to_the_product_where_the_lobe_allows_is_unbiased():
    """product_allocation: rough and diffuse lanes draw only product samples."""
    scene = make_scene(materials={k: MATERIALS[k] for k in ("ggx", "diffuse", "blend", "beckmann")},
                       area_light=True)
    sh = mi.load_dict({"type": "sh_direct", "max_bands": 5, "product_allocation": True})
    assert_unbiased(scene, sh, mi.load_dict({"type": "path", "max_depth": 2}))
