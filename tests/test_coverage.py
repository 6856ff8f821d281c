"""Specification of the coverage invariant of the SH integrators.

In every lane, the strategies that run cover every direction where
BSDF x radiance > 0: the product strategy's pdf is positive wherever the map
is lit, and lanes without a product lobe (transmissive or unfitted BSDFs) are
covered by Mitsuba's own emitter sampling. Frame-perturbing wrappers (``bumpmap``,
``normalmap``) are product-sampled with their nested BSDF's lobe about the
perturbed normal. Checked here by Monte
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
                    carrying_all: str | None = None) -> tuple[float, float]:
    """Share of the integral of BSDF x radiance (luminance, no visibility) over
    random shading points of a sphere that falls where the environment strategy
    of the lane (the product's pdf, or the environment alone's where the BSDF has
    no product lobe) is 0. Returns (share, fraction of lanes with a product lobe).
    With ``carrying_all`` (a strategy that carries every sample: "product_only",
    "environment_only" or "bsdf_only"), the scene's pyramid is MIS-compensated, that strategy is
    forced and only the lanes that run it (no BSDF sample) count: it must cover
    everything alone.

    The integral is estimated with one environment sample and one BSDF sample
    per point, balance-weighted: every direction where the integrand is > 0 is
    reachable by one of the two (BSDF sampling covers the BSDF's support).
    """
    scene = mi.load_dict({"type": "scene", "env": hard_sun_emitter(),
                          "ball": {"type": "sphere", "radius": 1.0, "bsdf": bsdf}})
    # Every scene BSDF goes through the same classification as in the integrators.
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        options = ProductOptions(max_bands=8, sh_depth=3, mis_compensation=carrying_all is not None,
                                 strategy=carrying_all or "product")
        env = ProductEnvironment(scene, options, carry_all=carrying_all is not None)
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
    if carrying_all:
        all_hits = hit.numpy().copy()
        hit &= env.carries_all(si, bsdf_ptr, smooth)
        use_product &= hit
        carrying_fraction = float(np.mean(np.broadcast_to(hit.numpy(), (points,))[all_hits]))
    sampler = rng.random((5, points)).astype(np.float32)

    def covering_pdf(d):
        assert env.active and not env.needs_emitter_sampling  # the environment is this package's alone
        if carrying_all == "product_only":
            return dr.select(use_product, env.warp_plain.pdf(lobe.coeffs, d, lobe.proxy), 0.0)
        if carrying_all == "environment_only":
            return dr.select(hit, env.env_plain.pdf(d), 0.0)
        if carrying_all == "bsdf_only":
            return dr.select(hit, bsdf_ptr.pdf(ctx, si, si.to_local(d), hit), 0.0)
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
    if carrying_all:
        return hole / total, carrying_fraction
    lanes = np.broadcast_to(use_product.numpy(), (points,))
    return hole / total, float(np.mean(lanes[hit.numpy()]))


#: BSDFs without a product lobe: their lanes sample the environment alone.
NO_PRODUCT_LOBE = ("roughdielectric",)


@pytest.mark.parametrize("name", list(BSDFS))
def test_no_lit_direction_is_left_to_bsdf_sampling_alone(name):
    share, product_lanes = uncovered_share(BSDFS[name])
    assert share < 1e-6, f"{name}: {share:.2e} of BSDF x radiance falls where the environment strategy has pdf 0"
    if name in NO_PRODUCT_LOBE:
        assert product_lanes == 0.0  # covered by the environment alone instead
    else:
        assert product_lanes > 0.5


@pytest.mark.parametrize("strategy", ["product_only", "environment_only", "bsdf_only"])
@pytest.mark.parametrize("name", ["diffuse", "ggx_0.05", "beckmann_0.3"])
def test_lanes_without_a_bsdf_sample_are_covered_by_their_uncompensated_strategy(name, strategy):
    share, carrying = uncovered_share(BSDFS[name], carrying_all=strategy)
    assert carrying > 0.5, "the check needs lanes that carry every sample"
    assert share < 1e-6


@pytest.mark.parametrize("name", ["diffuse", "ggx_0.05", "beckmann_0.3", "twosided"])
def test_a_bsdf_only_draw_returns_the_bsdfs_own_density_of_its_direction(name):
    """The pdf that bsdf_only's slot hands the estimator is the BSDF's pdf of the direction it drew
    (0 only where the BSDF's draw failed), so each sample weighs BSDF x radiance / that pdf."""
    from mitsuba_shsampling.integrators.environment import BSDFAlone

    scene = mi.load_dict({"type": "scene", "env": hard_sun_emitter(),
                          "ball": {"type": "sphere", "radius": 1.0, "bsdf": BSDFS[name]}})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        env = ProductEnvironment(scene, ProductOptions(max_bands=8, sh_depth=3, strategy="bsdf_only"), carry_all=True)
    rng = np.random.default_rng(1)
    origin = rng.normal(size=(2048, 3))
    origin = (4.0 * origin / np.linalg.norm(origin, axis=1, keepdims=True)).astype(np.float32)
    si = scene.ray_intersect(mi.Ray3f(mi.Point3f(origin.T), mi.Vector3f(dr.normalize(mi.Vector3f(-origin.T)))))
    bsdf, ctx = si.bsdf(), mi.BSDFContext()
    smooth = si.is_valid() & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
    lanes = env.bsdf_alone(si, smooth)
    u1, u2 = (mi.Float(rng.random(2048).astype(np.float32)) for _ in range(2))
    lobe, use_product = env.lobe(si, smooth)
    d, pdf = env.sample_environment(lobe, mi.Point2f(u1, u2), use_product, env.carries_all(si, bsdf, smooth),
                                    alone=BSDFAlone(si, bsdf, ctx, mi.Float(rng.random(2048).astype(np.float32)),
                                                    lanes))
    value, own = bsdf.eval_pdf(ctx, si, si.to_local(d), lanes)
    drawn = np.broadcast_to(lanes.numpy(), (2048,)) & (pdf.numpy() > 0)
    assert drawn.mean() > 0.9
    # A GGX draw can leave the hemisphere (a microfacet seen at grazing angles): the BSDF's pdf and
    # value are 0 there, so the sample is worth 0 whatever density it came with, as in Mitsuba's own.
    counted = drawn & (own.numpy() > 0)
    assert np.all(np.max(np.abs(value.numpy()), axis=0)[drawn & ~counted] == 0.0)
    assert counted.sum() > 0.99 * drawn.sum()
    assert np.allclose(pdf.numpy()[counted], own.numpy()[counted], rtol=1e-4)


def strategies_of(bsdf: dict, carry_all: bool = True, **options) -> list[str]:
    scene = mi.load_dict({"type": "scene", "env": hard_sun_emitter(), "ball": {"type": "sphere", "bsdf": bsdf}})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        env = ProductEnvironment(scene, ProductOptions(max_bands=8, sh_depth=3, **options), carry_all=carry_all)
    (key,) = env.strategies.ids
    return [s.label for s in env.allowed(key)]


def test_a_bsdf_with_a_dirac_part_always_keeps_its_bsdf_sample():
    assert strategies_of(BSDFS["diffuse"]) == ["environment", "environment_only", "bsdf_only", "product", "product_only"]
    blend = {"type": "blendbsdf", "weight": 0.5, "bsdf_0": {"type": "diffuse"}, "bsdf_1": {"type": "conductor"}}
    assert strategies_of(blend) == ["environment", "product"]
    assert strategies_of({"type": "plastic"}) == ["environment", "product"]


def test_only_integrators_that_may_skip_the_bsdf_sample_offer_strategies_without_it():
    assert strategies_of(BSDFS["diffuse"], carry_all=False) == ["environment", "product"]


def test_bsdfs_without_a_product_lobe_choose_between_the_environment_strategies_only():
    assert strategies_of(BSDFS["roughdielectric"]) == ["environment", "environment_only", "bsdf_only"]
    bumped_glass = {"type": "bumpmap", "arbitrary": {"type": "bitmap", "bitmap": HEIGHT, "raw": True},
                    "bsdf": BSDFS["roughdielectric"]}
    assert strategies_of(bumped_glass) == ["environment", "environment_only", "bsdf_only"]
    bumped_normal_map = {"type": "bumpmap", "arbitrary": {"type": "bitmap", "bitmap": HEIGHT, "raw": True},
                         "bsdf": BSDFS["normalmap"]}
    assert strategies_of(bumped_normal_map) == ["environment", "environment_only", "bsdf_only"]


@pytest.mark.parametrize("name", ["bumpmap", "normalmap"])
def test_frame_perturbing_wrappers_are_product_sampled_with_their_nested_lobe(name):
    assert strategies_of(BSDFS[name]) == ["environment", "environment_only", "bsdf_only", "product", "product_only"]


def test_anisotropic_lobes_are_product_sampled_with_an_isotropic_proxy():
    assert strategies_of(BSDFS["anisotropic"]) == ["environment", "environment_only", "bsdf_only", "product", "product_only"]


def test_forcing_the_environment_strategy_builds_no_product():
    scene = mi.load_dict({"type": "scene", "env": hard_sun_emitter(),
                          "ball": {"type": "sphere", "bsdf": BSDFS["ggx_0.1"]}})
    env = ProductEnvironment(scene, ProductOptions(strategy="environment"), carry_all=True)
    assert env.active and env.warp is None
    si = scene.ray_intersect(mi.Ray3f(mi.Point3f(0, 0, 4), mi.Vector3f(0, 0, -1)))
    lobe, use_product = env.lobe(si, si.is_valid())
    assert lobe is None and not np.any(np.array(use_product))


@pytest.mark.parametrize("wrapped", [False, True])
def test_transmissive_lobes_fall_back_to_the_environment_alone_with_a_warning(wrapped):
    bsdf = BSDFS["roughdielectric"]
    if wrapped:
        bsdf = {"type": "bumpmap", "arbitrary": {"type": "bitmap", "bitmap": HEIGHT, "raw": True}, "bsdf": bsdf}
    scene = mi.load_dict({"type": "scene", "env": hard_sun_emitter(),
                          "ball": {"type": "sphere", "bsdf": bsdf},
                          "floor": {"type": "rectangle", "bsdf": {"type": "diffuse"}}})
    with pytest.warns(UserWarning, match="its nested BSDF is transmissive" if wrapped else "it is transmissive"):
        env = ProductEnvironment(scene, ProductOptions(max_bands=8, sh_depth=3))
    assert env.active and env.env_directions is not None
    # The environment is sampled by this package in every lane; Mitsuba's emitter
    # sampling has nothing left to do in a scene without other emitters.
    assert not env.needs_emitter_sampling


# ------------------------------------------------------------ end to end

WRAPPED = {"bumpmap": BSDFS["bumpmap"], "normalmap": BSDFS["normalmap"], "ggx": MATERIALS["ggx"],
           "anisotropic": BSDFS["anisotropic"], "roughdielectric": BSDFS["roughdielectric"],
           # A cut-out: partly transmissive (null), so no product lobe; the environment alone.
           "mask": {"type": "mask", "opacity": 0.6, "bsdf": {"type": "roughconductor", "alpha": 0.15}}}


@pytest.mark.parametrize("integrator", [
    {"type": "sh_direct", "max_bands": 5},
    {"type": "sh_direct", "max_bands": 5, "strategy": "product"},
    {"type": "sh_direct", "max_bands": 5, "strategy": "product_only"},
    {"type": "sh_path", "max_bands": 5, "max_depth": 3, "strategy": "product"},
])
def test_wrapped_anisotropic_and_transmissive_lobes_are_unbiased(integrator):
    """bumpmap and normalmap (product-sampled about the perturbed normal), an
    anisotropic lobe (isotropic proxy), a transmissive one and a mask (the environment
    alone) beside a product-sampled GGX."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        scene = make_scene(materials=WRAPPED)
        sh = mi.load_dict(integrator)
        sh.scenes.get(scene)
    depth = integrator.get("max_depth", 2)
    assert_unbiased(scene, sh, mi.load_dict({"type": "path", "max_depth": depth}))


# The rest of Mitsuba's BSDF plugins a user can write without data files: smooth plastic and
# conductor (Dirac only: no environment sample), the polarised plastic (its RGB form), the
# thin principled BSDF and the thin dielectric (transmissive: the environment alone).
OTHER_BSDFS = {"pplastic": {"type": "pplastic", "alpha": 0.15}, "plastic": {"type": "plastic"},
               "conductor": {"type": "conductor"}, "principledthin": {"type": "principledthin", "roughness": 0.3},
               "thindielectric": {"type": "thindielectric"}, "ggx": MATERIALS["ggx"]}


@pytest.mark.parametrize("integrator", [{"type": "sh_direct", "max_bands": 5},
                                        {"type": "sh_path", "max_bands": 5, "max_depth": 3}])
def test_the_other_bsdf_plugins_are_unbiased(integrator):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        scene = make_scene(materials=OTHER_BSDFS)
    depth = integrator.get("max_depth", 2)
    assert_unbiased(scene, mi.load_dict(integrator), mi.load_dict({"type": "path", "max_depth": depth}))


def test_product_only_sampling_is_unbiased_on_a_hard_sun_map():
    with pytest.warns(UserWarning, match="mis_compensation' is switched off"):
        sh = mi.load_dict({"type": "sh_direct", "max_bands": 5, "emitter_samples": 2, "bsdf_samples": 0})
    scene = make_scene(materials={k: MATERIALS[k] for k in ("ggx", "diffuse", "roughplastic", "blend")})
    assert_unbiased(scene, sh, mi.load_dict({"type": "path", "max_depth": 2}))


def test_product_only_sampling_is_unbiased_on_the_glossy_unit_scene():
    with pytest.warns(UserWarning, match="mis_compensation' is switched off"):
        sh = mi.load_dict({"type": "sh_direct", "emitter_samples": 2, "bsdf_samples": 0})
    scene = load_scene(unit_scene_path(), res=24)
    # The ground, sampled from the plain map without a BSDF sample, is lit by a sky that
    # the sun starves of samples: 8 x 16 spp missed its tail in one block (z = -5.1;
    # at 16 x 64 spp it agrees within 0.6 standard errors).
    assert_unbiased(scene, sh, mi.load_dict({"type": "path", "max_depth": 2}), spp=64, passes=16)


def test_brightest_pixel_over_ten_million_samples_is_no_firefly():
    """Same seeds, 1024 x 1024 x 10 spp = 10.5 M camera samples per method."""
    scene = load_scene(unit_scene_path(), res=1024)
    brightest = {}
    for name in ("direct", "sh_direct"):
        image = mi.render(scene, integrator=mi.load_dict({"type": name}), spp=10, seed=7).numpy()
        assert np.all(np.isfinite(image))
        brightest[name] = float(np.max(np.tensordot(image, [0.2126, 0.7152, 0.0722], axes=([2], [0]))))
    assert brightest["sh_direct"] <= 3.0 * brightest["direct"], brightest


@pytest.mark.parametrize("strategy", ["environment", "environment_only", "bsdf_only", "product", "product_only"])
def test_every_forced_strategy_is_unbiased_beside_an_area_light(strategy):
    """Materials that cannot run the forced strategy (a Dirac part, no lobe) fall back."""
    scene = make_scene(materials={k: MATERIALS[k] for k in ("ggx", "diffuse", "blend", "smooth")},
                       area_light=True)
    sh = mi.load_dict({"type": "sh_direct", "max_bands": 5, "strategy": strategy})
    assert_unbiased(scene, sh, mi.load_dict({"type": "path", "max_depth": 2}))


def test_without_bsdf_samples_the_dirac_components_still_reflect_the_environment():
    """``bsdf_samples`` 0: the environment samples evaluate the smooth components only;
    glass, a plastic's coating and a mirror are reached by a sample of their Dirac
    components alone (Mitsuba's ``direct`` leaves them black)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        scene = make_scene(materials={"smooth": MATERIALS["smooth"], "plastic": {"type": "plastic"},
                                      "glass": {"type": "dielectric"}, "diffuse": MATERIALS["diffuse"],
                                      "blend": {"type": "blendbsdf", "weight": 0.5, "bsdf_0": {"type": "plastic"},
                                                "bsdf_1": {"type": "roughconductor", "alpha": 0.2}}})
    reference = mi.load_dict({"type": "path", "max_depth": 2})
    for strategy in ("product", "environment"):
        assert_unbiased(scene, mi.load_dict({"type": "sh_direct", "emitter_samples": 2, "bsdf_samples": 0,
                                             "mis_compensation": False, "strategy": strategy, "max_bands": 5}),
                        reference)
    assert_unbiased(scene, mi.load_dict({"type": "oracle_direct", "emitter_samples": 2, "bsdf_samples": 0}),
                    reference)
