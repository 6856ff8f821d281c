"""Generate a small studio-like latitude-longitude map: softboxes on a dim room.

Three rectangular softboxes (key, fill, rim) of constant radiance on a dim
background that fades from a grey ceiling to a darker floor. Box edges are
anti-aliased by the fraction of each texel's cell they cover, so the map is
band-limited enough for bilinear lookups. Texel conventions are those of the
``envmap`` plugin (+Y up; column x at u = (x+0.5)/W, row y at
theta = y pi / (H-1)), see /work/shared/design/mitsuba.md.

Usage::

    python3 scripts/make_studio_envmap.py [--out mitsuba_shsampling/scenes/textures/studio.exr] [--width 512]
"""

from __future__ import annotations

import argparse
import os

import numpy as np

# (u centre, u width, theta centre [deg], theta height [deg], RGB radiance)
SOFTBOXES = [
    (0.36, 0.10, 50.0, 30.0, (40.0, 38.0, 35.0)),   # key, front-left of the camera
    (0.64, 0.07, 70.0, 20.0, (10.0, 10.5, 11.0)),   # fill, front-right
    (0.97, 0.05, 30.0, 16.0, (25.0, 25.0, 25.0)),   # rim, behind the subject
]


def coverage(centres: np.ndarray, cell: float, lo: float, hi: float) -> np.ndarray:
    """Fraction of the 1D cells [c - cell/2, c + cell/2] inside [lo, hi]."""
    return np.clip((np.minimum(centres + cell / 2, hi) - np.maximum(centres - cell / 2, lo)) / cell, 0, 1)


def studio_map(width: int) -> np.ndarray:
    """Radiance image (H, W, 3), float32, H = W / 2."""
    height = width // 2
    u = (np.arange(width) + 0.5) / width
    theta = np.degrees(np.arange(height) * np.pi / (height - 1))
    up = np.cos(np.radians(theta))[:, None, None]
    image = np.broadcast_to(0.03 + 0.02 * up, (height, width, 3)).copy()
    for uc, uw, tc, th, rgb in SOFTBOXES:
        cu = coverage(u, 1.0 / width, uc - uw / 2, uc + uw / 2)
        ct = coverage(theta, 180.0 / (height - 1), tc - th / 2, tc + th / 2)
        image += ct[:, None, None] * cu[None, :, None] * np.array(rgb)[None, None, :]
    return image.astype(np.float32)


def main() -> None:
    here = os.path.dirname(os.path.abspath(__file__))
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", default=os.path.join(here, "..", "mitsuba_shsampling", "scenes", "textures", "studio.exr"))
    parser.add_argument("--width", type=int, default=512)
    args = parser.parse_args()

    import mitsuba as mi
    mi.set_variant("scalar_rgb")
    image = studio_map(args.width)
    mi.Bitmap(image).write(args.out)
    print(f"wrote {args.out} ({image.shape[1]}x{image.shape[0]}, {os.path.getsize(args.out) / 1e6:.2f} MB)")


if __name__ == "__main__":
    main()
