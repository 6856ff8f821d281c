"""Cost breakdown of a product lane, stage by stage, against Mitsuba's ``direct`` (issue 21).

Each stage of what ``sh_direct`` does at a shading point that runs the product
strategy is traced as its own kernel, on the same lanes: the camera's first
hits of the scene whose material runs the product (``strategy`` forced to
``product``), at most ``--lanes`` of them taken evenly over the film. Each
stage reads its inputs from memory, evaluated by the stage before it:

- lobe lookup + SH rotation (``ProductEnvironment.lobe``: the strategy code, the
  lobe table row, the band-limited SH coefficients and the closed-form proxy);
- the product sample (``ProductWarp.sample``), and its parts: the SH levels and
  the closed-form proxy levels of the walk (the proxy levels are the difference
  of a walk down to ``walk_depth`` and one that stops after the SH levels: their
  state cannot be handed between kernels without changing what they compute),
  the telescoped pyramid descent below them and the placement in the leaf;
- the product pdf walk (``ProductWarp.pdf``) of the BSDF-sampled direction, as
  the pass evaluates it for the MIS weight;
- BSDF ``eval_pdf`` of the product direction, the BSDF sample and its ray
  (``ray_intersect``), the shadow ray of the product direction
  (``ray_test``), the envmap's radiance there (``eval``);
- the product's code fused in one kernel (lobe, sample, pdf): against the sum
  of its stages it shows what splitting costs (loads and stores);
- Mitsuba's envmap ``sample_direction``, the strategy the product replaces.

Then the whole pass (``mi.render``) of Mitsuba's ``direct`` and of ``sh_direct``
with ``strategy`` ``environment`` (the lean kernel, no product code) and
``product``, timed interleaved (pass k of each before pass k + 1 of any). Two
sums close the table: the product-only stages (lobe, sample, pdf), and what the
product pass costs over the lean one; the gap between them is what the pass's
structure around the stages adds (symbolic branches and the values they carry).

Cost is counted two ways. *Kernel ops*: Dr.Jit's operation count of the
kernel (``dr.kernel_history``; the ``ops=`` of ``dr.LogLevel.Info``; for a pass,
its largest kernel, the one that traces the camera samples, counted with only
that integrator alive: see :func:`measure_passes`), deterministic and
independent of the load of the machine. *ms per 2^20 lanes*: the kernels'
execution time as Dr.Jit records it (tracing in Python excluded), median of
``--repeats``, per 2^20 product lanes for a stage and per 2^20 camera samples
for a pass (whose lanes also hold sky, delta and non-product materials). A
stage kernel loads its inputs and stores its outputs, which the pass keeps in
registers.

    python scripts/bench_cost_breakdown.py [SCENE.xml] [--envmap MAP] --res 480 --spp 16 \\
        [--lanes 1048576] [--repeats 5] [--json OUT.json]
"""

from __future__ import annotations

import argparse
import dataclasses
import gc
import json
import statistics
import time
from typing import Callable

import numpy as np

import mitsuba_shsampling  # noqa: F401  (points Dr.Jit at a usable libLLVM first)
import drjit as dr
import mitsuba as mi

from mitsuba_shsampling.frozen import FrozenPass

LANES_UNIT = 2**20
"""Times are reported per this many lanes."""

#: The whole passes: row key -> integrator description.
PASSES = {
    "direct": {"type": "direct"},
    "sh_direct_environment": {"type": "sh_direct", "strategy": "environment"},
    "sh_direct_product": {"type": "sh_direct", "strategy": "product"},
}

#: What the ratios are taken against.
REFERENCE_STAGE, REFERENCE_PASS = "mitsuba_envmap_sample", "direct"


@dataclasses.dataclass
class KernelCost:
    """What one evaluation launched: JIT kernels, their operations and execution time."""

    kernels: int
    ops: int
    """Operations of the largest kernel (a stage launches exactly one)."""
    execution_ms: float
    """Execution time of all its JIT kernels, as Dr.Jit recorded it."""
    wall_ms: float
    """Wall time, tracing in Python included."""


def launch(run: Callable[[], object]) -> KernelCost:
    """Run ``run`` (which returns the values to evaluate), evaluate them and
    report the JIT kernels that launched."""
    dr.sync_thread()
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    dr.kernel_history()  # clear
    start = time.perf_counter()
    dr.eval(run())
    dr.sync_thread()
    wall = time.perf_counter() - start
    kernels = [k for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT]
    dr.set_flag(dr.JitFlag.KernelHistory, False)
    return KernelCost(len(kernels), max((int(k["operation_count"]) for k in kernels), default=0),
                      sum(k["execution_time"] for k in kernels), 1e3 * wall)


def evaluated(*values):
    """``values`` evaluated in place, so that the next stage reads them from memory.
    Dr.Jit traverses lists and plain tuples but neither NamedTuples nor plain
    objects (a :class:`~mitsuba_shsampling.grid.Cell`): their arrays are passed one by one."""
    dr.eval(*values)
    return values if len(values) > 1 else values[0]


def lobe_arrays(lobe) -> list:
    """The arrays of a :class:`~mitsuba_shsampling.integrators.environment.LaneLobe`
    (its lobes are a dataclass, which Dr.Jit traverses)."""
    return [lobe.coeffs, *tuple(lobe.proxy)]


# ------------------------------------------------------------------ the lanes

def camera_rays(scene: mi.Scene, spp: int, seed: int = 0):
    """(ray, number of camera samples): ``spp`` jittered camera rays per pixel, as a pass traces them."""
    sensor = scene.sensors()[0]
    width, height = sensor.film().crop_size()
    count = width * height * spp
    rng = mi.PCG32(count, seed)
    pixel = dr.arange(mi.UInt32, count) // spp
    position = mi.Point2f(mi.Float(pixel % width) + rng.next_float32(),
                          mi.Float(pixel // width) + rng.next_float32()) / mi.ScalarVector2f(width, height)
    ray, _ = sensor.sample_ray(0.0, 0.5, position, mi.Point2f(0.5))
    return ray, count


def smooth_lanes(si: mi.SurfaceInteraction3f) -> mi.Bool:
    """Lanes whose BSDF has a smooth part: the lanes that sample the environment."""
    return si.is_valid() & mi.has_flag(si.bsdf().flags(), mi.BSDFFlags.Smooth)


def product_lanes(scene: mi.Scene, env, spp: int, max_lanes: int):
    """(first hits of the product lanes, camera samples, product lanes in the film):
    the camera's first hits whose material runs the product strategy by its SH walk
    (diffuse lobes, sampled from the cosine tables, are timed apart: the stages
    ``cosine_table_*``), at most ``max_lanes`` of them, taken evenly over the film."""
    ray, count = camera_rays(scene, spp)
    dr.eval(ray)
    si = scene.ray_intersect(ray)
    lane_lobe, use_product = env.lobe(si, smooth_lanes(si))
    walks = use_product & ~mi.Bool(lane_lobe.proxy.cosine_only) if lane_lobe is not None else use_product
    chosen = np.flatnonzero(walks.numpy())
    found = len(chosen)
    if found == 0:
        raise SystemExit("no camera sample of this scene hits a material that runs the product strategy")
    if found > max_lanes:
        chosen = chosen[np.linspace(0, found - 1, max_lanes).astype(np.int64)]
    index = mi.UInt32(chosen.astype(np.uint32))
    kept = mi.Ray3f(dr.gather(mi.Point3f, ray.o, index), dr.gather(mi.Vector3f, ray.d, index))
    return evaluated(scene.ray_intersect(kept)), count, found


# ------------------------------------------------------------------ the stages

@dataclasses.dataclass
class Stage:
    """One row of the breakdown: a kernel, or the difference of two."""

    key: str
    """Its name in the JSON."""
    label: str
    """Its name in the table (indented: a part of the product sample)."""
    run: Callable[[], object] | None
    """Traces the stage and returns what to evaluate (None: the difference of two stages)."""
    difference: tuple[str, str] | None = None
    """(minuend, subtrahend) stage keys of a stage measured as a difference."""


def product_lane_stages(scene: mi.Scene, env, si: mi.SurfaceInteraction3f) -> list[Stage]:
    """The stages of a product lane, their inputs evaluated beforehand (one kernel each)."""
    from mitsuba_shsampling.grid import Cell
    from mitsuba_shsampling.integrators.estimators import environment_ray_target
    from mitsuba_shsampling.warp.hierarchy import descend_pyramid_sample, walk_sample_absolute
    from mitsuba_shsampling.warp.env_leaves import place_in_leaf

    lanes = dr.width(si)
    rng = mi.PCG32(lanes, 7)
    u_product, u_env, u_bsdf = (evaluated(mi.Point2f(rng.next_float32(), rng.next_float32())) for _ in range(3))
    u_lobe = evaluated(rng.next_float32())
    warp, pyramid, emitter = env.warp, env.pyramid, env.emitter
    ctx = mi.BSDFContext()

    def lobe():
        lane_lobe, use_product = env.lobe(si, smooth_lanes(si))
        return lobe_arrays(lane_lobe), use_product

    lane_lobe, _ = env.lobe(si, smooth_lanes(si))
    evaluated(lobe_arrays(lane_lobe))
    # These lanes walk their SH lobe: the stages trace that walk alone (no table branch).
    coeffs, proxy = lane_lobe.coeffs, lane_lobe.proxy._replace(cosine_only=False)
    weights = warp.weights(coeffs, proxy)

    def sh_levels():
        cell, t, prob, valid, _ = walk_sample_absolute(weights, weights.sh_depth, u_product)
        return cell.iz, cell.iphi, t, prob, valid

    def product_levels():
        cell, t, prob, valid, _ = walk_sample_absolute(weights, weights.walk_depth, u_product)
        return cell.iz, cell.iphi, t, prob, valid

    walked_iz, walked_iphi, walked_t, walked_prob, walked_valid = evaluated(*product_levels())
    walked_cell = Cell(weights.walk_depth, walked_iz, walked_iphi)

    def pyramid_descent():
        leaf, t, p_leaf = descend_pyramid_sample(pyramid, walked_cell, walked_t)
        return leaf.iz, leaf.iphi, t, p_leaf

    leaf_iz, leaf_iphi, leaf_t, p_leaf = evaluated(*pyramid_descent())
    leaf = Cell(pyramid.depth, leaf_iz, leaf_iphi)

    def leaf_placement():
        return place_in_leaf(pyramid, leaf, leaf_t, walked_prob * p_leaf, walked_valid)

    def product_sample():
        return warp.sample(coeffs, u_product, proxy)

    d_product, pdf_product = evaluated(*product_sample())
    product_active = evaluated(pdf_product > 0)

    def bsdf_sample():
        bs, weight = si.bsdf().sample(ctx, si, u_lobe, u_bsdf)
        return si.to_world(bs.wo), bs.pdf, weight

    d_bsdf, pdf_bsdf, _ = evaluated(*bsdf_sample())
    bsdf_active = evaluated(pdf_bsdf > 0)

    def bsdf_ray():
        hit = scene.ray_intersect(si.spawn_ray(d_bsdf), bsdf_active)
        return hit.t, hit.prim_index, hit.wi

    def product_pdf():
        return warp.pdf(coeffs, d_bsdf, proxy)

    def bsdf_eval_pdf():
        return si.bsdf().eval_pdf(ctx, si, si.to_local(d_product), product_active)

    def shadow_ray():
        return scene.ray_test(si.spawn_ray(d_product), product_active)

    def envmap_eval():
        return emitter.eval(environment_ray_target(d_product, si.wavelengths), product_active)

    def product_code_fused():
        lane_lobe, use_product = env.lobe(si, smooth_lanes(si))
        d, pdf = warp.sample(lane_lobe.coeffs, u_product, lane_lobe.proxy)
        return d, pdf, warp.pdf(lane_lobe.coeffs, d_bsdf, lane_lobe.proxy), use_product

    def mitsuba_envmap_sample():
        ds, weight = emitter.sample_direction(si, u_env)
        return ds.d, ds.pdf, weight

    # What the same lanes would cost with a diffuse lobe about their normal (its table).
    table = warp.cosine_table
    table_stages = [] if table is None else [
        Stage("cosine_table_sample", "cosine table sample (a diffuse lane)", lambda: table.sample(proxy.normal, u_product)),
        Stage("cosine_table_pdf", "cosine table pdf", lambda: table.pdf(proxy.normal, d_bsdf)),
    ]

    return [
        Stage("lobe", "lobe lookup + SH rotation", lobe),
        Stage("sh_levels", f"  walk: SH levels 0-{weights.sh_depth - 1}", sh_levels),
        Stage("product_levels", f"  walk: levels 0-{weights.walk_depth - 1}", product_levels),
        Stage("proxy_levels", f"  walk: proxy levels {weights.sh_depth}-{weights.walk_depth - 1} (diff.)", None,
              ("product_levels", "sh_levels")),
        Stage("pyramid_descent", f"  pyramid descent {weights.walk_depth}-{pyramid.depth - 1}", pyramid_descent),
        Stage("leaf_placement", "  leaf placement", leaf_placement),
        Stage("product_sample", "product sample (whole)", product_sample),
        Stage("product_pdf", "product pdf walk", product_pdf),
        Stage("bsdf_eval_pdf", "BSDF eval_pdf", bsdf_eval_pdf),
        Stage("shadow_ray", "shadow ray (ray_test)", shadow_ray),
        Stage("envmap_eval", "envmap radiance (eval)", envmap_eval),
        Stage("bsdf_sample", "BSDF sample", bsdf_sample),
        Stage("bsdf_ray", "BSDF-sample ray (ray_intersect)", bsdf_ray),
        Stage("product_code_fused", "lobe + sample + pdf in one kernel", product_code_fused),
        *table_stages,
        Stage(REFERENCE_STAGE, "Mitsuba envmap sample_direction", mitsuba_envmap_sample),
    ]


def measure_stages(stages: list[Stage], repeats: int) -> dict[str, dict]:
    """Kernel ops and median execution time of each stage, timed interleaved."""
    measured = [s for s in stages if s.run is not None]
    for stage in measured:  # compile outside the timed runs
        launch(stage.run)
    costs = {s.key: [] for s in measured}
    for _ in range(repeats):
        for stage in measured:
            costs[stage.key].append(launch(stage.run))
    result = {}
    for stage in stages:
        if stage.run is not None:
            runs = costs[stage.key]
            result[stage.key] = dict(kernels=runs[0].kernels, kernel_ops=runs[0].ops,
                                     execution_ms=statistics.median(r.execution_ms for r in runs),
                                     execution_ms_runs=[r.execution_ms for r in runs])
        else:
            whole, part = (result[k] for k in stage.difference)
            result[stage.key] = dict(kernels=0, kernel_ops=whole["kernel_ops"] - part["kernel_ops"],
                                     execution_ms=whole["execution_ms"] - part["execution_ms"],
                                     difference_of=list(stage.difference))
    return result


# ------------------------------------------------------------------ the passes

def measure_passes(scene: mi.Scene, spp: int, repeats: int) -> dict[str, dict]:
    """Kernel ops (largest kernel) and median kernel execution and wall time of
    a whole pass of each integrator of :data:`PASSES`.

    Dr.Jit traces a call through an ``Emitter`` or ``BSDF`` pointer (``direct``'s
    emitter sampling, every ``bsdf.eval``) into every live instance of that
    class, in the scene or not: each ``sh_direct`` holds a MIS-compensated copy
    of the envmap, which adds about 740 operations to every such kernel in the
    process, ``direct``'s too. So the ops of each integrator are first counted
    with only its own objects alive (``kernel_ops``: what it costs in a process
    of its own), then the passes are timed interleaved (pass k of each before
    pass k + 1 of any) with all of them alive (``shared_kernel_ops``: the
    kernels timed)."""
    def render(integrator, seed):
        return lambda: mi.render(scene, integrator=integrator, spp=spp, seed=seed)

    alone_ops = {}
    for key, description in PASSES.items():
        integrator = mi.load_dict(description)
        launch(render(integrator, 10_000))  # build the per-scene state and compile, untimed
        alone_ops[key] = launch(render(integrator, 10_001)).ops
        del integrator
        gc.collect()  # frees its envmap copy before the next one is counted
    integrators = {key: mi.load_dict(description) for key, description in PASSES.items()}
    for integrator in integrators.values():
        launch(render(integrator, 10_000))
    costs = {key: [] for key in integrators}
    for seed in range(repeats):
        for key, integrator in integrators.items():
            costs[key].append(launch(render(integrator, seed)))
    # The same passes replayed from a dr.freeze recording (what compare times): the
    # difference in wall time is the tracing that freezing removes.
    frozen = {key: FrozenPass(scene, scene.sensors()[0], integrator, spp) for key, integrator in integrators.items()}
    for key, frozen_pass in frozen.items():
        launch(lambda: frozen_pass(10_002))  # records
    frozen_wall = {key: [] for key in integrators}
    for seed in range(repeats):
        for key, frozen_pass in frozen.items():
            frozen_wall[key].append(launch(lambda: frozen_pass(seed)).wall_ms)
    return {key: dict(kernels=runs[0].kernels, kernel_ops=alone_ops[key], shared_kernel_ops=runs[0].ops,
                      execution_ms=statistics.median(r.execution_ms for r in runs),
                      execution_ms_runs=[r.execution_ms for r in runs],
                      wall_ms=statistics.median(r.wall_ms for r in runs),
                      frozen_wall_ms=statistics.median(frozen_wall[key]), frozen=frozen[key].frozen)
            for key, runs in costs.items()}


# ------------------------------------------------------------------ report

#: The stages that only the product strategy runs (the lean kernel has none of them).
PRODUCT_CODE_STAGES = ("lobe", "product_sample", "product_pdf")


def rows_of(stages: list[Stage], stage_costs: dict, pass_costs: dict, stage_lanes: int,
            camera_samples: int) -> list[dict]:
    """One record per stage and per pass, two sums that say how much of the
    product pass's extra cost the stages account for, the per-2^20-lane times
    and the ratios."""
    rows = [dict(key=s.key, label=s.label.strip(), kind="stage", lanes=stage_lanes, **stage_costs[s.key])
            for s in stages]
    product_code = [stage_costs[key] for key in PRODUCT_CODE_STAGES]
    rows.append(dict(key="product_code_stages", label="sum: " + " + ".join(PRODUCT_CODE_STAGES), kind="sum",
                     lanes=stage_lanes, kernel_ops=sum(c["kernel_ops"] for c in product_code),
                     execution_ms=sum(c["execution_ms"] for c in product_code)))
    rows += [dict(key=key, label=f"pass: {key}", kind="pass", lanes=camera_samples, **cost)
             for key, cost in pass_costs.items()]
    product, lean = pass_costs["sh_direct_product"], pass_costs["sh_direct_environment"]
    rows.append(dict(key="pass_product_minus_environment", label="pass: product - environment", kind="sum",
                     lanes=camera_samples, kernel_ops=product["kernel_ops"] - lean["kernel_ops"],
                     execution_ms=product["execution_ms"] - lean["execution_ms"]))
    for row in rows:
        row["ms_per_2p20_lanes"] = row["execution_ms"] * LANES_UNIT / row["lanes"]
    reference_stage = next(r for r in rows if r["key"] == REFERENCE_STAGE)
    reference_pass = next(r for r in rows if r["key"] == REFERENCE_PASS and r["kind"] == "pass")
    for row in rows:
        for name, reference in (("mitsuba_sample", reference_stage), ("direct_pass", reference_pass)):
            row[f"ops_over_{name}"] = row["kernel_ops"] / reference["kernel_ops"]
            row[f"time_over_{name}"] = row["ms_per_2p20_lanes"] / reference["ms_per_2p20_lanes"]
    return rows


def print_table(rows: list[dict], labels: dict[str, str]) -> None:
    print(f"{'stage':48s} {'ops':>7s} {'ms/2^20':>8s} {'ops/Mi':>7s} {'ms/Mi':>6s} "
          f"{'ops/dir':>7s} {'ms/dir':>6s}")
    for row in rows:
        print(f"{labels.get(row['key'], row['label']):48s} {row['kernel_ops']:>7d} {row['ms_per_2p20_lanes']:>8.2f} "
              f"{row['ops_over_mitsuba_sample']:>7.2f} {row['time_over_mitsuba_sample']:>6.2f} "
              f"{row['ops_over_direct_pass']:>7.3f} {row['time_over_direct_pass']:>6.3f}")


def add_scene_arguments(parser: argparse.ArgumentParser, repeats: int) -> None:
    """The scene and timing options of this script, shared with ``ab_product_kernel.py``."""
    parser.add_argument("scene", nargs="?", default=None, help="scene file (default: the material studio)")
    parser.add_argument("--envmap", default=None)
    parser.add_argument("--res", type=int, default=480)
    parser.add_argument("--spp", type=int, default=16)
    parser.add_argument("--lanes", type=int, default=LANES_UNIT, help="product lanes per stage kernel, at most")
    parser.add_argument("--repeats", type=int, default=repeats, help="timed runs per kernel (median)")
    parser.add_argument("--json", default=None)


def load_scene_of(args) -> tuple[str, mi.Scene]:
    """(path, scene) of the options of :func:`add_scene_arguments`, in ``llvm_ad_rgb``."""
    mi.set_variant("llvm_ad_rgb")
    mitsuba_shsampling.register()
    from mitsuba_shsampling.scenes import default_scene_path, load_scene

    path = args.scene or default_scene_path()
    return path, load_scene(path, envmap=args.envmap, res=args.res, spp=args.spp)


def forced_product_environment(scene: mi.Scene):
    """The per-scene state of ``sh_direct`` with the product strategy forced, as the pass
    builds it; exits with the reason when no material of the scene can run the product."""
    from mitsuba_shsampling.integrators.environment import ProductEnvironment
    from mitsuba_shsampling.integrators.options import DirectOptions

    env = ProductEnvironment(scene, DirectOptions(strategy="product"))
    if env.warp is None:
        raise SystemExit(f"no material of this scene runs the product strategy ({env.reason or 'no product lobe'})")
    return env


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_scene_arguments(parser, repeats=5)
    args = parser.parse_args()
    path, scene = load_scene_of(args)
    # The passes first: the stages' per-scene state below holds an envmap copy
    # that would add to every pass kernel (see measure_passes).
    pass_costs = measure_passes(scene, args.spp, args.repeats)
    gc.collect()
    env = forced_product_environment(scene)
    si, camera_samples, product_in_film = product_lanes(scene, env, args.spp, args.lanes)
    lanes = dr.width(si)
    print(f"{path}: {args.res} px, {args.spp} spp: {camera_samples} camera samples, "
          f"{product_in_film} on product lanes; stages on {lanes} of them. {env.lobes.n_bands} bands, "
          f"pyramid depth {env.pyramid.depth}", flush=True)

    stages = product_lane_stages(scene, env, si)
    stage_costs = measure_stages(stages, args.repeats)
    rows = rows_of(stages, stage_costs, pass_costs, lanes, camera_samples)
    print_table(rows, {s.key: s.label for s in stages})
    print("ops: Dr.Jit operations of the kernel (a pass: its largest); ms/2^20: kernel execution time per "
          "2^20 product lanes (a pass: camera samples), median of "
          f"{args.repeats}; /Mi: over Mitsuba's envmap sample_direction; /dir: over direct's pass")
    print("pass wall time (ms, median; tracing included): "
          + ", ".join(f"{key} {cost['wall_ms']:.0f}" for key, cost in pass_costs.items()))
    print("pass wall time (ms, median; frozen replay, as compare times it): "
          + ", ".join(f"{key} {cost['frozen_wall_ms']:.0f}" for key, cost in pass_costs.items()))
    print("pass kernel ops with all three integrators alive (the kernels timed): "
          + ", ".join(f"{key} {cost['shared_kernel_ops']}" for key, cost in pass_costs.items()))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(dict(scene=path, envmap=args.envmap, res=args.res, spp=args.spp, repeats=args.repeats,
                           camera_samples=camera_samples, product_lanes_in_film=product_in_film,
                           stage_lanes=lanes, bands=env.lobes.n_bands, pyramid_depth=env.pyramid.depth,
                           rows=rows), f, indent=1)
        print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
