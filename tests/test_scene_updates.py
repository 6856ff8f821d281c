"""Specification: the SH integrators' per-scene state (pyramid, lobe table) follows
parameter updates made through ``mi.traverse`` + ``params.update()``.

The renders use product sampling alone (``bsdf_samples`` 0): with MIS, BSDF
sampling would hide stale state (it covers every direction, so a stale pyramid
or lobe costs only variance); alone, a pyramid that still thinks a lit region
is black, or a lobe narrower than the BSDF, misses light and is biased.
"""

import mitsuba as mi
import numpy as np
import pytest

import mitsuba_shsampling  # noqa: F401  (registers the plugins)

mi.set_variant("llvm_ad_rgb")

from mitsuba_shsampling.envmap import EnvPyramid  # noqa: E402
from mitsuba_shsampling.envmap.synthetic import envmap_emitter  # noqa: E402

RES, SPP, PASSES = 16, 16, 8
PATCH = (slice(2, 12), slice(21, 45))  # rows, columns (halo included) of the traversed data


def make_scene():
    """A GGX sphere (alpha 0.05) under a grey map with a black patch in its upper sky."""
    image = np.full((32, 64, 3), 0.2, np.float32)
    image[2:12, 20:44] = 0.0
    return mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 30,
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 4], target=[0, 0, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": RES, "height": RES, "rfilter": {"type": "box"}}},
        "s": {"type": "sphere", "bsdf": {"type": "roughconductor", "alpha": 0.05}},
        "env": envmap_emitter(image),
    })


def product_only():
    return mi.load_dict({"type": "sh_direct", "emitter_samples": 2, "bsdf_samples": 0,
                         "mis_compensation": False, "max_bands": 6})


def light_the_patch(scene):
    params = mi.traverse(scene)
    data = params["env.data"].numpy()
    data[PATCH] = 30.0
    params["env.data"] = mi.TensorXf(data)
    params.update()


def roughen_the_sphere(scene):
    params = mi.traverse(scene)
    params["s.bsdf.alpha.value"] = 0.5
    params.update()


def image_means(scene, integrator):
    return np.array([np.array(mi.render(scene, integrator=integrator, spp=SPP, seed=100 + k)).mean()
                     for k in range(PASSES)])


def test_state_is_reused_while_no_parameter_changes():
    scene, integrator = make_scene(), product_only()
    mi.render(scene, integrator=integrator, spp=1)
    first = integrator.scenes.get(scene)
    mi.render(scene, integrator=integrator, spp=1, seed=1)
    assert integrator.scenes.get(scene) is first


def test_an_envmap_data_update_rebuilds_the_pyramid_from_the_new_data():
    scene, integrator = make_scene(), product_only()
    before = integrator.scenes.get(scene).pyramid
    light_the_patch(scene)
    after = integrator.scenes.get(scene).pyramid
    assert after is not before
    assert after.radiant_total == pytest.approx(EnvPyramid(scene.environment()).radiant_total, rel=1e-6)
    assert after.radiant_total > 2 * before.radiant_total


def test_an_in_place_write_to_the_envmap_scale_is_noticed():
    scene, integrator = make_scene(), product_only()
    before = integrator.scenes.get(scene)
    params = mi.traverse(scene)
    params["env.scale"][0] = 3.0
    params.update()
    after = integrator.scenes.get(scene)
    assert after is not before
    assert after.pyramid.radiant_total == pytest.approx(3 * before.pyramid.radiant_total, rel=1e-5)


def test_a_bsdf_update_refits_the_lobe_table():
    scene, integrator = make_scene(), product_only()
    before = integrator.scenes.get(scene).lobes
    roughen_the_sphere(scene)
    after = integrator.scenes.get(scene).lobes
    assert after is not before
    # The fitted Phong exponents (last parameter) follow the roughness: far wider lobes.
    exponent = lambda lobes: max(fit[..., 2].max() for fit in lobes.fits.values())  # noqa: E731
    assert exponent(after) < exponent(before) / 10


@pytest.mark.parametrize("update", [light_the_patch, roughen_the_sphere])
def test_after_an_update_sh_direct_agrees_with_mitsubas_direct(update):
    scene, integrator = make_scene(), product_only()
    mi.render(scene, integrator=integrator, spp=1)  # build the state from the old parameters
    update(scene)
    sh, direct = image_means(scene, integrator), image_means(scene, mi.load_dict({"type": "direct"}))
    assert np.all(np.isfinite(sh))
    se = np.sqrt(sh.var(ddof=1) / PASSES + direct.var(ddof=1) / PASSES)
    z = (sh.mean() - direct.mean()) / se
    assert abs(z) < 5, f"image mean {sh.mean():.4g} vs direct {direct.mean():.4g}: {z:.1f} standard errors"


def hair_scene():
    """make_scene's map over a GGX sphere and a hair-BSDF sphere set by melanin concentration,
    whose ``sigma_a`` parameter ``mi.traverse`` lists without a value."""
    scene = make_scene()
    return mi.load_dict({
        "type": "scene", "sensor": scene.sensors()[0], "env": scene.environment(),
        "s": {"type": "sphere", "center": [-0.6, 0, 0], "radius": 0.5,
              "bsdf": {"type": "roughconductor", "alpha": 0.2}},
        "h": {"type": "sphere", "center": [0.6, 0, 0], "radius": 0.5,
              "bsdf": {"type": "hair", "eumelanin": 1.3}},
    })


def test_a_bsdf_parameter_without_a_value_is_skipped_and_its_other_parameters_still_key_the_state():
    scene, integrator = hair_scene(), product_only()
    image = np.array(mi.render(scene, integrator=integrator, spp=2))
    assert np.all(np.isfinite(image)) and image.mean() > 0
    first = integrator.scenes.get(scene)
    assert integrator.scenes.get(scene) is first
    assert first.active  # the GGX sphere is product sampled; the hair keeps Mitsuba's sampling
    params = mi.traverse(scene)
    params["h.bsdf.eumelanin"] = 0.4
    params.update()
    assert integrator.scenes.get(scene) is not first
