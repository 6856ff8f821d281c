"""What a first render costs before its first pass: set-up against Mitsuba's ``direct``.

The report's equal-time figures time passes only (``compare`` renders every
method once, untimed, first). A user who times a whole render also pays each
method's set-up once: for ``sh_direct`` the pyramid, the lobe fits, the strategy
choice (quadrature and pilot passes) and the kernels' compilation; for Mitsuba's
``direct`` its kernel's compilation. This benchmark measures it, per method, in a
fresh process each:

- ``cold``: an empty Dr.Jit kernel cache (``DRJIT_CACHE_DIR`` pointed at a new
  directory), as on a scene's and map's first render on a machine;
- ``warm``: the same cache again (a scene rendered before: Dr.Jit reloads the
  compiled kernels from disk, the host-side set-up is paid again).

Per run: the first ``mi.render`` call's wall time (set-up, tracing, compilation,
one pass) and the median wall time of the next passes as ``mi.render`` runs them
(traced from Python each call). Set-up = first call - one pass. The table gives
it in seconds and in passes of ``direct``, and the render time from which the
set-up is paid back at a given equal-time efficiency E (``--efficiency``):
a method with set-up T and E times the best strategy's efficiency gives the
lower error from t = T E / (E - 1) of wall time on.

    python3 scripts/bench_setup.py [--scene material_studio] [--envmap FILE] [--res 480]
                                   [--spp 16] [--methods direct sh_direct] [--json OUT.json]
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


def run_child(scene_name: str, envmap: str | None, res: int, spp: int, method: str) -> dict:
    """In this process: load the scene, render once (timed whole), then :data:`NEXT_PASSES` more."""
    import drjit as dr
    import mitsuba as mi

    from mitsuba_shsampling.benchmarks import set_default_variant

    set_default_variant()
    import mitsuba_shsampling  # noqa: F401  (registers the plugins)
    from mitsuba_shsampling.scenes import builtin_scenes, load_scene

    path = builtin_scenes().get(scene_name, scene_name)
    scene = load_scene(path, envmap=envmap, res=res, spp=spp)
    integrator = mi.load_dict({"type": method})

    def one_pass(seed: int) -> float:
        start = time.perf_counter()
        image = mi.render(scene, integrator=integrator, spp=spp, seed=seed)
        dr.eval(image)
        dr.sync_thread()
        return time.perf_counter() - start

    first = one_pass(0)
    passes = [one_pass(1 + k) for k in range(NEXT_PASSES)]
    record = {"first_call_s": first, "pass_s": statistics.median(passes), "passes_s": passes}
    choice = getattr(integrator, "choice", None)
    made = choice(scene) if choice is not None else None
    if made is not None:
        record["choice_s"] = made.seconds
        record["choice"] = made.summary()
    env = getattr(getattr(integrator, "scenes", None), "get", None)
    pyramid = getattr(env(scene), "pyramid", None) if env is not None else None
    if pyramid is not None:
        record["pyramid_build_s"] = pyramid.build_time_s
    return record


def measure(args, method: str, cache_dir: str) -> dict:
    """One child process; its record plus the method's name."""
    command = [sys.executable, os.path.abspath(__file__), CHILD_FLAG,
               "--scene", args.scene, "--res", str(args.res), "--spp", str(args.spp), "--methods", method]
    if args.envmap:
        command += ["--envmap", args.envmap]
    environment = {**os.environ, "DRJIT_CACHE_DIR": cache_dir}
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
    parser.add_argument("--json", default="bench_setup.json")
    parser.add_argument(CHILD_FLAG, action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        print(json.dumps(run_child(args.scene, args.envmap, args.res, args.spp, args.methods[0])))
        return

    rows = []
    with tempfile.TemporaryDirectory(prefix="bench_setup_") as root:
        for method in args.methods:
            cache = os.path.join(root, method)  # a cache of its own: cold is cold for every method
            for state in ("cold", "warm"):
                record = measure(args, method, cache)
                record.update(method=method, cache=state, setup_s=record["first_call_s"] - record["pass_s"])
                rows.append(record)
    direct_pass = next((r["pass_s"] for r in rows if r["method"] == "direct"), None)
    print(f"{args.scene} at {args.res} px wide, {args.spp} spp a pass"
          + (f", envmap {os.path.basename(args.envmap)}" if args.envmap else ""))
    print(f"{'method':<12}{'cache':<7}{'first call s':>13}{'pass s':>9}{'set-up s':>10}"
          f"{'in direct passes':>18}{'choice s':>10}{'pyramid s':>11}{'payback s':>11}")
    for r in rows:
        in_passes = r["setup_s"] / direct_pass if direct_pass else float("nan")
        extra = r["setup_s"] - next((d["setup_s"] for d in rows if d["method"] == "direct" and d["cache"] == r["cache"]), 0.0)
        r["payback_s"] = payback_time(max(extra, 0.0), args.efficiency) if r["method"] != "direct" else None
        payback = f"{r['payback_s']:>11.1f}" if r["payback_s"] is not None else f"{'':>11}"
        print(f"{r['method']:<12}{r['cache']:<7}{r['first_call_s']:>13.2f}{r['pass_s']:>9.3f}{r['setup_s']:>10.2f}"
              f"{in_passes:>18.1f}{r.get('choice_s', float('nan')):>10.2f}{r.get('pyramid_build_s', float('nan')):>11.2f}"
              + payback)
    print(f"payback: wall time from which the method's lower error at {args.efficiency}x direct's "
          "equal-time efficiency has paid for its extra set-up")
    from mitsuba_shsampling.benchmarks import write_json
    write_json(args.json, {"scene": args.scene, "envmap": args.envmap, "res": args.res, "spp": args.spp,
                           "efficiency": args.efficiency, "runs": rows})


if __name__ == "__main__":
    main()
