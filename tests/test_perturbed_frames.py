"""Specification of the lobes of frame-perturbing wrappers (``bumpmap``, ``normalmap``).

The product strategy orients a wrapper's lobe about the normal the wrapper hands
its nested BSDF. That normal is ours (``lobes/perturbed_frames.py``), so it is
checked against Mitsuba's: the wrapper's ``eval`` equals its nested BSDF's
``eval`` in the frame of our normal. (A wrong normal would cost variance, never
bias: the pdf of the product sampler is exact for any lobe.)
"""

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

mi.set_variant("llvm_ad_rgb")

from mitsuba_shsampling.lobes import SceneLobes  # noqa: E402
from mitsuba_shsampling.lobes.perturbed_frames import PerturbedNormal  # noqa: E402

from test_coverage import BSDFS  # noqa: E402


def hits(bsdf: dict, count=4096, seed=3):
    """Camera-like hits on a sphere with the wrapper, from random directions above it."""
    scene = mi.load_dict({"type": "scene", "ball": {"type": "sphere", "bsdf": bsdf}})
    rng = np.random.default_rng(seed)
    target = rng.normal(size=(count, 3)) * 0.4
    origin = np.tile([0.0, 0.0, 6.0], (count, 1)) + rng.normal(size=(count, 3))
    d = target - origin
    ray = mi.Ray3f(mi.Point3f(*origin.T.astype(np.float32)), mi.Vector3f(*(d / np.linalg.norm(d, axis=1)[:, None]).T.astype(np.float32)))
    si = scene.ray_intersect(ray)
    return scene, si


@pytest.mark.parametrize("name", ["bumpmap", "normalmap"])
def test_the_lobe_is_oriented_about_the_normal_mitsuba_shades_with(name):
    # Without the wrapper's shadowing term (a factor <= 1 on top of the nested BSDF).
    scene, si = hits(dict(BSDFS[name], use_shadowing_function=False))
    wrapper = scene.shapes()[0].bsdf()
    nested = mi.load_dict(BSDFS[name]["bsdf"])
    normal = PerturbedNormal(wrapper).local_normal(si, si.is_valid())
    assert np.mean(np.array(normal.z) < 0.999) > 0.3, "the test needs perturbed normals"

    # Directions where the wrapper reflects: its own samples.
    ctx = mi.BSDFContext()
    u = np.random.default_rng(5).random((3, dr.width(si))).astype(np.float32)
    bs, _ = wrapper.sample(ctx, si, mi.Float(u[0]), mi.Point2f(u[1], u[2]), si.is_valid())
    wo_world = si.to_world(bs.wo)
    expected = wrapper.eval(ctx, si, si.to_local(wo_world), si.is_valid())

    perturbed = mi.SurfaceInteraction3f(si)
    perturbed.sh_frame = mi.Frame3f(si.to_world(normal))
    perturbed.wi = perturbed.to_local(si.to_world(si.wi))
    wo = perturbed.to_local(wo_world)
    # Mitsuba's wrappers also drop directions on opposite sides of the two frames.
    same_side = si.to_local(wo_world).z * wo.z > 0
    value = dr.select(same_side & si.is_valid(), nested.eval(ctx, perturbed, wo), 0.0)

    e, v = np.array(expected)[0], np.array(value)[0]
    lit = e > 1e-3
    assert lit.sum() > 1000
    close = np.abs(v - e) <= 2e-3 * np.maximum(e, 1.0) + 1e-4
    assert close[lit].mean() > 0.99, f"{close[lit].mean():.3f} of lit lanes agree"


def test_unperturbed_lanes_keep_the_shading_normal():
    scene, si = hits({"type": "roughconductor", "alpha": 0.1})
    lobes = SceneLobes(scene, max_bands=5)
    normal = np.array(lobes.local_normals(si, si.is_valid()))
    assert np.all(normal == np.array([[0.0], [0.0], [1.0]]))


def test_a_wrapper_whose_normal_is_degenerate_falls_back_to_the_shading_normal():
    data = np.full((4, 4, 3), 0.5, np.float32)  # (0, 0, 0) after the [0, 1] -> [-1, 1] map
    flat = {"type": "normalmap", "normalmap": {"type": "bitmap", "bitmap": mi.Bitmap(data), "raw": True},
            "bsdf": {"type": "roughconductor", "alpha": 0.1}}
    scene, si = hits(flat)
    normal = np.array(PerturbedNormal(scene.shapes()[0].bsdf()).local_normal(si, si.is_valid()))
    assert np.all(np.isfinite(normal)) and np.allclose(normal[:, np.array(si.is_valid())], [[0.0], [0.0], [1.0]])
