"""Figure hook: warped sample points drawn over the density they should follow.

The samplers themselves live elsewhere (``warp/``); this module only draws.
Wire a sampler in by passing a function that turns uniform points into warped
points in the same coordinates as the density image, e.g. the equal-area
(z, phi) grid of ARCHITECTURE.md with ``extent=(0, 2 pi, -1, 1)``.
"""

from __future__ import annotations

import io
from typing import Callable

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

#: (x_min, x_max, y_min, y_max) of the equal-area grid: phi on x, z on y.
EQUAL_AREA_EXTENT = (0.0, 2 * np.pi, -1.0, 1.0)


def warped_points_figure(density: np.ndarray,
                         sample: Callable[[np.ndarray], np.ndarray],
                         n_points: int = 2048,
                         extent: tuple[float, float, float, float] = EQUAL_AREA_EXTENT,
                         seed: int = 0,
                         title: str = "") -> bytes:
    """PNG of ``n_points`` warped points over a density image.

    :param density: (H, W) target density; row 0 is drawn at ``extent``'s y_min
        (for the equal-area grid: row iz covers the z band iz, column iphi the phi band iphi).
    :param sample: maps uniform points (N, 2) in [0, 1)^2 to warped points (N, 2) as (x, y)
        in ``extent`` coordinates.
    :param n_points: number of points drawn.
    :param extent: (x_min, x_max, y_min, y_max) of the density image.
    :param seed: seed of the uniform points.
    :raises ValueError: if ``sample`` returns the wrong shape or non-finite points.
    """
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
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=90)
    plt.close(fig)
    return buffer.getvalue()
