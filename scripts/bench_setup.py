"""What a first render costs before its first pass: set-up against Mitsuba's ``direct``.

The report's equal-time figures time passes only (``compare`` renders every
method once, untimed, first). A user who times a whole render also pays each
method's set-up once: for ``sh_direct`` the per-scene state (pyramid, lobe fits,
cosine tables), the plan (quadrature and untimed pilot passes) and the kernels'
compilation; for Mitsuba's ``direct`` its kernel's compilation. This benchmark
measures it, per method, in a fresh process each, in three states of the caches:

- ``cold``: an empty Dr.Jit kernel cache (``DRJIT_CACHE_DIR``) and an empty build
  cache (``SHSAMPLING_CACHE_DIR``), as on a machine's first render;
- ``new map``: the kernels cached, the builds not (a scene or map not rendered
  before, on a machine that has rendered);
- ``warm``: both caches filled (a scene rendered before, in a new process).

Per run: the first ``mi.render`` call's wall time (set-up, tracing, compilation,
one pass) and the median wall time of the next passes as ``mi.render`` runs them
(traced from Python each call). Set-up = first call - one pass; the plugin's own
share of it (``integrator.plan``, timed before the first render: state, then
plan) is given apart. Then, in the same process: a second integrator object with
the same options (its first call - a pass), and a BSDF parameter change (the
first call after ``params.update()`` - a pass), and with ``--map-change FILE`` the map
replaced by another of the same resolution (the envmap's ``data``, as an animation or a
user trying maps does; the first call after the update - a pass). The table gives the set-up in
seconds and in passes of ``direct``, and the render time from which the set-up is
paid back at a given equal-time efficiency E (``--efficiency``): a method with
set-up T and E times the other's efficiency gives the lower error from
t = T E / (E - 1) of wall time on.

Each record also gives what the first call compiled: Dr.Jit's kernels that were not in
its cache (``kernels_compiled``), the seconds LLVM took on them (``llvm_s``) and the largest
(operations, milliseconds). A warm process compiles none: the kernels are the same in every
process. With ``--then-envmap FILE`` the states after the first render FILE instead of the
scene's map: ``cold`` then ``new map`` is then a map the machine has not rendered, as a user's
own map is (Mitsuba's envmap sampler, which the environment strategies run, is traced per
resolution: a map of a new resolution compiles the plan's and the render's kernels again).

With ``--renders-first N`` each child first renders the scene N times with Mitsuba's
``direct`` and N times with its ``path`` (untimed), as ``compare`` and the sweep's cells do
before the plugin's set-up: there the set-up runs in a process whose memory other renders
have shaped (docs/MEASUREMENTS.md, "A pyramid's arrays mapped, not copied").

    python3 scripts/bench_setup.py [--scene material_studio] [--envmap FILE] [--res 480]
                                   [--spp 16] [--methods direct sh_direct] [--map-change FILE]
                                   [--renders-first N] [--then-envmap FILE] [--json OUT.json]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

CHILD_FLAG = "--child"
NEXT_PASSES = 5
"""Passes timed after the first call (their median is the pass time)."""

STATES = {"cold": (False, False), "new map": (True, False), "warm": (True, True)}
"""Cache state -> (Dr.Jit kernel cache filled, build cache filled)."""


def run_child(scene_name: str, envmap: str | None, res: int, spp: int, method: str,
              map_change: str | None = None, renders_first: int = 0) -> dict:
    """In this process: load the scene, plan (timed), render once (timed whole), then
    :data:`NEXT_PASSES` more; then a second object, a BSDF change, and with ``map_change``
    the envmap's texels replaced by that file's."""
    import drjit as dr
    import mitsuba as mi

    from mitsuba_shsampling.benchmarks import set_default_variant

    set_default_variant()
    import mitsuba_shsampling  # noqa: F401  (registers the plugins)
    from mitsuba_shsampling.scenes import builtin_scenes, load_scene

    path = builtin_scenes().get(scene_name, scene_name)
    scene = load_scene(path, envmap=envmap, res=res, spp=spp)
    for other in ("direct", "path"):
        for seed in range(renders_first):
            dr.eval(mi.render(scene, integrator=mi.load_dict({"type": other}), spp=spp, seed=1000 + seed))
    dr.sync_thread()

    def one_pass(integrator, seed: int) -> float:
        start = time.perf_counter()
        image = mi.render(scene, integrator=integrator, spp=spp, seed=seed)
        dr.eval(image)
        dr.sync_thread()
        return time.perf_counter() - start

    def timed_plan(integrator) -> float:
        start = time.perf_counter()
        if hasattr(integrator, "plan"):
            integrator.plan(scene)
        return time.perf_counter() - start

    integrator = mi.load_dict({"type": method})
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    dr.kernel_history()  # (emptied: only the first call's kernels count)
    plan_s = timed_plan(integrator)
    first = plan_s + one_pass(integrator, 0)
    compiled = compiled_kernels(dr.kernel_history())
    dr.set_flag(dr.JitFlag.KernelHistory, False)
    passes = [one_pass(integrator, 1 + k) for k in range(NEXT_PASSES)]
    pass_s = statistics.median(passes)
    record = {"first_call_s": first, "plan_s": plan_s, "pass_s": pass_s, "passes_s": passes, **compiled}
    made = integrator.plan(scene) if hasattr(integrator, "plan") else None
    if made is not None:
        env = integrator.scenes.get(scene)
        record.update(state_s=env.build_seconds, choice_s=made.setup_seconds - env.build_seconds,
                      choice=made.summary(), plan_mode=made.mode, costs=made.costs["source"],
                      pyramid_build_s=env.pyramid.build_time_s if env.pyramid is not None else None)

    second = mi.load_dict({"type": method})
    record["second_object_s"] = timed_plan(second) + one_pass(second, 100) - pass_s

    params = mi.traverse(scene)
    key = next((k for k in params.keys() if k.endswith(".alpha.value") or k.endswith(".alpha")), None)
    if key is not None:
        params[key] = params[key] * 1.5
        params.update()
        record["bsdf_change_s"] = timed_plan(integrator) + one_pass(integrator, 200) - pass_s
        record["bsdf_changed"] = key
    if map_change:
        from mitsuba_shsampling.scenes import scene_envmap

        texels = mi.traverse(mi.load_dict({"type": "envmap", "filename": map_change}))["data"]
        envmap = mi.traverse(scene_envmap(scene))
        if dr.shape(texels) != dr.shape(envmap["data"]):
            raise SystemExit(f"--map-change: {map_change} is {dr.shape(texels)}, the scene's map "
                             f"{dr.shape(envmap['data'])}: give a map of the same resolution")
        radiant = (lambda: integrator.scenes.get(scene).pyramid.radiant_total) if hasattr(integrator, "plan") else None
        before = radiant() if radiant else None
        envmap["data"] = texels
        envmap.update()
        record["map_change_s"] = timed_plan(integrator) + one_pass(integrator, 300) - pass_s
        if radiant:  # the map the plan was made for: the new one's integral over the old one's
            record["map_change_radiant_ratio"] = radiant() / before
    return record


def compiled_kernels(history: list, largest: int = 3) -> dict:
    """What Dr.Jit compiled among the launches of ``history`` (``dr.kernel_history()``): its
    kernels that were not in the kernel cache, the seconds LLVM (or the CUDA driver) took on
    them, and the ``largest`` of them as (operations, milliseconds)."""
    misses = [k for k in history if k["type"].name == "JIT" and not k.get("cache_hit", True)]
    sizes = sorted(((int(k["operation_count"]), round(float(k["backend_time"]), 1)) for k in misses), reverse=True)
    return {"kernels_compiled": len(misses), "llvm_s": sum(float(k["backend_time"]) for k in misses) / 1000.0,
            "largest_compiled": [list(size) for size in sizes[:largest]]}


def state_envmap(args, index: int) -> str | None:
    """The map the ``index``-th state renders: ``--envmap`` (None: the scene's), and
    ``--then-envmap`` after the first."""
    return args.then_envmap if index > 0 and args.then_envmap else args.envmap


def measure(args, method: str, kernels: str, builds: str, envmap: str | None = None) -> dict:
    """One child process, with these kernel and build cache folders and this map; its record."""
    command = [sys.executable, os.path.abspath(__file__), CHILD_FLAG,
               "--scene", args.scene, "--res", str(args.res), "--spp", str(args.spp), "--methods", method]
    if envmap:
        command += ["--envmap", envmap]
    if args.map_change:
        command += ["--map-change", args.map_change]
    if args.renders_first:
        command += ["--renders-first", str(args.renders_first)]
    environment = {**os.environ, "DRJIT_CACHE_DIR": kernels, "SHSAMPLING_CACHE_DIR": builds}
    done = subprocess.run(command, env=environment, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise RuntimeError(f"{method}: the child process failed:\n{done.stderr[-2000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def payback_time(setup_s: float, efficiency: float) -> float:
    """Wall time from which a method with set-up ``setup_s`` and ``efficiency`` times the
    other's efficiency (1 / (MSE x time)) gives the lower error: (t - T) E = t."""
    return setup_s * efficiency / (efficiency - 1.0) if efficiency > 1.0 else float("inf")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene", default="material_studio", help="built-in scene name or XML path")
    parser.add_argument("--envmap", default=None, help="environment map file (default: the scene's)")
    parser.add_argument("--res", type=int, default=480)
    parser.add_argument("--spp", type=int, default=16)
    parser.add_argument("--methods", nargs="+", default=["direct", "sh_direct"])
    parser.add_argument("--efficiency", type=float, default=1.5,
                        help="equal-time efficiency over direct at which to state the payback time")
    parser.add_argument("--states", nargs="+", choices=list(STATES), default=list(STATES),
                        help="cache states to measure, in this order (default: all)")
    parser.add_argument("--map-change", default=None,
                        help="also time a change of the scene's map to this file's texels (same resolution)")
    parser.add_argument("--renders-first", type=int, default=0,
                        help="in each child, render the scene this many times with direct and with path first")
    parser.add_argument("--then-envmap", default=None,
                        help="render this map in the states after the first (a map new to the machine)")
    parser.add_argument("--json", default=os.path.join("docs", "bench_setup.json"))
    parser.add_argument(CHILD_FLAG, action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        print(json.dumps(run_child(args.scene, args.envmap, args.res, args.spp, args.methods[0], args.map_change,
                                   args.renders_first)))
        return

    rows = []
    with tempfile.TemporaryDirectory(prefix="bench_setup_") as root:
        for method in args.methods:
            # Caches of its own, so that cold is cold for every method; a state that keeps a
            # cache reads the one the states before it filled.
            kernels = builds = None
            for index, state in enumerate(args.states):
                kernels_kept, builds_kept = STATES[state]
                if not kernels_kept or kernels is None:
                    kernels = os.path.join(root, method, f"kernels-{state}")
                if not builds_kept or builds is None:
                    builds = os.path.join(root, method, f"builds-{state}")
                envmap = state_envmap(args, index)
                record = measure(args, method, kernels, builds, envmap)
                record.update(method=method, cache=state, envmap=envmap,
                              setup_s=record["first_call_s"] - record["pass_s"])
                rows.append(record)
    direct_pass = next((r["pass_s"] for r in rows if r["method"] == "direct"), None)
    print(f"{args.scene} at {args.res} px wide, {args.spp} spp a pass"
          + (f", envmap {os.path.basename(args.envmap)}" if args.envmap else "")
          + (f", then {os.path.basename(args.then_envmap)}" if args.then_envmap else "")
          + (f", after {args.renders_first} renders each of direct and path" if args.renders_first else ""))
    print(f"{'method':<12}{'cache':<9}{'first call s':>13}{'pass s':>9}{'set-up s':>10}{'in direct passes':>18}"
          f"{'state s':>9}{'plan s':>8}{'compile s':>11}{'LLVM s':>8}{'2nd object s':>14}{'BSDF change s':>15}"
          f"{'payback s':>11}"
          + (f"{'map change s':>14}" if args.map_change else ""))
    nan = float("nan")
    for r in rows:
        in_passes = r["setup_s"] / direct_pass if direct_pass else nan
        extra = r["setup_s"] - next((d["setup_s"] for d in rows if d["method"] == "direct" and d["cache"] == r["cache"]), 0.0)
        r["payback_s"] = payback_time(max(extra, 0.0), args.efficiency) if r["method"] != "direct" else None
        r["compile_s"] = r["setup_s"] - r["plan_s"]
        payback = f"{r['payback_s']:>11.1f}" if r["payback_s"] is not None else f"{'':>11}"
        print(f"{r['method']:<12}{r['cache']:<9}{r['first_call_s']:>13.2f}{r['pass_s']:>9.3f}{r['setup_s']:>10.2f}"
              f"{in_passes:>18.1f}{r.get('state_s', nan):>9.2f}{r.get('choice_s', nan):>8.2f}{r['compile_s']:>11.2f}"
              f"{r['llvm_s']:>8.2f}"
              f"{r['second_object_s']:>14.2f}{r.get('bsdf_change_s', nan):>15.2f}" + payback
              + (f"{r.get('map_change_s', nan):>14.2f}" if args.map_change else ""))
    print("state: the per-scene state (pyramid, lobe fits, tables); plan: the strategy plan; compile: the rest of "
          "the set-up (tracing and compiling the kernels); LLVM: the seconds LLVM spent compiling kernels not in "
          "Dr.Jit's cache, in the plan and the first pass")
    print(f"payback: wall time from which the method's lower error at {args.efficiency}x direct's "
          "equal-time efficiency has paid for its extra set-up")
    from mitsuba_shsampling.benchmarks import write_json
    write_json(args.json, {"scene": args.scene, "envmap": args.envmap, "then_envmap": args.then_envmap,
                           "map_change": args.map_change,
                           "res": args.res, "spp": args.spp, "renders_first": args.renders_first,
                           "efficiency": args.efficiency, "runs": rows})


if __name__ == "__main__":
    main()
