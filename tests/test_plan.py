"""Specification of the plan: made once, the same in every process, reusable and in view.

``strategy`` ``auto`` plans each material's environment strategy from a cost model
(a calibration of this machine, else the shipped figures), never from a clock
unless ``plan`` is ``measure``. The plan can be made before the first render,
saved, loaded and forced per material; its inputs are built once per content and
shared by every integrator object with the same options; a parameter change
rebuilds only what it touches; and the plan is logged.
"""

import gc
import json
import os
import subprocess
import sys
import warnings

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

mi.set_variant("llvm_ad_rgb")

from mitsuba_shsampling import build_cache  # noqa: E402
from mitsuba_shsampling.envmap import pyramid as pyramid_module  # noqa: E402
from mitsuba_shsampling.integrators import chooser as chooser_module  # noqa: E402
from mitsuba_shsampling.integrators import costs, pilots, register  # noqa: E402
from mitsuba_shsampling.integrators.options import OptionError  # noqa: E402
from mitsuba_shsampling.integrators.sharing import forget_shared  # noqa: E402
from mitsuba_shsampling.lobes import scene_lobes  # noqa: E402

from test_integrators import MATERIALS, make_scene, sphere  # noqa: E402

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PLANNED = ("ggx", "diffuse", "roughplastic")


@pytest.fixture(autouse=True)
def fresh_state():
    """Each test starts as a fresh process would: no shared state, no in-process builds."""
    register()
    forget_shared()
    build_cache.clear_in_process()
    yield
    forget_shared()


def scene_of(names=PLANNED):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return make_scene(materials={k: MATERIALS[k] for k in names})


def sh_direct(**params):
    return mi.load_dict({"type": "sh_direct", "max_bands": 5, **params})


def count_calls(monkeypatch, module, name):
    """Wrap ``module.name`` so that its calls are counted; returns the counter (a list)."""
    calls, original = [], getattr(module, name)

    def counted(*args, **kwargs):
        calls.append(args)
        return original(*args, **kwargs)
    monkeypatch.setattr(module, name, counted)
    return calls


# ------------------------------------------------------------ no clock by default

def test_the_default_plan_reads_no_clock_and_says_where_its_costs_come_from(monkeypatch):
    def no_clock(*_):
        raise AssertionError("a default plan timed a pass")
    monkeypatch.setattr(pilots, "kernel_time", no_clock)
    choice = sh_direct().plan(scene_of())
    assert choice.mode == "estimate"
    assert choice.costs["source"] == "shipped"
    assert {m.name for m in choice.materials} >= set(PLANNED)


def test_without_a_calibration_the_shipped_model_plans_and_with_one_the_calibration_does():
    assert costs.cost_model("direct") == costs.SHIPPED_MODELS["direct"]
    assert costs.cost_model("path") == costs.SHIPPED_MODELS["path"]
    calibrated = costs.CostModel(product_code=0.5, environment_only=9.0, product_walk=9.0, product_table=9.0,
                                 product_only_walk=9.0, product_only_table=9.0, bsdf_only=9.0)
    path = costs.save_calibration({"direct": calibrated, "path": calibrated}, seconds=1.0)
    try:
        model = costs.cost_model("direct")
        assert model.source == path and model.product_walk == 9.0
        # Every strategy but the environment now costs nine passes per unit of film: nothing pays for it.
        choice = sh_direct().plan(scene_of())
        assert choice.costs["source"] == path
        assert {m.strategy.label for m in choice.materials} <= {"environment"}
    finally:
        os.remove(path)
    assert costs.cost_model("direct").source == "shipped"


def test_a_calibration_of_other_code_is_not_read(tmp_path):
    path = costs.save_calibration({"direct": costs.SHIPPED, "path": costs.SHIPPED}, seconds=1.0)
    try:
        record = json.loads(open(path).read())
        record["code"] = "another version"
        record["models"]["direct"]["product_walk"] = 123.0
        open(path, "w").write(json.dumps(record))
        assert costs.cost_model("direct") == costs.SHIPPED_MODELS["direct"]
    finally:
        os.remove(path)


@pytest.mark.parametrize("cache", ["folder", "off"])
def test_on_a_backend_without_shipped_figures_the_first_plan_calibrates_the_machine_once(monkeypatch, tmp_path,
                                                                                         cache):
    # As on a CUDA machine: the LLVM figures are not used there (issue 47: they priced the
    # product into a loss on an H200). Timing itself is calibration.py's (its own test).
    from mitsuba_shsampling import calibration
    monkeypatch.setenv("SHSAMPLING_CACHE_DIR", str(tmp_path) if cache == "folder" else "off")
    monkeypatch.setattr(costs, "SHIPPED_BACKENDS", ())
    monkeypatch.setattr(costs, "_calibrated_here", {})
    measured = costs.CostModel(product_code=0.3, environment_only=0.2, product_walk=4.0, product_table=4.0,
                               product_only_walk=4.0, product_only_table=4.0, source="calibration")
    runs = []

    def calibrate(*args):
        runs.append(args)
        return {"direct": measured, "path": measured}, 2.0
    monkeypatch.setattr(calibration, "calibrate", calibrate)
    first, second = costs.cost_model("direct"), costs.cost_model("path")
    assert len(runs) == 1 and first.product_walk == second.product_walk == 4.0
    assert first.source == (costs.calibration_path() if cache == "folder" else "calibration")
    choice = sh_direct().plan(scene_of())
    assert len(runs) == 1 and choice.costs["product_walk"] == 4.0


FRESH_PROCESS = """
import json, sys
import numpy as np
import mitsuba_shsampling, mitsuba as mi
mi.set_variant("llvm_ad_rgb")
sys.path.insert(0, {tests!r})
from test_integrators import MATERIALS, make_scene
from mitsuba_shsampling.integrators import register
register()
scene = make_scene(materials={{k: MATERIALS[k] for k in {names!r}}})
sh = mi.load_dict({{"type": "sh_direct", "max_bands": 5}})
image = mi.render(scene, integrator=sh, spp=4, seed=7)
np.save({out!r}, np.asarray(image))
print(json.dumps(sh.choice(scene).assignment()))
"""


def test_five_fresh_processes_make_one_plan_and_the_same_image(tmp_path):
    """Each process builds from an empty cache folder, as on a new machine."""
    procs = []
    for k in range(5):
        code = FRESH_PROCESS.format(tests=os.path.join(REPO, "tests"), names=PLANNED, out=str(tmp_path / f"{k}.npy"))
        env = dict(os.environ, SHSAMPLING_CACHE_DIR=str(tmp_path / f"cache{k}"),
                   PYTHONPATH=REPO + os.pathsep + os.environ.get("PYTHONPATH", ""))
        procs.append(subprocess.Popen([sys.executable, "-c", code], env=env, stdout=subprocess.PIPE,
                                      stderr=subprocess.PIPE, text=True))
    plans = []
    for proc in procs:
        out, err = proc.communicate(timeout=600)
        assert proc.returncode == 0, err
        plans.append(out.strip().splitlines()[-1])
    assert len(set(plans)) == 1, plans
    images = [np.load(tmp_path / f"{k}.npy") for k in range(5)]
    for image in images[1:]:
        assert np.sqrt(np.mean((image - images[0]) ** 2)) / np.sqrt(np.mean(images[0] ** 2)) < 1e-4


UNDER_INFO_LOG = """
import sys
import drjit as dr, mitsuba as mi
mi.set_variant("llvm_ad_rgb")
sys.path.insert(0, {tests!r})
from test_integrators import MATERIALS, make_scene
from mitsuba_shsampling.integrators import register
register()
scene = make_scene(materials={{k: MATERIALS[k] for k in {names!r}}})
dr.set_log_level(dr.LogLevel.Info)
mi.load_dict({{"type": "sh_direct", "max_bands": 5}}).plan(scene)
print("planned")
"""


def test_a_plan_under_dr_jits_info_log_level_finishes():
    """Dr.Jit's log callback takes the GIL while Dr.Jit's lock is held: set-up work on Dr.Jit
    from two Python threads (the pyramids were once built beside the lobe fits) deadlocked
    here in every try."""
    code = UNDER_INFO_LOG.format(tests=os.path.join(REPO, "tests"), names=PLANNED)
    env = dict(os.environ, SHSAMPLING_CACHE_DIR="off", PYTHONPATH=REPO + os.pathsep + os.environ.get("PYTHONPATH", ""))
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip().splitlines()[-1] == "planned"


def test_the_plan_and_the_render_read_no_memory_whose_alignment_varies_from_run_to_run():
    """An array that Dr.Jit maps from numpy at an address not a multiple of 64 is read with
    'align 1' loads; numpy's addresses differ per process, so such a kernel was new to the
    kernel cache in about half of fresh processes (seconds of set-up compiled again)."""
    scene, sh = scene_of(), sh_direct()
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history()
        sh.plan(scene)
        mi.render(scene, integrator=sh, spp=1)
        kernels = [k for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT]
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    assert len(kernels) > 10
    unaligned = [k["hash"] for k in kernels if "align 1," in k["ir"].getvalue()]
    assert unaligned == []


# ------------------------------------------------------------ pinning

def test_plan_is_made_before_the_first_render_and_the_render_keeps_it(monkeypatch):
    scene = scene_of()
    sh = sh_direct()
    assert sh.choice(scene) is None
    choice = sh.plan(scene)
    assert choice is not None and sh.choice(scene) is choice
    chosen = count_calls(monkeypatch, chooser_module, "choose_strategies")
    mi.render(scene, integrator=sh, spp=1)
    assert chosen == [] and sh.choice(scene) is choice


def test_a_plan_file_is_written_then_read_and_runs_what_it_says(tmp_path, monkeypatch):
    path = str(tmp_path / "plan.json")
    scene = scene_of()
    made = sh_direct(plan_file=path).plan(scene)
    stored = json.loads(open(path).read())
    assert stored["strategies"] == made.assignment()

    forget_shared()
    chosen = count_calls(monkeypatch, chooser_module, "choose_strategies")
    loaded = sh_direct(plan_file=path).plan(scene)
    assert chosen == [] and loaded.mode == "file" and loaded.assignment() == made.assignment()
    assert loaded.lean == made.lean and loaded.cosine_tables == made.cosine_tables
    assert loaded.bsdf_shares == made.bsdf_shares


def test_a_plan_file_of_other_materials_or_options_is_replaced_with_a_warning(tmp_path):
    path = str(tmp_path / "plan.json")
    sh_direct(plan_file=path).plan(scene_of(("ggx", "diffuse")))
    forget_shared()
    with pytest.warns(RuntimeWarning, match="does not fit.*materials"):
        choice = sh_direct(plan_file=path).plan(scene_of())
    assert choice.mode == "estimate" and set(json.loads(open(path).read())["strategies"]) >= set(PLANNED)
    forget_shared()
    with pytest.warns(RuntimeWarning, match="other options"):
        sh_direct(plan_file=path, emitter_samples=2).plan(scene_of())


def test_an_unreadable_plan_file_is_replaced_with_a_warning(tmp_path):
    path = tmp_path / "plan.json"
    path.write_text("{ not json")
    with pytest.warns(RuntimeWarning, match="cannot be read"):
        choice = sh_direct(plan_file=str(path)).plan(scene_of())
    assert choice.mode == "estimate"


def test_a_measured_plan_is_kept_like_wisdom_and_reused_by_the_next_process(monkeypatch, tmp_path):
    monkeypatch.setenv("SHSAMPLING_CACHE_DIR", str(tmp_path))  # its wisdom is kept from other tests
    scene = scene_of(("ggx", "diffuse"))
    measured = sh_direct(plan="measure").plan(scene)
    assert measured.mode == "measure" and measured.costs["source"] == "measured in the scene"
    forget_shared()
    chosen = count_calls(monkeypatch, chooser_module, "choose_strategies")
    again = sh_direct(plan="measure").plan(scene)
    assert chosen == [] and again.mode == "kept" and again.assignment() == measured.assignment()


def test_an_estimated_plan_is_kept_for_the_next_process_and_a_new_cost_model_plans_again(monkeypatch, tmp_path):
    monkeypatch.setenv("SHSAMPLING_CACHE_DIR", str(tmp_path))
    scene = scene_of(("ggx", "diffuse"))
    made = sh_direct().plan(scene)
    assert made.mode == "estimate"
    forget_shared()
    build_cache.clear_in_process()
    chosen = count_calls(monkeypatch, chooser_module, "choose_strategies")
    kept = sh_direct().plan(scene)
    assert chosen == [] and kept.mode == "kept"
    # The same plan, with the predictions it was made with.
    assert kept.as_dict()["materials"] == made.as_dict()["materials"]
    assert kept.predicted_gain == made.predicted_gain and kept.lean == made.lean
    # Other cost figures (a calibration of this machine) make another plan.
    forget_shared()
    other = costs.CostModel(**{**costs.SHIPPED_MODELS["direct"].as_dict(), "product_walk": 9.0, "source": "test"})
    monkeypatch.setattr(chooser_module, "cost_model", lambda kind: other)
    again = sh_direct().plan(scene)
    assert len(chosen) == 1 and again.mode == "estimate" and again.costs["product_walk"] == 9.0


def test_materials_named_in_strategy_keep_their_strategy_and_the_rest_are_planned():
    choice = sh_direct(strategy="ggx=product,diffuse=environment").plan(scene_of())
    by_name = {m.name: m for m in choice.materials}
    assert by_name["ggx"].strategy.label == "product" and by_name["ggx"].forced
    assert by_name["diffuse"].strategy.label == "environment" and by_name["diffuse"].forced
    assert not by_name["roughplastic"].forced


def test_an_unknown_material_or_a_strategy_it_cannot_run_is_an_error_naming_it():
    with pytest.raises(OptionError, match="'copper'.*does not have.*ggx"):
        sh_direct(strategy="copper=product").plan(scene_of())
    with pytest.raises(OptionError, match="'smooth' cannot run 'product_only'"):
        sh_direct(strategy="smooth=product_only").plan(scene_of(("ggx", "smooth")))
    # Checked when the plugin loads (Mitsuba reports a plugin's error as a RuntimeError).
    with pytest.raises(RuntimeError, match="'ggx=' must be 'material=strategy'"):
        sh_direct(strategy="ggx=")


# ------------------------------------------------------------ reuse

def test_a_second_object_with_the_same_options_shares_the_state_and_the_plan(monkeypatch):
    scene = scene_of()
    first_object = sh_direct()
    first = first_object.plan(scene)
    built = count_calls(monkeypatch, pyramid_module, "_pyramid_arrays")
    chosen = count_calls(monkeypatch, chooser_module, "choose_strategies")
    second = sh_direct()
    assert second.plan(scene) is first
    assert built == [] and chosen == []


def test_the_shared_state_lets_a_scene_go_with_its_last_integrator_object():
    """A scene kept alive by the plugin would keep its AD graph too, which a later
    differentiable render on another scene cannot traverse (test_sh_prb's replay test)."""
    scene = scene_of()
    before = sys.getrefcount(scene)
    integrator = sh_direct()
    integrator.plan(scene)
    assert sys.getrefcount(scene) > before  # the state holds it while an object lives
    del integrator
    gc.collect()
    assert sys.getrefcount(scene) == before


def test_plan_runs_the_cycle_collector_once_a_call_and_before_a_build(monkeypatch):
    """The collector frees a dropped scene's objects before anything is traced (a frozen
    function's recording would meet them); once is enough, and each run costs ~20 ms."""
    import mitsuba_shsampling.integrators.environment as environment
    collections = count_calls(monkeypatch, environment.gc, "collect")
    built = count_calls(monkeypatch, environment.EnvPyramid, "__init__")
    scene, integrator = scene_of(), sh_direct()
    integrator.plan(scene)
    pyramids = len(built)
    assert pyramids > 0 and len(collections) == 1  # before the build, not again after it
    integrator.plan(scene)
    assert len(built) == pyramids and len(collections) == 2  # nothing built: plan's own


def test_two_objects_with_equal_options_on_two_scenes_keep_each_its_scenes_state():
    """A training and a validation scene, or two optimisations in one process: objects with
    equal options share a scene's state, and one on another scene does not rebuild it."""
    first_scene, second_scene = scene_of(("ggx",)), scene_of(("diffuse", "ggx"))
    first, second = sh_direct(), sh_direct()
    first_state, second_state = first.scenes.get(first_scene), second.scenes.get(second_scene)
    assert first_state is not second_state
    for _ in range(2):
        assert first.scenes.get(first_scene) is first_state and second.scenes.get(second_scene) is second_state
    assert sh_direct().scenes.get(second_scene) is second_state  # a third object: the state made for it
    moved = first.scenes.get(second_scene)  # an object that moves to the other scene takes its state
    assert moved is second_state


def planned_then_changed(monkeypatch, key, value):
    """Plan a scene, then set its parameter ``key`` to ``value(old)`` and plan again:
    (the lobe fits, the pyramid builds) that the second plan ran."""
    scene = scene_of()
    sh = sh_direct()
    sh.plan(scene)
    fitted = count_calls(monkeypatch, scene_lobes.SceneLobes, "_fit_bsdf_now")
    built = count_calls(monkeypatch, pyramid_module, "_pyramid_arrays")
    params = mi.traverse(scene)
    params[key] = value(params[key])
    params.update()
    assert sh.plan(scene) is not None
    return fitted, built


def test_a_bsdf_change_refits_that_bsdf_alone_and_keeps_the_pyramid(monkeypatch):
    """The state is rebuilt, but each build it reads is looked up by its inputs' content."""
    fitted, built = planned_then_changed(monkeypatch, "ggx.bsdf.alpha.value", lambda _: 0.35)
    assert len(fitted) == 1 and built == []


def test_an_envmap_change_rebuilds_the_pyramid_alone(monkeypatch):
    fitted, built = planned_then_changed(monkeypatch, "env.data", lambda data: data * 0.5 + 0.01)
    assert len(built) >= 1 and fitted == []


def test_a_pyramid_read_from_the_disk_cache_equals_a_fresh_build(monkeypatch, tmp_path):
    monkeypatch.setenv("SHSAMPLING_CACHE_DIR", str(tmp_path))
    scene = scene_of(("ggx",))
    fresh = sh_direct().scenes.get(scene).pyramid
    forget_shared()
    build_cache.flush()
    build_cache.clear_in_process()
    built = count_calls(monkeypatch, pyramid_module, "_pyramid_arrays")
    cached = sh_direct().scenes.get(scene).pyramid
    assert built == []
    assert (cached.depth, cached.total, cached.radiant_total) == (fresh.depth, fresh.total, fresh.radiant_total)
    for name in ("buffer", "records"):
        assert np.array_equal(getattr(fresh, name).numpy(), getattr(cached, name).numpy(), equal_nan=True)


def test_a_rebuild_after_a_parameter_change_keeps_its_builds_in_the_process_not_on_disk(monkeypatch, tmp_path):
    """An optimisation changes the parameters at every step: those builds are never met again.
    A first build of a scene (a new process's, a new integrator's) writes them as before."""
    monkeypatch.setenv("SHSAMPLING_CACHE_DIR", str(tmp_path))
    build_cache.clear_in_process()

    def files():
        build_cache.flush()
        return sorted(p.name for p in tmp_path.rglob("*.npz"))

    scene = scene_of(("ggx",))
    integrator = sh_direct()
    before = integrator.scenes.get(scene)
    first = files()
    assert first
    params = mi.traverse(scene)
    params["ggx.bsdf.alpha.value"] = 0.35
    params.update()
    assert integrator.scenes.get(scene) is not before  # rebuilt, the BSDF refitted
    assert files() == first
    forget_shared()
    build_cache.clear_in_process()
    sh_direct().scenes.get(scene)
    assert len(files()) > len(first)


# ------------------------------------------------------------ in view

def test_the_plan_is_one_info_line_with_the_set_up_time(capfd):
    level = mi.logger().log_level()
    mi.set_log_level(mi.LogLevel.Info)
    try:
        choice = sh_direct().plan(scene_of())
        sh_direct().plan(scene_of())  # another scene object with equal content: planned again
    finally:
        mi.set_log_level(level)
    lines = [line for line in capfd.readouterr().out.splitlines() if "sh_direct: plan" in line]
    assert len(lines) == 2
    assert f"set-up {choice.setup_seconds:.2f} s" in lines[0] and "ggx" in lines[0]
    assert choice.setup_seconds > 0
    # The kernels it compiled because Dr.Jit's cache did not hold them, said in the line where any were.
    assert choice.kernels_compiled >= 0
    assert ("new to this machine" in lines[0]) == (choice.kernels_compiled > 0)


def test_sh_path_plans_before_its_first_render_from_the_path_model():
    scene = scene_of(("ggx", "diffuse"))
    sh = mi.load_dict({"type": "sh_path", "max_depth": 3, "max_bands": 5})
    choice = sh.plan(scene)
    assert choice.mode == "estimate" and choice.costs["product_walk"] == costs.SHIPPED_MODELS["path"].product_walk


def test_a_device_array_read_for_a_content_key_leaves_the_scene_unchanged():
    """Reading a literal (the map's scale) for a key must not look like a parameter change."""
    scene = scene_of(("ggx",))
    sh = sh_direct()
    env = sh.scenes.get(scene)
    from mitsuba_shsampling.traversal import content_parts
    content_parts(scene)
    assert sh.scenes.get(scene) is env
    assert dr.width(env.pyramid.buffer) > 0


def test_a_scene_keeps_its_plan_key_whatever_order_its_objects_were_loaded_in():
    """Mitsuba's parallel loading lists a scene's shapes in another order in each process;
    the key that a kept plan is read by must not change with it (and must with the content)."""
    from mitsuba_shsampling.build_cache import content_key
    from mitsuba_shsampling.traversal import content_parts

    spheres = {name: sphere([0.9 * i - 0.9, 0.0, 0.0], MATERIALS[name])
               for i, name in enumerate(("ggx", "diffuse", "roughplastic"))}

    def key_of(order, alpha=0.2):
        parts = {"type": "scene", "env": {"type": "constant"}}
        for name in order:
            parts[name] = spheres[name]
        parts["ggx"] = {**parts["ggx"], "bsdf": {**MATERIALS["ggx"], "alpha": alpha}}
        scene = mi.load_dict(parts)
        return [s.id() for s in scene.shapes()], content_key(*content_parts(scene))

    order, key = key_of(("ggx", "diffuse", "roughplastic"))
    other_order, same_key = key_of(("roughplastic", "ggx", "diffuse"))
    assert order != other_order and key == same_key
    assert key_of(("ggx", "diffuse", "roughplastic"), alpha=0.3)[1] != key


def test_materials_of_shapes_without_ids_have_the_same_names_whatever_the_loading_order():
    """A material is named by its shape's position where neither has an id (``shape2``): the
    position in an order of the shapes' content, not in Mitsuba's (parallel) loading order,
    so that a plan or a ``strategy`` entry naming it means the same material in every process."""
    from mitsuba_shsampling.scene_materials import scene_materials

    spheres = {x: f'<shape type="sphere"><point name="center" x="{x}" y="0" z="0"/><float name="radius" '
                  f'value="0.4"/><bsdf type="{kind}"/></shape>'
               for x, kind in ((-1.0, "diffuse"), (0.0, "roughconductor"), (1.0, "roughplastic"))}

    def names(order):
        scene = mi.load_string('<scene version="3.0.0">' + "".join(spheres[x] for x in order) + "</scene>")
        return {m.name: m.bsdf.class_name() for m in scene_materials(scene)}

    first = names((-1.0, 0.0, 1.0))
    assert all(name.startswith("shape") for name in first)
    assert names((1.0, -1.0, 0.0)) == first == names((0.0, 1.0, -1.0))


def test_a_map_of_another_depth_compiles_no_kernel_again(monkeypatch):
    """A user's next map whose pyramid has another depth (another resolution, or features
    at another scale) reuses every kernel the last one compiled: the descent to the finest
    level reads the depth from the device. (The map keeps its resolution here: Mitsuba's
    own envmap compiles its lookups for each resolution.)"""
    scene = scene_of(("ggx", "diffuse"))
    sh = sh_direct(strategy="product")

    def kernels_of_a_plan_and_a_render(seed):
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        try:
            dr.kernel_history()
            sh.plan(scene)
            dr.eval(mi.render(scene, integrator=sh, spp=1, seed=seed))
            return {k["hash"]: k["operation_count"] for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT}
        finally:
            dr.set_flag(dr.JitFlag.KernelHistory, False)

    def new_map(max_depth):
        monkeypatch.setattr(pyramid_module, "DEFAULT_MAX_DEPTH", max_depth)
        params = mi.traverse(scene)
        params["env.data"] = params["env.data"] * 0.5
        params.update()

    depth = sh.scenes.get(scene).pyramid.depth
    # Two map updates at the same depth first: the layout of the call data of Mitsuba's
    # virtual calls alternates between two forms from one envmap update to the next, and
    # each form is a kernel of its own.
    seen = {}
    for seed in (0, 1):
        new_map(depth)
        seen.update(kernels_of_a_plan_and_a_render(seed))
    new_map(depth - 1)
    deeper = kernels_of_a_plan_and_a_render(2)
    assert sh.scenes.get(scene).pyramid.depth == depth - 1
    assert max(deeper.values()) > 1000  # the render kernel is among them
    assert [ops for h, ops in deeper.items() if h not in seen] == []
