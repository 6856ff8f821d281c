"""What the perturbed normal buys the product strategy on bump- and normal-mapped surfaces.

A GGX sphere over a GGX ground, both wrapped in a ``bumpmap`` or a ``normalmap``
with strong slopes, under one map. Per wrapper and strategy: the per-pixel
variance of the luminance across passes (mean over pixels, tails included), its
ratio to the ``environment`` strategy (what these wrappers ran before they had a
product lobe), and the brightest pixel. Equal samples, same seeds for every row.
The ``product, unperturbed lobe`` row is an ablation: the nested BSDF's lobe
about the unperturbed shading normal.

    python scripts/bench_perturbed_lobes.py --envmap tests/data/envmaps/forest_slope_1k.hdr \
        --alpha 0.1 --res 128 --spp 4 --passes 32 --json OUT.json
"""

from __future__ import annotations

import argparse
import contextlib
import json
from unittest import mock

import numpy as np

import mitsuba_shsampling  # noqa: F401  (points Dr.Jit at a usable libLLVM first)
import mitsuba as mi


def slopes(size: int = 64):
    """A height field and the matching tangent-space normals, with slopes up to ~30 degrees."""
    y, x = np.mgrid[0:size, 0:size] / size
    height = 0.5 + 0.5 * np.sin(6 * np.pi * x) * np.cos(4 * np.pi * y)
    normal = np.stack([0.6 * np.cos(6 * np.pi * x), 0.6 * np.sin(4 * np.pi * y), np.ones_like(x)], axis=-1)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    return mi.Bitmap(height[..., None].astype(np.float32)), mi.Bitmap((0.5 * normal + 0.5).astype(np.float32))


def wrapped(kind: str, alpha: float) -> dict:
    height, normals = slopes()
    inner = {"type": "roughconductor", "distribution": "ggx", "alpha": alpha}
    if kind == "normalmap":
        return {"type": "normalmap", "normalmap": {"type": "bitmap", "bitmap": normals, "raw": True}, "bsdf": inner}
    return {"type": "bumpmap", "scale": 0.5, "arbitrary": {"type": "bitmap", "bitmap": height, "raw": True},
            "bsdf": inner}


def scene_of(kind: str, alpha: float, envmap: str, res: int) -> mi.Scene:
    look = mi.ScalarTransform4f().look_at(origin=[0, -4, 1.5], target=[0, 0, 0], up=[0, 0, 1])
    return mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 40, "to_world": look,
                   "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"}}},
        "ball": {"type": "sphere", "bsdf": wrapped(kind, alpha)},
        "ground": {"type": "rectangle", "to_world": mi.ScalarTransform4f().translate([0, 0, -1]).scale(6),
                   "bsdf": wrapped(kind, alpha)},
        "env": {"type": "envmap", "filename": envmap},
    })


def luminance_passes(scene, integrator, spp: int, passes: int) -> np.ndarray:
    images = [np.array(mi.render(scene, integrator=integrator, spp=spp, seed=seed)) for seed in range(passes)]
    return np.stack(images) @ np.array([0.2126, 0.7152, 0.0722])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--envmap", required=True)
    parser.add_argument("--alpha", type=float, default=0.1)
    parser.add_argument("--res", type=int, default=128)
    parser.add_argument("--spp", type=int, default=4)
    parser.add_argument("--passes", type=int, default=32)
    parser.add_argument("--json", default=None)
    args = parser.parse_args()

    mi.set_variant("llvm_ad_rgb")
    mitsuba_shsampling.register()
    from mitsuba_shsampling.lobes.scene_lobes import SceneLobes

    def unperturbed(self, si, active=True):
        return mi.Vector3f(0.0, 0.0, 1.0)

    rows = []
    for kind in ("bumpmap", "normalmap"):
        scene = scene_of(kind, args.alpha, args.envmap, args.res)
        variance = {}
        for label, strategy, ablate in (("environment", "environment", False), ("product", "product", False),
                                        ("product, unperturbed lobe", "product", True)):
            integrator = mi.load_dict({"type": "sh_direct", "strategy": strategy})
            with mock.patch.object(SceneLobes, "local_normals", unperturbed) if ablate else contextlib.nullcontext():
                lum = luminance_passes(scene, integrator, args.spp, args.passes)
            variance[label] = float(lum.var(axis=0, ddof=1).mean())
            rows.append({"wrapper": kind, "strategy": label, "variance": variance[label],
                         "variance_over_environment": variance[label] / variance["environment"],
                         "brightest_pixel": float(lum.max())})

    print(f"{args.envmap}, GGX alpha {args.alpha}, {args.res} px, {args.spp} spp x {args.passes} passes (equal samples)")
    print("| wrapper | strategy | per-pixel variance | / environment | brightest pixel |")
    print("|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['wrapper']} | {r['strategy']} | {r['variance']:.4g} | {r['variance_over_environment']:.3f} "
              f"| {r['brightest_pixel']:.3g} |")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"args": vars(args), "rows": rows}, f, indent=2)


if __name__ == "__main__":
    main()
