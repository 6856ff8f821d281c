"""The built-in scenes and environment maps: they load, render, and the baked sky matches sunsky."""

import importlib.util
import os

import numpy as np
import pytest

import mitsuba_shsampling  # noqa: F401  (LLVM backend check)
import mitsuba as mi

mi.set_variant("llvm_ad_rgb")

from mitsuba_shsampling import scenes  # noqa: E402

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def render_tiny(scene: mi.Scene, spp: int = 2) -> np.ndarray:
    return np.array(mi.render(scene, integrator=mi.load_dict({"type": "direct"}), spp=spp, seed=1))


@pytest.mark.parametrize("name", sorted(scenes.builtin_scenes()))
def test_every_builtin_scene_loads_and_renders_a_finite_nonblack_image(name):
    scene = scenes.load_scene(scenes.builtin_scenes()[name], res=16)
    image = render_tiny(scene)
    assert image.shape[1:] == (16, 3)
    assert np.all(np.isfinite(image))
    assert image.mean() > 0


def test_builtin_scenes_cover_the_evaluation_materials():
    names = set(scenes.builtin_scenes())
    for material in ("diffuse", "ggx005", "ggx010", "ggx020", "ggx030", "ggx050",
                     "roughplastic", "principled", "conductor"):
        assert f"sphere_{material}" in names
    assert {"spheres", "material_preview", "material_studio", "interior"} <= names


def test_default_scene_has_an_envmap_and_declares_the_swappable_parameters():
    path = scenes.default_scene_path()
    assert os.path.isfile(path)
    assert {"envmap", "mis_compensation", "res", "spp", "sampler"} <= set(scenes.scene_parameters(path))
    assert scenes.scene_envmap(scenes.load_scene(path, res=8)) is not None


def test_load_scene_sets_resolution_and_swaps_the_envmap():
    path = scenes.builtin_scenes()["sphere_ggx010"]
    sun = render_tiny(scenes.load_scene(path, res=12, envmap=scenes.SUNSKY_MAP))
    studio = render_tiny(scenes.load_scene(path, res=12, envmap=scenes.STUDIO_MAP))
    assert sun.shape == studio.shape == (12, 12, 3)
    assert not np.allclose(sun, studio, rtol=0.05)


def test_load_scene_accepts_mis_compensation_on_envmap_scenes_only():
    scene = scenes.load_scene(scenes.builtin_scenes()["sphere_ggx010"], res=8, mis_compensation=True)
    assert np.all(np.isfinite(render_tiny(scene)))
    with pytest.raises(scenes.SceneError, match="mis_compensation"):
        scenes.load_scene(scenes.builtin_scenes()["area_light"], mis_compensation=True)


def test_scene_without_envmap_is_reported_as_such():
    scene = scenes.load_scene(scenes.builtin_scenes()["area_light"], res=8)
    assert scenes.scene_envmap(scene) is None


def test_load_scene_rejects_missing_files_and_undeclared_parameters():
    with pytest.raises(scenes.SceneError, match="not found"):
        scenes.load_scene("/nonexistent/scene.xml")
    with pytest.raises(scenes.SceneError, match="envmap"):
        scenes.load_scene(scenes.builtin_scenes()["area_light"], envmap=scenes.SUNSKY_MAP)
    with pytest.raises(scenes.SceneError, match="not found"):
        scenes.load_scene(scenes.default_scene_path(), envmap="/nonexistent/map.exr")


@pytest.mark.parametrize("path", [scenes.SUNSKY_MAP, scenes.STUDIO_MAP])
def test_shipped_maps_are_small_finite_nonnegative_latlong_images(path):
    assert os.path.getsize(path) < 2_000_000
    image = np.array(mi.Bitmap(path))
    assert image.shape == (256, 512, 3)
    assert np.all(np.isfinite(image)) and image.min() >= 0


def load_bake_script():
    spec = importlib.util.spec_from_file_location("bake_sunsky", os.path.join(REPO, "scripts", "bake_sunsky.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_baked_sunsky_map_loaded_as_envmap_reproduces_sunsky_sky_radiance():
    bake = load_bake_script()
    envmap = mi.load_dict({"type": "envmap", "filename": scenes.SUNSKY_MAP})
    sky = bake.load_sunsky(sun_scale=0.0)
    rng = np.random.default_rng(3)
    d = rng.normal(size=(3, 512))
    d /= np.linalg.norm(d, axis=0)
    away_from_sun = bake.sun_direction_env() @ d < np.cos(np.radians(5))
    d = d[:, (d[1] > 0.05) & away_from_sun]
    L_env, L_sky = bake.eval_emitter(envmap, d), bake.eval_emitter(sky, d)
    assert np.all(L_sky > 0)
    np.testing.assert_allclose(L_env, L_sky, rtol=0.02)


def test_baked_sunsky_map_has_its_brightest_texel_at_the_sun():
    bake = load_bake_script()
    image = np.array(mi.Bitmap(scenes.SUNSKY_MAP)).mean(axis=-1)
    row, col = np.unravel_index(np.argmax(image), image.shape)
    u, theta = (col + 0.5) / image.shape[1], row * np.pi / (image.shape[0] - 1)
    d = bake.env_direction(np.array([u]), np.array([theta]))[:, 0]
    angle = np.degrees(np.arccos(np.clip(d @ bake.sun_direction_env(), -1, 1)))
    assert angle < 1.0


def test_baked_sunsky_map_keeps_the_irradiance_of_sun_and_sky():
    bake = load_bake_script()
    envmap = mi.load_dict({"type": "envmap", "filename": scenes.SUNSKY_MAP})
    E_map = bake.irradiance_up(envmap, 1 << 20)
    E_sunsky = bake.irradiance_up(bake.load_sunsky(), 1 << 20)
    np.testing.assert_allclose(E_map, E_sunsky, rtol=0.03)


def test_load_scene_gives_the_scene_objects_the_same_registry_order_every_time():
    """Loaded serially: in parallel the BSDFs' registry ids come in a different order from
    load to load, and so does the order in which Dr.Jit traces their code, which makes
    every run's kernels new to its kernel cache (seconds of compilation a first render)."""
    from mitsuba_shsampling.scene_materials import registry_id, scene_materials

    path = scenes.builtin_scenes()["material_studio"]

    def names_by_id():
        scene = scenes.load_scene(path, res=8, spp=1)
        return [m.name for m in sorted(scene_materials(scene), key=lambda m: registry_id(m.bsdf))]

    first = names_by_id()
    assert len(first) >= 8
    assert all(names_by_id() == first for _ in range(4))
