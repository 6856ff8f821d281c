"""The ``compare`` command end to end on tiny scenes, its error handling, and the report pieces."""

import json
import os
import re
import subprocess
import sys

import numpy as np
import pytest

import mitsuba_shsampling  # noqa: F401  (LLVM backend check)
import mitsuba as mi

mi.set_variant("llvm_ad_rgb")

from mitsuba_shsampling import cli, scenes  # noqa: E402
from mitsuba_shsampling.report import figures  # noqa: E402
from mitsuba_shsampling.report.methods import METHODS, available_methods, plugin_status  # noqa: E402
from mitsuba_shsampling.report.rendering import admissible_spp  # noqa: E402

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PASS_KEYS = ("spp", "time_s", "times_s", "efficiency", "error", "tail", "bias", "files")


@pytest.fixture(scope="module")
def tiny_report(tmp_path_factory):
    out = tmp_path_factory.mktemp("report")
    code = cli.main(["compare", scenes.builtin_scenes()["sphere_ggx010"], "--out", str(out), "--res", "24", "--spp", "2", "--passes", "4", "--ref-spp", "16",
                     "--sampler", "independent", "--convergence-max-spp", "1",
                     "--cache-dir", str(out / "cache"), "--no-progress"])
    assert code == 0
    with open(out / "report.json") as f:
        return out, json.load(f)


def expected_direct_methods():
    runnable, _ = available_methods(None, multi_bounce=False)
    return [m.name for m in runnable]


def test_report_breaks_the_error_down_per_material(tiny_report):
    out, report = tiny_report
    rows = report["scenes"][0]["runs"][0]["materials"]["direct"]
    names = {row["name"] for row in rows}
    assert "background" in names and len(names) >= 3  # the sphere, the ground, the sky
    assert sum(row["pixel_share"] for row in rows) == pytest.approx(1.0)
    for name in ("direct", "sh_direct"):
        assert sum(row["error_share"][name] for row in rows) == pytest.approx(1.0)
    glossy = next(row for row in rows if row["plugin"] == "RoughConductor")
    assert glossy["best_mitsuba"]["equal_spp"] in ("direct", "direct_misc", "env_only")
    assert glossy["error_ratio"]["sh_direct"]["equal_spp"] > 0
    with open(out / "index.html") as f:
        assert "Per material" in f.read()


def test_report_names_each_materials_strategy_and_its_predicted_gain(tiny_report):
    out, report = tiny_report
    run = report["scenes"][0]["runs"][0]
    choice = run["methods"]["sh_direct"]["strategy_choice"]
    assert choice is not None and choice["predicted_gain"] >= 1.0
    assert run["methods"]["direct"]["strategy_choice"] is None
    glossy = next(row for row in run["materials"]["direct"] if row["plugin"] == "RoughConductor")
    assert glossy["strategy"]["sh_direct"]["strategy"] in ("environment", "environment_only", "product",
                                                           "product_only")
    assert glossy["strategy"]["sh_direct"]["predicted_gain"] > 0
    with open(out / "index.html") as f:
        assert "strategy (predicted variance gain)" in f.read()


def test_report_json_has_every_available_method_with_finite_metrics(tiny_report):
    _, report = tiny_report
    ggx = report["scenes"][0]
    assert ggx["scene"] == "sphere_ggx010" and ggx["has_envmap"]
    methods = ggx["runs"][0]["methods"]
    assert list(methods) == expected_direct_methods()
    # Every strategy of Mitsuba's direct at two rays a sample, BSDF sampling alone included: it is
    # the best of them under a low-contrast map.
    assert {"direct", "direct_misc", "env_only", "bsdf_only", "sh_direct"} <= set(methods)
    for entry in methods.values():
        for kind in ("equal_spp", "equal_time"):
            e = entry[kind]
            for key in PASS_KEYS:
                assert key in e
            for value in (e["error"]["mse"], e["error"]["rel_mse"], e["error"]["pixel_variance"],
                          e["time_s"], e["efficiency"], e["tail"]["max_pixel"]):
                assert value is not None and np.isfinite(value) and value > 0
            assert len(e["error"]["mse_per_pass"]) == len(e["times_s"]) == 4
            assert 0 <= e["bias"]["p_value"] <= 1


def test_report_states_machine_variant_versions_and_settings(tiny_report):
    _, report = tiny_report
    assert report["variant"] == "llvm_ad_rgb"
    assert report["versions"]["mitsuba"] == mi.__version__
    assert report["machine"]["cpu_count"] >= 1
    assert report["settings"]["spp"] == 2 and report["settings"]["passes"] == 4


def test_equal_spp_renders_give_every_direct_method_the_same_ray_budget(tiny_report):
    _, report = tiny_report
    methods = report["scenes"][0]["runs"][0]["methods"]
    budgets = {e["equal_spp"]["spp"] * e["rays_per_sample"] for e in methods.values()}
    assert budgets == {4}


def test_default_compare_job_takes_at_least_32_low_spp_passes_per_method():
    args = cli.build_parser().parse_args(["compare"])
    assert args.passes >= 32 and args.spp <= 8


def test_unskipped_sh_methods_are_reported_or_their_absence_is_noted(tiny_report):
    _, report = tiny_report
    ggx = report["scenes"][0]
    methods = ggx["runs"][0]["methods"]
    for name in ("sh_direct", "sh_product_only"):
        assert name in methods or any(f"'{name}'" in note for note in ggx["notes"])


def test_scene_without_envmap_renders_with_a_note(tmp_path):
    code = cli.main(["compare", scenes.builtin_scenes()["area_light"], "--out", str(tmp_path),
                     "--res", "16", "--spp", "2", "--passes", "2", "--ref-spp", "8",
                     "--sampler", "independent", "--methods", "direct,direct_misc",
                     "--convergence-max-spp", "0", "--cache-dir", str(tmp_path / "cache"), "--no-progress"])
    assert code == 0
    area = json.loads((tmp_path / "report.json").read_text())["scenes"][0]
    assert area["scene"] == "area_light" and not area["has_envmap"]
    assert any("no environment map" in note for note in area["notes"])
    assert any("direct_misc" in note for note in area["notes"])  # no envmap to compensate
    assert list(area["runs"][0]["methods"]) == ["direct"]
    assert (tmp_path / "index.html").is_file()


def test_html_is_self_contained_and_every_linked_file_exists(tiny_report):
    out, _ = tiny_report
    html = (out / "index.html").read_text()
    assert "data:image/png;base64," in html
    assert "llvm_ad_rgb" in html and mi.__version__ in html
    links = re.findall(r'(?:href|src)="([^"]+)"', html)
    files = [link for link in links if not link.startswith("data:")]
    assert any(f.endswith(".exr") for f in files)
    for link in files:
        assert (out / link).is_file(), link
    assert (out / "metrics.csv").is_file()


def test_reference_is_cached_and_reused(tiny_report, tmp_path):
    out, report = tiny_report
    ref = report["scenes"][0]["references"]["direct"]
    assert not ref["cached"] and os.path.isfile(ref["cache_file"])
    code = cli.main(["compare", scenes.builtin_scenes()["sphere_ggx010"], "--out", str(tmp_path),
                     "--res", "24", "--spp", "2", "--passes", "2", "--ref-spp", "16",
                     "--sampler", "independent", "--methods", "direct", "--convergence-max-spp", "0",
                     "--cache-dir", str(out / "cache"), "--no-progress"])
    assert code == 0
    again = json.loads((tmp_path / "report.json").read_text())["scenes"][0]["references"]["direct"]
    assert again["cached"] and again["cache_file"] == ref["cache_file"]


def run_cli(*args):
    return subprocess.run([sys.executable, "-m", "mitsuba_shsampling", *args], cwd=REPO,
                          capture_output=True, text=True, timeout=120)


def test_missing_scene_file_exits_with_code_2_and_a_one_line_message():
    proc = run_cli("compare", "/nonexistent/scene.xml")
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "scene file not found" in lines[0]


@pytest.mark.parametrize("args, message", [
    (["--variant", "scalar_rgb"], "not supported"),
    (["--variant", "llvm_no_such_variant"], "not available"),
    (["--methods", "direct,no_such_method"], "unknown method"),
    (["--sampler", "halton9"], "unknown sampler"),
    (["--passes", "1"], "at least 2"),
    (["--methods", ""], "--methods names no method"),
    (["--methods", " , "], "--methods names no method"),
    (["--max-depth", "1"], "--max-depth must be -1 (infinite, as Mitsuba's) or at least 2"),
    (["--max-depth", "-2"], "--max-depth must be -1 (infinite, as Mitsuba's) or at least 2"),
])
def test_bad_options_exit_with_code_2_and_a_one_line_message(args, message, capsys):
    assert cli.main(["compare", *args, "--no-progress"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]


@pytest.mark.parametrize("command", ["compare", "bench"])
@pytest.mark.parametrize("out", ["report.txt", "report.txt/sub"])
def test_an_out_folder_that_is_or_lies_in_a_file_is_refused_in_one_line_with_code_2(command, out, tmp_path,
                                                                                  capsys):
    (tmp_path / "report.txt").write_text("not a folder")
    assert cli.main([command, "--out", str(tmp_path / out), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].endswith("a file, not a folder") and "report.txt" in err[0]


def test_max_depth_minus_one_compares_the_multi_bounce_methods_at_infinite_depth(tmp_path):
    code = cli.main(["compare", scenes.builtin_scenes()["sphere_diffuse"], "--out", str(tmp_path),
                     "--res", "8", "--spp", "1", "--passes", "2", "--ref-spp", "8", "--max-depth", "-1",
                     "--sampler", "independent", "--convergence-max-spp", "0",
                     "--cache-dir", str(tmp_path / "cache"), "--no-progress"])
    assert code == 0
    report = json.loads((tmp_path / "report.json").read_text())
    scene = report["scenes"][0]
    assert {"path", "sh_path"} <= set(scene["runs"][0]["methods"])
    assert scene["references"]["path"]["integrator"] == "path, max_depth -1"
    assert "multi-bounce" in (tmp_path / "index.html").read_text()


def test_envmap_swap_on_a_scene_without_envmap_is_a_usage_error(capsys, tmp_path):
    code = cli.main(["compare", scenes.builtin_scenes()["area_light"], "--envmap", scenes.STUDIO_MAP,
                     "--out", str(tmp_path), "--no-progress"])
    assert code == 2
    assert "no envmap emitter" in capsys.readouterr().err


def test_plugin_status_accepts_mitsuba_integrators_and_explains_unknown_ones():
    assert plugin_status("direct") is None
    reason = plugin_status("no_such_integrator_xyz")
    assert reason is not None and "no_such_integrator_xyz" in reason


def test_every_method_counts_two_rays_per_sample_and_sh_methods_need_their_plugin():
    for method in METHODS:
        assert method.rays_per_sample == 2
        assert (method.plugin is not None) == (method.product_sampling or method.oracle)


def test_a_method_named_after_a_strategy_runs_exactly_that_strategy():
    """``sh_product_only`` reads ``strategy=product_only`` in the report, never another strategy
    that happens to behave alike under its other parameters. (Mitsuba's ``bsdf_only`` row is
    ``direct`` with BSDF samples alone: the estimator of the plugin's ``bsdf_only`` strategy.)"""
    from mitsuba_shsampling.integrators.strategy import STRATEGY_NAMES

    named = {m.name: m.name.removeprefix("sh_") for m in METHODS
             if m.name.startswith("sh_") and m.name.removeprefix("sh_") in STRATEGY_NAMES}
    assert named == {"sh_product_only": "product_only"}
    for method in METHODS:
        if method.name in named or "strategy" in method.integrator:
            assert method.integrator.get("strategy") == named.get(method.name), method.name


def test_admissible_spp_matches_what_each_sampler_renders():
    assert admissible_spp("independent", 23) == 23
    assert admissible_spp("stratified", 16) == 16
    assert admissible_spp("ldsampler", 16) == 16
    assert admissible_spp("ldsampler", 40) in (16, 64)
    sampler = mi.load_dict({"type": "stratified"})
    sampler.set_sample_count(admissible_spp("stratified", 20))
    assert sampler.sample_count() == admissible_spp("stratified", 20)


def test_warped_points_figure_draws_sampler_output_and_rejects_bad_shapes():
    density = np.outer(np.linspace(0, 1, 16), np.ones(32))
    png = figures.warped_points_figure(density, lambda u: u * [2 * np.pi, 2] - [0, 1], n_points=64)
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(ValueError, match="shape"):
        figures.warped_points_figure(density, lambda u: u[:, :1], n_points=64)


def verdict_of(mse_per_pass: dict[str, list[float]], time_s: float = 0.1):
    """The verdict rows of a one-scene report whose methods have these per-pass MSEs."""
    from mitsuba_shsampling.report.verdict import verdict

    def phase(values):
        return {"error": {"mse_per_pass": values, "mse": float(np.mean(values)), "non_finite": 0},
                "times_s": [time_s] * len(values), "time_s": time_s, "spp": 8, "time_budget_s": time_s,
                "budget_method": "direct", "tail_worse_than_baseline": [], "bias": {"flagged": False, "p_value": 0.5}}
    methods = {n: {"family": "direct", "equal_spp": phase(v), "equal_time": phase(v)} for n, v in mse_per_pass.items()}
    return verdict({"scenes": [{"scene": "s", "path": "s.xml", "references": {},
                                "runs": [{"sampler": "independent", "methods": methods}]}]})


def test_the_printed_verdict_says_best_only_where_the_interval_and_the_caveats_allow(capsys):
    cli._print_verdict(verdict_of({"direct": [1.0, 1.3, 0.7, 1.0], "sh_direct": [1.3, 0.7, 1.0, 1.0]}))
    tied = capsys.readouterr().out
    assert "best" not in tied and tied.count("no clear winner (") == 3
    cli._print_verdict(verdict_of({"direct": [1.0, 1.1, 0.9, 1.0], "sh_direct": [0.5, 0.55, 0.45, 0.5]},
                                  time_s=0.005))
    lines = capsys.readouterr().out.splitlines()
    assert "caveat: time budget too small to be meaningful" in "\n".join(lines)
    contests = {line.split(":")[0].strip(): line for line in lines if " / direct " in line}
    assert "sh_direct best of all" in contests["equal samples"]
    for title in ("equal time", "equal time, from the equal-sample passes"):
        assert "best" not in contests[title] and "no winner: time budget too small" in contests[title]
