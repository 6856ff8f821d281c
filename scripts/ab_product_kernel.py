"""Kernel time of the product sample and pdf walk: the working tree against a git revision.

Where a change to the product warp moves less than the noise between two runs
of ``scripts/bench_cost_breakdown.py`` (kernel times there vary by 10 % from run
to run on a shared machine), run both versions in one process, interleaved:
``warp/product.py``, ``warp/hierarchy.py``, ``warp/hsw.py``, ``warp/proxy_lobe.py``,
``warp/env_leaves.py`` and ``envmap/pyramid.py`` of the revision ``--base`` are
loaded beside the working tree's (``git show``, into a temporary package; the
rest of the package is the working tree's), the base version walks a pyramid
of the scene's map built by the base revision's code (its memory layout), and
each repeat launches both versions' kernels in alternating order on the same
lanes.

The lanes are those of ``bench_cost_breakdown.py``: the camera's first hits of
the scene whose material runs the product (``strategy`` ``product``), at most
``--lanes``. Each kernel computes the lane's lobe as a pass does (from the
surface interaction, not loaded from memory: 64 coefficients per lane read from
memory would make the walks look memory-bound) and then the product sample of a
uniform point, or the pdf walk of a uniform direction.

    python scripts/ab_product_kernel.py [--base HEAD] [SCENE.xml] [--envmap MAP] [--res 480] \\
        [--spp 16] [--repeats 15] [--json OUT.json]

Prints, per kernel, the median execution time of each version (ms per 2^20
lanes), their operation counts and the ratio working tree / base.
"""

from __future__ import annotations

import argparse
import importlib
import json
import pathlib
import re
import statistics
import subprocess
import sys
import tempfile

import mitsuba_shsampling  # noqa: F401  (points Dr.Jit at a usable libLLVM first)
import drjit as dr
import mitsuba as mi

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
import bench_cost_breakdown as breakdown  # noqa: E402
from mitsuba_shsampling.sh.zonal import RotatedZonalLobes  # noqa: E402

#: The modules of the product walk loaded from the base revision: module -> its folder in the package.
BASE_MODULES = {"product": "warp", "hierarchy": "warp", "hsw": "warp", "proxy_lobe": "warp",
                "env_leaves": "warp", "pyramid": "envmap"}
BASE_PACKAGE = "base_product_warp"


def load_base(revision: str, directory: pathlib.Path):
    """The base revision's ``warp/product.py``, ``warp/proxy_lobe.py`` and
    ``envmap/pyramid.py`` as modules, importing that revision's other
    :data:`BASE_MODULES` (relative imports kept inside the copy) and the working
    tree's everything else."""
    root = pathlib.Path(__file__).resolve().parent.parent
    package = directory / BASE_PACKAGE
    package.mkdir()
    (package / "__init__.py").write_text("")
    for name, folder in BASE_MODULES.items():
        source = subprocess.run(["git", "show", f"{revision}:mitsuba_shsampling/{folder}/{name}.py"], cwd=root,
                                check=True, capture_output=True, text=True).stdout
        # Inside the copy: the package's top level is mitsuba_shsampling, and sibling
        # modules outside BASE_MODULES are the working tree's.
        source = re.sub(r"^from \.\.envmap\.pyramid import", "from .pyramid import", source, flags=re.M)
        source = source.replace("from ..", "from mitsuba_shsampling.")
        source = re.sub(r"^from \.(\w+) import",
                        lambda m: f"from .{m.group(1)} import" if m.group(1) in BASE_MODULES
                        else f"from mitsuba_shsampling.{folder}.{m.group(1)} import", source, flags=re.M)
        (package / f"{name}.py").write_text(source)
    sys.path.insert(0, str(directory))
    return tuple(importlib.import_module(f"{BASE_PACKAGE}.{name}") for name in ("product", "proxy_lobe", "pyramid"))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--base", default="HEAD", help="git revision to compare the working tree with")
    breakdown.add_scene_arguments(parser, repeats=15)
    args = parser.parse_args()
    path, scene = breakdown.load_scene_of(args)
    env = breakdown.forced_product_environment(scene)
    si = breakdown.product_lanes(scene, env, args.spp, args.lanes)[0]
    lanes = dr.width(si)
    rng = mi.PCG32(lanes, 7)
    u = mi.Point2f(rng.next_float32(), rng.next_float32())
    d = mi.warp.square_to_uniform_sphere(mi.Point2f(rng.next_float32(), rng.next_float32()))
    dr.eval(u, d)

    with tempfile.TemporaryDirectory() as directory:
        base_product, base_proxy, base_pyramid = load_base(args.base, pathlib.Path(directory))
        options = dict(sh_depth=env.warp.sh_depth, defensive_share=env.warp.defensive_share,
                       proxy_depth=env.warp.proxy_depth)
        # The same map, laid out in memory as the base revision lays it out.
        pyramid = base_pyramid.EnvPyramid(env.emitter, mis_compensation=env.warp.pyramid.mis_compensation)
        versions = {"base": (base_product.ProductWarp(pyramid, **options), base_proxy.ProxyLobe),
                    "tree": (env.warp, None)}
        # Revisions before the factored lobes (RotatedZonalLobes) take coefficients only.
        base_takes_factored = hasattr(base_product, "RotatedZonalLobes")

        def kernel(version: str, walk: str):
            warp, proxy_type = versions[version]
            lobe, _ = env.lobe(si, breakdown.smooth_lanes(si))
            # The lanes walk their SH lobe (breakdown.product_lanes): no cosine-table branch,
            # and a base revision's proxy type takes the fields it has.
            fields = tuple(lobe.proxy._replace(cosine_only=False))
            proxy = proxy_type(*fields[:len(proxy_type._fields)]) if proxy_type else lobe.proxy._replace(cosine_only=False)
            coeffs = lobe.coeffs
            if proxy_type and not base_takes_factored and isinstance(coeffs, RotatedZonalLobes):
                coeffs = coeffs.coefficients()
            return warp.sample(coeffs, u, proxy) if walk == "sample" else warp.pdf(coeffs, d, proxy)

        walks = ("sample", "pdf")
        times = {(v, w): [] for v in versions for w in walks}
        ops = {}
        for repeat in range(args.repeats):
            for walk in walks:
                order = ("base", "tree") if repeat % 2 == 0 else ("tree", "base")
                for version in order:
                    cost = breakdown.launch(lambda: kernel(version, walk))
                    times[(version, walk)].append(cost.execution_ms * breakdown.LANES_UNIT / lanes)
                    ops[(version, walk)] = cost.ops

    rows = []
    print(f"{path}: {lanes} product lanes; working tree against {args.base}; median of {args.repeats}, "
          "ms per 2^20 lanes (lobe computed in the kernel)")
    print(f"{'kernel':22s} {'base ms':>8s} {'tree ms':>8s} {'base ops':>9s} {'tree ops':>9s} {'tree/base':>9s}")
    for walk in walks:
        base, tree = statistics.median(times[("base", walk)]), statistics.median(times[("tree", walk)])
        label = "lobe + product sample" if walk == "sample" else "lobe + product pdf"
        print(f"{label:22s} {base:8.2f} {tree:8.2f} {ops[('base', walk)]:9d} {ops[('tree', walk)]:9d} {tree / base:9.3f}")
        rows.append(dict(kernel=walk, base_ms=base, tree_ms=tree, base_ops=ops[("base", walk)],
                         tree_ops=ops[("tree", walk)], ratio=tree / base, base_samples=times[("base", walk)],
                         tree_samples=times[("tree", walk)]))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(dict(scene=path, envmap=args.envmap, base=args.base, lanes=lanes, repeats=args.repeats,
                           rows=rows), f, indent=2)
        print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
