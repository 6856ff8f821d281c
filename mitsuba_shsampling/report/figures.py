"""Figure hook: warped sample points drawn over the density they should follow.

The samplers themselves live elsewhere (``warp/``); this module only draws.
Wire a sampler in by passing a function that turns uniform points into warped
points in the same coordinates as the density image, e.g. the equal-area
(z, phi) grid of ARCHITECTURE.md with ``extent=(0, 2 pi, -1, 1)``.
"""

from __future__ import annotations

from typing import Callable

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from .plots import figure_png  # noqa: E402

#: (x_min, x_max, y_min, y_max) of the equal-area grid: phi on x, z on y.
EQUAL_AREA_EXTENT = (0.0, 2 * np.pi, -1.0, 1.0)


def warped_points_figure(density: np.ndarray,
                         sample: Callable[[np.ndarray], np.ndarray],
                         n_points: int = 2048,
                         extent: tuple[float, float, float, float] = EQUAL_AREA_EXTENT,
                         seed: int = 0,
                         title: str = "",
                         uniform: np.ndarray | None = None) -> bytes:
    """PNG of ``n_points`` warped points over a density image.

    :param density: (H, W) target density; row 0 is drawn at ``extent``'s y_min
        (for the equal-area grid: row iz covers the z band iz, column iphi the phi band iphi).
    :param sample: maps uniform points (N, 2) in [0, 1)^2 to warped points (N, 2) as (x, y)
        in ``extent`` coordinates.
    :param n_points: number of points drawn.
    :param extent: (x_min, x_max, y_min, y_max) of the density image.
    :param seed: seed of the uniform points.
    :param uniform: input points (n_points, 2) to warp instead of seeded random ones
        (e.g. a low-discrepancy set).
    :raises ValueError: if ``sample`` returns the wrong shape or non-finite points.
    """
    if uniform is None:
        uniform = np.random.default_rng(seed).random((n_points, 2))
    points = np.asarray(sample(uniform), dtype=np.float64)
    if points.shape != (n_points, 2):
        raise ValueError(f"sampler returned shape {points.shape}, expected ({n_points}, 2)")
    if not np.all(np.isfinite(points)):
        raise ValueError("sampler returned non-finite points")
    fig, ax = plt.subplots(figsize=(7, 3.8))
    ax.imshow(density, origin="lower", extent=extent, aspect="auto", cmap="viridis")
    ax.scatter(points[:, 0], points[:, 1], s=1.5, c="white", alpha=0.7, linewidths=0)
    ax.set_xlim(extent[0], extent[1])
    ax.set_ylim(extent[2], extent[3])
    ax.set_xlabel("phi")
    ax.set_ylabel("z")
    if title:
        ax.set_title(title)
    return figure_png(fig)


def hammersley(n_points: int) -> np.ndarray:
    """The 2D Hammersley set (i/N, radical inverse base 2 of i): a low-discrepancy input."""
    i = np.arange(n_points, dtype=np.uint64)
    bits = np.zeros(n_points, dtype=np.float64)
    scale, rest = 0.5, i.copy()
    while np.any(rest):
        bits += scale * (rest & 1)
        rest >>= np.uint64(1)
        scale *= 0.5
    return np.stack([(i.astype(np.float64) + 0.5) / n_points, bits], axis=1)


def sampler_demo_figures(emitter, n_bands: int = 8, exponent: float = 20.0,
                         axis=(0.35, -0.45, 0.82), n_points: int = 1024,
                         grid: int = 128) -> list[tuple[str, bytes]]:
    """The paper's demonstration: warped points over their target densities.

    One Phong lobe (exponent ``exponent``, ``n_bands`` bands, about ``axis`` in
    the grid frame) is warped alone (SH hierarchical sample warping) and as a
    product with the environment ``emitter`` (SH product warp), each from
    independent uniform points and from a Hammersley set: hierarchical warping
    keeps the input's stratification. Returns (caption, PNG) pairs.
    """
    import drjit as dr
    import mitsuba as mi

    from ..envmap.pyramid import EnvPyramid
    from ..sh.basis import sh_eval_sum
    from ..sh.zonal import phong_attenuation, zonal_to_sh
    from ..grid import grid_coordinates
    from ..warp.hsw import SHWarp
    from ..warp.product import ProductWarp

    axis = mi.Vector3f(*(float(a) for a in np.asarray(axis) / np.linalg.norm(axis)))
    coeffs = [mi.Float(c) for c in zonal_to_sh(list(phong_attenuation(exponent, n_bands)), axis)]

    # Target densities on the equal-area grid (cell centres), rows = z.
    z = -1 + (np.arange(grid) + 0.5) * 2 / grid
    phi = (np.arange(grid) + 0.5) * 2 * np.pi / grid
    zz, pp = np.meshgrid(z, phi, indexing="ij")
    s = np.sqrt(1 - zz ** 2)
    dirs = mi.Vector3f(*(mi.Float(v.ravel().astype(np.float32)) for v in (s * np.cos(pp), s * np.sin(pp), zz)))
    lobe = np.maximum(sh_eval_sum(coeffs, dirs).numpy().reshape(grid, grid), 0)
    pyramid = EnvPyramid(emitter)
    level = min(pyramid.depth, int(np.log2(grid)))
    env = pyramid.level_numpy(level)
    env = np.kron(env, np.ones((grid // env.shape[0], grid // env.shape[1])))

    def as_points(d_grid) -> np.ndarray:
        zs, ps = grid_coordinates(d_grid)
        return np.stack([ps.numpy(), zs.numpy()], axis=1)

    sh_warp, product = SHWarp(depth=6), ProductWarp(pyramid)

    def sh_sampler(u):
        d, _ = sh_warp.sample(coeffs, mi.Point2f(*(mi.Float(c.astype(np.float32)) for c in u.T)))
        return as_points(d)

    def product_sampler(u):
        d, _ = product.sample(coeffs, mi.Point2f(*(mi.Float(c.astype(np.float32)) for c in u.T)))
        return as_points(pyramid.grid_from_world(d))

    out = []
    for name, density, sampler in (("SH lobe", lobe, sh_sampler),
                                   ("SH lobe x environment", lobe * env, product_sampler)):
        # Square-root scale: the peak and the lobe's shoulders both stay visible.
        shown = np.sqrt(density / max(density.max(), 1e-30))
        for input_name, uniform in (("independent", None), ("Hammersley", hammersley(n_points))):
            title = f"{name}: {n_points} points from {input_name} input"
            png = warped_points_figure(shown, sampler, n_points=n_points, title=title, uniform=uniform)
            out.append((title, png))
        dr.eval()
    return out
