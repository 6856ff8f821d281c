"""Bake Mitsuba's ``sunsky`` emitter into a latitude-longitude EXR for ``envmap``.

The result reproduces ``sunsky`` when loaded as an ``envmap`` with an identity
``to_world`` in a **+Y-up world** (the frame of every built-in scene, ``mitsuba_shsampling/scenes/``):

- ``sunsky`` is z-up in its local frame; it is loaded with a ``to_world``
  that turns its zenith into +Y (``sun_direction`` is then given in world
  space), and evaluated in the envmap's local directions (conventions of
  /work/shared/design/mitsuba.md).
- Texel ``(col, row)`` is the envmap's bilinear vertex at
  ``u = (col + 0.5) / W``, ``theta = row * pi / (H - 1)``. Each vertex stores
  the solid-angle average of the radiance over its cell
  ``[u +- 0.5/W] x [theta +- 0.5 pi/(H-1)]``, so that the bilinear
  reconstruction keeps the emitted power. The sky is smooth: 4x4 samples per
  cell. The sun (0.54 degrees wide, about 1e5 times brighter than the sky)
  covers about one texel; point sampling would miss or multiply its power, so
  cells near the sun get 64x64 samples of the sun-only emitter.

After writing, the script checks the bake against ``sunsky`` itself: radiance
in sky directions away from the sun (bilinear interpolation error), and the
irradiance on a horizontal plane (sun included) estimated with each emitter's
own importance sampling.

Usage::

    python3 scripts/bake_sunsky.py [--out mitsuba_shsampling/scenes/textures/sunsky.exr] [--width 512]
"""

from __future__ import annotations

import argparse
import json
import math
import os

import numpy as np

import mitsuba as mi
import drjit as dr

mi.set_variant("llvm_ad_rgb")

# Sun 35 degrees above the horizon, behind-left of the default camera (which
# looks along -Z from +Z), so that glossy spheres show its highlight.
SUN_ELEVATION_DEG = 35.0
SUN_AZIMUTH_DEG = 140.0  # measured from -Z towards +X in the envmap's y-up world
TURBIDITY = 3.0
SUN_HALF_APERTURE_DEG = 0.5358 / 2


def env_direction(u: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """Envmap local direction (3, N) of texture coordinate u and polar angle theta."""
    phi = 2 * np.pi * u
    return np.stack([np.sin(phi) * np.sin(theta), np.cos(theta), -np.cos(phi) * np.sin(theta)])


def sun_direction_env() -> np.ndarray:
    """Unit direction towards the sun in the +Y-up world."""
    el, az = np.radians(SUN_ELEVATION_DEG), np.radians(SUN_AZIMUTH_DEG)
    return env_direction(np.array([az / (2 * np.pi)]), np.array([np.pi / 2 - el]))[:, 0]


# sunsky's local frame (x, y, z), z the zenith -> world (x, z, -y), +Y up.
SKY_TO_WORLD = [[1, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]]


def load_sunsky(sun_scale: float = 1.0, sky_scale: float = 1.0) -> mi.Emitter:
    """The sun-and-sky emitter in the +Y-up world."""
    return mi.load_dict({
        "type": "sunsky",
        "to_world": mi.ScalarTransform4f(SKY_TO_WORLD),
        "sun_direction": mi.ScalarVector3f(*sun_direction_env()),
        "turbidity": TURBIDITY,
        "sun_scale": sun_scale,
        "sky_scale": sky_scale,
    })


def eval_emitter(emitter: mi.Emitter, d_world: np.ndarray) -> np.ndarray:
    """Radiance (N, 3) arriving from world directions d_world (3, N)."""
    si = dr.zeros(mi.SurfaceInteraction3f, d_world.shape[1])
    si.wi = -mi.Vector3f(d_world.astype(np.float32))
    return np.array(emitter.eval(si)).T.reshape(-1, 3)


def cell_average(emitter: mi.Emitter, cols: np.ndarray, rows: np.ndarray, width: int,
                 height: int, n_sub: int) -> np.ndarray:
    """Solid-angle average radiance (N, 3) over the cells of vertices (cols, rows)."""
    du, dtheta = 1.0 / width, np.pi / (height - 1)
    offs = (np.arange(n_sub) + 0.5) / n_sub - 0.5
    ou, ot = [o.ravel() for o in np.meshgrid(offs, offs, indexing="ij")]
    u = ((cols[:, None] + 0.5) / width + ou[None] * du).ravel()
    theta = np.clip(rows[:, None] * dtheta + ot[None] * dtheta, 0.0, np.pi).ravel()
    L = eval_emitter(emitter, env_direction(u, theta))
    w = np.maximum(np.sin(theta), 1e-6)[:, None]
    L = (L * w).reshape(len(cols), -1, 3).sum(1) / w.reshape(len(cols), -1, 1).sum(1)
    return L


def bake(width: int) -> np.ndarray:
    height = width // 2
    rows, cols = [a.ravel() for a in np.meshgrid(np.arange(height), np.arange(width), indexing="ij")]
    image = cell_average(load_sunsky(sun_scale=0.0), cols, rows, width, height, 4)

    # Cells whose centre lies within 2 degrees of the sun: the sun's power
    # integrated finely (the texel diagonal is ~1 degree at 512x256).
    centre = env_direction((cols + 0.5) / width, rows * np.pi / (height - 1))
    near_sun = np.degrees(np.arccos(np.clip(sun_direction_env() @ centre, -1, 1))) < 2.0
    image[near_sun] += cell_average(load_sunsky(sky_scale=0.0), cols[near_sun], rows[near_sun],
                                    width, height, 64)
    return image.reshape(height, width, 3).astype(np.float32)


def irradiance_up(emitter: mi.Emitter, n: int = 1 << 22) -> np.ndarray:
    """Irradiance (RGB) on a +Y-facing plane, by the emitter's own sampling."""
    it = dr.zeros(mi.Interaction3f, n)
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(7, n)
    ds, weight = emitter.sample_direction(it, sampler.next_2d())
    cos = dr.maximum(ds.d.y, 0.0)
    return np.array([dr.mean(weight[i] * cos)[0] for i in range(3)])


def check(path: str, n_dirs: int = 4096) -> dict:
    """Compare the baked envmap with sunsky in the same +Y-up world."""
    envmap = mi.load_dict({"type": "envmap", "filename": path})
    sky, sunsky = load_sunsky(sun_scale=0.0), load_sunsky()

    rng = np.random.default_rng(1)
    d = rng.normal(size=(3, n_dirs))
    d /= np.linalg.norm(d, axis=0)
    d = d[:, (d[1] > 0.05) & (sun_direction_env() @ d < math.cos(math.radians(5)))]
    L_env, L_sky = eval_emitter(envmap, d), eval_emitter(sky, d)
    rel = np.abs(L_env - L_sky).mean(1) / L_sky.mean(1)

    E_env, E_sunsky = irradiance_up(envmap), irradiance_up(sunsky)
    return {
        "sky_directions": int(d.shape[1]),
        "sky_radiance_rel_err_median": float(np.median(rel)),
        "sky_radiance_rel_err_p99": float(np.quantile(rel, 0.99)),
        "irradiance_envmap_rgb": E_env.tolist(),
        "irradiance_sunsky_rgb": E_sunsky.tolist(),
        "irradiance_ratio": float(E_env.mean() / E_sunsky.mean()),
    }


def main() -> None:
    here = os.path.dirname(os.path.abspath(__file__))
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", default=os.path.join(here, "..", "mitsuba_shsampling", "scenes", "textures", "sunsky.exr"))
    parser.add_argument("--width", type=int, default=512)
    args = parser.parse_args()

    image = bake(args.width)
    mi.Bitmap(image).write(args.out)
    print(f"wrote {args.out} ({image.shape[1]}x{image.shape[0]}, max {image.max():.1f}, "
          f"{os.path.getsize(args.out) / 1e6:.2f} MB)")
    print(json.dumps(check(args.out), indent=2))


if __name__ == "__main__":
    main()
