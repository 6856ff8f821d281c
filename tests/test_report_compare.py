"""``compare`` on scenes written without this project in mind: any camera, content-keyed cache, verdict, NaN texels."""

import copy
import json
import os
import re

import numpy as np
import pytest

import mitsuba_shsampling  # noqa: F401  (LLVM backend check)
import mitsuba as mi

mi.set_variant("llvm_ad_rgb")

from mitsuba_shsampling import cli, scenes  # noqa: E402
from mitsuba_shsampling.report import scene_setup  # noqa: E402
from mitsuba_shsampling.scenes import SceneError  # noqa: E402

#: A plain Mitsuba 3 scene: no <default> at all, its own sampler and a 4:3 film; a textured
#: diffuse ground and a glossy sphere under a small envmap, all files next to it.
PLAIN_SCENE = """<scene version="3.0.0">
    <integrator type="path"/>
    <sensor type="perspective">
        <float name="fov" value="35"/>
        <transform name="to_world"><lookat origin="0, 1.5, 6" target="0, 0, 0" up="0, 1, 0"/></transform>
        <sampler type="stratified"><integer name="sample_count" value="9"/></sampler>
        <film type="hdrfilm"><integer name="width" value="400"/><integer name="height" value="300"/></film>
    </sensor>
    <emitter type="envmap"><string name="filename" value="sky.exr"/></emitter>
    <shape type="sphere">
        <bsdf type="roughconductor"><float name="alpha" value="0.2"/></bsdf>
    </shape>
    <shape type="rectangle">
        <transform name="to_world"><rotate x="1" angle="-90"/><scale value="8"/><translate y="-1"/></transform>
        <bsdf type="diffuse">
            <texture type="bitmap" name="reflectance"><string name="filename" value="{texture}"/></texture>
        </bsdf>
    </shape>
</scene>
"""

#: Direct light from a small, bright area light only: BSDF sampling rarely finds it.
SMALL_LIGHT_SCENE = """<scene version="3.0.0">
    <sensor type="perspective">
        <float name="fov" value="40"/>
        <transform name="to_world"><lookat origin="0, 3, 5" target="0, 0, 0" up="0, 1, 0"/></transform>
        <film type="hdrfilm"><integer name="width" value="16"/><integer name="height" value="16"/></film>
    </sensor>
    <shape type="rectangle">
        <transform name="to_world"><rotate x="1" angle="-90"/><scale value="4"/></transform>
        <bsdf type="diffuse"/>
    </shape>
    <shape type="rectangle">
        <transform name="to_world"><rotate x="1" angle="90"/><scale value="0.05"/><translate y="2"/></transform>
        <emitter type="area"><rgb name="radiance" value="4000"/></emitter>
    </shape>
</scene>
"""


def write_image(path, image):
    mi.Bitmap(np.ascontiguousarray(image, dtype=np.float32)).write(str(path))


def sky(height=16, width=32):
    v = np.linspace(0, 1, height)[:, None, None]
    return np.broadcast_to(0.2 + 2.0 * (1 - v), (height, width, 3)).copy()


@pytest.fixture
def plain_scene(tmp_path):
    write_image(tmp_path / "sky.exr", sky())
    write_image(tmp_path / "checker.exr", np.indices((8, 8)).sum(axis=0)[..., None].repeat(3, -1) % 2 * 0.6 + 0.2)
    (tmp_path / "scene.xml").write_text(PLAIN_SCENE.format(texture="checker.exr"))
    return tmp_path


def compare(folder, scene, out, *extra, methods="direct", passes="4"):
    """Run ``compare`` from ``folder`` with a relative scene path (or a list of them); returns the report dict."""
    cwd = os.getcwd()
    os.chdir(folder)
    try:
        code = cli.main(["compare", *([scene] if isinstance(scene, str) else scene), "--out", str(out), "--res", "16", "--spp", "2",
                         "--passes", passes, "--ref-spp", "32", "--methods", methods,
                         "--convergence-max-spp", "0", "--cache-dir", str(folder / "cache"),
                         "--no-progress", *extra])
    finally:
        os.chdir(cwd)
    assert code == 0
    return json.loads((out / "report.json").read_text())


def test_a_scene_without_any_defaults_renders_with_each_requested_sampler_at_the_requested_size(plain_scene):
    report = compare(plain_scene, "scene.xml", plain_scene / "out", "--sampler", "independent,multijitter",
                     methods="direct,direct_misc")
    runs = report["scenes"][0]["runs"]
    assert [r["sampler"] for r in runs] == ["independent", "multijitter"]
    assert [r["sampler_plugin"] for r in runs] == ["IndependentSampler", "MultijitterSampler"]
    for run in runs:
        assert run["film_size"] == [16, 12]  # --res is the width; the scene's 4:3 aspect is kept
        assert set(run["methods"]) == {"direct", "direct_misc"}  # the envmap was rebuilt compensated
        first = mi.Bitmap(str(plain_scene / "out" / run["methods"]["direct"]["equal_spp"]["files"]["first_pass"]))
        assert (first.width(), first.height()) == (16, 12)
    # The multijitter passes render 2 spp, not the scene's own stratified 9.
    assert runs[1]["methods"]["direct"]["equal_spp"]["spp"] == 2


def test_editing_a_referenced_texture_never_reuses_the_old_reference(plain_scene):
    first = compare(plain_scene, "scene.xml", plain_scene / "a")["scenes"][0]["references"]["direct"]
    again = compare(plain_scene, "scene.xml", plain_scene / "b")["scenes"][0]["references"]["direct"]
    assert not first["cached"] and again["cached"] and again["cache_file"] == first["cache_file"]

    write_image(plain_scene / "checker.exr", np.full((8, 8, 3), 0.9))  # same name, new texels
    edited = compare(plain_scene, "scene.xml", plain_scene / "c")["scenes"][0]["references"]["direct"]
    assert not edited["cached"] and edited["cache_file"] != first["cache_file"]

    # A referenced file the loaded scene does not expose as a parameter: the XML text.
    xml = (plain_scene / "scene.xml").read_text()
    (plain_scene / "scene.xml").write_text(xml.replace('value="0.2"/></bsdf>', 'value="0.3"/></bsdf>'))
    alpha = compare(plain_scene, "scene.xml", plain_scene / "d")["scenes"][0]["references"]["direct"]
    assert not alpha["cached"] and alpha["cache_file"] not in (first["cache_file"], edited["cache_file"])


def test_verdict_names_direct_the_clear_winner_over_bsdf_sampling_of_a_small_light(tmp_path):
    (tmp_path / "small_light.xml").write_text(SMALL_LIGHT_SCENE)
    report = compare(tmp_path, "small_light.xml", tmp_path / "out", "--sampler", "independent",
                     methods="direct,bsdf_only", passes="16")
    (row,) = report["verdict"]
    assert row["scene"] == "small_light" and row["sampler"] == "independent"
    spp, time_ = row["equal_spp"], row["equal_time"]
    assert spp["winner"] == time_["winner"] == "direct"
    assert (spp["numerator"], spp["denominator"]) == ("direct", "bsdf_only")
    assert spp["quantity"] == "MSE" and spp["high"] < 0.2  # far lower MSE, and the interval says so
    assert time_["quantity"] == "efficiency" and time_["low"] > 5
    assert spp["low"] <= spp["ratio"] <= spp["high"] and time_["low"] <= time_["ratio"] <= time_["high"]
    page = (tmp_path / "out" / "index.html").read_text()
    verdict_table = page[page.index('<table id="verdict">'):]
    verdict_table = verdict_table[:verdict_table.index("</table>")]
    assert verdict_table.count('<td class="name win"><b>direct</b> wins') == 3  # every kind of contest
    assert page.index('id="verdict"') < page.index("<details>")  # verdict on top, settings at the bottom


def test_a_non_finite_texel_never_prints_nan_and_the_report_says_why(tmp_path):
    texels = sky()
    texels[5, 7] = np.nan
    write_image(tmp_path / "sky.exr", texels)
    write_image(tmp_path / "checker.exr", np.full((4, 4, 3), 0.5))
    (tmp_path / "scene.xml").write_text(PLAIN_SCENE.format(texture="checker.exr"))
    report = compare(tmp_path, "scene.xml", tmp_path / "out", "--sampler", "independent",
                     methods="direct,env_only")
    json.loads((tmp_path / "out" / "report.json").read_text(),
               parse_constant=lambda c: pytest.fail(f"report.json holds {c}"))
    notes = report["scenes"][0]["notes"]
    assert any("non-finite texel" in n for n in notes)
    page = re.sub(r'data:image/png;base64,[^"]+', "", (tmp_path / "out" / "index.html").read_text())
    assert not re.search(r"\b(nan|inf)\b", page)  # how Python prints a non-finite number
    for entry in report["scenes"][0]["runs"][0]["methods"].values():
        for kind in ("equal_spp", "equal_time"):
            error = entry[kind]["error"]
            # Either a finite number, or its non-finite pixels are counted (and noted on the page).
            assert error["mse"] is not None or error["non_finite"] > 0
            if error["non_finite"]:
                assert "non-finite pixel values" in page


def test_the_rebuilt_camera_renders_exactly_what_the_scenes_own_camera_renders():
    scene = scenes.load_scene(scenes.builtin_scenes()["sphere_ggx010"], res=16, sampler="independent")
    sensor = scene_setup.comparison_sensor(scene, 16, "independent", 4)
    integrator = mi.load_dict({"type": "direct"})
    own = np.array(mi.render(scene, integrator=integrator, spp=4, seed=3))
    rebuilt = np.array(mi.render(scene, sensor=sensor, integrator=integrator, spp=4, seed=3))
    assert np.allclose(own, rebuilt, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("camera, kept", [
    ({"type": "thinlens", "fov": 30, "aperture_radius": 0.05, "focus_distance": 4.0},
     {"aperture_radius": 0.05, "focus_distance": 4.0, "x_fov": 30.0}),
    ({"type": "orthographic"}, {}),
    ({"type": "perspective", "fov": 50, "fov_axis": "y", "principal_point_offset_x": 0.1},
     {"principal_point_offset_x": 0.1}),
])
def test_the_rebuilt_camera_keeps_the_lens_pose_and_aspect_of_the_scenes_camera(camera, kept):
    pose = mi.ScalarTransform4f().look_at(origin=[1, 2, 5], target=[0, 0, 0], up=[0, 1, 0])
    scene = mi.load_dict({"type": "scene", "sensor": dict(camera, to_world=pose, near_clip=0.5,
                                                           film={"type": "hdrfilm", "width": 60, "height": 30})})
    original = mi.traverse(scene.sensors()[0])
    sensor = scene_setup.comparison_sensor(scene, 20, "multijitter", 4)
    params = mi.traverse(sensor)
    assert sensor.class_name() == scene.sensors()[0].class_name()
    assert sensor.sampler().class_name() == "MultijitterSampler"
    assert list(sensor.film().size()) == [20, 10]
    assert np.allclose(np.array(params["to_world"].matrix), np.array(original["to_world"].matrix), atol=1e-5)
    assert np.ravel(params["near_clip"])[0] == pytest.approx(0.5)
    for name in kept:
        assert np.allclose(np.array(params[name]), np.array(original[name]), rtol=1e-5), name


def test_a_camera_compare_cannot_rebuild_is_refused_with_a_clear_message():
    scene = mi.load_dict({"type": "scene", "sensor": {"type": "radiancemeter",
                                                       "film": {"type": "hdrfilm", "width": 1, "height": 1}}})
    with pytest.raises(SceneError, match="perspective, thin-lens and orthographic"):
        scene_setup.comparison_sensor(scene, 16, "independent", 1)


def test_rebuilding_the_envmap_keeps_every_other_emitter_shape_and_the_image():
    scene = mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "to_world": mi.ScalarTransform4f().look_at(
            origin=[0, 2, 6], target=[0, 0, 0], up=[0, 1, 0]), "film": {"type": "hdrfilm", "width": 16, "height": 16}},
        "env": {"type": "envmap", "bitmap": mi.Bitmap(sky().astype(np.float32)), "scale": 0.5,
                "to_world": mi.ScalarTransform4f().rotate([0, 1, 0], 40)},
        "sphere": {"type": "sphere", "bsdf": {"type": "roughconductor", "alpha": 0.3}},
        "light": {"type": "rectangle", "emitter": {"type": "area", "radiance": 5.0},
                  "to_world": mi.ScalarTransform4f().translate([0, 3, 0]).rotate([1, 0, 0], 90)},
        "point": {"type": "point", "position": [2, 2, 2], "intensity": 10.0},
    })
    rebuilt = scene_setup.with_environment(scene)
    assert len(rebuilt.emitters()) == len(scene.emitters()) == 3
    assert len(rebuilt.shapes()) == len(scene.shapes())
    integrator = mi.load_dict({"type": "direct"})
    own, again = (np.array(mi.render(s, integrator=integrator, spp=8, seed=5)) for s in (scene, rebuilt))
    assert np.allclose(own, again, rtol=1e-4, atol=1e-6)
    compensated = scene_setup.with_environment(scene, mis_compensation=True)
    assert not np.allclose(own, np.array(mi.render(compensated, integrator=integrator, spp=8, seed=5)))


def test_an_interrupted_reference_write_leaves_no_cache_entry_to_be_reused(tmp_path, monkeypatch):
    """The cache entry appears by rename, so a crash mid-write (or a reader on another
    worker) never sees half a reference."""
    from mitsuba_shsampling.report import rendering

    settings = {"res": 8, "sampler": "independent", "max_depth": 2, "envmap": None}
    scene_path = scenes.builtin_scenes()["sphere_ggx010"]

    def broken_savez(file, **arrays):
        file.write(b"half a reference")
        raise OSError("disk full")

    monkeypatch.setattr(rendering.np, "savez", broken_savez)
    with pytest.raises(OSError, match="disk full"):
        rendering.render_reference(scene_path, settings, "direct", 8, str(tmp_path))
    assert not any(name.endswith(".npz") or name.endswith(".partial") for name in os.listdir(tmp_path))
    monkeypatch.undo()
    first = rendering.render_reference(scene_path, settings, "direct", 8, str(tmp_path))
    again = rendering.render_reference(scene_path, settings, "direct", 8, str(tmp_path))
    assert not first.cached and again.cached
    np.testing.assert_array_equal(first.chunks, again.chunks)


def test_a_scene_with_a_hair_bsdf_compares_and_its_reference_key_follows_the_melanin(plain_scene):
    """A hair BSDF set by melanin lists ``sigma_a`` without a value: the reference key skips it
    and still changes with the concentration."""
    hair = PLAIN_SCENE.replace('<bsdf type="roughconductor"><float name="alpha" value="0.2"/></bsdf>',
                               '<bsdf type="hair"><float name="eumelanin" value="{melanin}"/></bsdf>')
    assert hair != PLAIN_SCENE
    (plain_scene / "hair.xml").write_text(hair.format(texture="checker.exr", melanin=1.3))
    report = compare(plain_scene, "hair.xml", plain_scene / "out", "--sampler", "independent",
                     methods="direct,sh_direct", passes="2")
    assert set(report["scenes"][0]["runs"][0]["methods"]) == {"direct", "sh_direct"}
    digests = []
    for melanin in (1.3, 1.3, 0.4):
        (plain_scene / "hair.xml").write_text(hair.format(texture="checker.exr", melanin=melanin))
        path = str(plain_scene / "hair.xml")
        digests.append(scene_setup.content_digest(path, scenes.load_scene(path)))
    assert digests[0] == digests[1] != digests[2]


def test_an_all_black_environment_gives_a_verdict_with_n_a_ratios_and_a_caveat_saying_why(plain_scene):
    write_image(plain_scene / "sky.exr", np.zeros((16, 32, 3)))
    report = compare(plain_scene, "scene.xml", plain_scene / "out", "--sampler", "independent",
                     methods="direct,env_only,sh_direct", passes="2")
    (row,) = report["verdict"]
    from mitsuba_shsampling.report.schema import CONTEST_TITLES
    for kind, title in CONTEST_TITLES.items():
        assert row[kind]["ratio"] is row[kind]["low"] is row[kind]["high"] is None
        assert any(c.startswith(f"at {title} the ratio of sh_direct to ") and "is n/a" in c
                   for c in row["caveats"])
    page = (plain_scene / "out" / "index.html").read_text()
    assert "n/a" in page


def test_a_pass_without_any_finite_pixel_makes_its_ratio_n_a_never_a_crash():
    from mitsuba_shsampling.report import verdict

    def entry(mse_per_pass):
        finite = [v for v in mse_per_pass if v is not None]
        return {"error": {"mse_per_pass": mse_per_pass, "mse": sum(finite) / len(finite) if finite else None,
                          "non_finite": 12 * (len(mse_per_pass) - len(finite))},
                "times_s": [0.1] * len(mse_per_pass), "spp": 8, "time_budget_s": 0.1, "budget_method": "direct",
                "tail_worse_than_baseline": [], "bias": {"flagged": False, "p_value": 0.5}}

    methods = {"direct": {"family": "direct", "equal_spp": entry([None, None, None]),
                          "equal_time": entry([None, None, None])},
               "sh_direct": {"family": "direct", "equal_spp": entry([0.2, 0.3, 0.1]),
                             "equal_time": entry([0.2, None, 0.1])}}
    report = {"scenes": [{"scene": "s", "path": "s.xml", "references": {"direct": {"mean_variance": None}},
                          "runs": [{"sampler": "independent", "methods": methods}]}]}
    (row,) = verdict.verdict(report)
    assert row.equal_spp.winner == "sh_direct"  # the only finite MSE
    assert np.isnan(row.equal_spp.ratio) and np.isnan(row.equal_time.ratio) and not row.equal_time.decided
    assert any("non-finite pixel values" in c for c in row.caveats)
    assert sum("is n/a" in c for c in row.caveats) == 3  # each kind of contest


def test_two_scenes_of_the_same_file_name_keep_their_own_images_and_names(plain_scene):
    for folder, alpha in (("a", "0.2"), ("b", "0.6")):
        (plain_scene / folder).mkdir()
        xml = PLAIN_SCENE.format(texture="../checker.exr").replace('value="sky.exr"', 'value="../sky.exr"')
        (plain_scene / folder / "scene.xml").write_text(xml.replace('value="0.2"/></bsdf>', f'value="{alpha}"/></bsdf>'))
    report = compare(plain_scene, ["a/scene.xml", "b/scene.xml"], plain_scene / "out", "--sampler", "independent",
                     methods="direct,env_only", passes="2")
    assert [s["scene"] for s in report["scenes"]] == ["a/scene", "b/scene"]
    assert [r["scene"] for r in report["verdict"]] == ["a/scene", "b/scene"]
    files = [s["runs"][0]["methods"]["direct"]["equal_spp"]["files"]["first_pass"] for s in report["scenes"]]
    references = [s["references"]["direct"]["file"] for s in report["scenes"]]
    assert files[0] != files[1] and references[0] != references[1]
    images = [np.array(mi.Bitmap(str(plain_scene / "out" / f))) for f in references]
    assert not np.allclose(*images)  # each scene's own reference, neither overwritten


def test_scene_labels_name_scenes_apart_by_the_fewest_parent_folders():
    from mitsuba_shsampling.report.compare import scene_labels
    assert scene_labels(["x/a/s.xml", "x/b/s.xml", "t.xml"]) == ["a/s", "b/s", "t"]
    assert scene_labels(["p/a/s.xml", "q/a/s.xml", "q/b.xml"]) == ["p/a/s", "q/a/s", "b"]
    assert scene_labels(["s.xml", "./s.xml"]) == ["s", "s_2"]


def verdict_entry(mse_per_pass, time_s=0.1, tail_worse=()):
    """A report.json method entry as the verdict reads it (both comparisons alike)."""
    kind = {"error": {"mse_per_pass": list(mse_per_pass), "mse": float(np.mean(mse_per_pass)), "non_finite": 0},
            "times_s": [time_s] * len(mse_per_pass), "time_s": time_s, "spp": 8, "time_budget_s": 0.1,
            "budget_method": "direct", "tail_worse_than_baseline": list(tail_worse),
            "bias": {"flagged": False, "p_value": 0.5}}
    return {"equal_spp": kind, "equal_time": copy.deepcopy(kind)}


def test_the_verdicts_first_line_is_the_plugin_at_its_defaults_against_the_best_mitsuba_strategy():
    from mitsuba_shsampling.report.methods import METHODS
    from mitsuba_shsampling.report.verdict import verdict

    mse = {"direct": 1.0, "direct_misc": 0.8, "bsdf_only": 3.0, "sh_direct": 0.9, "sh_product_only": 0.3}
    methods = {n: {"family": "direct", "integrator": next(m.integrator for m in METHODS if m.name == n),
                   **verdict_entry([v, 1.1 * v, 0.9 * v])} for n, v in mse.items()}
    report = {"scenes": [{"scene": "s", "path": "s.xml", "references": {},
                          "runs": [{"sampler": "independent", "methods": methods}]}]}
    (row,) = verdict(report)
    for cell in (row.equal_spp, row.equal_time):
        assert (cell.numerator, cell.denominator, cell.winner) == ("sh_direct", "direct_misc", "sh_product_only")
    assert row.configuration == "sh_direct (defaults)"
    (other,) = row.others
    assert other.method == "sh_product_only" and other.equal_spp.denominator == "direct_misc"
    assert other.configuration == "sh_direct (strategy=product_only)"
    assert other.equal_spp.ratio == pytest.approx(0.3 / 0.8)


def one_cell_report(methods):
    for entry in methods.values():
        entry["family"] = "direct"
    return {"scenes": [{"scene": "s", "path": "s.xml", "references": {},
                        "runs": [{"sampler": "independent", "methods": methods}]}]}


def test_noise_both_methods_draw_alike_cancels_in_the_efficiency_of_the_equal_sample_passes():
    from mitsuba_shsampling.report.verdict import verdict

    # A mirror: at one seed and spp both methods render the same image, rare bright passes
    # included; the plugin's pass takes 0.8x the time. At equal time their spp differ, so
    # the rare passes fall apart and leave the renders' interval undecided.
    shared = [1.0, 1.0, 40.0, 1.0, 1.0, 1.0, 25.0, 1.0]
    methods = {"direct_misc": verdict_entry(shared), "sh_direct": verdict_entry(shared, time_s=0.08)}
    methods["direct_misc"]["equal_time"]["error"]["mse_per_pass"] = [1.0, 40.0, 1.0, 1.0, 1.0, 1.0, 1.0, 25.0]
    methods["sh_direct"]["equal_time"]["error"]["mse_per_pass"] = [1.0, 1.0, 1.0, 40.0, 25.0, 1.0, 1.0, 1.0]
    (row,) = verdict(one_cell_report(methods))
    assert row.time_normalised.ratio == pytest.approx(1.25)
    assert row.time_normalised.low == pytest.approx(1.25) and row.time_normalised.numerator_better
    assert not row.equal_time.decided
    assert [title for title, _ in row.contests()] == ["equal samples", "equal time",
                                                      "equal time, from the equal-sample passes"]


def test_equal_time_estimates_that_disagree_get_a_caveat():
    from mitsuba_shsampling.report.verdict import verdict

    methods = {"direct": verdict_entry([1.0, 1.1, 0.9, 1.0]), "sh_direct": verdict_entry([0.5, 0.55, 0.45, 0.5])}
    (row,) = verdict(one_cell_report(methods))
    assert not any("disagree" in c for c in row.caveats)
    # Its equal-time renders twice as noisy as its equal-sample passes predict.
    methods["sh_direct"]["equal_time"]["error"]["mse_per_pass"] = [2.0, 2.2, 1.8, 2.0]
    (row,) = verdict(one_cell_report(methods))
    assert any(c.startswith("the two equal-time estimates disagree") for c in row.caveats)


def test_the_equal_sample_estimate_agrees_with_the_equal_time_renders_when_a_pass_has_a_fixed_overhead():
    from mitsuba_shsampling.report.verdict import verdict

    # Pass time = overhead + spp x cost per sample; per-sample variance sigma^2, so a pass's
    # MSE is sigma^2 / spp (noise-free here: the expectation). The plugin's sample costs 1.5x
    # and has a quarter of the variance: at equal time it is 4 / 1.5 = 2.67x as efficient.
    overhead, spp, budget = 0.1, 8, 0.3
    cost = {"direct": 0.01, "sh_direct": 0.015}
    sigma2 = {"direct": 1.0, "sh_direct": 0.25}
    methods = {}
    for name in cost:
        passes = 16
        equal_spp = verdict_entry([sigma2[name] / spp] * passes, time_s=overhead + spp * cost[name])
        timed_spp = round((budget - overhead) / cost[name])
        equal_spp["equal_spp"]["spp"] = spp
        equal_spp["equal_time"].update(spp=timed_spp, time_s=overhead + timed_spp * cost[name],
                                       times_s=[overhead + timed_spp * cost[name]] * passes)
        equal_spp["equal_time"]["error"]["mse_per_pass"] = [sigma2[name] / timed_spp] * passes
        equal_spp["equal_time"]["error"]["mse"] = sigma2[name] / timed_spp
        methods[name] = equal_spp
    (row,) = verdict(one_cell_report(methods))
    assert row.equal_time.ratio == pytest.approx(4 / 1.5, rel=0.02)
    assert row.time_normalised.ratio == pytest.approx(row.equal_time.ratio, rel=1e-9)
    assert not any("disagree" in c for c in row.caveats)
    # Timed as its own pass, the overhead would have diluted the plugin's extra cost per sample:
    naive = (sigma2["direct"] * (overhead + spp * cost["direct"])) / (sigma2["sh_direct"] * (overhead + spp * cost["sh_direct"]))
    assert abs(naive / row.equal_time.ratio - 1) > 0.15


def test_heavy_tails_are_flagged_only_for_the_methods_the_verdict_shows():
    from mitsuba_shsampling.report.verdict import verdict

    methods = {"direct": verdict_entry([1.0, 1.1]), "direct_misc": verdict_entry([0.8, 0.9]),
               "bsdf_only": verdict_entry([3.0, 3.3], tail_worse=["9 fireflies against direct's 0"])}
    report = one_cell_report(methods)
    (row,) = verdict(report)
    assert not any("heavy tails" in c for c in row.caveats)
    methods["direct_misc"]["equal_time"]["tail_worse_than_baseline"] = ["brightest pixel 9 > 3 x direct's 2"]
    (row,) = verdict(report)
    assert [c for c in row.caveats if "heavy tails" in c][0].startswith("heavy tails: direct_misc is worse")


def test_the_zoomed_crop_shows_noise_the_page_displays_not_a_highlight_it_clips():
    """A highlight (radiance 50, noise 20) is white in every method's PNG; a grey patch with
    visible noise is where the methods differ on the page, so the crop shows it."""
    import types

    from mitsuba_shsampling.report.compare import crop

    rng = np.random.default_rng(1)
    reference = np.full((48, 48, 3), 0.2)
    reference[:8, :8] = 50.0
    passes = np.repeat(reference[None], 8, axis=0)
    passes[:, :8, :8] += rng.normal(0.0, 20.0, (8, 8, 8, 3))
    passes[:, 32:40, 24:32] += rng.normal(0.0, 0.1, (8, 8, 8, 3))
    method = types.SimpleNamespace(name="direct", family="direct")
    x, y, size = crop([method], {"direct": types.SimpleNamespace(images=passes)},
                      {"direct": types.SimpleNamespace(image=reference)}, exposure_value=1.0)
    assert (x, y, size) == (24, 32, 8)


@pytest.mark.parametrize("quantity, ratio, low, high, shown", [
    ("efficiency", 0.833, 0.725, 0.953, "loses"),  # less efficient, and the interval says so
    ("efficiency", 1.25, 1.1, 1.4, "wins"),
    ("efficiency", 0.98, 0.9, 1.05, "tie"),
    ("MSE", 0.8, 0.7, 0.9, "wins"),
    ("MSE", 1.2, 1.1, 1.3, "loses"),
    ("MSE", 1.0, 0.95, 1.05, "tie"),
])
def test_a_verdict_cell_is_green_for_a_win_red_for_a_loss_and_neutral_for_a_tie(quantity, ratio, low, high, shown):
    from mitsuba_shsampling.report.html import _cell_html
    from mitsuba_shsampling.report.schema import VerdictCell

    cell = VerdictCell(quantity=quantity, winner="direct_misc", winner_is_project=False, numerator="sh_direct",
                       denominator="direct_misc", ratio=ratio, low=low, high=high)
    (classes, word), = re.findall(r'<td class="([^"]*)"><b>sh_direct \(defaults\)</b> (\w+)<br>',
                                  _cell_html(cell, "sh_direct (defaults)", "equal_spp", []))
    colour = {"wins": "win", "loses": "loss", "tie": None}[shown]
    assert word == shown
    assert ({"win", "loss"} & set(classes.split())) == ({colour} if colour else set())


def test_best_of_all_is_said_only_where_the_winners_interval_over_the_runner_up_excludes_1():
    from mitsuba_shsampling.report.verdict import verdict, winner_text

    clear = {"direct": verdict_entry([1.0, 1.1, 0.9, 1.0]), "sh_direct": verdict_entry([0.5, 0.55, 0.45, 0.5])}
    (row,) = verdict(one_cell_report(clear))
    assert row.equal_spp.runner_up == "direct" and row.equal_spp.winner_high < 1
    assert winner_text(row.equal_spp, "equal_spp", row.caveats).startswith("sh_direct best of all")
    # The same MSE, pass for pass in a different order: the interval contains 1.
    tie = {"direct": verdict_entry([1.0, 1.3, 0.7, 1.0]), "sh_direct": verdict_entry([1.3, 0.7, 1.0, 1.0])}
    (row,) = verdict(one_cell_report(tie))
    assert any("no clear winner" in c for c in row.caveats)
    text = winner_text(row.equal_spp, "equal_spp", row.caveats)
    assert "best" not in text and text.startswith("no clear winner")


def test_no_winner_is_named_at_equal_time_beside_a_caveat_that_voids_the_times():
    from mitsuba_shsampling.report.verdict import verdict, winner_text

    methods = {"direct": verdict_entry([1.0, 1.1, 0.9, 1.0], time_s=0.005),
               "sh_direct": verdict_entry([0.5, 0.55, 0.45, 0.5], time_s=0.005)}
    for entry in methods.values():
        for kind in ("equal_spp", "equal_time"):
            entry[kind]["time_budget_s"] = 0.005
    (row,) = verdict(one_cell_report(methods))
    assert any(c.startswith("time budget too small to be meaningful") for c in row.caveats)
    for kind in ("equal_time", "time_normalised"):
        text = winner_text(getattr(row, kind), kind, row.caveats)
        assert "best" not in text and text.startswith("no winner: time budget too small")
    assert "best of all" in winner_text(row.equal_spp, "equal_spp", row.caveats)  # samples need no clock


def test_the_page_never_says_best_of_all_in_a_tied_cell():
    from mitsuba_shsampling.report.html import _verdict_section
    from mitsuba_shsampling.report.schema import load_report
    from mitsuba_shsampling.report.verdict import verdict

    tie = {"direct": verdict_entry([1.0, 1.3, 0.7, 1.0]), "sh_direct": verdict_entry([1.3, 0.7, 1.0, 1.0])}
    report = load_report(one_cell_report(tie))
    report.verdict = verdict(report)
    page = _verdict_section(report)
    assert "best" not in page.replace("best Mitsuba", "").replace("best of Mitsuba", "")
    assert "no clear winner" in page


def test_every_method_the_verdict_compares_is_defined_on_the_page():
    from mitsuba_shsampling.report.html import _verdict_section
    from mitsuba_shsampling.report.methods import method_by_name
    from mitsuba_shsampling.report.schema import load_report
    from mitsuba_shsampling.report.verdict import verdict

    mse = {"direct": 1.0, "direct_misc": 0.8, "env_only": 1.5, "sh_direct": 0.7, "sh_product_only": 0.9}
    methods = {}
    for name, value in mse.items():
        m = method_by_name(name)
        methods[name] = {"label": m.label, "integrator": m.integrator, "scene_params": m.scene_params,
                         **verdict_entry([value, 1.1 * value, 0.9 * value])}
    report = load_report(one_cell_report(methods))
    report.verdict = verdict(report)
    page = _verdict_section(report)
    defined = dict(re.findall(r"<dt>([^<]+)</dt><dd>(.*?)</dd>", page))
    (row,) = report.verdict
    named = {c.numerator for _, c in row.contests()} | {c.denominator for _, c in row.contests()}
    assert named | set(mse) | {"best Mitsuba"} == set(defined)
    assert defined["direct_misc"].startswith("Mitsuba&#x27;s own strategy: <code>direct (defaults)</code>")
    assert "mis_compensation=true" in defined["direct_misc"]
    assert "emitter_samples=2, bsdf_samples=0" in defined["env_only"]
    assert defined["sh_product_only"].startswith("this package&#x27;s plugin: <code>sh_direct (strategy=product_only)")
    assert "direct, direct_misc, env_only" in defined["best Mitsuba"]


def test_the_plugins_set_up_is_reported_apart_from_the_kernels_compilation(plain_scene):
    """Mitsuba's integrators set up at load; the plugin's per-scene state and plan are timed
    on their own, before the first (compiling) pass, in the JSON, the CSV and the page."""
    report = compare(plain_scene, "scene.xml", plain_scene / "out", methods="direct,sh_direct", passes="2")
    methods = report["scenes"][0]["runs"][0]["methods"]
    assert methods["direct"]["setup_time_s"] < 0.01
    assert methods["sh_direct"]["setup_time_s"] > 0
    assert all(m["compile_time_s"] >= 0 for m in methods.values())
    assert "setup_time_s" in (plain_scene / "out" / "metrics.csv").read_text().splitlines()[0]
    page = (plain_scene / "out" / "index.html").read_text()
    assert "<th>set-up (s)</th><th>compile (s)</th>" in page
    # The page says which of its two equal-time estimates decides, and when the other holds.
    assert re.search(r'id="deciding-estimate".*the renders at equal time.*1/spp.*fixed overhead', page)
