"""The ``sweep`` command: grid files, content keys, resumable Dask runs, the aggregate report."""

import dataclasses
import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

import mitsuba_shsampling  # noqa: F401  (LLVM backend check)
import mitsuba as mi

mi.set_variant("llvm_ad_rgb")

from mitsuba_shsampling import cli, scenes  # noqa: E402
from mitsuba_shsampling.report.compare import CompareSettings, run_compare  # noqa: E402
from mitsuba_shsampling.report.schema import serialise  # noqa: E402
from mitsuba_shsampling.sweep import aggregate  # noqa: E402
from mitsuba_shsampling.sweep.cells import cell_inputs, cell_key, describe_failure, run_cell  # noqa: E402
from mitsuba_shsampling.sweep.grid import GridError, load_grid  # noqa: E402
from mitsuba_shsampling.sweep.run import (MIN_DRJIT_THREADS, oversubscribed_hosts,  # noqa: E402
                                          run_sweep, thread_plan)

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
STUDIO_MAP = os.path.join(REPO, "tests", "data", "envmaps", "studio_small_03_1k.hdr")
TINY = {"res": 16, "spp": 2, "passes": 2, "ref_spp": 16, "convergence_max_spp": 0}
METHODS = ["direct", "sh_direct"]


def write_grid(path, scenes_, maps, **settings) -> str:
    """A grid file with TINY settings (overridden by ``settings``) and the two test methods."""
    values = {"scenes": scenes_, "maps": maps, "methods": METHODS, **TINY, **settings}
    lines = [f"{k} = {json.dumps(v)}" for k, v in values.items()]
    path.write_text("\n".join(lines) + "\n")
    return str(path)


def copy_scene(src_name: str, folder, name: str | None = None, replace: tuple[str, str] | None = None) -> str:
    """Copy a built-in scene (with the include and texture folders it refers to) into ``folder``,
    optionally editing its text."""
    for sub in ("include", "textures"):
        shutil.copytree(os.path.join(scenes.SCENES_DIR, sub), folder / sub, dirs_exist_ok=True)
    text = open(scenes.builtin_scenes()[src_name]).read()
    if replace:
        assert replace[0] in text
        text = text.replace(*replace)
    path = folder / f"{name or src_name}.xml"
    path.write_text(text)
    return str(path)


def report_mtimes(out) -> dict[str, int]:
    cells = os.path.join(out, "cells")
    return {d: os.stat(os.path.join(cells, d, "report.json")).st_mtime_ns for d in os.listdir(cells)
            if os.path.isfile(os.path.join(cells, d, "report.json"))}


@pytest.fixture(scope="module")
def first_sweep(tmp_path_factory):
    """2 scenes (copies of built-ins) x 2 maps on a 2-worker LocalCluster: (folder, grid, out, summary)."""
    root = tmp_path_factory.mktemp("sweep")
    scene_dir = root / "scenes"
    copy_scene("sphere_diffuse", scene_dir)
    copy_scene("sphere_ggx010", scene_dir)
    grid_path = write_grid(root / "grid.toml", ["scenes/sphere_diffuse.xml", "scenes/sphere_ggx010.xml"],
                           ["sunsky", STUDIO_MAP])
    out = str(root / "out")
    summary = run_sweep(load_grid(grid_path), out, workers=2, cache_dir=str(root / "cache"), progress=False)
    return root, grid_path, out, summary


def copy_sweep(first_sweep, tmp_path):
    """An independent copy of the first sweep's scenes, grid and output folder."""
    root, _, _, _ = first_sweep
    for name in ("scenes", "out"):
        shutil.copytree(root / name, tmp_path / name)
    shutil.copy(root / "grid.toml", tmp_path / "grid.toml")
    return str(tmp_path / "grid.toml"), str(tmp_path / "out")


# Grid files ---------------------------------------------------------------------------------

def test_grid_names_builtins_files_and_globs_relative_to_the_grid_file(tmp_path):
    copy_scene("sphere_ggx010", tmp_path / "s", name="mine")
    (tmp_path / "maps").mkdir()
    for stem in ("b", "a"):
        shutil.copy(STUDIO_MAP, tmp_path / "maps" / f"{stem}.hdr")
    grid = load_grid(write_grid(tmp_path / "g.toml", ["sphere_diffuse", "s/mine.xml"],
                                ["sunsky", "maps/*.hdr", "scene"], samplers=["independent", "stratified"]))
    assert [s.name for s in grid.scenes] == ["sphere_diffuse", "mine"]
    assert grid.scenes[0].file is None and grid.scenes[1].file == str(tmp_path / "s" / "mine.xml")
    assert [m.name for m in grid.maps] == ["sunsky", "a", "b", "scene"]
    cells = grid.cells()
    assert len(cells) == 2 * 4 * 2
    assert cells[0].label == "sphere_diffuse/sunsky/independent"
    assert cells[0].scene_path() == scenes.builtin_scenes()["sphere_diffuse"]
    assert cells[0].map_path() == scenes.SUNSKY_MAP
    assert [c for c in cells if c.map.name == "scene"][0].map_path() is None
    assert dict(cells[0].settings) == TINY and cells[0].methods == tuple(METHODS)


@pytest.mark.parametrize("text, message", [
    ('scenes = ["sphere_diffuse"]\nspp_count = 4\n', "unknown key"),
    ('scenes = ["missing.xml"]\n', "scene file not found"),
    ('scenes = ["no_such_builtin"]\n', "unknown built-in scene"),
    ('scenes = ["sphere_diffuse"]\nmaps = ["*.nothing"]\n', "matches no file"),
    ('scenes = ["sphere_diffuse", "sphere_diffuse"]\n', "must be unique"),
    ('scenes = ["sphere_diffuse"]\nsamplers = ["sobol"]\n', "unknown sampler"),
    ('scenes = ["sphere_diffuse"]\nmethods = ["fast"]\n', "unknown method"),
    ('scenes = ["sphere_diffuse"]\npasses = 1\n', "'passes' must be an integer >= 2"),
    ('maps = ["sunsky"]\n', "needs a 'scenes' list"),
    ('scenes = [\n', "cannot parse"),
])
def test_bad_grids_are_refused_with_the_reason_and_exit_code_2(tmp_path, capsys, text, message):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(GridError, match=message):
        load_grid(str(path))
    assert cli.main(["sweep", str(path), "--out", str(tmp_path / "out"), "--no-progress"]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("depth, accepted", [(-2, False), (-1, True), (0, False), (1, False), (2, True), (5, True)])
def test_a_grid_takes_exactly_the_max_depths_compare_takes(tmp_path, capsys, depth, accepted):
    """-1 (infinite, as Mitsuba's) or at least 2: one check (command_line.max_depth_problem) for both."""
    path = tmp_path / "g.toml"
    path.write_text(f'scenes = ["sphere_diffuse"]\nmax_depth = {depth}\n')
    if accepted:
        assert dict(load_grid(str(path)).settings)["max_depth"] == depth
    else:
        with pytest.raises(GridError, match="'max_depth' must be -1 \\(infinite"):
            load_grid(str(path))
    # compare checks --methods after --max-depth: an empty one is refused only once the depth passed.
    assert cli.main(["compare", "--max-depth", str(depth), "--methods", "", "--no-progress"]) == 2
    assert ("--max-depth must be -1 (infinite" in capsys.readouterr().err) is not accepted


def test_readme_grid_is_every_evaluation_sphere_under_sunsky_and_the_shipped_maps():
    grid = load_grid(os.path.join(REPO, "sweeps", "readme_table.toml"))
    assert [s.name for s in grid.scenes] == [
        "sphere_diffuse", "sphere_ggx005", "sphere_ggx010", "sphere_ggx020", "sphere_ggx030",
        "sphere_ggx050", "sphere_roughplastic", "sphere_principled", "sphere_conductor"]
    shipped = sorted(os.path.splitext(f)[0] for f in os.listdir(os.path.dirname(STUDIO_MAP)) if f.endswith(".hdr"))
    assert [m.name for m in grid.maps] == ["sunsky"] + shipped
    assert {"direct", "direct_misc", "env_only", "sh_direct"} <= set(grid.methods)
    assert len(grid.cells()) == 9 * 5


def test_the_mirror_row_grid_is_the_readme_grids_conductor_row_at_twice_the_passes():
    table = load_grid(os.path.join(REPO, "sweeps", "readme_table.toml"))
    mirror = load_grid(os.path.join(REPO, "sweeps", "readme_table_mirror.toml"))
    assert [s.name for s in mirror.scenes] == ["sphere_conductor"]
    assert [m.name for m in mirror.maps] == [m.name for m in table.maps]
    assert mirror.methods == table.methods
    settings, base = dict(mirror.cells()[0].settings), dict(table.cells()[0].settings)
    assert settings["passes"] == 2 * base["passes"]
    assert {k: v for k, v in settings.items() if k != "passes"} == {k: v for k, v in base.items() if k != "passes"}


def test_a_cell_of_the_readme_grid_runs(tmp_path):
    cell = load_grid(os.path.join(REPO, "sweeps", "readme_table.toml")).cells()[1]
    tiny = dataclasses.replace(cell, settings=tuple(TINY.items()))
    result = run_cell(tiny, cache_dir=str(tmp_path / "cache"))
    assert result.status == "ok", result.traceback
    assert result.archive and result.drjit_threads >= 1


# Content keys -------------------------------------------------------------------------------

def test_content_key_follows_scene_includes_and_map_bytes_settings_and_nothing_else(tmp_path):
    scene = copy_scene("sphere_ggx010", tmp_path / "s")
    env = tmp_path / "studio.hdr"
    shutil.copy(STUDIO_MAP, env)
    grid_path = write_grid(tmp_path / "g.toml", [scene], [str(env)])

    def key(path=grid_path):
        return cell_key(cell_inputs(load_grid(path).cells()[0]))

    base = key()
    (tmp_path / "s" / "unrelated.txt").write_text("not part of the scene")
    assert key() == base
    inputs = cell_inputs(load_grid(grid_path).cells()[0])
    assert [f for f, _ in inputs["files"]][:2] == ["sphere_ggx010.xml", os.path.join("include", "sphere_stage.xml")]

    changes = []
    with open(env, "ab") as f:
        f.write(b"\0")
    changes.append(key())
    stage = tmp_path / "s" / "include" / "sphere_stage.xml"
    stage.write_text(stage.read_text().replace('value="28"', 'value="30"'))
    changes.append(key())
    changes.append(key(write_grid(tmp_path / "g2.toml", [scene], [str(env)], spp=4)))
    changes.append(key(write_grid(tmp_path / "g3.toml", [scene], [str(env)], samplers=["stratified"])))
    assert len({base, *changes}) == 1 + len(changes)


# Sweeps -------------------------------------------------------------------------------------

def test_two_worker_sweep_computes_every_cell_and_writes_the_aggregate_report(first_sweep):
    _, _, out, summary = first_sweep
    assert sorted(summary.computed) == sorted(f"{s}/{m}/independent" for s in ("sphere_diffuse", "sphere_ggx010")
                                              for m in ("sunsky", "studio_small_03_1k"))
    assert summary.reused == [] and summary.failed == {}
    with open(os.path.join(out, "aggregate.json")) as f:
        agg = json.load(f)
    assert agg["kind"] == aggregate.KIND and len(agg["cells"]) == 4
    for row in agg["cells"]:
        assert row["status"] == "ok"
        assert row["winner"] in METHODS and row["best_mitsuba_efficiency"] == "direct"
        assert row["bias"] in ("ok", "unknown") or row["bias"].startswith("flagged")
        ratio = row["methods"]["sh_direct"]["efficiency_ratio_vs_best_mitsuba"]
        assert np.isfinite(ratio) and ratio > 0
        assert os.path.isfile(os.path.join(out, row["index_html"]))
        assert row["drjit_threads"] >= MIN_DRJIT_THREADS
    assert agg["heatmaps"] == {"independent": "heatmap_independent.png"}
    with open(os.path.join(out, "heatmap_independent.png"), "rb") as f:
        assert f.read(8) == b"\x89PNG\r\n\x1a\n"
    page = open(os.path.join(out, "index.html")).read()
    assert all(row["index_html"] in page for row in agg["cells"]) and "heatmap_independent.png" in page
    lines = open(os.path.join(out, "aggregate.csv")).read().strip().splitlines()
    assert len(lines) == 1 + 4 * len(METHODS)


def test_running_again_computes_nothing_and_rewrites_no_cell(first_sweep, tmp_path):
    grid_path, out = copy_sweep(first_sweep, tmp_path)
    before = report_mtimes(out)
    summary = run_sweep(load_grid(grid_path), out, workers=2, progress=False)
    assert summary.computed == [] and summary.failed == {} and len(summary.reused) == 4
    assert report_mtimes(out) == before


def test_editing_one_scene_file_recomputes_only_its_cells(first_sweep, tmp_path):
    grid_path, out = copy_sweep(first_sweep, tmp_path)
    scene = tmp_path / "scenes" / "sphere_ggx010.xml"
    scene.write_text(scene.read_text().replace('name="alpha" value="0.1"', 'name="alpha" value="0.2"'))
    summary = run_sweep(load_grid(grid_path), out, workers=2, cache_dir=str(tmp_path / "cache"), progress=False)
    assert sorted(summary.computed) == ["sphere_ggx010/studio_small_03_1k/independent",
                                        "sphere_ggx010/sunsky/independent"]
    assert sorted(summary.reused) == ["sphere_diffuse/studio_small_03_1k/independent",
                                      "sphere_diffuse/sunsky/independent"]


def test_a_broken_scene_fails_alone_and_the_other_cells_complete(tmp_path, capsys):
    good = copy_scene("sphere_diffuse", tmp_path / "s")
    broken = copy_scene("sphere_diffuse", tmp_path / "s", name="broken",
                        replace=('<bsdf type="diffuse" id="material">', '<bsdf type="no_such_bsdf" id="material">'))
    grid_path = write_grid(tmp_path / "g.toml", [good, broken], ["sunsky"], seed=7)
    out = tmp_path / "out"
    code = cli.main(["sweep", grid_path, "--out", str(out), "--workers", "2",
                     "--cache-dir", str(tmp_path / "cache"), "--no-progress"])
    assert code == 1
    printed = capsys.readouterr().out
    assert "1 cells computed, 0 reused, 1 failed" in printed and "failed: broken/sunsky/independent" in printed
    rows = {r["scene"]: r for r in json.load(open(out / "aggregate.json"))["cells"]}
    assert rows["sphere_diffuse"]["status"] == "ok"
    assert rows["broken"]["status"] == "failed" and "no_such_bsdf" in rows["broken"]["error"]
    record = json.load(open(out / rows["broken"]["folder"] / "cell.json"))
    assert "Traceback" in record["traceback"]
    assert "no_such_bsdf" in open(out / "index.html").read()


def test_a_failed_cells_error_keeps_the_exception_type_its_whole_message_and_the_last_frames():
    def load_material():
        raise RuntimeError("cannot load scene.xml\nplugin 'no_such_bsdf' is not registered")

    def load_scene():
        load_material()

    with pytest.raises(RuntimeError) as caught:
        load_scene()
    error = describe_failure(caught.value)
    assert error.startswith("RuntimeError: cannot load scene.xml\nplugin 'no_such_bsdf' is not registered")
    assert "in load_scene" in error and "in load_material" in error


def chosen(strategy_choice: dict | None):
    """What ``strategy`` ``auto`` chose (the kernel and each material's strategy), or None."""
    if not strategy_choice:
        return None
    return strategy_choice["lean"], tuple((m["name"], m["strategy"]) for m in strategy_choice["materials"])


def test_aggregate_numbers_are_those_of_compare_on_the_same_cell(first_sweep, tmp_path):
    root, _, out, _ = first_sweep
    row = next(r for r in json.load(open(os.path.join(out, "aggregate.json")))["cells"]
               if (r["scene"], r["map"]) == ("sphere_ggx010", "sunsky"))
    stored = json.load(open(os.path.join(out, row["report"])))["scenes"][0]["runs"][0]["methods"]

    # The aggregate summarises the cell's own report ...
    eff = {m: stored[m]["equal_time"]["efficiency"] for m in METHODS}
    assert row["methods"]["sh_direct"]["efficiency_ratio_vs_best_mitsuba"] == pytest.approx(
        eff["sh_direct"] / eff["direct"], rel=1e-12)
    for m in METHODS:
        assert row["methods"][m]["equal_spp_mse"] == stored[m]["equal_spp"]["error"]["mse"]
        worse = [w for kind in ("equal_spp", "equal_time") for w in stored[m][kind]["tail_worse_than_baseline"]]
        assert row["methods"][m]["tail_ok"] is (not worse)

    # ... and that report is what compare renders for the cell's settings (equal-spp renders
    # are seeded; equal-time spp and all timings depend on the run, so they are not compared).
    direct = run_compare([str(root / "scenes" / "sphere_ggx010.xml")], CompareSettings(
        out=str(tmp_path / "compare"), samplers=("independent",), methods=tuple(METHODS),
        envmap=scenes.SUNSKY_MAP, cache_dir=str(tmp_path / "cache"), progress=False, **TINY))
    methods = direct.scenes[0].runs[0].methods
    compared = []
    for m in METHODS:
        assert methods[m].equal_spp.spp == stored[m]["equal_spp"]["spp"]
        if chosen(methods[m].strategy_choice) != chosen(stored[m].get("strategy_choice")):
            # strategy auto chooses from its pilots' pass times, measured on the machine as it
            # is: at 16 px the lean and the product kernel can swap between two runs, and the
            # seeded renders are then of two estimators. The identity holds per estimator.
            continue
        assert methods[m].equal_spp.error.mse == pytest.approx(row["methods"][m]["equal_spp_mse"], rel=1e-5)
        compared.append(m)
    assert "direct" in compared  # no choice to make: always compared
    local = ("out", "cache_dir", "progress")
    settings = json.load(open(os.path.join(out, row["report"])))["settings"]
    assert {k: v for k, v in serialise(direct.settings).items() if k not in local} == \
        {k: v for k, v in settings.items() if k not in local}


def test_sweep_runs_on_a_cluster_given_by_scheduler_address(tmp_path):
    from distributed import Client, LocalCluster

    scene = copy_scene("sphere_diffuse", tmp_path / "s")
    grid_path = write_grid(tmp_path / "g.toml", [scene], [STUDIO_MAP], seed=11)
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address=None) as cluster, Client(cluster) as client:
        assert cluster.scheduler_address.startswith("tcp://127.0.0.1:")
        worker_pids = set(client.run(os.getpid).values())
        summary = run_sweep(load_grid(grid_path), str(tmp_path / "out"), scheduler=cluster.scheduler_address,
                            workers=1, cache_dir=str(tmp_path / "cache"), progress=False)
    assert summary.computed == ["sphere_diffuse/studio_small_03_1k/independent"] and summary.failed == {}
    row = json.load(open(tmp_path / "out" / "aggregate.json"))["cells"][0]
    assert row["status"] == "ok" and int(row["host"].rsplit(":", 1)[1]) in worker_pids


def test_results_table_script_reads_the_aggregate(first_sweep):
    _, _, out, _ = first_sweep
    printed = subprocess.run([sys.executable, os.path.join(REPO, "scripts", "results_table.py"),
                              os.path.join(out, "aggregate.json")], capture_output=True, text=True, check=True).stdout
    table = [line for line in printed.splitlines() if line.startswith("| ") and "sphere_" in line]
    assert sorted((line.split(" | ")[0][2:], line.split(" | ")[1]) for line in table) == sorted(
        (m, s) for s in ("sphere_diffuse", "sphere_ggx010") for m in ("sunsky", "studio_small_03_1k"))


def test_results_table_script_sets_the_choosers_predictions_against_the_measurement(first_sweep):
    _, _, out, _ = first_sweep
    printed = subprocess.run([sys.executable, os.path.join(REPO, "scripts", "results_table.py"),
                              os.path.join(out, "aggregate.json"), "--choices"],
                             capture_output=True, text=True, check=True).stdout
    table = [line.split(" | ") for line in printed.splitlines() if line.startswith("| ") and "sphere_" in line]
    assert len(table) == 4
    for cells in table:
        assert cells[2] in ("lean", "with product")
        assert float(cells[3]) >= 1.0  # the predicted gain over the lean kernel
        assert float(cells[4].split(" ")[0]) > 0  # the measured equal-time ratio


# Pieces -------------------------------------------------------------------------------------

def test_thread_plan_shares_each_hosts_cores_between_its_workers():
    cores = {"tcp://127.0.0.1:1001": 8, "tcp://127.0.0.1:1002": 8, "tcp://127.0.0.2:1001": 4}
    plan = thread_plan(cores)
    assert plan == {"tcp://127.0.0.1:1001": 4, "tcp://127.0.0.1:1002": 4, "tcp://127.0.0.2:1001": 4}
    assert oversubscribed_hosts(cores, plan) == []
    two_on_two = {"tcp://127.0.0.1:1001": 2, "tcp://127.0.0.1:1002": 2}
    assert thread_plan(two_on_two) == dict.fromkeys(two_on_two, MIN_DRJIT_THREADS)
    assert oversubscribed_hosts(two_on_two, thread_plan(two_on_two)) == ["127.0.0.1"]


def _report(methods: dict) -> dict:
    return {"scenes": [{"notes": [], "runs": [{"methods": methods}]}]}


def _entry(per_pass, time=1.0, flagged=False, tail_worse=()):
    """A report entry in compare's format: expected MSE over passes, efficiency, bias, and the
    tail statistics worse than the baseline's (a list of texts, empty when none is)."""
    mse = float(np.mean(per_pass))
    e = {"error": {"mse": mse, "mse_per_pass": list(per_pass)}, "time_s": time,
         "efficiency": 1 / (mse * time), "bias": {"flagged": flagged},
         "tail_worse_than_baseline": list(tail_worse)}
    return {"equal_spp": e, "equal_time": e}


def test_summary_picks_the_best_mitsuba_strategy_and_reports_flags():
    summary = aggregate.summarise_report(_report({
        "direct": _entry([1.0, 3.0]),
        "direct_misc": _entry([0.9, 1.1]),
        # A Mitsuba strategy like the others (report/methods.py), the worst of them here.
        "bsdf_only": _entry([4.0, 4.0]),
        "sh_direct": _entry([0.4, 0.6], flagged=True, tail_worse=["12 fireflies against direct's 0"]),
    }))
    assert summary["best_mitsuba_efficiency"] == summary["best_mitsuba_mse"] == "direct_misc"
    assert summary["winner"] == "sh_direct"
    sh = summary["methods"]["sh_direct"]
    assert sh["efficiency_ratio_vs_best_mitsuba"] == pytest.approx(2.0)
    assert sh["mse_ratio_vs_best_mitsuba"] == pytest.approx(0.5)
    assert sh["time_ratio_vs_direct"] == pytest.approx(1.0)
    assert summary["methods"]["direct_misc"]["efficiency_ratio_vs_best_mitsuba_err"] == 0.0
    assert sh["bias_ok"] is False and sh["tail_ok"] is False
    assert summary["methods"]["direct"]["bias_ok"] is True and summary["methods"]["direct"]["tail_ok"] is True
    assert summary["bias"] == "flagged: sh_direct"


def test_ratio_uncertainty_cancels_what_paired_passes_share():
    rng = np.random.default_rng(3)
    best = rng.uniform(0.5, 1.5, 64)
    # Passes that share a seed share their luck: a method that is the best one scaled has no
    # uncertainty in the ratio, however noisy each is.
    assert aggregate.ratio_stderr(0.5, 0.5 * best, best) == pytest.approx(0.0, abs=1e-12)
    # Unpaired (different pass counts): the two relative standard errors add in quadrature.
    other = rng.uniform(0.2, 0.8, 32)
    rse = lambda v: v.std(ddof=1) / np.sqrt(len(v)) / v.mean()  # noqa: E731
    ratio = other.mean() / best.mean()
    assert aggregate.ratio_stderr(ratio, other, best) == pytest.approx(ratio * np.hypot(rse(other), rse(best)))
    summary = aggregate.summarise_report(_report({"direct": _entry(list(best)), "sh_direct": _entry(list(other))}))
    assert summary["methods"]["sh_direct"]["mse_ratio_vs_best_mitsuba_err"] == pytest.approx(
        ratio * np.hypot(rse(other), rse(best)))


def test_summary_reads_missing_fields_as_unknown_instead_of_failing():
    summary = aggregate.summarise_report(_report({"direct": {"equal_spp": {"mse": 1.0}}, "sh_direct": {}}))
    assert summary["winner"] is None and summary["best_mitsuba_mse"] == "direct"
    assert summary["methods"]["sh_direct"]["efficiency_ratio_vs_best_mitsuba"] is None
    assert summary["methods"]["direct"]["efficiency_ratio_vs_best_mitsuba_err"] is None
    assert summary["bias"] == "unknown"
    assert "error" in aggregate.summarise_report({"scenes": []})


def test_a_saved_results_file_regenerates_the_readme_table_and_a_stale_one_is_caught(first_sweep, tmp_path):
    _, _, out, _ = first_sweep
    script = os.path.join(REPO, "scripts", "results_table.py")
    results = tmp_path / "results" / "tiny.json"
    subprocess.run([sys.executable, script, os.path.join(out, "aggregate.json"), "--save", str(results),
                    "--command", "sweep tiny.toml"], capture_output=True, text=True, check=True)
    saved = json.loads(results.read_text())
    assert saved["command"] == "sweep tiny.toml" and saved["commit"] and saved["machine"]["cores"]
    assert len(saved["rows"]) == 4
    readme = tmp_path / "README.md"
    readme.write_text("# t\n<!-- table: results/tiny.json -->\n| old |\n<!-- end table -->\nafter\n")

    def sync(flag):
        return subprocess.run([sys.executable, script, "--readme", str(readme), flag], capture_output=True, text=True)

    stale = sync("--check")
    assert stale.returncode == 1 and "results/tiny.json" in stale.stdout
    assert sync("--write").returncode == 0
    text = readme.read_text()
    assert "| old |" not in text and text.endswith("<!-- end table -->\nafter\n")
    assert sum(line.startswith("| sphere_") for line in text.splitlines()) == 4
    assert sync("--check").returncode == 0
