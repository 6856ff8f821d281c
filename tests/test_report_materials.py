"""The report's per-material breakdown: which material each pixel shows, and where a method wins or loses."""

import re

import numpy as np
import pytest

import mitsuba_shsampling  # noqa: F401  (LLVM backend check)
import mitsuba as mi

mi.set_variant("llvm_ad_rgb")

from mitsuba_shsampling.report import materials  # noqa: E402
from mitsuba_shsampling.report.schema import MaterialEntry  # noqa: E402


def two_sphere_scene() -> mi.Scene:
    """A gold sphere on the left and a diffuse sphere on the right, sharing nothing; sky behind."""
    shared = mi.load_dict({"type": "diffuse", "id": "shared_white"})
    return mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 40,
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 8], target=[0, 0, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 40, "height": 20, "rfilter": {"type": "gaussian"}}},
        "left": {"type": "sphere", "center": [-1.5, 0, 0], "radius": 1.0,
                 "bsdf": {"type": "roughconductor", "id": "gold"}},
        "right": {"type": "sphere", "center": [1.5, 0, 0], "radius": 1.0, "bsdf": shared},
        "tiny": {"type": "sphere", "center": [0, 1.1, 0], "radius": 0.3, "bsdf": shared},
        "sky": {"type": "constant"},
    })


def test_every_pixel_centre_is_labelled_with_the_bsdf_it_sees():
    scene = two_sphere_scene()
    ids, labels = materials.material_map(scene, scene.sensors()[0])
    assert ids.shape == (20, 40)
    names = [name for name, _ in labels]
    # Shapes sharing a BSDF instance share one material.
    assert len(labels) == 2
    gold = names.index("gold")
    white = 1 - gold
    assert ids[10, 10] == gold and ids[10, 30] == white
    assert ids[2, 20] == white  # the tiny sphere above, same BSDF instance
    assert ids[0, 0] == -1 and ids[19, 39] == -1  # corners see the sky
    assert dict(labels)["gold"] == "RoughConductor"


def test_a_cropped_films_pixels_are_labelled_as_the_same_pixels_of_the_whole_film():
    """The sensor places a film position relative to the crop window (as Mitsuba's integrators
    and the pilots do): the crop's labels are the whole film's in that window."""
    whole = two_sphere_scene()
    ids, _ = materials.material_map(whole, whole.sensors()[0])
    cropped = mi.load_dict({
        "type": "perspective", "fov": 40,
        "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 8], target=[0, 0, 0], up=[0, 1, 0]),
        "film": {"type": "hdrfilm", "width": 40, "height": 20, "crop_offset_x": 22, "crop_offset_y": 3,
                 "crop_width": 12, "crop_height": 9}})
    window, _ = materials.material_map(whole, cropped)
    assert window.shape == (9, 12)
    assert np.array_equal(window, ids[3:12, 22:34])


def synthetic_passes(rng, scale: np.ndarray, passes: int = 400) -> np.ndarray:
    """K passes of a (H, W, 3) image of mean 1 whose per-pixel noise has standard deviation ``scale``."""
    return 1.0 + scale[None, :, :, None] * rng.standard_normal((passes,) + scale.shape + (3,))


def test_error_ratio_compares_with_the_best_mitsuba_strategy_on_each_material():
    rng = np.random.default_rng(0)
    ids = np.zeros((4, 8), dtype=np.int64)
    ids[:, 4:] = 1
    left, right = ids == 0, ids == 1
    # direct is noisy on the left, env_only on the right; the project method halves the
    # error of the best one on the left and doubles it on the right.
    sd = {"direct": np.where(left, 2.0, 1.0), "env_only": np.where(left, 1.0, 2.0),
          "sh_direct": np.where(left, np.sqrt(0.5), np.sqrt(2.0))}
    passes = {n: synthetic_passes(rng, s) for n, s in sd.items()}
    rows = materials.breakdown(ids, [("glossy", "RoughConductor"), ("ground", "SmoothDiffuse")],
                               passes, passes, np.ones((4, 8, 3)), ["sh_direct"], ["direct", "env_only"])
    by_name = {r.name: r for r in rows}
    assert by_name["glossy"].best_mitsuba == {"equal_spp": "env_only", "equal_time": "env_only"}
    assert by_name["ground"].best_mitsuba["equal_spp"] == "direct"
    assert by_name["glossy"].error_ratio["sh_direct"]["equal_spp"] == pytest.approx(0.5, rel=0.1)
    assert by_name["ground"].error_ratio["sh_direct"]["equal_time"] == pytest.approx(2.0, rel=0.1)
    assert by_name["glossy"].pixel_share == pytest.approx(0.5)
    # sh_direct's squared error: 0.5 on 16 pixels and 2 on 16 pixels, so a fifth on the glossy part.
    assert by_name["glossy"].error_share["sh_direct"] == pytest.approx(0.2, rel=0.1)
    for name in passes:
        assert sum(r.error_share[name] for r in rows) == pytest.approx(1.0)


def test_each_error_ratio_has_a_paired_interval_that_tells_a_win_a_loss_and_a_tie_apart():
    rng = np.random.default_rng(3)
    ids = np.repeat(np.arange(3), 4)[None].repeat(2, axis=0)  # three materials, 8 pixels each
    sd = {"direct": np.ones((2, 12)), "sh_direct": np.sqrt(np.array([0.5, 2.0, 1.0]))[ids]}
    passes = {n: synthetic_passes(rng, s, passes=64) for n, s in sd.items()}
    passes["sh_direct"][:, :, 8:] = passes["direct"][:, :, 8:]  # the same samples: exactly 1
    rows = materials.breakdown(ids, [("win", "A"), ("loss", "B"), ("tie", "C")], passes, passes,
                               np.ones((2, 12, 3)), ["sh_direct"], ["direct"])
    interval = {r.name: r.error_ratio_interval["sh_direct"]["equal_spp"] for r in rows}
    assert interval["win"][1] < 1 < interval["loss"][0]
    assert interval["tie"] == [pytest.approx(1.0), pytest.approx(1.0)]
    for row in rows:
        low, high = row.error_ratio_interval["sh_direct"]["equal_time"]
        assert low <= row.error_ratio["sh_direct"]["equal_time"] <= high


def material_row(ratio: float, low: float, high: float) -> MaterialEntry:
    return MaterialEntry(name="m", plugin="Diffuse", pixel_share=1.0,
                         error_ratio={"sh_direct": {"equal_spp": ratio, "equal_time": ratio}},
                         best_mitsuba={"equal_spp": "direct", "equal_time": "direct"},
                         error_share={"sh_direct": 1.0, "direct": 1.0},
                         error_ratio_interval={"sh_direct": {"equal_spp": [low, high], "equal_time": [low, high]}})


@pytest.mark.parametrize("ratio, low, high, shown", [
    (0.5, 0.4, 0.6, "win"), (2.0, 1.5, 2.5, "loss"), (1.0, 0.97, 1.03, "tie"), (1.004, 0.99, 1.02, "tie")])
def test_the_page_colours_a_material_ratio_by_its_interval_and_a_tie_is_never_red(ratio, low, high, shown):
    from mitsuba_shsampling.report.html import _materials_table

    table = _materials_table([material_row(ratio, low, high)])
    cells = re.findall(r'<td class="(\w*)" title="[^"]*">([^<]*)</td>', table)
    assert [c for c, _ in cells] == [shown, shown]
    assert "sh_direct: error ratio to the best Mitsuba there, equal samples" in table
    assert "sh_direct: error ratio, equal time" in table


def test_a_report_from_before_the_intervals_shows_its_material_ratios_uncoloured():
    from mitsuba_shsampling.report.html import _materials_table

    row = material_row(3.0, 2.0, 4.0)
    row.error_ratio_interval = None
    assert 'class="win"' not in _materials_table([row]) and 'class="loss"' not in _materials_table([row])


def test_a_strategy_that_leaves_a_material_dark_is_not_its_best():
    """envmap-only sampling gives a smooth glass no light: noiseless, and wrong."""
    rng = np.random.default_rng(2)
    ids = np.zeros((2, 4), dtype=np.int64)
    lit = synthetic_passes(rng, np.full((2, 4), 0.3))
    dark = np.zeros_like(lit)
    noisier = synthetic_passes(rng, np.full((2, 4), 0.6))
    passes = {"direct": lit, "env_only": dark, "sh_direct": noisier}
    (row,) = materials.breakdown(ids, [("glass", "SmoothDielectric")], passes, passes, np.ones((2, 4, 3)),
                                 ["sh_direct"], ["direct", "env_only"])
    assert row.best_mitsuba["equal_spp"] == "direct"
    assert row.error_ratio["sh_direct"]["equal_spp"] == pytest.approx(4.0, rel=0.2)


def test_materials_no_pixel_shows_are_left_out_and_the_background_is_a_row():
    ids = np.full((2, 2), -1, dtype=np.int64)
    ids[0, 0] = 1
    passes = {n: np.random.default_rng(1).random((3, 2, 2, 3)) for n in ("direct", "sh_direct")}
    rows = materials.breakdown(ids, [("unseen", "Diffuse"), ("seen", "Diffuse")], passes, {},
                               np.full((2, 2, 3), 0.5), ["sh_direct"], ["direct"])
    assert [r.name for r in rows] == [materials.BACKGROUND, "seen"]
    # No equal-time passes: no equal-time ratio, rather than a made-up one.
    assert rows[0].error_ratio["sh_direct"]["equal_time"] is None


def test_materials_keep_their_shape_names_when_compare_rebuilds_the_envmap():
    from mitsuba_shsampling import scenes
    from mitsuba_shsampling.report import scene_setup

    scene = scenes.load_scene(scenes.builtin_scenes()["material_studio"], res=32)
    rebuilt = scene_setup.with_environment(scene, scenes.STUDIO_MAP, mis_compensation=True)
    _, labels = materials.material_map(rebuilt, scene_setup.comparison_sensor(rebuilt, 32, "independent", 1))
    names = {name for name, _ in labels}
    # Inline BSDFs are named after their shape, named BSDFs after themselves.
    assert {"ground", "gold_ball", "copper_ggx010", "brushed_aluminium"} <= names
