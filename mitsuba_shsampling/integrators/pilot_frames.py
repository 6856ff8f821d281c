"""More quadrature frames where the pilots' pixels are noisiest.

The quadrature's stratified grid (:func:`.quadrature.camera_frames`) gives a material as
many of its few thousand shading points as it has of the film. Where a material's variance
sits in a handful of its pixels (a sun's highlight on a small glossy ball) the grid holds
none of them or one, and the material's figures are mostly that luck. The pilots
(:mod:`.pilots`) see every pixel, and their per-pixel variances say where the variance is,
however loosely they measure how much of it each strategy removes.

So once the pilots have run, :data:`PILOT_FRAMES` more shading points are drawn with a
density proportional to the pilots' per-pixel variance (:class:`PixelDensity`), and every
frame, the grid's and these, is weighed by the balance heuristic over the two densities
(:meth:`PixelDensity.frame_weights`). The film's mean of each strategy's variance is then
estimated without bias whatever the pilots measured (the grid keeps its say where they
measured little), and with far fewer frame-sampling misses where the variance is
concentrated. On the material studio at 256 x 192 under its sun-and-sky map the grid put the
gold GGX 0.05 ball's environment-strategy variance at 6e-4, under a tenth of what its pilot
pixels hold (docs/MEASUREMENTS.md, "Quadrature frames where the pilots are noisy").

Conventions: film positions are in [0, 1]^2 over the film's crop window, as
:func:`.quadrature.camera_frames` and the pilots (:func:`.pilots.pilot_pixels`) place them;
pixels are numbered in raster order over the crop.
"""

from __future__ import annotations

import dataclasses

import numpy as np

PILOT_FRAMES = 1024
"""Shading points drawn from the pilots' density, beside the grid's :data:`~.quadrature.FRAMES`."""

PILOT_FRAMES_SEED = 1
"""The quadrature's seed for these frames (the grid's is 0): their directions are their own."""

_PLASTIC = (0.7548776662466927, 0.5698402909980532)
"""The R2 sequence's steps (the plastic number's inverse powers): a pixel's jitter per frame."""

_GOLDEN = 0.6180339887498949
"""The golden ratio's step: which pixel of a lane's run of pixels a frame takes."""


@dataclasses.dataclass(frozen=True)
class PixelDensity:
    """A density over the film, uniform within each pilot lane's pixels and proportional
    there to the lane's weight (its per-pixel variance).

    A lane's pixels: itself on a film pass (a lane a pixel); on a camera-sample pass of
    fewer lanes than pixels, the run of raster-order pixels from its pixel to the next
    lane's (:func:`~.pilots.pilot_pixels` strides them evenly)."""

    width: int
    height: int
    start: np.ndarray
    """First pixel of each lane's run, and the film's pixel count last (increasing)."""
    mass: np.ndarray
    """Each lane's probability (sums to 1)."""

    @classmethod
    def from_lanes(cls, width: int, height: int, lane_pixels: np.ndarray,
                   weights: np.ndarray) -> "PixelDensity | None":
        """The density of lanes at film pixels ``lane_pixels`` with ``weights``; None where
        no lane has a positive finite weight (nothing to draw from). Lanes that share a
        pixel (more lanes than pixels) share it with their mean weight."""
        pixels = width * height
        weights = np.where(np.isfinite(weights) & (weights > 0), weights, 0.0).astype(np.float64)
        lane_pixels = np.asarray(lane_pixels, dtype=np.int64)
        if len(lane_pixels) >= pixels or np.any(np.diff(lane_pixels) <= 0) or lane_pixels[0] != 0:
            counts = np.bincount(lane_pixels, minlength=pixels)
            weights = np.bincount(lane_pixels, weights=weights, minlength=pixels) / np.maximum(counts, 1)
            lane_pixels = np.arange(pixels)
        start = np.append(lane_pixels, pixels)
        # A lane's weight is a per-pixel variance: its run holds that much at each of its pixels.
        mass = weights * np.diff(start)
        total = mass.sum()
        if not (total > 0 and np.isfinite(total)):
            return None
        return cls(width, height, start, mass / total)

    def ratio(self, pixels: np.ndarray) -> np.ndarray:
        """The density at film pixels ``pixels`` over the uniform density's."""
        lane = np.searchsorted(self.start, pixels, side="right") - 1
        run = self.start[lane + 1] - self.start[lane]
        return self.mass[lane] * (self.start[-1] / run)

    def positions(self, count: int) -> tuple[np.ndarray, np.ndarray]:
        """``count`` film positions ``(x, y)`` drawn from the density without random numbers:
        lanes by systematic sampling of their cumulative mass (a lane of mass m gets m x count
        frames, give or take one), each frame at its own pixel of the lane's run and its own
        point of the pixel (low-discrepancy sequences), so that the same pilots give the same
        frames in every process."""
        j = np.arange(count, dtype=np.float64)
        cumulative = np.cumsum(self.mass)
        lane = np.minimum(np.searchsorted(cumulative, (j + 0.5) / count, side="right"), len(self.mass) - 1)
        run = self.start[lane + 1] - self.start[lane]
        pixel = self.start[lane] + np.minimum(np.floor(np.modf(j * _GOLDEN)[0] * run), run - 1).astype(np.int64)
        jitter_x, jitter_y = (np.modf(0.5 + j * step)[0] for step in _PLASTIC)
        return (pixel % self.width + jitter_x) / self.width, (pixel // self.width + jitter_y) / self.height

    def pixels_at(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """The film pixel (raster order) of each film position."""
        column = np.clip(np.floor(np.asarray(x) * self.width), 0, self.width - 1).astype(np.int64)
        row = np.clip(np.floor(np.asarray(y) * self.height), 0, self.height - 1).astype(np.int64)
        return row * self.width + column

    def frame_weights(self, x: np.ndarray, y: np.ndarray, grid_positions: int, drawn: int) -> np.ndarray:
        """Each frame's weight in a film mean (a sum over all frames, the grid's and the drawn
        ones, of weight x value), by the balance heuristic: 1 / (grid_positions + drawn x ratio)
        at its pixel. ``grid_positions``: the grid's film positions (those that hit no smooth
        BSDF included); ``drawn``: the positions drawn here (likewise)."""
        return 1.0 / (grid_positions + drawn * self.ratio(self.pixels_at(x, y)))
