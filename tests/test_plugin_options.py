"""Specification of the plugins' parameters (integrators/options.py): types, ranges,
Mitsuba's max_depth conventions, defaults and the generated documentation."""

import dataclasses

import mitsuba as mi
import numpy as np
import pytest

import mitsuba_shsampling  # noqa: F401  (registers the plugins)

mi.set_variant("llvm_ad_rgb")

from mitsuba_shsampling.envmap.synthetic import envmap_emitter, sun_sky_latlong  # noqa: E402
from mitsuba_shsampling.integrators.options import (  # noqa: E402
    DEFAULT_SH_DEPTH, MAX_BANDS, MIN_BANDS, DirectOptions, OptionError, OraclePathOptions, PathOptions)
from mitsuba_shsampling.lobes.scene_lobes import DIFFUSE_BANDS  # noqa: E402
from mitsuba_shsampling.sh.basis import MAX_ORDER  # noqa: E402
from mitsuba_shsampling.warp.hierarchy import MAX_DEPTH  # noqa: E402
from mitsuba_shsampling.warp.product import DEFAULT_DEFENSIVE_SHARE  # noqa: E402


def load_error(props) -> str:
    with pytest.raises(RuntimeError) as info:
        mi.load_dict(props)
    return str(info.value)


@pytest.mark.parametrize("plugin, name, value, expected, kind", [
    ("sh_direct", "max_bands", "8", "an integer", "string '8'"),
    ("sh_direct", "max_bands", 8.0, "an integer", "float 8.0"),
    ("sh_direct", "max_bands", True, "an integer", "boolean True"),
    ("sh_direct", "sh_depth", "3", "an integer", "string '3'"),
    ("sh_direct", "emitter_samples", 1.5, "an integer", "float 1.5"),
    ("sh_direct", "mis_compensation", 1, "a boolean", "integer 1"),
    ("sh_direct", "defensive_share", "0.1", "a float", "string '0.1'"),
    ("sh_direct", "proxy_depth", 6.0, "an integer", "float 6.0"),
    ("sh_path", "max_depth", "4", "an integer", "string '4'"),
    ("sh_path", "rr_depth", 5.0, "an integer", "float 5.0"),
    ("sh_path", "product_depth", 1.0, "an integer", "float 1.0"),
])
def test_a_parameter_of_the_wrong_type_names_plugin_parameter_expected_type_and_value(
        plugin, name, value, expected, kind):
    message = load_error({"type": plugin, name: value})
    assert f"{plugin}: parameter '{name}' must be {expected}, got {kind}" in message


def test_a_float_parameter_also_takes_an_integer_as_mitsubas_do():
    assert mi.load_dict({"type": "sh_path", "defensive_share": 1}).options.defensive_share == 1.0


def test_hide_emitters_of_the_wrong_type_is_refused_by_mitsubas_own_property_check():
    assert 'The property "hide_emitters" has the wrong type' in load_error({"type": "sh_path", "hide_emitters": 1})


@pytest.mark.parametrize("plugin, name, value, requirement", [
    ("sh_path", "max_depth", -2, "must be -1 (infinite) or >= 0"),
    ("sh_path", "rr_depth", 0, "must be > 0"),
    ("sh_path", "product_depth", 0, "must be -1 (every vertex) or >= 1"),
    ("sh_prb", "product_depth", -2, "must be -1 (every vertex) or >= 1"),
    ("sh_direct", "emitter_samples", -1, "must be >= 0"),
    ("sh_direct", "bsdf_samples", -1, "must be >= 0"),
    ("sh_direct", "sh_depth", -2, f"must be in [1, {MAX_DEPTH}] or -1 (automatic)"),
    ("sh_path", "max_bands", MAX_BANDS + 1, f"must be in [{MIN_BANDS}, {MAX_BANDS}]"),
    ("sh_path", "defensive_share", 1.5, "must be in (0, 1]"),
    ("sh_path", "proxy_depth", MAX_DEPTH + 1, f"must be in [0, {MAX_DEPTH}]"),
])
def test_a_parameter_out_of_range_names_the_allowed_range(plugin, name, value, requirement):
    kind = "float" if isinstance(value, float) else "integer"
    assert f"{plugin}: parameter '{name}' {requirement}, got {kind} {value}" in load_error({"type": plugin, name: value})


def test_a_misspelled_parameter_is_reported_by_mitsubas_parser():
    assert "max_bandz" in load_error({"type": "sh_direct", "max_bandz": 5})


def test_limits_and_defaults_come_from_the_modules_that_impose_them():
    assert (MIN_BANDS, MAX_BANDS) == (DIFFUSE_BANDS, MAX_ORDER + 1)
    assert PathOptions().defensive_share == DEFAULT_DEFENSIVE_SHARE
    PathOptions(sh_depth=MAX_DEPTH)
    with pytest.raises(OptionError, match="sh_depth"):
        PathOptions(sh_depth=MAX_DEPTH + 1)


def test_options_validate_outside_plugins_too():
    assert PathOptions(max_depth=0).max_depth == 0
    with pytest.raises(OptionError, match="sh_path: parameter 'max_depth'"):
        PathOptions(max_depth=-5)
    assert DirectOptions(sh_depth=-1).warp_sh_depth is None and DirectOptions().warp_sh_depth == DEFAULT_SH_DEPTH


def small_scene(pixel_format="rgba"):
    return mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 40,
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 4], target=[0, 0, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 8, "height": 8, "pixel_format": pixel_format}},
        "sphere": {"type": "sphere", "bsdf": {"type": "roughconductor", "alpha": 0.2}},
        "env": envmap_emitter(sun_sky_latlong(16, 32, sun_radiance=20.0)),
    })


@pytest.mark.parametrize("max_depth", [0, 1])
def test_sh_path_renders_what_mitsubas_path_renders_at_max_depth_0_and_1(max_depth):
    # 0: nothing at all (black, alpha 0); 1: only the directly visible environment.
    scene = small_scene()
    images = [np.array(mi.render(scene, integrator=mi.load_dict({"type": name, "max_depth": max_depth}),
                                 spp=4, seed=5)) for name in ("path", "sh_path")]
    np.testing.assert_allclose(images[1], images[0], rtol=1e-5, atol=1e-6)
    if max_depth == 0:
        assert not np.any(images[1])
    else:
        assert images[1][..., 3].min() == 1 and images[1][..., :3].max() > 0


@pytest.mark.parametrize("plugin, options", [("sh_direct", DirectOptions), ("sh_path", PathOptions)])
def test_plugins_build_their_lobes_with_their_own_max_bands_default(plugin, options):
    integrator = mi.load_dict({"type": plugin})
    env = integrator.scenes.get(small_scene())
    assert env.lobes.max_bands == options().max_bands
    assert integrator.options == options()


@pytest.mark.parametrize("plugin, options", [("sh_direct", DirectOptions), ("sh_path", PathOptions),
                                             ("oracle_path", OraclePathOptions)])
def test_the_docstring_lists_every_parameter_with_its_default(plugin, options):
    doc = mi.load_dict({"type": plugin}).__doc__
    for field in dataclasses.fields(options):
        row = doc[doc.index(f"* - {field.name}\n"):]
        default = str(field.default).lower() if isinstance(field.default, bool) else str(field.default)
        assert f"(Default: {default})" in row.split("* -")[1], field.name


@pytest.mark.parametrize("plugin", ["sh_direct", "sh_path", "sh_prb", "oracle_direct", "oracle_path"])
def test_the_docstring_examples_load_in_xml_and_python_with_the_same_parameters(plugin):
    doc = mi.load_dict({"type": plugin}).__doc__
    xml = doc[doc.index(f'<integrator type="{plugin}">'):doc.index("</integrator>") + len("</integrator>")]
    python = doc[doc.index(f"'type': '{plugin}'"):].split("\n")[0]
    from_xml = mi.load_string(xml.replace("<integrator ", '<integrator version="3.0.0" ', 1))
    from_python = mi.load_dict(eval("{" + python + "}"))
    assert from_xml.options == from_python.options


def test_sh_direct_without_bsdf_samples_switches_mis_compensation_off_with_a_warning():
    with pytest.warns(UserWarning, match="'mis_compensation' is switched off"):
        options = DirectOptions(bsdf_samples=0)
    assert not options.mis_compensation
    assert PathOptions().mis_compensation  # sh_path's BSDF samples continue every path
