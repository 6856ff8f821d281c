"""Skies as users write them: ``sunsky`` and ``constant`` emitters in place of an ``envmap``.

Their pyramid is built from their own radiance, evaluated in a kernel; a sunsky's sun,
which no lat-long grid of that size resolves, is left to the emitter's own sampling in a
per-lane mixture with the product (``warp/sky_mixture.py``). Specified here: what the
evaluation holds, that the mixture's samples follow its pdf (chi2) and that the renders
are unbiased against Mitsuba's ``path``.
"""

import math
import subprocess
import sys

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

mi.set_variant("llvm_ad_rgb")

from mitsuba import chi2  # noqa: E402
from test_integrators import MATERIALS, assert_unbiased, make_scene  # noqa: E402
from test_product import CHI2_DEPTH, PDF_ROUND_TRIP_RTOL, phong_attenuation, run_chi2, zonal_lobe  # noqa: E402

from mitsuba_shsampling.envmap import EnvPyramid  # noqa: E402
from mitsuba_shsampling.envmap.emitter import EmitterDirections  # noqa: E402
from mitsuba_shsampling.envmap.evaluated import sky_components  # noqa: E402
from mitsuba_shsampling.envmap.synthetic import envmap_emitter  # noqa: E402
from mitsuba_shsampling.integrators import register  # noqa: E402
from mitsuba_shsampling.warp.product import ProductWarp  # noqa: E402
from mitsuba_shsampling.warp.proxy_lobe import ProxyLobe  # noqa: E402
from mitsuba_shsampling.warp.sky_mixture import MAX_EMITTER_SHARE, MIN_EMITTER_SHARE, SkyMixture  # noqa: E402

#: The scenes' z is up; a sunsky's sun is given in world coordinates.
HIGH_SUN = {"type": "sunsky", "sun_direction": [0.3, 0.4, 0.8]}
LOW_SUN = {"type": "sunsky", "sun_direction": [0.8, -0.5, 0.12]}
CONSTANT = {"type": "constant", "radiance": {"type": "rgb", "value": [0.5, 1.0, 2.0]}}
SKY_MATERIALS = {k: MATERIALS[k] for k in ("diffuse", "ggx", "roughplastic", "blend")}


@pytest.fixture(scope="module", autouse=True)
def registered():
    register()


# ------------------------------------------------------------ the evaluation

def test_a_constant_emitter_is_a_uniform_image_holding_its_integral():
    emitter = mi.load_dict(CONSTANT)
    sky = sky_components(emitter)
    luminance = 0.212671 * 0.5 + 0.715160 * 1.0 + 0.072169 * 2.0
    np.testing.assert_allclose(sky.image, luminance, rtol=1e-6)
    assert sky.sun is None and sky.sun_power == 0.0
    np.testing.assert_allclose(EnvPyramid.from_latlong(sky.image).total, 4 * math.pi * luminance, rtol=1e-4)


def test_a_sunsky_is_evaluated_without_its_sun_and_gets_it_back():
    emitter = mi.load_dict(HIGH_SUN)
    sky = sky_components(emitter)
    # The image is the sky alone: the same as a sunsky without a sun gives.
    no_sun = sky_components(mi.load_dict(dict(HIGH_SUN, sun_scale=0.0)))
    np.testing.assert_allclose(sky.image, no_sun.image, rtol=1e-6)
    assert no_sun.sun is None
    # The sun holds the rest of the emitter's integral, in the direction the user gave; the
    # emitter's own sampling puts a share of its samples on it. (Its radiance there is
    # checked in a fresh interpreter: test_the_evaluated_copy_has_the_emitters_sky_and_sun.)
    assert 0 < sky.sun_power < sky.total
    np.testing.assert_allclose(np.array(sky.sun), np.array(HIGH_SUN["sun_direction"]) / np.linalg.norm(
        HIGH_SUN["sun_direction"]), atol=1e-5)
    assert 0.01 < sky.sun_sampling_share <= 1


#: The fidelity check of the copies evaluates the scene's own emitters in kernels of their
#: own, which is what the set-up avoids (evaluated._sunsky_copy): it runs in a fresh
#: interpreter, so that no later test in this process renders after it.
COPY_CHECK = """
import sys
import mitsuba as mi, numpy as np
mi.set_variant("llvm_ad_rgb")
from mitsuba_shsampling.envmap.evaluated import _sunsky_copy, radiance_luminance
skies = [{"type": "sunsky", "sun_direction": [0.3, 0.4, 0.8], "turbidity": 4.0,
          "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], 90)},
         {"type": "sunsky", "hour": 17.0, "sky_scale": 2.0, "albedo": {"type": "rgb", "value": [0.2, 0.4, 0.6]}}]
rng = np.random.default_rng(5)
directions = rng.normal(size=(3, 4096))
d = mi.Vector3f(directions / np.linalg.norm(directions, axis=0))
worst = 0.0
for sky in skies:
    for with_sun in (False, True):
        emitter = mi.load_dict(sky if with_sun else dict(sky, sun_scale=0.0))
        a = radiance_luminance(_sunsky_copy(emitter, with_sun), d).numpy()
        b = radiance_luminance(emitter, d).numpy()
        worst = max(worst, float(np.max(np.abs(a - b) / (np.abs(b) + 1e-7))))
print("WORST", worst)
"""


def test_the_evaluated_copy_has_the_emitters_sky_and_sun():
    """Under a to_world with the sun given by its direction, and by time with an RGB albedo
    and a sky scale: the copy sends the emitter's radiance, with and without its sun."""
    result = subprocess.run([sys.executable, "-c", COPY_CHECK], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    assert float(result.stdout.split("WORST")[-1]) < 1e-5


# ------------------------------------------------------------ the mixture

def smooth_sky(height=32, width=64) -> np.ndarray:
    """A smooth sky, brighter towards +Y and one side, never black."""
    theta = (np.arange(height) + 0.5) / height * math.pi
    phi = (np.arange(width) + 0.5) / width * 2 * math.pi
    return (0.3 + np.cos(theta / 2)[:, None] ** 2 * (1.2 + np.sin(phi)[None, :])).astype(np.float32)


def proxy_lobe(normal, mirror, diffuse, glossy, exponent) -> ProxyLobe:
    normal = mi.Vector3f(dr.normalize(mi.ScalarVector3f(normal)))
    mirror = mi.Vector3f(dr.normalize(mi.ScalarVector3f(mirror)))
    return ProxyLobe(normal, mi.Float(diffuse), mirror, mi.Float(glossy), mi.Float(exponent))


#: (lobe attenuation and axis, proxy) in the grid frame: a lobe facing the sun takes
#: most of the emitter's share, one facing away the least.
MIXTURE_LOBES = {
    "glossy_towards_sun": ((phong_attenuation(20.0, 10), (0.3, 0.2, 0.93)),
                           ((0.0, 0.0, 1.0), (0.3, 0.2, 0.93), 0.2, 0.8, 20.0)),
    "glossy_away_from_sun": ((phong_attenuation(20.0, 10), (-0.6, 0.3, 0.2)),
                             ((0.0, 0.0, 1.0), (-0.6, 0.3, 0.2), 0.1, 0.9, 20.0)),
}


@pytest.fixture(scope="module")
def mixture_parts():
    image = smooth_sky()
    pyramid = EnvPyramid.from_latlong(image, max_depth=CHI2_DEPTH)
    # The emitter part is Mitsuba's sampling of the same smooth sky: continuous, so chi2's
    # bins integrate it as they do the product's.
    directions = EmitterDirections(envmap_emitter(image))
    return pyramid, directions


@pytest.mark.parametrize("lobe", sorted(MIXTURE_LOBES))
def test_chi2_the_mixtures_samples_follow_its_pdf(mixture_parts, lobe):
    pyramid, directions = mixture_parts
    (attenuation, axis), proxy_args = MIXTURE_LOBES[lobe]
    mixture = SkyMixture(ProductWarp(pyramid), directions, (0.3, 0.2, 0.93), sun_power=2.0,
                         sky_total=pyramid.total)
    test = run_chi2(mixture, zonal_lobe(attenuation, axis), proxy_lobe(*proxy_args))
    assert test.run(0.01), test.messages


def test_a_lane_gives_the_sun_the_share_its_lobe_sees_of_it(mixture_parts):
    pyramid, directions = mixture_parts
    mixture = SkyMixture(ProductWarp(pyramid), directions, (0.3, 0.2, 0.93), sun_power=2.0,
                         sky_total=pyramid.total)
    towards = mixture.share(proxy_lobe(*MIXTURE_LOBES["glossy_towards_sun"][1]))[0]
    away = mixture.share(proxy_lobe(*MIXTURE_LOBES["glossy_away_from_sun"][1]))[0]
    assert away == pytest.approx(MIN_EMITTER_SHARE) and MIN_EMITTER_SHARE < towards <= MAX_EMITTER_SHARE
    # A lane without a proxy gets the sun's share of the power, and a broken proxy that too.
    fixed = mixture.share(None)[0]
    assert fixed == pytest.approx(min(max(2.0 / (2.0 + pyramid.total), MIN_EMITTER_SHARE), MAX_EMITTER_SHARE))
    broken = proxy_lobe((0, 0, 1), (0, 0, 1), float("nan"), 0.5, 10.0)
    assert mixture.share(broken)[0] == pytest.approx(fixed)


def test_under_a_real_sunsky_sample_returns_the_pdf_that_pdf_evaluates():
    emitter = mi.load_dict(LOW_SUN)
    sky = sky_components(emitter)
    pyramid = EnvPyramid.from_latlong(sky.image)
    sun = pyramid.grid_from_world(mi.Vector3f(sky.sun))
    mixture = SkyMixture(ProductWarp(pyramid), EmitterDirections(emitter), (sun.x[0], sun.y[0], sun.z[0]),
                         sky.sun_power, pyramid.total, sky.sun_sampling_share)
    rng = np.random.default_rng(3)
    count = 1 << 14
    coeffs = [dr.opaque(mi.Float, c) for c in zonal_lobe(phong_attenuation(40.0, 8), (0.8, 0.12, 0.5))]
    proxy = proxy_lobe((0.0, 0.0, 1.0), (0.8, 0.12, 0.5), 0.3, 0.7, 40.0)
    d, pdf = mixture.sample(coeffs, mi.Point2f(rng.random((2, count)).astype(np.float32)), proxy)
    again = mixture.pdf(coeffs, d, proxy)
    assert np.all(pdf.numpy() > 0)
    np.testing.assert_allclose(again.numpy(), pdf.numpy(), rtol=PDF_ROUND_TRIP_RTOL)
    # Some samples land on the sun: the emitter's part draws it.
    on_sun = dr.dot(d, mi.Vector3f(sky.sun)).numpy() > math.cos(math.radians(0.5))
    assert on_sun.mean() > 0.01


# ------------------------------------------------------------ the renders

@pytest.mark.parametrize("sky, integrator", [
    (HIGH_SUN, {"type": "sh_direct", "max_bands": 5}),
    (HIGH_SUN, {"type": "sh_direct", "max_bands": 5, "strategy": "product"}),
    (LOW_SUN, {"type": "sh_direct", "max_bands": 5, "strategy": "product_only"}),
    (LOW_SUN, {"type": "sh_path", "max_bands": 5, "max_depth": 3, "strategy": "product"}),
    (CONSTANT, {"type": "sh_direct", "max_bands": 5, "strategy": "product"}),
], ids=["high_sun_auto", "high_sun_product", "low_sun_product_only", "low_sun_path", "constant_product"])
def test_renders_under_skies_are_unbiased(sky, integrator):
    scene = make_scene(environment=sky, materials=SKY_MATERIALS)
    sh = mi.load_dict(integrator)
    env = sh.scenes.get(scene)
    assert env.active and env.sky is not None
    assert (env.sky.sun is not None) == (sky["type"] == "sunsky")
    depth = integrator.get("max_depth", 2)
    # Sun-lit glossy pixels are heavy-tailed: 16 x 32 spp, as for the other sun tests.
    assert_unbiased(scene, sh, mi.load_dict({"type": "path", "max_depth": depth}), spp=32, passes=16)


def test_a_changed_sky_rebuilds_the_state_and_stays_unbiased():
    scene = make_scene(environment=HIGH_SUN, materials=SKY_MATERIALS)
    sh = mi.load_dict({"type": "sh_direct", "max_bands": 5, "strategy": "product"})
    before = sh.scenes.get(scene)
    params = mi.traverse(scene)
    key = next(k for k in params.keys() if k.endswith("turbidity"))
    params[key] = 6.0
    params.update()
    after = sh.scenes.get(scene)
    assert after is not before and after.sky.total != before.sky.total
    assert_unbiased(scene, sh, mi.load_dict({"type": "path", "max_depth": 2}), spp=32, passes=16)


def test_the_oracle_leaves_a_sunsky_to_mitsubas_sampling_and_is_unbiased():
    scene = make_scene(environment=LOW_SUN, materials=SKY_MATERIALS)
    oracle = mi.load_dict({"type": "oracle_direct"})
    env = oracle.scenes.get(scene)
    assert "'SunskyEmitter', not one of 'envmap'" in env.reason
    assert_unbiased(scene, oracle, mi.load_dict({"type": "path", "max_depth": 2}))
