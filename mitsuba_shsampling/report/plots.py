"""Convergence plots of a comparison: log-log error versus spp and versus time (matplotlib)."""

from __future__ import annotations

import io

import matplotlib

from .schema import ConvergencePoint

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def convergence_figure(curves: dict[str, list[ConvergencePoint]], title: str) -> bytes:
    """PNG of two log-log panels: MSE vs spp and MSE vs wall time.

    :param curves: method label -> its points (one render each).
    :param title: figure title (scene, sampler).
    """
    fig, (ax_spp, ax_time) = plt.subplots(1, 2, figsize=(10, 3.8))
    for label, points in curves.items():
        points = [p for p in points if p.mse > 0 and p.time_s > 0]
        if not points:
            continue
        ax_spp.loglog([p.spp for p in points], [p.mse for p in points], "o-", label=label, ms=3)
        ax_time.loglog([p.time_s for p in points], [p.mse for p in points], "o-", label=label, ms=3)
    ax_spp.set_xlabel("samples per pixel")
    ax_time.set_xlabel("wall time per render (s, warm)")
    for ax in (ax_spp, ax_time):
        ax.set_ylabel("MSE")
        ax.grid(True, which="both", alpha=0.3)
    if ax_spp.get_legend_handles_labels()[0]:
        ax_spp.legend(fontsize=7)
    fig.suptitle(title)
    return figure_png(fig)


def figure_png(fig) -> bytes:
    """Lay out ``fig``, return it as PNG bytes and close it."""
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=90)
    plt.close(fig)
    return buffer.getvalue()
