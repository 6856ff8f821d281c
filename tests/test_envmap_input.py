"""Specification: bad environment maps. Non-finite texels are set to 0 in the emitter
itself (the whole render sees a finite map); a ``to_world`` the pyramid cannot follow
is refused with a one-line reason."""

import warnings

import mitsuba as mi
import numpy as np
import pytest

import mitsuba_shsampling  # noqa: F401  (registers the plugins)

mi.set_variant("llvm_ad_rgb")

from mitsuba_shsampling import cli  # noqa: E402
from mitsuba_shsampling.envmap import EnvmapError  # noqa: E402
from mitsuba_shsampling.envmap.synthetic import envmap_emitter, sun_sky_latlong  # noqa: E402

RES = 16


def scene_with(emitter):
    return mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 40,
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 4], target=[0, 0, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": RES, "height": RES, "rfilter": {"type": "box"}}},
        "sphere": {"type": "sphere", "bsdf": {"type": "diffuse"}},
        "env": emitter,
    })


def map_with_nan_patch():
    image = sun_sky_latlong(8, 16, sun_radiance=50.0)
    image[2:4, 3:6, :] = np.nan  # six texels, large enough for BSDF samples to hit
    image[5, 9, 1] = np.inf      # and one texel with a single bad channel
    return image


def test_mitsubas_own_direct_renders_nan_from_the_unsanitised_map():
    # The premise: without sanitising, the texels poison the image.
    image = np.array(mi.render(scene_with(envmap_emitter(map_with_nan_patch())),
                               integrator=mi.load_dict({"type": "direct"}), spp=16))
    assert np.isnan(image).any()


def test_nan_texels_are_set_to_zero_in_the_emitter_for_the_whole_render():
    scene = scene_with(envmap_emitter(map_with_nan_patch()))
    with pytest.warns(RuntimeWarning, match=r"7 with a NaN or infinite channel were set to 0 in the "
                                            r"envmap emitter's own data, for the whole render"):
        image = np.array(mi.render(scene, integrator=mi.load_dict({"type": "sh_direct"}), spp=16))
    assert np.all(np.isfinite(image))
    assert np.all(np.isfinite(mi.traverse(scene.environment())["data"].numpy()))
    # Mitsuba's own strategies now see the same finite map.
    assert np.all(np.isfinite(np.array(mi.render(scene, integrator=mi.load_dict({"type": "direct"}), spp=16))))


def test_the_sanitised_render_agrees_with_direct_on_the_map_with_those_texels_zeroed():
    clean = map_with_nan_patch()
    clean[~np.all(np.isfinite(clean), axis=-1)] = 0.0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        sh = [np.array(mi.render(scene_with(envmap_emitter(map_with_nan_patch())),
                                 integrator=mi.load_dict({"type": "sh_direct"}), spp=16, seed=k)).mean()
              for k in range(6)]
    reference = scene_with(envmap_emitter(clean))
    direct = [np.array(mi.render(reference, integrator=mi.load_dict({"type": "direct"}), spp=16,
                                 seed=k)).mean() for k in range(6)]
    se = np.sqrt(np.var(sh, ddof=1) / 6 + np.var(direct, ddof=1) / 6)
    assert abs(np.mean(sh) - np.mean(direct)) < 5 * se


def test_a_map_too_dim_for_float32_cell_integrals_is_left_to_mitsubas_sampling():
    """Radiance ~1e-24: the pyramid's cell integrals would near the float32 denormals, whose
    sums are off by percents. The map is sampled as black, with a warning; the integrator then
    samples it with Mitsuba's own emitter sampling and agrees with Mitsuba's direct."""
    image = sun_sky_latlong(8, 16, sun_radiance=50.0) * np.float32(1e-24)
    with pytest.warns(RuntimeWarning, match=r"below 1e-20.*sampled as black"):
        sh = [np.array(mi.render(scene_with(envmap_emitter(image)), integrator=mi.load_dict({"type": "sh_direct"}),
                                 spp=16, seed=k), dtype=np.float64) for k in range(6)]
    direct = [np.array(mi.render(scene_with(envmap_emitter(image)), integrator=mi.load_dict({"type": "direct"}),
                                 spp=16, seed=k), dtype=np.float64) for k in range(6)]
    assert all(np.all(np.isfinite(x)) for x in sh) and min(x.max() for x in sh) > 0
    sh_means, direct_means = [x.mean() for x in sh], [x.mean() for x in direct]
    se = np.sqrt(np.var(sh_means, ddof=1) / 6 + np.var(direct_means, ddof=1) / 6)
    assert abs(np.mean(sh_means) - np.mean(direct_means)) < 5 * se


def non_rotation_scene():
    return scene_with(envmap_emitter(sun_sky_latlong(8, 16), to_world=mi.ScalarTransform4f().scale(2.0)))


def test_a_scaled_to_world_is_refused_with_a_one_line_reason():
    with pytest.raises(RuntimeError) as info:  # mi.render wraps what the integrator raises
        mi.render(non_rotation_scene(), integrator=mi.load_dict({"type": "sh_direct"}), spp=1)
    cause = info.value.__cause__
    assert isinstance(cause, EnvmapError)
    message = str(cause)
    assert "\n" not in message
    assert "to_world is not a rotation" in message and "singular values 2, 2, 2" in message


def test_the_command_line_prints_that_reason_alone(tmp_path, capsys):
    envmap = tmp_path / "sky.exr"
    mi.Bitmap(sun_sky_latlong(8, 16)).write(str(envmap))
    scene = tmp_path / "scaled_sky.xml"
    scene.write_text(f"""<scene version="3.0.0">
        <sensor type="perspective"><film type="hdrfilm"><integer name="width" value="4"/>
            <integer name="height" value="4"/></film></sensor>
        <shape type="sphere"><bsdf type="diffuse"/></shape>
        <emitter type="envmap"><string name="filename" value="{envmap}"/>
            <transform name="to_world"><scale value="2"/></transform></emitter>
    </scene>""")
    code = cli.main(["render", str(scene), "--integrator", "sh_direct", "--spp", "1", "--no-progress",
                     "-o", str(tmp_path / "out.exr")])
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert err.startswith("mitsuba-shsampling: error: the envmap's to_world is not a rotation")
    assert len(err.splitlines()) == 1
