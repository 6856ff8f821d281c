"""Specification of ``python -m mitsuba_shsampling render``: a drop-in for the ``mitsuba``
executable that knows the project's plugins."""

import os
import subprocess
import sys

import mitsuba as mi
import numpy as np
import pytest

import mitsuba_shsampling  # noqa: F401  (registers the plugins)

mi.set_variant("llvm_ad_rgb")

from mitsuba_shsampling import cli, scenes  # noqa: E402
from mitsuba_shsampling.render import RenderError, parse_defines, parse_integrator, pass_plan  # noqa: E402

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_render_writes_a_finite_exr_of_the_requested_size_with_a_python_plugin(tmp_path):
    out = tmp_path / "out.exr"
    env = dict(os.environ, PYTHONPATH=REPO + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.run([sys.executable, "-m", "mitsuba_shsampling", "render",
                           scenes.builtin_scenes()["sphere_ggx010"], "--integrator", "sh_path",
                           "--spp", "6", "--passes", "3", "-o", str(out), "-D", "res=12"],
                          env=env, cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "6/6 [" in proc.stderr  # the progress bar, complete
    # The plan, before the passes: how it was made, what it cost, each material's strategy.
    assert "plan (estimate, set-up " in proc.stdout and "material: " in proc.stdout.split("plan (")[1]
    image = np.array(mi.Bitmap(str(out)))
    assert image.shape == (12, 12, 3)
    assert np.all(np.isfinite(image)) and image.mean() > 0


def test_the_written_image_is_the_spp_weighted_mean_of_the_passes(tmp_path):
    path = scenes.builtin_scenes()["sphere_ggx010"]
    out = tmp_path / "mean.exr"
    assert cli.main(["render", path, "-D", "res=8", "--spp", "5", "--passes", "2", "--seed", "7",
                     "--no-progress", "-o", str(out)]) == 0
    scene = mi.load_file(path, res="8")
    passes = [np.array(mi.render(scene, spp=spp, seed=seed)) for spp, seed in ((3, 7), (2, 8))]
    np.testing.assert_allclose(np.array(mi.Bitmap(str(out))), (3 * passes[0] + 2 * passes[1]) / 5,
                               rtol=1e-5, atol=1e-6)


def test_a_builtin_scene_name_and_an_xml_integrator_chosen_by_define_work(tmp_path):
    out = tmp_path / "named.png"
    assert cli.main(["render", "sphere_diffuse", "-D", "res=6", "-D", "integrator=sh_direct",
                     "--spp", "1", "--no-progress", "-o", str(out)]) == 0
    assert np.array(mi.Bitmap(str(out))).shape == (6, 6, 3)


def test_integrator_parameters_are_read_with_the_types_the_plugins_check():
    desc = parse_integrator("sh_direct:emitter_samples=2, bsdf_samples=0,defensive_share=0.25,"
                            "hide_emitters=True,strategy=product_only,mis_compensation=false")
    assert desc == {"type": "sh_direct", "emitter_samples": 2, "bsdf_samples": 0, "defensive_share": 0.25,
                    "hide_emitters": True, "strategy": "product_only", "mis_compensation": False}
    assert [type(desc[k]) for k in ("emitter_samples", "defensive_share", "hide_emitters", "strategy")] == [
        int, float, bool, str]
    assert parse_integrator("path") == {"type": "path"}


def test_the_integrator_renders_with_the_parameters_given_on_the_command_line(tmp_path):
    """max_depth=1 sees only the emitters: what Mitsuba's path renders with that parameter."""
    path = scenes.builtin_scenes()["sphere_diffuse"]
    out = tmp_path / "depth1.exr"
    assert cli.main(["render", path, "-D", "res=8", "--integrator", "path:max_depth=1", "--spp", "2",
                     "--seed", "3", "--no-progress", "-o", str(out)]) == 0
    scene = mi.load_file(path, res="8")
    expected = mi.render(scene, integrator=mi.load_dict({"type": "path", "max_depth": 1}), spp=2, seed=3)
    np.testing.assert_allclose(np.array(mi.Bitmap(str(out))), np.array(expected), rtol=1e-5, atol=1e-6)


def test_a_project_plugin_takes_integer_float_boolean_and_text_parameters(tmp_path):
    out = tmp_path / "product_only.exr"
    assert cli.main(["render", "sphere_diffuse", "-D", "res=4", "--spp", "1", "--no-progress", "-o", str(out),
                     "--integrator", "sh_direct:emitter_samples=1,bsdf_samples=1,defensive_share=0.5,"
                                     "hide_emitters=true,strategy=product_only"]) == 0
    assert np.all(np.isfinite(np.array(mi.Bitmap(str(out)))))


def test_envmap_replaces_the_scenes_map_and_keeps_its_integrator(tmp_path):
    """``--envmap FILE`` renders what the scene renders with FILE as its map (here set through
    the scene's own $envmap parameter), with the scene's integrator (direct, not Mitsuba's
    default path)."""
    path = scenes.builtin_scenes()["sphere_diffuse"]
    out = tmp_path / "swapped.exr"
    assert cli.main(["render", path, "-D", "res=8", "-D", "integrator=direct", "--envmap", scenes.STUDIO_MAP,
                     "--spp", "2", "--seed", "5", "--no-progress", "-o", str(out)]) == 0
    scene = mi.load_file(path, res="8", integrator="direct", envmap=scenes.STUDIO_MAP)
    expected = np.array(mi.render(scene, spp=2, seed=5))
    np.testing.assert_allclose(np.array(mi.Bitmap(str(out))), expected, rtol=1e-4, atol=1e-5)
    default = np.array(mi.render(mi.load_file(path, res="8", integrator="direct"), spp=2, seed=5))
    assert not np.allclose(expected, default, rtol=1e-2)  # another map: another image


@pytest.mark.parametrize("argv, message", [
    (["missing.xml"], "scene file not found: missing.xml"),
    (["sphere_diffuse", "--integrator", "no_such_plugin_xyz"],
     "cannot load the integrator 'no_such_plugin_xyz': At dictionary node \"root\": failed to instantiate "
     "unknown plugin of type \"no_such_plugin_xyz\""),
    (["sphere_diffuse", "--integrator", "diffuse"], "'diffuse' is a BSDF plugin, not an integrator"),
    (["sphere_diffuse", "--integrator", "sh_path:max_depth=-3"],
     "OptionError: sh_path: parameter 'max_depth' must be -1 (infinite) or >= 0, got integer -3"),
    (["sphere_diffuse", "--integrator", "path:max_depth"], "--integrator parameters are NAME=VALUE"),
    (["sphere_diffuse", "--integrator", ":max_depth=2"], "--integrator expects TYPE[:NAME=VALUE,...]"),
    (["sphere_diffuse", "--integrator", "path:max_depth=2,max_depth=3"], "sets 'max_depth' twice"),
    (["sphere_diffuse", "--envmap", "no_such_map.exr"], "environment map not found: no_such_map.exr"),
    (["area_light", "--envmap", scenes.STUDIO_MAP], "no envmap emitter to replace"),
    (["sphere_diffuse", "-D", "res"], "-D expects NAME=VALUE, got 'res'"),
    (["sphere_diffuse", "-D", "undeclared=1"], "Found unused parameters: - $undeclared=1"),
    (["sphere_diffuse", "--integrator", "sh_path", "--passes", "9", "--spp", "4"], "--passes must be in [1, spp = 4]"),
    (["sphere_diffuse", "--variant", "scalar_rgb"], "variant 'scalar_rgb' is not supported"),
    (["sphere_diffuse", "--spp", "0"], "--spp must be >= 1, got 0"),
])
def test_bad_input_is_one_line_and_exit_code_2(argv, message, capsys, tmp_path):
    assert cli.main(["render", *argv, "--no-progress", "-o", str(tmp_path / "x.exr")]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1


@pytest.mark.parametrize("output, message", [
    ("no_such_folder/x.exr", "the folder"),
    ("x.tiff", "the output format follows the extension"),
    ("x", "the output format follows the extension"),
])
def test_an_output_path_that_cannot_be_written_is_refused_before_rendering(output, message, capsys, tmp_path,
                                                                          monkeypatch):
    def no_render(*args, **kwargs):
        raise AssertionError("rendered before checking the output path")

    monkeypatch.setattr(mi, "render", no_render)
    assert cli.main(["render", "sphere_diffuse", "-D", "res=4", "--spp", "1", "--no-progress",
                     "-o", str(tmp_path / output)]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1


def test_a_plugin_parameter_error_in_the_scene_file_is_reported_in_one_line(tmp_path, capsys):
    scene = tmp_path / "bad.xml"
    scene.write_text('<scene version="3.0.0"><integrator type="sh_path">'
                     '<integer name="max_depth" value="-3"/></integrator></scene>')
    assert cli.main(["render", str(scene), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.endswith("OptionError: sh_path: parameter 'max_depth' must be -1 (infinite) or >= 0, got integer -3")
    assert len(err.splitlines()) == 1


def test_pass_plan_splits_spp_evenly_and_checks_its_input():
    assert pass_plan(40) == [14, 13, 13]
    assert pass_plan(5, 2) == [3, 2] and pass_plan(16) == [16]
    with pytest.raises(RenderError):
        pass_plan(0)
    with pytest.raises(RenderError):
        pass_plan(4, 5)


def test_defines_keep_everything_after_the_first_equals_sign():
    assert parse_defines(["a=1", "path=x=y.exr", "empty="]) == {"a": "1", "path": "x=y.exr", "empty": ""}
