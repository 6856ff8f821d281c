"""Specification of ProductWarp: sampling max(f_SH, 0) x environment luminance.

Lobes are zonal Phong / clamped-cosine lobes built here from their per-band
attenuation (lambda_l y_lm(axis), in the pyramid's grid frame). Coefficients
are passed as opaque per-call values so that every lobe of one band count
reuses the same compiled kernels.
"""

from __future__ import annotations

import math
import os
import warnings

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

mi.set_variant("llvm_ad_rgb")

from mitsuba import chi2  # noqa: E402

from mitsuba_shsampling.grid import Cell, child_phi_centres, grid_direction  # noqa: E402
from mitsuba_shsampling.envmap import EnvPyramid  # noqa: E402
from mitsuba_shsampling.envmap.synthetic import constant_latlong, envmap_emitter, sun_sky_latlong, window_latlong  # noqa: E402
from mitsuba_shsampling.sh.basis import sh_eval  # noqa: E402
from mitsuba_shsampling.sh.zonal import rotate_zonal_lobes  # noqa: E402
from mitsuba_shsampling.fidelity import product_fidelity  # noqa: E402
from mitsuba_shsampling.envmap.emitter import EmitterDirections, compensated_copy  # noqa: E402
from mitsuba_shsampling.warp.product import ProductWarp, default_sh_depth  # noqa: E402
from mitsuba_shsampling.warp.proxy_lobe import ProxyLobe, moment_proxy  # noqa: E402

from conftest import ENVMAPS_DIR
from leaf_chi2 import LeafAlignedChiSquareTest

ENVMAP_DIR = str(ENVMAPS_DIR)
REAL_MAP = os.path.join(ENVMAP_DIR, "immenstadter_horn_1k.hdr")
TILTED = mi.ScalarAffineTransform4f().rotate((np.array([0.3, 0.8, -0.52]) / np.linalg.norm([0.3, 0.8, -0.52])).tolist(), 40.0)


# ----------------------------------------------------------------- helpers

def phong_attenuation(s: float, n_bands: int) -> list[float]:
    """lambda_l of the normalised Phong lobe (recurrence of docs/MATH.md section 8)."""
    lam = [1.0, (s + 1) / (s + 2)]
    for l in range(n_bands - 2):
        lam.append(lam[l] * (s - l) / (s + l + 3))
    return lam[:n_bands]


def cosine_attenuation(n_bands: int) -> list[float]:
    return [math.pi * x for x in phong_attenuation(1.0, n_bands)]


def zonal_lobe(attenuation: list[float], axis) -> list[float]:
    """f_lm = lambda_l y_lm(axis) as Python floats (one lobe)."""
    basis = sh_eval(mi.Vector3f(*axis), len(attenuation) - 1)
    return [attenuation[math.isqrt(i)] * float(y.numpy()[0]) for i, y in enumerate(basis)]


def opaque(coeffs: list[float]) -> list:
    return [dr.opaque(mi.Float, c) for c in coeffs]


def per_lane_lobes(n_bands: int, count: int, seed: int) -> list:
    """``count`` Phong lobes (s in [5, 40]) with random axes, one per lane."""
    rng = np.random.default_rng(seed)
    axes = rng.normal(size=(3, count)).astype(np.float32)
    s = mi.Float(rng.uniform(5.0, 40.0, count).astype(np.float32))
    lam = [mi.Float(1.0), (s + 1) / (s + 2)]
    for l in range(n_bands - 2):
        lam.append(lam[l] * (s - l) / (s + l + 3))
    basis = sh_eval(mi.Vector3f(axes), n_bands - 1)
    coeffs = [lam[math.isqrt(i)] * y for i, y in enumerate(basis)]
    dr.eval(*coeffs)
    return coeffs


def leaf_centre_directions(warp: ProductWarp) -> mi.Vector3f:
    """World directions of the centres of all 4^depth leaves."""
    cells = 1 << warp.depth
    centres = (np.arange(cells) + 0.5) / cells
    z = mi.Float(np.repeat(-1.0 + 2.0 * centres, cells))
    phi = mi.Float(np.tile(2.0 * math.pi * centres, cells))
    return warp.pyramid.world_from_grid(grid_direction(z, phi))


def leaf_probability_sum(warp: ProductWarp, coeffs) -> float:
    """Integral of the pdf: it is constant on leaves, so a leaf-centre sum is exact."""
    pdf = warp.pdf(coeffs, leaf_centre_directions(warp)).numpy().astype(np.float64)
    return float(pdf.sum() * 4.0 * math.pi / 4**warp.depth)


def uniform_samples(count: int, seed: int = 7) -> mi.Point2f:
    rng = np.random.default_rng(seed)
    return mi.Point2f(rng.random((2, count)).astype(np.float32))


#: Pyramid depth of the chi2 tests: 2^7 x 2^7 leaves, one chi2 bin per
#: half leaf (see :func:`run_chi2`); deep enough that the default sh_depth
#: leaves environment-only levels below it.
CHI2_DEPTH = 7

#: How far pdf(d) may be from the pdf sample() returned with d: inside a leaf on a sun the
#: bilinear density is steep, and the float32 round trip of d through the world frame moves
#: the point enough to change it by up to 2e-4.
PDF_ROUND_TRIP_RTOL = 1e-3


@pytest.fixture(scope="module")
def sun_pyramid() -> EnvPyramid:
    """Sky plus a tiny (0.5 degree), 1e5 times brighter sun, under a tilted to_world."""
    return EnvPyramid.from_latlong(sun_sky_latlong(128, 256), to_world=TILTED, max_depth=CHI2_DEPTH)


@pytest.fixture(scope="module")
def real_pyramid() -> EnvPyramid:
    return EnvPyramid(mi.load_dict({"type": "envmap", "filename": REAL_MAP}), max_depth=CHI2_DEPTH)


def run_chi2(warp: ProductWarp, coeffs, proxy=None) -> chi2.ChiSquareTest:
    """Chi-square test of the warp's samples against its own pdf.

    The test runs in the pyramid's grid frame (a rotation of the world: the
    density is unchanged), where chi2's (cos theta, phi) bins can be aligned
    with the leaves, inside which the pdf is bilinear: chi2 makes half as many
    phi bins as cos theta bins, so ``res`` = 2^(D+1) gives 2^D phi bins (one
    per leaf) and 2^(D+1) cos theta bins (two per leaf). The expected counts
    come from Gauss-Legendre nodes away from the bins' edges
    (:mod:`leaf_chi2`). With ``res`` = 2^D (two leaves per phi bin) and
    chi2's trapezoid rule the sun map's integrated pdf was 0.4 % short and the
    p-values 0.0006-0.05 over 8 seeds, for the walk before and after a change
    that only moved its rounding.
    """
    coeffs = opaque(coeffs) if isinstance(coeffs, list) else coeffs  # factored lobes: evaluated arrays
    pyramid = warp.pyramid
    return LeafAlignedChiSquareTest(
        domain=chi2.SphericalDomain(),
        sample_func=lambda u: pyramid.grid_from_world(warp.sample(coeffs, u, proxy)[0]),
        pdf_func=lambda d: warp.pdf(coeffs, pyramid.world_from_grid(d), proxy),
        sample_dim=2, sample_count=1_000_000, res=2 << warp.depth, seed=3)


# ------------------------------------------------------------------- chi2

CHI2_LOBES = {
    "diffuse_cosine_up": (cosine_attenuation(3), (0.0, 0.0, 1.0)),
    "phong20_rotated": (phong_attenuation(20.0, 10), (0.5, -0.4, 0.77)),
    # Truncated to 10 bands this lobe rings (negative side lobes): exercises
    # the clamping at 0. Same band count as above: the kernels are reused.
    "phong100_rotated": (phong_attenuation(100.0, 10), (-0.6, 0.3, 0.2)),
}


@pytest.mark.parametrize("lobe", sorted(CHI2_LOBES))
def test_chi2_samples_follow_own_pdf_on_real_map(real_pyramid, lobe):
    attenuation, axis = CHI2_LOBES[lobe]
    test = run_chi2(ProductWarp(real_pyramid), zonal_lobe(attenuation, axis))
    assert test.run(0.01), test.messages


@pytest.mark.parametrize("lobe", ["diffuse_cosine_up", "phong20_rotated"])
def test_chi2_samples_follow_own_pdf_on_sun_map_with_rotated_to_world(sun_pyramid, lobe):
    attenuation, axis = CHI2_LOBES[lobe]
    test = run_chi2(ProductWarp(sun_pyramid), zonal_lobe(attenuation, axis))
    assert test.run(0.01), test.messages


# ------------------------------------------------ the environment alone

@pytest.mark.parametrize("compensated", [False, True])
def test_chi2_environment_alone_samples_follow_own_pdf(compensated):
    """The environment strategies (Mitsuba's envmap sampling, through EmitterDirections),
    plain and MIS-compensated, under a tilted to_world (chi2 also checks that the pdf
    integrates to one). A smooth map, and 16 x 16 points per cell: the chi2 test
    integrates the pdf by the trapezoid rule, whose error at the kink of the
    compensated map (and at a sharp-edged sun) exceeds the test's tolerance with 4."""
    emitter = envmap_emitter(window_latlong(64, 128), to_world=TILTED)
    directions = EmitterDirections(compensated_copy(emitter) if compensated else emitter)
    test = chi2.ChiSquareTest(
        domain=chi2.SphericalDomain(), sample_func=lambda u: directions.sample(u)[0],
        pdf_func=directions.pdf, sample_dim=2, sample_count=1_000_000, res=64, ires=16, seed=5)
    assert test.run(0.01), test.messages


def test_the_compensated_copy_has_the_radiance_of_the_map_it_copies():
    emitter = mi.load_dict({"type": "envmap", "filename": REAL_MAP, "to_world": TILTED, "scale": 2.5})
    copy = compensated_copy(emitter)
    rng = np.random.default_rng(4)
    d = dr.normalize(mi.Vector3f(rng.normal(size=(3, 4096)).astype(np.float32)))
    target = dr.zeros(mi.SurfaceInteraction3f)
    target.wi = -d
    assert np.allclose(emitter.eval(target).numpy(), copy.eval(target).numpy(), rtol=1e-3, atol=1e-6)


# ------------------------------------------------------- exactness of pdf

@pytest.mark.parametrize("sh_depth", [None, 1])
def test_sample_returns_the_pdf_that_pdf_evaluates(sun_pyramid, sh_depth):
    warp = ProductWarp(sun_pyramid, sh_depth=sh_depth)
    count = 1 << 14
    coeffs = per_lane_lobes(5, count, seed=1)
    d, pdf = warp.sample(coeffs, uniform_samples(count))
    again = warp.pdf(coeffs, d)
    pdf, again = pdf.numpy(), again.numpy()
    assert np.all(np.isfinite(pdf)) and np.all(pdf > 0)
    assert np.allclose(np.linalg.norm(d.numpy(), axis=0), 1.0, atol=1e-5)
    assert np.max(np.abs(again - pdf) / pdf) <= PDF_ROUND_TRIP_RTOL


@pytest.mark.parametrize("lobe", ["diffuse_cosine_up", "phong20_rotated"])
def test_pdf_integrates_to_one(sun_pyramid, lobe):
    attenuation, axis = CHI2_LOBES[lobe]
    coeffs = opaque(zonal_lobe(attenuation, axis))
    assert leaf_probability_sum(ProductWarp(sun_pyramid), coeffs) == pytest.approx(1.0, abs=2e-5)


def test_samples_land_where_the_pdf_is_positive_in_the_world_frame(sun_pyramid):
    """Directions are world directions: a lobe around the world-space sun
    direction concentrates the samples on it."""
    local_sun = np.array([0.3, 0.8, -0.5]) / np.linalg.norm([0.3, 0.8, -0.5])
    world_sun = np.array(TILTED @ mi.ScalarVector3f(*local_sun), dtype=np.float64)
    grid_sun = sun_pyramid.grid_from_world(mi.Vector3f(*map(float, world_sun))).numpy().ravel()
    warp = ProductWarp(sun_pyramid)
    coeffs = opaque(zonal_lobe(phong_attenuation(20.0, 10), [float(x) for x in grid_sun]))
    d, _ = warp.sample(coeffs, uniform_samples(1 << 14))
    cos_to_sun = world_sun @ d.numpy()
    # The sun holds most of the product's mass (radiance 1e5 over ~1e-4 sr).
    assert np.mean(cos_to_sun > math.cos(math.radians(2.0))) > 0.5


# ---------------------------------------------------------------- fidelity

def test_fidelity_against_exact_product_is_reported_and_bounded(sun_pyramid):
    warp = ProductWarp(sun_pyramid)
    coeffs = zonal_lobe(phong_attenuation(20.0, 10), (0.5, -0.4, 0.77))
    figures = product_fidelity(warp, coeffs)
    print("product fidelity (sun map, Phong 20, 10 bands):", figures)
    assert figures["probability_sum"] == pytest.approx(1.0, abs=2e-5)
    # Loose: the coarse levels weight children by (lobe integral) x (env
    # integral), not the integral of the product; that costs fidelity but a
    # sampler that ignored the lobe or the map would be far off.
    assert figures["mean_relative_error"] < 0.5
    assert figures["wasted_mass"] < 0.01


def test_fidelity_of_a_constant_lobe_is_exact(sun_pyramid):
    coeffs = [0.0] * 16
    coeffs[0] = 1.0
    figures = product_fidelity(ProductWarp(sun_pyramid), coeffs)
    assert figures["mean_relative_error"] < 1e-4
    assert figures["missed_mass"] == 0.0


# --------------------------------------------------------------- bad input

def test_bad_pixels_are_sampled_as_zero_with_one_warning():
    image = sun_sky_latlong(32, 64)
    image[3, 5] = np.nan
    image[10, 7] = np.inf
    image[20, 30] = -5.0
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        pyramid = EnvPyramid.from_latlong(image)
    assert len([w for w in caught if issubclass(w.category, RuntimeWarning)]) == 1
    warp = ProductWarp(pyramid)
    coeffs = opaque(zonal_lobe(cosine_attenuation(3), (0.0, 0.0, 1.0)))
    d, pdf = warp.sample(coeffs, uniform_samples(4096))
    assert np.all(np.isfinite(d.numpy())) and np.all(np.isfinite(pdf.numpy()))
    assert np.all(pdf.numpy() > 0)
    assert leaf_probability_sum(warp, coeffs) == pytest.approx(1.0, abs=2e-5)


def test_all_zero_map_gives_no_samples_and_zero_pdf():
    warp = ProductWarp(EnvPyramid.from_latlong(constant_latlong(16, 32, 0.0)))
    coeffs = opaque(zonal_lobe(cosine_attenuation(3), (0.0, 0.0, 1.0)))
    d, pdf = warp.sample(coeffs, uniform_samples(256))
    assert np.all(pdf.numpy() == 0.0)
    assert np.all(np.isfinite(d.numpy()))
    assert np.all(warp.pdf(coeffs, d).numpy() == 0.0)


def test_lobe_without_positive_mass_or_non_finite_falls_back_to_environment_sampling(sun_pyramid):
    environment_only = ProductWarp(sun_pyramid, defensive_share=1.0)
    warp = ProductWarp(sun_pyramid)
    negative = [0.0] * 9
    negative[0] = -1.0
    broken = [float("nan")] * 9
    for coeffs in (negative, broken):
        d, pdf = warp.sample(opaque(coeffs), uniform_samples(4096))
        assert np.all(np.isfinite(d.numpy()))
        assert np.all(pdf.numpy() > 0)
        expected = environment_only.pdf(opaque(zonal_lobe(cosine_attenuation(3), (0.0, 0.0, 1.0))), d)
        assert np.allclose(pdf.numpy(), expected.numpy(), rtol=PDF_ROUND_TRIP_RTOL)
        assert np.allclose(warp.pdf(opaque(coeffs), d).numpy(), pdf.numpy(), rtol=PDF_ROUND_TRIP_RTOL)


@pytest.mark.parametrize("share", [0.05, 0.1, 0.5])
def test_pdf_is_never_below_the_defensive_share_of_the_environments(sun_pyramid, share):
    """q = (1 - e) p_product + e p_env >= e p_env, for ringing, clamped lobes too."""
    environment_only = ProductWarp(sun_pyramid, defensive_share=1.0)
    warp = ProductWarp(sun_pyramid, defensive_share=share)
    coeffs = per_lane_lobes(8, 1 << 14, seed=5)
    d = mi.warp.square_to_uniform_sphere(uniform_samples(1 << 14, seed=6))
    pdf_env = environment_only.pdf(coeffs, d).numpy()
    pdf = warp.pdf(coeffs, d).numpy()
    assert np.all(pdf[pdf_env > 0] > 0)
    assert np.all(pdf >= share * pdf_env * (1.0 - 1e-4))


def test_defensive_share_must_be_in_the_unit_interval(sun_pyramid):
    for bad in (0.0, -0.1, 1.5):
        with pytest.raises(ValueError, match="defensive share"):
            ProductWarp(sun_pyramid, defensive_share=bad)
    with pytest.raises(TypeError, match="defensive share"):
        ProductWarp(sun_pyramid, defensive_share="0.1")


@pytest.mark.parametrize("shape", [(1, 1), (3, 5), (17, 33)])
def test_tiny_and_odd_sized_maps_sample_consistently(shape):
    image = sun_sky_latlong(*shape, sun_radius_deg=5.0, sun_radiance=100.0)
    warp = ProductWarp(EnvPyramid.from_latlong(image))
    coeffs = per_lane_lobes(5, 2048, seed=2)
    d, pdf = warp.sample(coeffs, uniform_samples(2048))
    again = warp.pdf(coeffs, d).numpy()
    assert np.all(pdf.numpy() > 0)
    assert np.max(np.abs(again - pdf.numpy()) / pdf.numpy()) <= PDF_ROUND_TRIP_RTOL
    single = opaque(zonal_lobe(phong_attenuation(20.0, 5), (0.2, 0.1, 0.9)))
    assert leaf_probability_sum(warp, single) == pytest.approx(1.0, abs=2e-5)


def test_large_map_is_sampled_at_the_pyramids_capped_depth():
    """A 2048 x 4096 map: the pyramid stops at its depth cap (<= 12, the
    deepest tree float32 samples can drive; 89 MB shared by all shading
    points), the warp follows it; per shading point only the n^2
    coefficients are stored."""
    image = sun_sky_latlong(2048, 4096)
    pyramid = EnvPyramid.from_latlong(image, to_world=TILTED)
    del image
    warp = ProductWarp(pyramid)
    assert warp.depth == pyramid.depth <= 12
    assert pyramid.nbytes <= 4 * (4 ** (pyramid.depth + 1) + 8) // 3 + 4 * (2 ** pyramid.depth + 1) ** 2
    coeffs = per_lane_lobes(3, 1 << 16, seed=4)
    d, pdf = warp.sample(coeffs, uniform_samples(1 << 16))
    again = warp.pdf(coeffs, d).numpy()
    assert np.all(pdf.numpy() > 0)
    # Leaves of 1e-3 in z: the same world-frame round trip is a larger step inside them.
    assert np.max(np.abs(again - pdf.numpy()) / pdf.numpy()) <= 5 * PDF_ROUND_TRIP_RTOL


# ------------------------------------------------------------- parameters

def test_default_sh_depth_grows_with_band_count_and_is_capped_by_the_map():
    depths = [default_sh_depth(n) for n in (1, 3, 5, 10, 15, 20, 32)]
    assert depths == sorted(depths)
    warp = ProductWarp(EnvPyramid.from_latlong(constant_latlong(4, 8)))  # depth 3
    coeffs = opaque(zonal_lobe(phong_attenuation(20.0, 10), (0.0, 0.0, 1.0)))
    assert leaf_probability_sum(warp, coeffs) == pytest.approx(1.0, abs=2e-5)


def test_invalid_sh_depth_is_rejected(sun_pyramid):
    for bad in (-1, 0, 13):
        with pytest.raises(ValueError):
            ProductWarp(sun_pyramid, sh_depth=bad)
    with pytest.raises(TypeError):
        ProductWarp(sun_pyramid, sh_depth=2.5)


# ------------------------------------- closed-form proxy below the SH levels

def proxy_lobe(normal, w_d, mirror, w_g, s) -> ProxyLobe:
    """One two-lobe proxy (grid frame) shared by all lanes."""
    def unit(v):
        return mi.Vector3f(*(float(x) for x in np.asarray(v) / np.linalg.norm(v)))
    return ProxyLobe(unit(normal), mi.Float(w_d), unit(mirror), mi.Float(w_g), mi.Float(s))


def per_lane_proxies(count: int, seed: int) -> ProxyLobe:
    """Random proxies, exponents from 0 to +inf (a mirror), one per lane."""
    rng = np.random.default_rng(seed)
    normal = rng.normal(size=(3, count)).astype(np.float32)
    mirror = rng.normal(size=(3, count)).astype(np.float32)
    s = 10.0 ** rng.uniform(-1.0, 4.0, count)
    s[::17], s[::23] = np.inf, 0.0
    return ProxyLobe(dr.normalize(mi.Vector3f(normal)), mi.Float(rng.uniform(0, 1, count).astype(np.float32)),
                     dr.normalize(mi.Vector3f(mirror)), mi.Float(rng.uniform(0, 1, count).astype(np.float32)),
                     mi.Float(s.astype(np.float32)))


#: A sharp glossy lobe (s = 400, far beyond what 8 bands hold) plus a diffuse part.
SHARP_PROXY = dict(normal=(0.2, -0.3, 0.93), w_d=0.2, mirror=(0.5, -0.4, 0.77), w_g=0.7, s=400.0)


def test_chi2_samples_follow_own_pdf_with_proxy_levels(real_pyramid):
    warp = ProductWarp(real_pyramid, sh_depth=3, proxy_depth=6)
    proxy = proxy_lobe(**SHARP_PROXY)
    test = run_chi2(warp, zonal_lobe(phong_attenuation(20.0, 8), SHARP_PROXY["mirror"]), proxy)
    assert test.run(0.01), test.messages


def test_proxy_levels_sample_returns_the_pdf_that_pdf_evaluates_and_keep_the_defensive_share(sun_pyramid):
    count = 1 << 14
    coeffs, proxies = per_lane_lobes(5, count, seed=2), per_lane_proxies(count, seed=3)
    warp = ProductWarp(sun_pyramid, sh_depth=2, proxy_depth=6)
    d, pdf = warp.sample(coeffs, uniform_samples(count), proxies)
    pdf, again = pdf.numpy(), warp.pdf(coeffs, d, proxies).numpy()
    assert np.all(np.isfinite(pdf)) and np.all(pdf > 0)
    assert np.max(np.abs(again - pdf) / pdf) <= PDF_ROUND_TRIP_RTOL
    uniform = mi.warp.square_to_uniform_sphere(uniform_samples(count, seed=8))
    pdf_env = ProductWarp(sun_pyramid, defensive_share=1.0).pdf(coeffs, uniform).numpy()
    pdf = warp.pdf(coeffs, uniform, proxies).numpy()
    assert np.all(pdf >= warp.defensive_share * pdf_env * (1.0 - 1e-4))


#: Maps for the mixture's bookkeeping: a 1e5 sun; a window over a black half (cells with no
#: light at all); the same at 1e-12 (dim, well above EnvPyramid's DIM_TOTAL, below which a
#: map's float32 cell integrals stop summing to their parents and it is sampled as black).
ABSOLUTE_WEIGHT_MAPS = {
    "sun": lambda: sun_sky_latlong(128, 256),
    "black_half": lambda: window_latlong(64, 128, ambient=0.0),
    "dim": lambda: window_latlong(64, 128, ambient=0.0) * np.float32(1e-12),
}


@pytest.mark.parametrize("envmap", sorted(ABSOLUTE_WEIGHT_MAPS))
def test_mixture_weights_are_absolute_children_sum_to_their_parent_at_every_level(envmap):
    """The contract of walk_sample_absolute / walk_pdf_absolute: the four children's weights
    are finite, non-negative and sum to the weight of the cell they split, from 1 at the root
    down to the last product level, for any lobe (ringing clamped at 0, sharp proxies and
    mirrors, a lobe with no mass, NaN) and any light."""
    pyramid = EnvPyramid.from_latlong(ABSOLUTE_WEIGHT_MAPS[envmap](), to_world=TILTED, max_depth=CHI2_DEPTH)
    count = 1 << 12
    coeffs = per_lane_lobes(8, count, seed=4)
    coeffs[0] = dr.select(dr.arange(mi.UInt32, count) % 97 == 0, -1.0, coeffs[0])  # no positive mass
    coeffs[5] = dr.select(dr.arange(mi.UInt32, count) % 89 == 0, dr.nan, coeffs[5])
    warp = ProductWarp(pyramid, sh_depth=2, proxy_depth=6)
    provider = warp.weights(coeffs, per_lane_proxies(count, seed=5))
    rng = np.random.default_rng(6)
    state, iz, iphi, parent = provider.root(), mi.UInt32(0), mi.UInt32(0), np.float32(1.0)
    for level in range(provider.walk_depth):
        cell = Cell(level, iz, iphi)
        split = provider.children(state, cell)
        weights = np.stack([w.numpy() for w in split.weights])
        assert np.all(np.isfinite(weights)) and np.all(weights >= 0), level
        np.testing.assert_allclose(weights.sum(axis=0), np.broadcast_to(parent, (count,)), rtol=2e-6, atol=1e-30,
                                   err_msg=f"level {level}")
        # Follow each lane down to a child of positive weight: the sampled one, else the heaviest.
        sampled = rng.integers(0, 4, count)
        index = np.where(weights[sampled, np.arange(count)] > 0, sampled, weights.argmax(axis=0))
        a, b = mi.Bool(index >= 2), mi.Bool(index % 2 == 1)
        state = provider.advance(state, split.pending, cell, a, b)
        parent = weights[index, np.arange(count)]
        iz, iphi = 2 * iz + dr.select(a, 1, 0), 2 * iphi + dr.select(b, 1, 0)


def test_a_black_map_gives_samples_of_pdf_zero_with_a_finite_unit_direction():
    """Nothing to place: every lane is invalid. Its sample carries no weight, and its direction
    is still a unit vector (a shadow ray may be traced along it), not NaN."""
    pyramid = EnvPyramid.from_latlong(np.zeros((32, 64, 3), dtype=np.float32), to_world=TILTED)
    assert pyramid.is_black
    count = 1 << 10
    d, pdf = ProductWarp(pyramid).sample(per_lane_lobes(8, count, seed=9), uniform_samples(count, seed=10))
    assert np.all(pdf.numpy() == 0.0)
    np.testing.assert_allclose(np.linalg.norm(np.asarray(d.numpy()).reshape(3, -1), axis=0), 1.0, rtol=1e-6)


def test_proxy_levels_pdf_integrates_to_one(sun_pyramid):
    warp = ProductWarp(sun_pyramid, sh_depth=3, proxy_depth=7)
    coeffs = opaque(zonal_lobe(phong_attenuation(20.0, 8), (0.5, -0.4, 0.77)))
    pdf = warp.pdf(coeffs, leaf_centre_directions(warp), proxy_lobe(**SHARP_PROXY)).numpy().astype(np.float64)
    assert pdf.sum() * 4.0 * math.pi / 4**warp.depth == pytest.approx(1.0, rel=1e-4)


def all_children_values(proxy: ProxyLobe, level: int) -> np.ndarray:
    """The proxy's values at the children of every cell of ``level``: shape (4, 4^level)."""
    cells = 1 << level
    iz, iphi = np.meshgrid(np.arange(cells), np.arange(cells), indexing="ij")
    cell = Cell(level, mi.UInt32(iz.ravel()), mi.UInt32(iphi.ravel()))
    sin_c, cos_c = dr.sincos(cell.phim)
    return np.stack([v.numpy() for v in proxy.children_values(cell, child_phi_centres(cos_c, sin_c, level))])


@pytest.mark.parametrize("s", [0.0, 3.0, 40.0])
def test_closed_form_proxy_has_the_fitted_energy(s):
    """Each part of the proxy has unit integral, so on a grid fine against the
    lobe the children's values times their solid angle sum to w_d + w_g."""
    proxy = proxy_lobe(normal=(0.3, 0.1, 0.9), w_d=0.25, mirror=(-0.2, 0.6, 0.4), w_g=0.75, s=s)
    level = 7
    child_area = 4.0 * math.pi / 4 ** (level + 1)
    assert all_children_values(proxy, level).sum() * child_area == pytest.approx(1.0, rel=0.01)


@pytest.mark.parametrize("s", [1e4, math.inf])
def test_closed_form_proxy_peaks_at_the_mirror_and_stays_finite_for_sharp_lobes(s):
    mirror = np.array([-0.2, 0.6, 0.4]) / np.linalg.norm([-0.2, 0.6, 0.4])
    proxy = proxy_lobe(normal=(0.3, 0.1, 0.9), w_d=0.25, mirror=mirror, w_g=0.75, s=s)
    level = 4
    values = all_children_values(proxy, level)
    assert np.all(np.isfinite(values)) and np.all(values >= 0)
    cells = 1 << (level + 1)
    z, phi = mirror[2], math.atan2(mirror[1], mirror[0]) % (2 * math.pi)
    iz, iphi = int((z + 1) / 2 * cells), int(phi / (2 * math.pi) * cells)
    child = 2 * (iz & 1) + (iphi & 1)
    parent = (iz >> 1) * (cells >> 1) + (iphi >> 1)
    assert values[child, parent] == values.max()


# ------------------------- the proxy read off the coefficients (moment_proxy)

@pytest.mark.parametrize("s", [0.5, 4.0, 20.0, 300.0])
def test_moment_proxy_gives_back_a_phong_lobes_exponent_and_axis_at_any_band_count(s):
    """Bands 0 and 1 do not depend on the band limit: even at 3 bands a
    rotated Phong lobe's expansion names its own exponent and axis."""
    axis = np.array([0.5, -0.4, 0.77]) / np.linalg.norm([0.5, -0.4, 0.77])
    for n_bands in (3, 10):
        proxy = moment_proxy(opaque(zonal_lobe(phong_attenuation(s, n_bands), axis.tolist())))
        assert proxy.exponent.numpy()[0] == pytest.approx(s, rel=2e-3)
        assert np.allclose(proxy.mirror.numpy().ravel(), axis, atol=1e-5)
        assert proxy.diffuse_weight.numpy()[0] == 0.0


def test_moment_proxy_of_a_function_without_a_bright_side_is_flat():
    """A clamped cosine has mean cosine 2/3 (Phong exponent 1); a constant and a
    function even in w (band 2 only) have none: exponent 0, the walk below the SH
    levels then follows the environment."""
    up = moment_proxy(opaque(zonal_lobe(cosine_attenuation(3), (0.0, 0.0, 1.0))))
    assert up.exponent.numpy()[0] == pytest.approx(1.0, rel=1e-4)
    constant = [1.0] + [0.0] * 8
    even = [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.7, 0.0, 0.0]
    for coeffs in (constant, even):
        assert moment_proxy(opaque(coeffs)).exponent.numpy()[0] == 0.0


@pytest.mark.parametrize("coeffs", [[0.0] * 9, [-1.0, 0.0, 0.5, 0.0] + [0.0] * 5,
                                    [math.nan] * 9, [1.0, math.inf, 0.0, 0.0] + [0.0] * 5])
def test_moment_proxy_of_bad_coefficients_is_finite(coeffs):
    """No mass, negative mass, NaN, an infinite first moment: a flat proxy with
    a unit axis, never a NaN that would reach the walk's weights."""
    proxy = moment_proxy(opaque(coeffs))
    exponent, mirror = proxy.exponent.numpy()[0], proxy.mirror.numpy().ravel()
    assert exponent == 0.0
    assert np.all(np.isfinite(mirror)) and np.linalg.norm(mirror) == pytest.approx(1.0, abs=1e-6)


def test_the_default_warp_reads_its_proxy_off_the_coefficients(sun_pyramid):
    """Without a proxy the default warp runs SH levels on top and the moment proxy
    below: the same densities as the same warp handed moment_proxy explicitly."""
    warp = ProductWarp(sun_pyramid)
    assert warp.sh_depth_for(10) == 2 and warp.proxy_depth == 6
    coeffs = per_lane_lobes(10, 1 << 12, seed=9)
    u = uniform_samples(1 << 12)
    d, pdf = warp.sample(coeffs, u)
    d_explicit, pdf_explicit = warp.sample(coeffs, u, moment_proxy(coeffs))
    assert np.array_equal(d.numpy(), d_explicit.numpy()) and np.array_equal(pdf.numpy(), pdf_explicit.numpy())


@pytest.mark.parametrize("lobe", ["phong20_rotated", "phong100_rotated"])
def test_chi2_without_proxy_levels(real_pyramid, lobe):
    """``proxy_depth=None``: SH levels (from the band count), then the map alone."""
    attenuation, axis = CHI2_LOBES[lobe]
    test = run_chi2(ProductWarp(real_pyramid, sh_depth=None, proxy_depth=None), zonal_lobe(attenuation, axis))
    assert test.run(0.01), test.messages


# --------------------------------------------- lobes in factored form (as the integrators pass)

def factored_lobes(count: int, seed: int):
    """Per lane a Phong lobe (8 bands) about one axis plus a clamped cosine about another,
    in the factored form the integrators build (RotatedZonalLobes)."""
    rng = np.random.default_rng(seed)
    s = mi.Float(rng.uniform(5.0, 40.0, count).astype(np.float32))
    mirror, normal = (mi.Vector3f(rng.normal(size=(3, count)).astype(np.float32)) for _ in range(2))
    lam_s = [mi.Float(1.0), (s + 1) / (s + 2)]
    for l in range(6):
        lam_s.append(lam_s[l] * (s - l) / (s + l + 3))
    lobes = rotate_zonal_lobes([(lam_s, mirror), ([0.3 * c for c in cosine_attenuation(3)], normal)])
    dr.eval(lobes)
    return lobes


@pytest.mark.parametrize("sh_depth", [None, 2])
def test_factored_lobes_are_sampled_as_their_coefficients_are(sun_pyramid, sh_depth):
    """The factored form only reorders the sums over l: same directions, same pdfs."""
    count = 1 << 14
    lobes = factored_lobes(count, seed=5)
    coeffs = lobes.coefficients()
    dr.eval(coeffs)
    warp = ProductWarp(sun_pyramid, sh_depth=sh_depth)
    u = uniform_samples(count)
    d_factored, pdf_factored = warp.sample(lobes, u)
    d_coeffs, pdf_coeffs = warp.sample(coeffs, u)
    same_leaf = np.max(np.abs(d_factored.numpy() - d_coeffs.numpy()), axis=0) < 1e-4
    # Rounding alone differs: a child whose weight ties with its sibling's may flip, and
    # the deep SH levels' cell integrals cancel (a few lanes in 10^4 differ by up to 2 %).
    assert same_leaf.mean() > 0.999
    relative = np.abs(pdf_factored.numpy() / pdf_coeffs.numpy() - 1.0)[same_leaf]
    assert np.quantile(relative, 0.999) < 1e-3 and np.max(relative) < 0.05
    again = warp.pdf(lobes, d_factored).numpy()
    assert np.max(np.abs(again - pdf_factored.numpy()) / pdf_factored.numpy()) <= PDF_ROUND_TRIP_RTOL


def test_chi2_factored_lobes_follow_own_pdf(real_pyramid):
    test = run_chi2(ProductWarp(real_pyramid), factored_lobes(1, seed=6))
    assert test.run(0.01), test.messages
