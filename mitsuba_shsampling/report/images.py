"""Image files of a report: EXR renders, tone-mapped and false-colour PNGs, base64 embedding."""

from __future__ import annotations

import base64
import io

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def display(image: np.ndarray, exposure: float = 1.0) -> np.ndarray:
    """Linear RGB (..., 3) radiance -> sRGB-encoded values in [0, 1] (..., 3), as a report's PNGs
    show it: exposed, non-finite values as black (NaN) or white (+inf), clipped at 1."""
    x = np.clip(np.nan_to_num(image[..., :3] * exposure, nan=0.0, posinf=1.0), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def clipped_pixels(image: np.ndarray, exposure: float = 1.0) -> np.ndarray:
    """(...) whether :func:`display` clips a channel of each pixel of ``image`` (..., C) at white."""
    return np.any(np.nan_to_num(image[..., :3] * exposure, nan=0.0, posinf=1.0) >= 1.0, axis=-1)


def tonemap(image: np.ndarray, exposure: float = 1.0) -> np.ndarray:
    """Linear RGB (H, W, 3) radiance -> sRGB-encoded uint8 (H, W, 3) (:func:`display`)."""
    return np.round(display(image, exposure) * 255).astype(np.uint8)


def false_colour(values: np.ndarray, vmin: float, vmax: float, cmap: str = "inferno") -> np.ndarray:
    """Scalar map (H, W) -> uint8 RGB (H, W, 3) on a log scale from vmin to vmax (both > 0)."""
    vmin = max(vmin, 1e-30)
    vmax = max(vmax, vmin * 10)
    t = (np.log10(np.clip(values, vmin, vmax)) - np.log10(vmin)) / (np.log10(vmax) - np.log10(vmin))
    return np.round(plt.get_cmap(cmap)(np.nan_to_num(t))[..., :3] * 255).astype(np.uint8)


def noisiest_window(values: np.ndarray, size: int) -> tuple[int, int]:
    """(x, y) of the top-left corner of the ``size`` x ``size`` window of (H, W) ``values``
    with the largest sum (the first one on ties); ``size`` is clipped to the map."""
    height, width = values.shape
    size = min(size, height, width)
    table = np.pad(np.nan_to_num(values, nan=0.0, posinf=0.0).cumsum(0).cumsum(1), ((1, 0), (1, 0)))
    sums = table[size:, size:] - table[:-size, size:] - table[size:, :-size] + table[:-size, :-size]
    y, x = np.unravel_index(int(np.argmax(sums)), sums.shape)
    return int(x), int(y)


def thumbnail(image: np.ndarray, width: int = 256) -> np.ndarray:
    """A lat-long map (H, W, C) as sRGB uint8 at most ``width`` wide (every k-th texel), exposed
    so that its 99th luminance percentile shows at 0.9."""
    step = max(1, int(np.ceil(image.shape[1] / width)))
    small = np.nan_to_num(image[::step, ::step, :3], nan=0.0, posinf=0.0)
    p99 = float(np.quantile(small.mean(axis=-1), 0.99)) if small.size else 0.0
    return tonemap(small, 0.9 / p99 if p99 > 0 else 1.0)


def log_range(maps: list[np.ndarray], low_quantile: float = 0.02) -> tuple[float, float]:
    """Shared log-scale range of several non-negative maps: (a low quantile of positives, max)."""
    values = np.concatenate([m.ravel() for m in maps])
    positive = values[values > 0]
    if positive.size == 0:
        return 1e-6, 1e-5
    return float(np.quantile(positive, low_quantile)), float(positive.max())


def png_bytes(rgb8: np.ndarray) -> bytes:
    """Encode a uint8 RGB image (H, W, 3) as PNG."""
    buffer = io.BytesIO()
    plt.imsave(buffer, rgb8, format="png")
    return buffer.getvalue()


def write_png(path: str, rgb8: np.ndarray) -> bytes:
    """Write a uint8 RGB image as PNG; returns the encoded bytes (for embedding)."""
    data = png_bytes(rgb8)
    with open(path, "wb") as f:
        f.write(data)
    return data


def data_uri(png: bytes) -> str:
    """``data:`` URI of PNG bytes, for a self-contained HTML page."""
    return "data:image/png;base64," + base64.b64encode(png).decode("ascii")
