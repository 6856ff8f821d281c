"""Specification: the benchmarks are importable functions of the package, the
``scripts/bench_*.py`` files only call them, and ``bench`` runs them in-process."""

import dataclasses
import json
import os
import subprocess
import sys

import pytest

import mitsuba_shsampling  # noqa: F401
import mitsuba as mi

mi.set_variant("llvm_ad_rgb")

from mitsuba_shsampling import benchmarks  # noqa: E402
from mitsuba_shsampling.benchmarks import env_pyramid  # noqa: E402
from mitsuba_shsampling.integrators import register  # noqa: E402
from mitsuba_shsampling.report.bench import run_benchmark  # noqa: E402

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.mark.parametrize("name", benchmarks.NAMES)
def test_each_benchmark_has_run_and_main_and_a_thin_script(name):
    module = benchmarks.benchmark(name)
    assert callable(module.run) and callable(module.main)
    with open(os.path.join(REPO, "scripts", f"bench_{name}.py")) as f:
        script = f.read()
    assert f"from mitsuba_shsampling.benchmarks.{name} import main" in script
    assert len(script.splitlines()) < 10


def test_an_unknown_benchmark_name_is_refused():
    with pytest.raises(ValueError, match="unknown benchmark"):
        benchmarks.benchmark("nope")


def test_a_script_runs_its_benchmark_and_writes_json(tmp_path):
    out = tmp_path / "pyramid.json"
    env = dict(os.environ, PYTHONPATH=REPO + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.run([sys.executable, os.path.join(REPO, "scripts", "bench_env_pyramid.py"),
                           "--sizes", "16x32", "--repeats", "1", "--json", str(out)],
                          env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "16x32" in proc.stdout.replace(" ", "")
    (row,) = json.loads(out.read_text())
    assert (row["height"], row["width"]) == (16, 32) and row["total"] > 0


def test_bench_calls_run_in_process_and_saves_records_and_output(tmp_path, monkeypatch):
    monkeypatch.setattr(env_pyramid, "QUICK_SIZES", ("8x16",))
    result = run_benchmark("env_pyramid", str(tmp_path), quick=True)
    assert result["error"] is None
    folder = tmp_path / "bench_env_pyramid"
    assert json.loads((folder / "bench_env_pyramid.json").read_text()) == result["results"]
    assert [(r["height"], r["width"]) for r in result["results"]] == [(8, 16)]
    assert "8x16" in (folder / "stdout.txt").read_text().replace(" ", "")


def test_the_pyramid_benchmark_builds_each_repeat_and_its_child_never_reads_the_disk_cache(monkeypatch):
    """A build the disk cache or the process held would be timed as a read, not a build."""
    from mitsuba_shsampling import build_cache
    monkeypatch.setenv(build_cache.ENVIRONMENT_VARIABLE, "off")  # as in the benchmark's child
    from mitsuba_shsampling.envmap import pyramid
    from mitsuba_shsampling.envmap.synthetic import envmap_emitter, sun_sky_latlong
    built = []
    real = pyramid._pyramid_arrays
    monkeypatch.setattr(pyramid, "_pyramid_arrays", lambda *a, **k: built.append(1) or real(*a, **k))
    emitter = envmap_emitter(sun_sky_latlong(8, 16))
    env_pyramid._rebuilt(emitter)
    env_pyramid._rebuilt(emitter)
    assert len(built) == 2

    seen = {}

    def child(command, env, **kwargs):
        seen.update(env)
        return subprocess.CompletedProcess(command, 0, stdout='{"height": 8}\n', stderr="")

    monkeypatch.setattr(env_pyramid.subprocess, "run", child)
    assert env_pyramid.measure(8, 16, 1) == {"height": 8}
    assert seen[build_cache.ENVIRONMENT_VARIABLE] == "off"


def test_a_child_that_dies_names_the_map_and_gives_its_own_error(monkeypatch):
    def child(command, **kwargs):
        return subprocess.CompletedProcess(command, -11, stdout="", stderr="Fatal Python error: Segmentation fault")

    monkeypatch.setattr(env_pyramid.subprocess, "run", child)
    with pytest.raises(RuntimeError, match=r"8x16 map failed \(exit -11\):\nFatal Python error"):
        env_pyramid.measure(8, 16, 1)


def test_a_failing_benchmark_is_recorded_not_raised(tmp_path, monkeypatch):
    def broken(quick=False):
        raise RuntimeError("no kernel today")

    monkeypatch.setattr(env_pyramid, "run", broken)
    result = run_benchmark("env_pyramid", str(tmp_path), quick=True)
    assert result["error"] == "RuntimeError: no kernel today" and result["json"] is None
    assert "no kernel today" in (tmp_path / "bench_env_pyramid" / "error.txt").read_text()


def test_the_interleaved_ab_script_reports_variance_time_and_efficiency_against_the_first(tmp_path):
    out = tmp_path / "ab.json"
    env = dict(os.environ, PYTHONPATH=REPO + os.pathsep + os.environ.get("PYTHONPATH", ""))
    scene = os.path.join(REPO, "mitsuba_shsampling", "scenes", "sphere_diffuse.xml")
    envmap = os.path.join(REPO, "tests", "data", "envmaps", "immenstadter_horn_1k.hdr")
    proc = subprocess.run([sys.executable, os.path.join(REPO, "scripts", "ab_interleaved.py"), scene,
                           "--envmap", envmap, "--res", "48", "--spp", "2", "--passes", "4", "--instances", "2",
                           "--json", str(out),
                           '{"type": "direct"}', '{"type": "direct", "bsdf_samples": 2, "emitter_samples": 0}'],
                          env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    report = json.loads(out.read_text())
    first, second = report["rows"]
    assert report["instances"] == 2 and len(first["pass_times_s"]) == 4
    assert first["instance_time_spread"] >= 1.0 and second["instance_time_spread"] >= 1.0
    assert first["variance_ratio"] == first["time_ratio"] == first["efficiency_ratio"] == 1.0
    assert second["efficiency_ratio"] == pytest.approx(1.0 / (second["variance_ratio"] * second["time_ratio"]))
    # BSDF sampling alone rarely finds the map's sun: far noisier than 1 + 1 MIS.
    assert second["pixel_variance"] > first["pixel_variance"]


def test_the_ab_script_sets_a_path_loops_settings_that_no_plugin_parameter_sets():
    sys.path.insert(0, os.path.join(REPO, "scripts"))
    try:
        import ab_interleaved
    finally:
        sys.path.pop(0)
    register()
    strict = ab_interleaved.load_integrator({"type": "sh_path", "path_settings": {"through_dirac": False}})
    default = ab_interleaved.load_integrator({"type": "sh_path"})
    assert strict.settings.through_dirac is False and default.settings.through_dirac is True
    assert dataclasses.replace(strict.settings, through_dirac=True) == default.settings


def test_the_product_benchmark_times_the_warp_with_its_lobes_from_memory_and_built_in_the_kernel(tmp_path):
    """Both against Mitsuba's own envmap sampler in the same run: the benchmark's lanes read
    their n^2 coefficients from memory, an integrator's build them from a lobe axis."""
    from mitsuba_shsampling.benchmarks import product
    from mitsuba_shsampling.envmap.synthetic import sun_sky_latlong
    path = str(tmp_path / "sun.exr")
    mi.Bitmap(sun_sky_latlong(32, 64, sun_radius_deg=5.0)).write(path)
    (row,) = product.run(quick=True, envmaps=[path], bands=[3], lanes=1 << 12, repeats=1)
    for key in ("ratio_to_mitsuba", "lobe_in_kernel_ratio_to_mitsuba", "msamples_per_s",
                "lobe_in_kernel_msamples_per_s"):
        assert 0.0 < row[key] < float("inf"), key


def test_interleaved_timing_runs_each_kernel_once_a_round_in_a_rotating_order():
    """Round k starts with run k (mod their number): no run always follows the same one, and a
    slow spell of the machine falls on all of them. Times are the kernels' execution times."""
    import drjit as dr
    calls = []

    def run(name):
        def launch():
            calls.append(name)
            dr.eval(dr.arange(mi.Float, 1000) * 2.0)
            dr.sync_thread()
        return launch

    times = benchmarks.interleaved_kernel_seconds({n: run(n) for n in "abc"}, repeats=4)
    assert calls == list("abc" "bca" "cab" "abc")
    assert {n: len(t) for n, t in times.items()} == {"a": 4, "b": 4, "c": 4}
    assert all(t >= 0.0 for ts in times.values() for t in ts)
    assert benchmarks.kernel_seconds(lambda: None) == 0.0  # no kernel launched, no time


def test_the_required_gain_script_prices_each_cells_best_product_plan_against_its_measured_gain(tmp_path):
    """The plan's candidate (predicted gain over the lean kernel) beside what forcing it
    measured at equal time, for a cell whose candidate falls within ``--near``."""
    out = tmp_path / "gain.json"
    env = dict(os.environ, PYTHONPATH=REPO + os.pathsep + os.environ.get("PYTHONPATH", ""))
    envmap = os.path.join(REPO, "tests", "data", "envmaps", "forest_slope_1k.hdr")
    proc = subprocess.run([sys.executable, os.path.join(REPO, "scripts", "bench_required_gain.py"),
                           "--scenes", "sphere_ggx010", "--maps", envmap, "--res", "32", "--spp", "2",
                           "--passes", "2", "--near", "0", "1000", "--json", str(out)],
                          env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    (row,) = json.loads(out.read_text())["rows"]
    assert row["scene"] == "sphere_ggx010" and row["map"] == "forest_slope_1k"
    assert row["predicted"] > 0 and set(row["strategies"].values()) & {"product", "product_only"}
    assert row["measured"] > 0 and row["time_ratio"] > 0
    assert "sphere_ggx010" in proc.stdout
