"""Environment-map luminance on the equal-area (z, phi) grid, as a sum pyramid.

The pyramid is what hierarchical warps descend: level ``k`` has 2^k x 2^k
cells of the equal-area cylinder (see docs/ARCHITECTURE.md), each holding the
integral of the envmap's luminance over the cell, in units of radiance x
steradian (cell solid angle = dz dphi). A parent is the sum of its four
children, so the root holds the integral over the whole sphere.

Frames. Mitsuba's ``envmap`` is latitude-longitude in a +Y-up *local* frame
(``u = atan2(d.x, -d.z) / 2 pi``, ``v = acos(d.y) / pi``, ``to_world`` maps
local to world). The pyramid lives in the right-handed z-up *grid frame*

    z_g = local.y,   x_g = -local.z,   y_g = -local.x,

so that ``z_g = cos(theta_env)`` and ``phi_g = 2 pi (1 - u) (mod 2 pi)``.

Resampling is exact, not supersampled: the emitter's radiance is bilinear in
(u, theta) between texels, i.e. a sum of texel values times separable hat
functions, and a grid cell is a rectangle in (z, phi) with ``z = cos(theta)``
and ``phi`` affine in ``u``. Both 1D integrals of a hat have closed forms
(``int (a + b t) sin t dt`` along theta, a trapezoid along u), so every cell
integral is computed exactly (float64 prefix sums, stored as float32). Thin
features (a sun of one texel) can therefore not be missed at any depth.
"""

from __future__ import annotations

import contextlib
import math
import numbers
import threading
import time
import warnings
import weakref

import drjit as dr
import mitsuba as mi
import numpy as np

from ..build_cache import cached_build, content_key
from ..device_arrays import aligned_empty, device_array
from ..grid import TWO_PI, Cell
from ..host_memory import kept_copy, ordinary_pages

#: Deepest level built by default. 2^11 x 2^11 cells resolve a 2k map; the
#: pyramid takes 39 MB. Deeper levels would not help the warps anyway: rescaling
#: a float32 sample loses about one bit per split, so ~11 levels per
#: dimension is what a 24-bit mantissa supports (docs/MATH.md, section 5).
DEFAULT_MAX_DEPTH = 11

#: Rec. 709 luminance weights, identical to ``mi.luminance``.
LUMINANCE_WEIGHTS = np.array([0.212671, 0.715160, 0.072169])

#: Number of 4-float blocks before level k+1 is ``1 + (4^k - 1) / 3``; the
#: quotient is the bit pattern 0b0101...01 (k ones), i.e. this mask cut to
#: 2k bits, which avoids an integer division in traced code.
_BLOCK_COUNT_MASK = 0x55555555
#: Texel rows / grid rows processed at once while resampling (bounds the
#: float64 temporaries to a few times 8 * _CHUNK * max(W, 2^D) bytes).
_CHUNK = 64

DIM_TOTAL = 1e-20
"""Integral (radiance x sr) below which a map is sampled as black. Its cells' float32
integrals would reach the denormal range (an average finest cell of a depth-12 pyramid holds
total / 4^12), where they round to a few bits: the pyramid's levels would no longer sum to
their parents, which its walks rely on (a 1e-36 map put the product walk's pdf 8 % off).
The integrators then leave the map to Mitsuba's own sampling, which is exact at any scale."""

BLACK_MAP_REASON = "the environment map is black (or too dim for float32 cell integrals: EnvPyramid.DIM_TOTAL)"
"""Why an integrator leaves a map whose pyramid ``is_black`` to Mitsuba's own sampling."""


SUBTEXEL_LEVELS = 2
"""Levels finer than the texels, up to :data:`DEFAULT_MAX_DEPTH`. Radiance is
bilinear between texels and the leaves are sampled uniformly, so a one-texel
sun (a two-texel hat after interpolation) falls linearly across a texel-sized
leaf: 1/3 relative variance per sample. Two levels helped a 512-wide
sun-and-sky map a lot, one was best on 1k maps (docs/MEASUREMENTS.md,
"Environment pyramid"); capping at depth 11 gives each map what it needs, and
:data:`LEVEL_TOLERANCE` drops them again where the map has no detail for them."""


LEVEL_TOLERANCE = 2.5e-3
"""How much a finest level must improve sampling to be kept: the relative second moment by
which the level above, with its bilinear leaves, samples the finest cells worse than they
are (:func:`coarse_leaf_excess`). Why this value: a level above 10 MB makes every walk
that ends in it wait for memory (docs/MEASUREMENTS.md, "The pyramid's depth and the warp's
memory": the product warp 28 % faster at depth 10 than at 11, a scene's pass 3-7 %), and an
estimator's variance grows by the excess times ``S / (S - 1)`` (S its relative second
moment), up to about 20x where a sun dominates a well-sampled pixel; 20 x 2.5e-3 = 5 %,
about what the level saves in time."""

COMPENSATION_RESIDUE = 1e-6
"""A compensated target that keeps less than this share of the map's integral is taken for
rounding noise (a constant map: every cell its mean), and the map stays uncompensated."""

TRIM_FLOOR_DEPTH = 9
"""Trimming never takes a pyramid below this level: at depth 9 the whole pyramid is 2 MB
and its walks are no longer waiting for memory, so a coarser one would save nothing."""


def auto_depth(height: int, width: int, max_depth: int = DEFAULT_MAX_DEPTH) -> int:
    """Finest level D for an H x W lat-long map: 2^D >= 2^SUBTEXEL_LEVELS max(W, H),
    in [1, max_depth].

    With 2^D >= W the grid resolves the map's azimuthal texel spacing; near
    the equator 2^D >= H cells in z are finer than the H - 1 rows in theta;
    :data:`SUBTEXEL_LEVELS` more levels follow the bilinear slopes inside texels.
    """
    if max_depth < 1:
        raise ValueError(f"EnvPyramid: max_depth must be >= 1, got {max_depth}")
    need = int(np.ceil(np.log2(max(height, width, 2)))) + SUBTEXEL_LEVELS
    return int(min(max(need, 1), max_depth))


def _theta_integrals(lum: np.ndarray, n: int) -> np.ndarray:
    """Integrate each texel column over the n z-bands of the grid.

    ``lum`` is (H, W) texel luminance, row y at theta_y = y pi / (H-1),
    linearly interpolated in theta. Returns R (n, W), float64:
    ``R[iz, x] = int_{z_iz}^{z_iz+1} f_x(acos z) dz`` with z_i = -1 + 2 i / n.
    """
    height, width = lum.shape
    z_edges = np.linspace(-1.0, 1.0, n + 1)
    if height == 1:
        # A single row is constant in theta (the emitter reads row 0 everywhere).
        return np.outer(np.diff(z_edges), lum[0].astype(np.float64))

    h = np.pi / (height - 1)
    theta_nodes = np.arange(height) * h

    def hat_weights(y: np.ndarray, s: np.ndarray):
        """int_{t_y}^{s} (1-w) sin t dt and int_{t_y}^{s} w sin t dt, w = (t - t_y)/h."""
        t0 = theta_nodes[y]
        sin_integral = np.cos(t0) - np.cos(s)
        upper = (-(s - t0) * np.cos(s) + np.sin(s) - np.sin(t0)) / h
        return sin_integral - upper, upper

    # Full-interval weights: C[y] = int_0^{t_y} f sin = sum_{j<y} A_j T_j + B_j T_{j+1}.
    full_a, full_b = hat_weights(np.arange(height - 1), theta_nodes[1:])
    # G(theta_i) at the grid's band edges, theta_i = acos(z_i) (decreasing in i).
    theta_edges = np.arccos(z_edges)
    y_edge = np.minimum((theta_edges / h).astype(np.int64), height - 2)
    part_a, part_b = hat_weights(y_edge, theta_edges)

    # Sweep the rows once, keeping the prefix integral C[y] of every column,
    # and read it off at the edge rows. (A row loop over full-width vectors:
    # np.cumsum along axis 0 of a row-major array is ~8x slower.)
    # In aligned memory, read-only once written: the kernels map it without a copy (device_array).
    g = aligned_empty((n + 1, width), np.float64)
    order = np.argsort(y_edge, kind="stable")
    first_edge = np.searchsorted(y_edge[order], np.arange(height), side="left")
    last_edge = np.searchsorted(y_edge[order], np.arange(height), side="right")
    prefix = np.zeros(width)
    for y in range(height - 1):
        row, next_row = lum[y].astype(np.float64), lum[y + 1].astype(np.float64)
        for i in order[first_edge[y]:last_edge[y]]:
            g[i] = prefix + part_a[i] * row + part_b[i] * next_row
        prefix += full_a[y] * row + full_b[y] * next_row
    # Cell iz spans theta from theta_{iz+1} up to theta_iz.
    np.subtract(g[:-1], g[1:], out=g[:-1])
    g.flags.writeable = False
    return g[:-1]


def _phi_integrals(bands: np.ndarray, n: int, scale: float = 1.0) -> mi.Float64:
    """Integrate band profiles over the n phi-cells of the grid, times ``scale``.

    ``bands`` (n, W) are values at texel columns x (u_x = (x+0.5)/W), linear in u
    between columns and periodic (one row per z-band: :func:`_theta_integrals`).
    Returns the (n, n) cells row-major as a float64 device array, column iphi =
    integral over phi_g in [2 pi iphi/n, 2 pi (iphi+1)/n].

    Two kernels: the rows' trapezoid prefix sums (a block prefix sum), then the n^2
    cells, a lane per cell, reading the antiderivative at its two edges.
    The sizes are opaque: every map and depth runs the same compiled code. (In numpy,
    with the corners, the compensation and the sums, the build of a 512 x 256 map's two
    pyramids took 0.7 s of a new scene's set-up; docs/MEASUREMENTS.md.)
    """
    rows, width = bands.shape
    # Texel coordinate s = u W - 0.5; cell edges u_k = k/n.
    s_edges = np.arange(n + 1) * (width / n) - 0.5
    floor_s = np.floor(s_edges)
    frac = s_edges - floor_s
    # Extended node j sits at s = j - 1 and holds column (j - 1) mod W.
    node = (floor_s + 1).astype(np.uint32)

    u32, f64 = mi.UInt32, mi.Float64
    values = device_array(f64, bands)
    size, texels, stride = dr.opaque(u32, n), dr.opaque(u32, width), dr.opaque(u32, width + 2)

    def extended(row, j):  # the value at extended node j of a row
        return dr.gather(f64, values, row * texels + (j + texels - 1) % texels)

    # Each row's trapezoid prefix sums over the extended nodes: cumulative[j] = sum over
    # i < j of (ext[i] + ext[i + 1]) / 2.
    lane = dr.arange(u32, rows * (width + 2))
    row, j = lane // stride, lane % stride
    trapezoid = dr.select(j <= texels, 0.5 * (extended(row, j) + extended(row, j + 1)), 0.0)
    cumulative = dr.block_prefix_sum(trapezoid, width + 2, exclusive=True)
    node, frac = device_array(u32, node), device_array(f64, frac)
    lane = dr.arange(u32, rows * n)
    row, column = lane // size, lane % size

    def antiderivative(edge):
        first = dr.gather(u32, node, edge)
        lo, hi = extended(row, first), extended(row, first + 1)
        f = dr.gather(f64, frac, edge)
        return (dr.gather(f64, cumulative, row * stride + first) + lo * f) + (hi - lo) * (0.5 * f * f)

    # phi_g = 2 pi (1 - u): phi-cell iphi is u-cell n - 1 - iphi.
    u_cell = size - 1 - column
    cells = (dr.opaque(f64, TWO_PI / width) * (antiderivative(u_cell + 1) - antiderivative(u_cell)))
    return cells * dr.opaque(f64, scale) if scale != 1.0 else cells


def _corner_radiance(lum: np.ndarray, n: int, scale: float = 1.0) -> mi.Float:
    """The map's luminance at the corners of the finest cells times ``scale``, clamped at 0:
    (n + 1)^2 float32 values on the device, row-major, rows iz (z = -1 + 2 iz / n),
    columns iphi (phi = 2 pi iphi / n).

    The same interpolant as the integrals: linear in theta between rows (row y at
    theta = y pi / (H - 1), the +Y pole first), linear in u between columns (column x
    at u = (x + 0.5) / W, periodic), with u = 1 - phi / (2 pi) in the grid frame. One
    kernel, a lane per corner, from per-row and per-column weights made on the host, in
    float32 arithmetic: along theta at the texel columns, then along u.
    """
    height, width = lum.shape
    theta = np.arccos(np.clip(-1.0 + 2.0 * np.arange(n + 1) / n, -1.0, 1.0))
    row = np.clip(theta * (height - 1) / np.pi, 0.0, height - 1)
    r0 = np.minimum(row.astype(np.int64), max(height - 2, 0))
    fr = row - r0
    r1 = np.minimum(r0 + 1, height - 1)
    column = ((1.0 - np.arange(n + 1) / n) * width - 0.5) % width
    c0 = np.floor(column).astype(np.int64) % width
    fc = column - np.floor(column)
    c1 = (c0 + 1) % width

    u32, f32 = mi.UInt32, mi.Float
    texels = device_array(f32, lum)
    size = dr.opaque(u32, n + 1)
    lane = dr.arange(u32, (n + 1) * (n + 1))
    i, j = lane // size, lane % size

    upper, lower = dr.gather(u32, device_array(u32, r0 * width), i), dr.gather(u32, device_array(u32, r1 * width), i)
    keep_r, take_r = (dr.gather(f32, device_array(f32, w), i) for w in (1 - fr, fr))
    left, right = dr.gather(u32, device_array(u32, c0), j), dr.gather(u32, device_array(u32, c1), j)
    keep_c, take_c = (dr.gather(f32, device_array(f32, w), j) for w in (1 - fc, fc))

    def along_theta(c):
        return dr.gather(f32, texels, upper + c) * keep_r + dr.gather(f32, texels, lower + c) * take_r

    out = along_theta(left) * keep_c + along_theta(right) * take_c
    return dr.maximum(out * dr.opaque(f32, np.float32(scale)), 0.0)


def coarse_leaf_excess(finest: np.ndarray, corners: np.ndarray, level: int) -> float:
    """How much worse level ``level``'s leaves sample the finest level than the finest
    level's own cells: ``sum t^2 / q - 1`` over the finest cells, t a cell's share of the
    total and q the probability that a walk to ``level`` and the bilinear placement in the
    leaf (:meth:`EnvPyramid.leaf_corners`, corner floor included) give the cell.

    This is the relative second moment an estimator gains from sampling the map at
    ``level`` rather than at the finest level (0 when the bilinear leaves reproduce the finer
    cells, e.g. a constant map). ``finest`` is (2^D, 2^D), ``corners`` (2^D + 1, 2^D + 1), both
    of the sampling target, as :class:`EnvPyramid` builds them; a black map gives 0.

    One float64 kernel, a lane per finest cell; the sizes are opaque, so every depth and
    level runs the same compiled code. (In numpy, block by block, it was a fifth to a half
    of a 1k map's pyramid build: 0.17-0.23 s an evaluation.)
    """
    n = finest.shape[0]
    parts = n >> level
    total = float(finest.sum(dtype=np.float64))
    if parts <= 1 or total <= 0:
        return 0.0
    m = n // parts
    leaf_share = finest.reshape(m, parts, m, parts).sum(axis=(1, 3), dtype=np.float64) / total
    # Read in its own precision (a float32 level is not copied to float64 on the host; a cell
    # below float32's normal range would add under 1e-60 to the sum).
    share = mi.Float64(device_array(mi.Float if finest.dtype == np.float32 else mi.Float64, finest)) / total
    return _leaf_excess(share, device_array(mi.Float64, leaf_share),
                        device_array(mi.Float64, corners[::parts, ::parts]), n, level)


def _leaf_excess(share: mi.Float64, leaf_share: mi.Float64, leaf_corners: mi.Float64, n: int, level: int) -> float:
    """:func:`coarse_leaf_excess` from device arrays: the finest cells' shares of the total
    (n^2), level ``level``'s (m^2, m = 2^level) and the target at that level's corners
    ((m + 1)^2), all row-major."""
    parts = n >> level
    m = n // parts
    u32 = mi.UInt32
    shift, size, sub_cells = dr.opaque(u32, parts.bit_length() - 1), dr.opaque(u32, n), dr.opaque(u32, parts)
    lane = dr.arange(u32, n * n)
    row, column = lane // size, lane % size
    leaf_row, leaf_column = row >> shift, column >> shift
    leaves = dr.opaque(u32, m)
    first = leaf_row * (leaves + 1) + leaf_column
    v = [dr.gather(mi.Float64, leaf_corners, index) for index in (first, first + 1, first + leaves + 1, first + leaves + 2)]
    floor = CORNER_FLOOR * (v[0] + v[1] + v[2] + v[3])
    v = [x + floor for x in v]
    quarter_sum = 0.25 * (v[0] + v[1] + v[2] + v[3])
    # A leaf with black corners is placed uniformly: as four equal corners.
    lit = quarter_sum > 0
    scale = dr.gather(mi.Float64, leaf_share, leaf_row * leaves + leaf_column) \
        / dr.select(lit, quarter_sum, 1.0)
    v00, v01, v10, v11 = (dr.select(lit, x, 1.0) * scale for x in v)

    def hats(index):  # integrals of (1 - x) and x over the sub-cell [index, index + 1] / parts
        width = 1.0 / mi.Float64(sub_cells)
        x0 = mi.Float64(index & (sub_cells - 1)) * width
        rising = 0.5 * width * (2.0 * x0 + width)
        return width - rising, rising

    low_z, high_z = hats(row)
    low_phi, high_phi = hats(column)
    # q = leaf share x the bilinear mass of the sub-cell; 0 only in a leaf of zero share,
    # whose cells' shares are 0 too.
    q = low_z * (v00 * low_phi + v01 * high_phi) + high_z * (v10 * low_phi + v11 * high_phi)
    second_moment = dr.sum(dr.select(q > 0, share * share / q, 0.0))
    return float(second_moment.numpy()[0]) - 1.0


def check_level_tolerance(tolerance) -> float:
    """``tolerance`` as a float if it is a finite real number >= 0, else ``ValueError``."""
    if isinstance(tolerance, bool) or not isinstance(tolerance, numbers.Real) \
            or not np.isfinite(tolerance) or tolerance < 0:
        raise ValueError(f"EnvPyramid: level_tolerance must be a finite number >= 0, got {tolerance!r}")
    return float(tolerance)


def trimmed_depth(levels: list, corners: mi.Float, tolerance: float, floor_depth: int = TRIM_FLOOR_DEPTH) -> int:
    """The coarsest level >= ``floor_depth`` whose leaves sample the finest level within
    ``tolerance`` (:func:`coarse_leaf_excess` below it); the finest level D if none is.
    ``levels``: :func:`sum_levels`' (level k at index k, float64 on the device), ``corners``
    the target at level D's corners ((2^D + 1)^2, row-major, on the device)."""
    depth = len(levels) - 1
    total = float(levels[0].numpy()[0])
    # 1 / total as an opaque value: a literal of each map's total made these kernels new to
    # Dr.Jit's kernel cache for every map.
    inverse = dr.opaque(mi.Float64, 1.0 / total) if total > 0 else None
    share = levels[depth] * inverse if total > 0 else None
    keep = depth
    for level in range(depth - 1, floor_depth - 1, -1):
        excess = 0.0 if share is None else _leaf_excess(
            share, levels[level] * inverse, mi.Float64(corners_at_level(corners, depth, level)), 1 << depth, level)
        if not excess < tolerance:
            break
        keep = level
    return keep


def corners_at_level(corners: mi.Float, depth: int, level: int) -> mi.Float:
    """Level ``level``'s corners ((2^level + 1)^2) among level ``depth``'s (every
    2^(depth - level)-th row and column: a coarser level's corners are a subset)."""
    if level == depth:
        return corners
    u32 = mi.UInt32
    m, parts = 1 << level, 1 << (depth - level)
    lane = dr.arange(u32, (m + 1) * (m + 1))
    size = dr.opaque(u32, m + 1)
    row, column = lane // size, lane % size
    return dr.gather(type(corners), corners, (row * dr.opaque(u32, parts)) * dr.opaque(u32, (1 << depth) + 1)
                     + column * dr.opaque(u32, parts))


def in_blocks(level_values: mi.Float64, level: int, count: int = 1) -> mi.Float64:
    """Level ``level`` of ``count`` pyramids (4^level values each, row-major, one pyramid
    after the other) in :func:`sum_pyramid_blocks`' order: per pyramid one 4-value block
    per level - 1 parent (row-major), its children (0,0), (0,1), (1,0), (1,1)."""
    u32 = mi.UInt32
    lane = dr.arange(u32, count << (2 * level))
    shift = dr.opaque(u32, level - 1)
    pyramid, block = lane >> (2 * shift + 2), lane & ((u32(1) << (2 * shift + 2)) - 1)
    parent, child = block >> 2, block & 3
    parent_row, parent_column = parent >> shift, parent & ((u32(1) << shift) - 1)
    row, column = (parent_row << 1) | (child >> 1), (parent_column << 1) | (child & 1)
    return dr.gather(type(level_values), level_values, (pyramid << (2 * shift + 2)) | (row << (shift + 1)) | column)


def sum_levels(finest: mi.Float64, depth: int, count: int = 1) -> tuple[list, list]:
    """The sum pyramids of ``count`` levels ``depth`` (4^depth cells each, row-major, one
    after the other) on the device, in float64: ``(levels, blocks)``, ``levels[k]`` level k
    row-major (k = 0 .. depth) and ``blocks[k]`` level k in block order (:func:`in_blocks`;
    k = 1 .. depth, ``blocks[0]`` None). A parent is the sum of its block's four children
    (one block reduction a level: the same order of additions in every process)."""
    levels, blocks = [None] * (depth + 1), [None] * (depth + 1)
    levels[depth] = mi.Float64(finest)
    for k in range(depth, 0, -1):
        blocks[k] = in_blocks(levels[k], k, count)
        dr.eval(blocks[k])
        levels[k - 1] = dr.block_sum(blocks[k], 4, mode="evaluated")
    return levels, blocks


def sum_pyramid_blocks(finest: mi.Float64, depth: int, count: int = 1) -> mi.Float64:
    """The sum pyramids of ``count`` finest levels (4^depth cells each, row-major, one after
    the other, on the device) in :class:`EnvPyramid`'s buffer layout, float64, one after the
    other (4 * block_offset(depth) values each). Block 0 is [root, 0, 0, 0]; then level by
    level one block per parent, its children in (z-half, phi-half) order (0,0), (0,1),
    (1,0), (1,1). (In numpy, the 486 cosine tables of a map took 0.09 s; docs/MEASUREMENTS.md.)"""
    return blocks_buffer(*sum_levels(finest, depth, count), depth, count)


def blocks_buffer(levels: list, blocks: list, depth: int, count: int = 1) -> mi.Float64:
    """Levels 0 .. ``depth`` of :func:`sum_levels` (which may hold finer ones) in the buffer
    layout of :func:`sum_pyramid_blocks`."""
    u32 = mi.UInt32
    stride = 4 * block_offset(depth)
    out = dr.zeros(mi.Float64, count * stride)
    dr.scatter(out, levels[0], dr.arange(u32, count) * stride)
    for k in range(1, depth + 1):
        lane = dr.arange(u32, count << (2 * k))
        per_pyramid = dr.opaque(u32, 2 * k)
        pyramid, local = lane >> per_pyramid, lane & ((u32(1) << per_pyramid) - 1)
        dr.scatter(out, blocks[k], pyramid * dr.opaque(u32, stride) + dr.opaque(u32, 4 * block_offset(k - 1)) + local)
    return out


def block_offset(level):
    """Index of the first 4-float block of level+1 (Python int or traced UInt32)."""
    if isinstance(level, numbers.Integral):
        return 1 + ((4 ** int(level) - 1) // 3)
    return 1 + (mi.UInt32(_BLOCK_COUNT_MASK) & ((mi.UInt32(1) << (2 * level)) - 1))


LEAF_RECORD_FLOATS = 8
"""Floats per leaf record: 32 bytes, two records to a cache line."""

CORNER_LEVELS = 255
"""A leaf's corner values are stored as bytes, in units of their largest over this."""

CORNER_FLOOR = 0.025
"""Share of the four corner values' sum added to each before the bilinear placement (a tenth
of their mean): :meth:`EnvPyramid.leaf_corners` and :func:`coarse_leaf_excess` alike."""


def _float64_of_float32_bits(bits: mi.UInt32) -> mi.Float64:
    """The float64 value of non-negative float32 ``bits``, exact for denormals too: a kernel
    may run with denormals flushed to zero (depending on what ran on its thread before), and
    a denormal corner must keep its shape (its mantissa times 2^-149, computed in float64)."""
    mantissa = mi.Float64(bits & 0x7FFFFF) * 2.0**-149
    return dr.select((bits >> 23) == 0, mantissa, mi.Float64(dr.reinterpret_array(mi.Float, bits)))


def leaf_records(finest_blocks: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """The finest level and the corner values in one array of records, float32
    (m, m, :data:`LEAF_RECORD_FLOATS`) for the m x m cells of level D - 1 (m = 2^(D-1)).

    ``finest_blocks`` and ``corners`` are numpy arrays or flat device arrays (the same
    values row-major). Record (I, J) holds that cell's four children (the 4-float block of
    :func:`sum_pyramid_blocks`, ``finest_blocks`` row I m + J), then one 32-bit word per
    child, in the same order, with the target at that leaf's four corners (z0 phi0, z0
    phi1, z1 phi0, z1 phi1: ``corners`` (2m + 1, 2m + 1) at rows iz, iz + 1 and columns
    iphi, iphi + 1) as bytes, lowest first, each rounded in units of the largest of the
    four over :data:`CORNER_LEVELS` (the bits of a uint32 in a float32 slot).

    Why: a walk's last split reads the four children and the bilinear placement then
    reads the chosen leaf's corners. Stored apart (the corners as a float32 (2^D + 1)^2
    array), that is three cache lines from two arrays of 17 MB each at depth 11, cold for
    most samples: a fifth of the product sample's time (docs/MEASUREMENTS.md, "Leaf
    records"). In one record the corners come from the line the children's gather has
    just brought in. Only the four values' ratios shape the placement (it normalises
    them), and the placement raises each by a fortieth of their sum
    (:meth:`EnvPyramid.leaf_corners`), so bytes lose nothing that the floor does not
    already set; the sample and its pdf read the same bytes.
    """
    on_host = isinstance(corners, np.ndarray)
    m = (corners.shape[0] if on_host else math.isqrt(dr.width(corners))) // 2
    n = 2 * m
    u32 = mi.UInt32
    size = dr.opaque(u32, n)
    # A lane per leaf (row, column) of level D; its record is cell (row / 2, column / 2) of
    # level D - 1, where it is child 2 (row mod 2) + (column mod 2). The sizes are opaque:
    # every depth packs with the same kernel.
    leaf = dr.arange(u32, n * n)
    row, column = leaf // size, leaf % size
    # float32 corners in float64 lanes (exactly: :func:`_float64_of_float32_bits`), each step
    # rounded to float32 as float32 arithmetic would round it.
    corner = device_array(mi.UInt32, np.ascontiguousarray(corners, dtype=np.float32).view(np.uint32)) if on_host \
        else dr.reinterpret_array(u32, mi.Float(corners))
    first = row * (size + 1) + column
    value = [_float64_of_float32_bits(dr.gather(u32, corner, index))
             for index in (first, first + 1, first + size + 1, first + size + 2)]
    largest = dr.maximum(dr.maximum(value[0], value[1]), dr.maximum(value[2], value[3]))
    # value / largest first (at most 1), then the scale: 255 over a denormal largest would
    # overflow float32. A black leaf (0 / 0) gets zeros. Rounded to nearest, ties to even.
    largest = dr.select(largest == 0, 1.0, largest)
    word = dr.zeros(u32, n * n)
    for k in range(4):
        ratio = mi.Float(value[k] / largest)
        word |= u32(dr.round(mi.Float(mi.Float64(ratio) * CORNER_LEVELS))) << (8 * k)
    record = (row >> 1) * (size >> 1) + (column >> 1)
    records = dr.zeros(mi.Float, m * m * LEAF_RECORD_FLOATS)
    dr.scatter(records, dr.reinterpret_array(mi.Float, word),
               record * LEAF_RECORD_FLOATS + 4 + ((row & 1) << 1) + (column & 1))
    child = dr.arange(u32, m * m * 4)
    children = device_array(mi.Float, finest_blocks) if isinstance(finest_blocks, np.ndarray) else finest_blocks
    dr.scatter(records, children, (child >> 2) * LEAF_RECORD_FLOATS + (child & 3))
    return np.asarray(records.numpy(), dtype=np.float32).reshape(m, m, LEAF_RECORD_FLOATS)


class EnvmapError(ValueError):
    """An ``envmap`` the pyramid cannot represent (a ``to_world`` that is not a
    rotation, a negative or non-finite ``scale``); the message is one line."""


def _check_to_world(to_world: mi.AffineTransform4f) -> None:
    linear = np.asarray(to_world.matrix.numpy(), dtype=np.float64)[:3, :3].reshape(3, 3)
    if not np.allclose(linear.T @ linear, np.eye(3), atol=1e-4):
        singular = ", ".join(f"{s:.4g}" for s in np.linalg.svd(linear, compute_uv=False))
        raise EnvmapError(
            f"the envmap's to_world is not a rotation (its 3x3 part has singular values {singular}, "
            "not 1, 1, 1): the envmap emitter maps directions through it without normalising them, "
            "which product sampling cannot follow; remove the scale or shear from to_world")


def _sanitise_emitter_data(params: mi.SceneParameters, data: np.ndarray) -> tuple[np.ndarray, int]:
    """Set every texel with a NaN or infinite channel to 0 in the emitter's own ``data``.

    The emitter then evaluates and samples (Mitsuba's own sampler is rebuilt by
    ``params.update()``) the same map the pyramid integrates, so no strategy of
    any integrator can return NaN from it. Returns the data and the number of
    texels set to 0 (halo columns not counted).
    """
    bad = ~np.all(np.isfinite(data), axis=-1)
    count = int(np.count_nonzero(bad[:, 1:-1]))
    if count:
        data = np.where(bad[..., None], np.float32(0), data)
        params["data"] = type(params["data"])(data)
        params.update()
    return data, count


class EnvPyramid:
    """Sum pyramid of an ``envmap`` emitter's luminance on the equal-area grid.

    Level k (0 <= k <= ``depth``) has 2^k x 2^k cells; cell (iz, iphi)
    covers z in [-1 + 2 iz/2^k, -1 + 2 (iz+1)/2^k] and phi in
    [2 pi iphi/2^k, 2 pi (iphi+1)/2^k] of the *grid frame* (module docstring)
    and holds the integral of ``scale * luminance(radiance)`` over that
    solid angle (radiance x sr).

    Storage: one flat ``mi.Float`` ``buffer`` of 4-float blocks for levels 0 .. D-1.
    Block 0 is ``[total, 0, 0, 0]``; the 4^(k+1) values of level k+1 follow, one
    block per level-k parent (row-major in (iz, iphi)), each block holding the
    children (a, b) = (0,0), (0,1), (1,0), (1,1), a = z-half, b = phi-half. So
    :meth:`children` is a single ``dr.gather(mi.Vector4f, ...)``. Level D is in
    ``records``, one 32-byte record per level D-1 cell: its four children's block,
    then their corner values (:func:`leaf_records`), which the bilinear placement
    inside a leaf reads from the cache line the last split has just loaded.

    Bad texels, with one warning: a texel with a NaN or infinite channel is
    set to 0 *in the emitter's own data* (``mi.traverse`` + ``params.update()``),
    so that the whole render, Mitsuba's own sampling and evaluation included,
    sees the same finite map; texels with negative luminance stay in the
    emitter but get no product-sampling probability (BSDF sampling under MIS
    still reaches them). :meth:`from_latlong` has no emitter: bad texels count
    as 0 there. An all-zero map gives ``total == 0`` and ``is_black``; a map whose
    integral is below :data:`DIM_TOTAL` (mean radiance below ~1e-21) is
    ``is_black`` too, with a warning.

    Raises :class:`EnvmapError` (one line) for a ``to_world`` that is not a
    rotation or a ``scale`` that is negative or not finite.

    Parameters
    ----------
    emitter: a Mitsuba ``envmap`` emitter (``TypeError`` otherwise).
    max_depth: cap on the finest level D (default :data:`DEFAULT_MAX_DEPTH`);
        D = min(ceil(log2(max(W, H))) + SUBTEXEL_LEVELS, max_depth), at least 1
        (a 1024x512 map: D = 11, 39 MB, well under a second to build), then
        trimmed (below).
    mis_compensation: subtract the map's mean radiance from every finest cell
        (clamped at 0) before summing, as Mitsuba's ``envmap`` option of the
        same name does for its own sampler. ``total`` is then the integral of
        the compensated target; ``radiant_total`` is always the map's integral.
    level_tolerance: the finest levels are dropped, down to :data:`TRIM_FLOOR_DEPTH`,
        while the level above them samples their cells within this relative second
        moment (:func:`coarse_leaf_excess`; default :data:`LEVEL_TOLERANCE`): a map
        without features finer than its texels (most 1k photographs) is walked at
        depth 10 in a quarter of the memory, a small sun keeps its subtexel level.
        0 keeps every level; ``trimmed_levels`` says how many were dropped.
    """

    def __init__(self, emitter: mi.Emitter, max_depth: int | None = None,
                 mis_compensation: bool = False, level_tolerance: float = LEVEL_TOLERANCE) -> None:
        level_tolerance = check_level_tolerance(level_tolerance)  # before the emitter's data is touched
        name = emitter.class_name() if hasattr(emitter, "class_name") else type(emitter).__name__
        if name != "EnvironmentMapEmitter":
            raise TypeError(f"EnvPyramid needs an 'envmap' emitter, got {name}")
        params = mi.traverse(emitter)
        data = params["data"].numpy()  # (H, W + 2, C): one halo column each side
        channels = (4,) if mi.is_spectral else (1, 3)
        if data.ndim != 3 or data.shape[2] not in channels:
            raise TypeError(f"EnvPyramid: unsupported envmap data of shape {data.shape} "
                            f"(expected (H, W+2, {' or '.join(map(str, channels))}) in {mi.variant()})")
        start = time.perf_counter()
        to_world = mi.AffineTransform4f(params["to_world"])
        _check_to_world(to_world)  # before the emitter's data is touched
        data, sanitised = _sanitise_emitter_data(params, data)
        luminance = self._texel_luminance(data[:, 1:-1, :])
        self._build(luminance, float(dr.ravel(params["scale"])[0]), to_world, max_depth, start,
                    mis_compensation, level_tolerance, sanitised)

    @classmethod
    def from_latlong(cls, image: np.ndarray, scale: float = 1.0,
                     to_world: mi.ScalarAffineTransform4f | None = None,
                     max_depth: int | None = None, mis_compensation: bool = False,
                     level_tolerance: float = LEVEL_TOLERANCE) -> "EnvPyramid":
        """Pyramid of a lat-long image in the ``envmap`` layout, without an emitter.

        ``image`` is (H, W) luminance or (H, W, 1|3) linear RGB, row 0 at the
        local +Y pole, column x centred at u = (x + 0.5)/W. Equals the pyramid
        of ``envmap`` emitter built from the same image, scale and to_world.
        """
        level_tolerance = check_level_tolerance(level_tolerance)
        image = np.asarray(image)
        if image.ndim == 2:
            image = image[..., None]
        if image.ndim != 3 or image.shape[2] not in (1, 3) or min(image.shape[:2]) < 1:
            raise ValueError(f"EnvPyramid.from_latlong: expected (H, W) or (H, W, 1|3), got {image.shape}")
        start = time.perf_counter()
        pyramid = cls.__new__(cls)
        to_world = mi.ScalarAffineTransform4f() if to_world is None else to_world
        pyramid._build(cls._texel_luminance(image), float(scale),
                       mi.AffineTransform4f(to_world), max_depth, start, mis_compensation, level_tolerance)
        return pyramid

    # ------------------------------------------------------------------ build

    @staticmethod
    def _texel_luminance(texels: np.ndarray) -> np.ndarray:
        """(H, W, 1|3|4) texels -> (H, W) float32 luminance, row block by row block
        (a contiguous RGB copy of an 8k map would be 400 MB).

        Four channels are a spectral ``envmap``'s: the coefficients of the sRGB spectral
        upsampling model and a scale. Their weight is what Mitsuba's own envmap sampling
        uses in spectral variants, the model's mean over the wavelengths times the scale,
        so that the product's target and the environment strategies' match there too."""
        height = texels.shape[0]
        out = np.empty(texels.shape[:2], dtype=np.float32)
        for y0 in range(0, height, _CHUNK):
            block = texels[y0:y0 + _CHUNK].astype(np.float64)
            if block.shape[2] == 4:
                coefficients = block[..., :3].reshape(-1, 3).astype(np.float32)
                mean = mi.srgb_model_mean(mi.Vector3f(*(device_array(mi.Float, coefficients[:, i]) for i in range(3))))
                out[y0:y0 + _CHUNK] = np.asarray(mean.numpy(), dtype=np.float64).reshape(block.shape[:2]) \
                    * block[..., 3]
            else:
                out[y0:y0 + _CHUNK] = block[..., 0] if block.shape[2] == 1 else block @ LUMINANCE_WEIGHTS
        return out

    def _build(self, luminance: np.ndarray, scale: float, to_world: mi.AffineTransform4f,
               max_depth: int | None, start: float, mis_compensation: bool = False,
               level_tolerance: float = LEVEL_TOLERANCE, sanitised: int | None = None) -> None:
        """``sanitised``: texels already set to 0 in the emitter (None: no emitter)."""
        if not np.isfinite(scale) or scale < 0:
            raise EnvmapError(f"the envmap's scale must be finite and >= 0, got {scale}")
        _check_to_world(to_world)
        bad = ~np.isfinite(luminance) | (luminance < 0)
        bad_count = int(np.count_nonzero(bad))
        if sanitised is None and bad_count:
            warnings.warn(f"EnvPyramid: {bad_count} envmap texel(s) with NaN, infinite or negative "
                          "luminance are treated as 0", RuntimeWarning, stacklevel=3)
        elif sanitised or bad_count:
            parts = [f"{sanitised} with a NaN or infinite channel were set to 0 in the envmap "
                     "emitter's own data, for the whole render"] if sanitised else []
            parts += [f"{bad_count} with negative luminance get no product-sampling probability "
                      "(the emitter keeps them)"] if bad_count else []
            warnings.warn(f"EnvPyramid: {sanitised + bad_count} envmap texel(s) unusable: "
                          + "; ".join(parts), RuntimeWarning, stacklevel=3)
        if bad_count:
            luminance = np.where(bad, np.float32(0), luminance)

        height, width = luminance.shape
        depth = auto_depth(height, width, DEFAULT_MAX_DEPTH if max_depth is None else max_depth)
        # The same texels, scale and settings always give the same levels: a map seen
        # before (this process, or an earlier one through the disk cache) is not summed again.
        key = content_key(luminance, scale, depth, bool(mis_compensation), float(level_tolerance))
        built = cached_build("pyramid", key, lambda: _pyramid_arrays(luminance, scale, depth, mis_compensation,
                                                                     level_tolerance))
        depth, buffer, records = int(built["depth"]), built["buffer"], built["records"]
        blocks_root, radiant_total, compensated = float(built["total"]), float(built["radiant_total"]), \
            bool(built["compensated"])

        #: Finest level D; levels 0..D exist.
        self.depth: int = depth
        #: D and the extents (dz, dphi) of a level-D cell as opaque device values, for the
        #: kernels: the descent below a warp's own levels loops to D (a literal D made every
        #: map of a new depth compile the quadrature's, the pilots' and the render's kernels
        #: again; docs/MEASUREMENTS.md, "A map new to the machine compiles its kernels again").
        self.finest_level: mi.UInt32 = dr.opaque(mi.UInt32, depth)
        self.leaf_extent: tuple[mi.Float, mi.Float] = (dr.opaque(mi.Float, 2.0 / 2**depth),
                                                       dr.opaque(mi.Float, TWO_PI / 2**depth))
        #: Levels built below D and dropped because they did not pay (LEVEL_TOLERANCE).
        self.trimmed_levels: int = int(built["trimmed_levels"])
        #: Sum of the pyramid's root (the sampling target's integral), float64.
        self.total: float = blocks_root
        #: 1 / :attr:`total` (0 for a black map) as an opaque device value, for the kernels: a
        #: literal of each map's integral made every kernel that walks the map (quadrature,
        #: pilots, render) new to Dr.Jit's kernel cache for each new map (docs/MEASUREMENTS.md,
        #: "A map new to the machine compiles its kernels again").
        self.inverse_total: mi.Float = dr.opaque(mi.Float, 1.0 / blocks_root if blocks_root > 0 else 0.0)
        #: Integral of scale * luminance over the sphere (radiance x sr).
        self.radiant_total: float = radiant_total
        #: Whether the mean radiance was subtracted (MIS compensation).
        self.mis_compensation: bool = compensated
        self.is_black: bool = self.total < DIM_TOTAL
        if 0.0 < self.total < DIM_TOTAL:
            warnings.warn(f"EnvPyramid: the map's integral {self.total:.3g} (radiance x sr) is below {DIM_TOTAL:g}, "
                          "where float32 cell integrals lose their precision: it is sampled as black, and "
                          "Mitsuba's own envmap sampling takes over", RuntimeWarning, stacklevel=3)
        #: Levels 0 .. D-1 in 4-float blocks (the class docstring's layout).
        self.buffer: mi.Float = device_array(mi.Float, buffer)
        #: Level D with the sampling target (radiance, compensated like the cells) at its
        #: cells' corners, one :data:`LEAF_RECORD_FLOATS`-float record per level D-1 cell
        #: (:func:`leaf_records`): the bilinear density inside a leaf.
        self.records: mi.Float = device_array(mi.Float, records)
        self.nbytes: int = buffer.nbytes + records.nbytes
        self.to_world: mi.AffineTransform4f = to_world
        self.to_local: mi.AffineTransform4f = to_world.inverse()
        self.texel_resolution: tuple[int, int] = (height, width)
        dr.eval(self.buffer, self.records)
        self.build_time_s: float = time.perf_counter() - start

    # ----------------------------------------------------------------- lookups

    def children(self, level: int | mi.UInt32, iz: mi.UInt32, iphi: mi.UInt32,
                 active: mi.Bool = True) -> mi.Vector4f:
        """Integrals of the 4 children of cell (iz, iphi) at ``level`` (< depth).

        Returns (c00, c01, c10, c11) with c_ab the child (2 iz + a, 2 iphi + b),
        a = upper-z half, b = upper-phi half. One gather; ``level`` may be a
        traced ``mi.UInt32`` (e.g. a ``dr.while_loop`` state variable).
        """
        iz, iphi = mi.UInt32(iz), mi.UInt32(iphi)
        cell = (iz << level) | iphi
        last = self.depth - 1
        # A record is LEAF_RECORD_FLOATS / 4 Vector4f long and starts with the four children.
        in_records = (LEAF_RECORD_FLOATS // 4) * cell
        if isinstance(level, numbers.Integral):
            if level == last:
                return dr.gather(mi.Vector4f, self.records, in_records, active)
            return dr.gather(mi.Vector4f, self.buffer, block_offset(level) + cell, active)
        is_last = mi.UInt32(level) == last
        return dr.select(is_last, dr.gather(mi.Vector4f, self.records, in_records, active & is_last),
                         dr.gather(mi.Vector4f, self.buffer, block_offset(level) + cell, active & ~is_last))

    def cell_integral(self, level: int | mi.UInt32, iz: mi.UInt32, iphi: mi.UInt32,
                      active: mi.Bool = True) -> mi.Float:
        """Integral over cell (iz, iphi) at ``level`` (0..depth), radiance x sr."""
        iz, iphi = mi.UInt32(iz), mi.UInt32(iphi)
        parent_level = dr.maximum(mi.UInt32(level), 1) - 1
        parent = ((iz >> 1) << parent_level) | (iphi >> 1)
        child = 2 * (iz & 1) + (iphi & 1)
        finest = mi.UInt32(level) == self.finest_level
        in_buffer = dr.select(mi.UInt32(level) == 0, 0, 4 * (block_offset(parent_level) + parent) + child)
        from_records = self.leaf_integral(iz, iphi, active & finest)
        from_buffer = dr.gather(mi.Float, self.buffer, in_buffer, active & ~finest)
        if isinstance(level, numbers.Integral):
            return from_records if level == self.depth else from_buffer  # the other is never traced
        return dr.select(finest, from_records, from_buffer)

    def block_children(self, level: mi.UInt32, iz: mi.UInt32, iphi: mi.UInt32) -> mi.Vector4f:
        """:meth:`children` of a cell of a traced ``level`` < D - 1 (the buffer's levels)."""
        return dr.gather(mi.Vector4f, self.buffer, block_offset(level) + ((iz << level) | iphi))

    def leaf_children(self, iz: mi.UInt32, iphi: mi.UInt32) -> mi.Vector4f:
        """:meth:`children` of a level D - 1 cell: the four leaves, from its record."""
        cell = (iz << (self.finest_level - 1)) | iphi
        return dr.gather(mi.Vector4f, self.records, (LEAF_RECORD_FLOATS // 4) * cell)

    def leaf_integral(self, iz: mi.UInt32, iphi: mi.UInt32, active: mi.Bool = True) -> mi.Float:
        """:meth:`cell_integral` of a level-D cell (a leaf), from its parent's record."""
        record = ((iz >> 1) << (self.finest_level - 1)) | (iphi >> 1)
        return dr.gather(mi.Float, self.records, LEAF_RECORD_FLOATS * record + 2 * (iz & 1) + (iphi & 1), active)

    def leaf_cell(self, iz: mi.UInt32, iphi: mi.UInt32) -> Cell:
        """The level-D cell (iz, iphi), its level and extents read from device values."""
        return Cell(self.finest_level, iz, iphi, *self.leaf_extent)

    def leaf_corners(self, leaf) -> list:
        """The target at a finest cell's corners (z0 phi0, z0 phi1, z1 phi0, z1 phi1), each
        raised by a tenth of their mean: samples follow the bilinear slope inside the leaf
        (a sun smaller than a texel is then drawn where it is, not spread over the leaf),
        and the density stays within a bounded factor of uniform everywhere in it. They
        share a cache line with the leaf's own integral (:func:`leaf_records`)."""
        iz, iphi = mi.UInt32(leaf.iz), mi.UInt32(leaf.iphi)
        record = ((iz >> 1) << (self.finest_level - 1)) | (iphi >> 1)
        child = 2 * (iz & 1) + (iphi & 1)
        word = dr.reinterpret_array(mi.UInt32, dr.gather(mi.Float, self.records, LEAF_RECORD_FLOATS * record + 4 + child))
        values = [mi.Float((word >> shift) & 0xFF) for shift in (0, 8, 16, 24)]
        floor = CORNER_FLOOR * ((values[0] + values[1]) + (values[2] + values[3]))
        return [v + floor for v in values]

    def level_numpy(self, k: int) -> np.ndarray:
        """Level k as a (2^k, 2^k) float32 array, rows = iz, columns = iphi."""
        k = int(k)
        if not 0 <= k <= self.depth:
            raise ValueError(f"EnvPyramid.level_numpy: level {k} outside 0..{self.depth}")
        if k == 0:
            return self.buffer.numpy()[:1].reshape(1, 1).copy()
        m = 1 << (k - 1)
        if k == self.depth:
            blocks = self.records.numpy().reshape(m, m, LEAF_RECORD_FLOATS)[..., :4].reshape(m, m, 2, 2)
        else:
            begin = 4 * block_offset(k - 1)
            blocks = self.buffer.numpy()[begin:begin + 4 * m * m].reshape(m, m, 2, 2)
        return blocks.transpose(0, 2, 1, 3).reshape(2 * m, 2 * m).copy()

    # ------------------------------------------------------------------ frames

    def grid_from_world(self, d: mi.Vector3f) -> mi.Vector3f:
        """World direction -> grid-frame direction (z_g = local.y, x_g = -local.z, y_g = -local.x)."""
        local = self.to_local @ mi.Vector3f(d)
        return mi.Vector3f(-local.z, -local.x, local.y)

    def world_from_grid(self, d: mi.Vector3f) -> mi.Vector3f:
        """Grid-frame direction -> world direction (inverse of :meth:`grid_from_world`)."""
        d = mi.Vector3f(d)
        return self.to_world @ mi.Vector3f(-d.y, d.z, -d.x)

    def __repr__(self) -> str:
        height, width = self.texel_resolution
        return (f"EnvPyramid[texels={height}x{width}, depth={self.depth}, trimmed_levels={self.trimmed_levels}, "
                f"total={self.total:.6g}, "
                f"nbytes={self.nbytes}, build_time_s={self.build_time_s:.3f}]")


class _FinestLevel:
    """Level D's cell integrals (float64, 4^D row-major) and corner radiance (float32,
    (2^D + 1)^2 row-major) of a map's uncompensated target, on the device; read-only
    (``_pyramid_arrays`` never writes them)."""

    def __init__(self, luminance: np.ndarray, scale: float, depth: int) -> None:
        n = 1 << depth
        finest = _phi_integrals(_theta_integrals(luminance, n), n, scale)
        corners = _corner_radiance(luminance, n, scale)
        dr.eval(finest, corners)
        self.arrays = (finest, corners)


_finest_lock = threading.Lock()
_finest_last: dict = {"key": None, "level": lambda: None, "held": None, "keeping": 0}


@contextlib.contextmanager
def finest_level_kept():
    """Within this block, the pyramids built of one map share its finest level
    (:func:`_target_at_finest_level`): the integrators build the compensated pyramid and then
    the plain one. On leaving it, the level is let go."""
    with _finest_lock:
        _finest_last["keeping"] += 1
    try:
        yield
    finally:
        with _finest_lock:
            _finest_last["keeping"] -= 1
            if not _finest_last["keeping"]:
                _finest_last["held"] = None


def _target_at_finest_level(luminance: np.ndarray, scale: float, depth: int) -> _FinestLevel:
    """The map's level D, computed once for the compensated and the plain pyramid: a build
    takes the level of the build before it while something still holds that level (a weak
    reference), or inside :func:`finest_level_kept`; else it computes its own."""
    key = content_key(luminance, scale, depth)
    with _finest_lock:
        level = _finest_last["level"]() if _finest_last["key"] == key else None
        if level is None:
            level = _FinestLevel(luminance, scale, depth)
            _finest_last.update(key=key, level=weakref.ref(level))
        if _finest_last["keeping"]:
            _finest_last["held"] = level
        return level


def _pyramid_arrays(luminance: np.ndarray, scale: float, depth: int, mis_compensation: bool,
                    level_tolerance: float) -> dict:
    """The levels of :class:`EnvPyramid` from sanitised texel luminance, as a
    :mod:`~mitsuba_shsampling.build_cache` record: ``buffer`` (levels 0..D-1 in 4-float
    blocks), ``records`` (level D's leaf records), ``depth`` D after trimming,
    ``trimmed_levels``, ``total`` (the root), ``radiant_total`` and ``compensated``."""
    # The sums and the level test touch ~9x the memory of what is kept (a depth-11 map: ~400 MB
    # against 39 MB): on ordinary pages (host_memory). What is kept, read at random by every
    # pass, is copied out of them, into pages the process gives as it would.
    with ordinary_pages():
        corners, levels, blocks, depth, built_depth, radiant_total, compensated = _summed_and_trimmed(
            luminance, scale, depth, mis_compensation, level_tolerance)
        # Levels 0 .. D-1 stay in 4-float blocks; the finest level's blocks go into the
        # leaf records with the corners they need (see :func:`leaf_records`).
        buffer = mi.Float(blocks_buffer(levels, blocks, depth - 1)).numpy()
        records = leaf_records(mi.Float(blocks[depth]), corners)
        total = float(levels[0].numpy()[0])
    # Never written to again: the pyramid maps them without another copy.
    return {"buffer": kept_copy(buffer), "records": kept_copy(records),
            "depth": depth, "trimmed_levels": built_depth - depth, "total": total,
            "radiant_total": radiant_total, "compensated": compensated}


def _summed_and_trimmed(luminance: np.ndarray, scale: float, depth: int, mis_compensation: bool,
                        level_tolerance: float) -> tuple:
    """:func:`_pyramid_arrays`' levels before they are packed: (the target at the kept depth's
    corners, levels, blocks, kept depth, built depth, radiant total, compensated)."""
    level = _target_at_finest_level(luminance, scale, depth)  # kept alive for the other pyramid's build
    finest, corners = level.arrays
    radiant_total = float(dr.sum(finest).numpy()[0])
    compensated = False
    if mis_compensation and radiant_total > 0:
        # MIS compensation (Karlik et al. 2019): subtract the mean radiance
        # (cells have equal solid angle) so this strategy concentrates on
        # what is brighter than average and leaves the rest to BSDF sampling.
        # A constant map would become black: keep it uncompensated then. (Its cells differ
        # from their mean by rounding alone: what compensation leaves of such a map is noise,
        # under COMPENSATION_RESIDUE of its integral.)
        # The map's mean as opaque values: as literals they made these kernels new to Dr.Jit's
        # kernel cache for every map.
        mean_cell = dr.opaque(mi.Float64, radiant_total / (1 << (2 * depth)))
        # Rounded to float32 as the cells are stored, held in float64 for the sums: one array.
        sharpened = mi.Float64(mi.Float(dr.maximum(finest - mean_cell, 0.0)))
        dr.eval(sharpened)
        if float(dr.sum(sharpened).numpy()[0]) > COMPENSATION_RESIDUE * radiant_total:
            finest, compensated = sharpened, True
            corners = dr.maximum(corners - dr.opaque(mi.Float, np.float32(radiant_total / (4 * np.pi))), 0.0)

    levels, blocks = sum_levels(finest, depth)
    built_depth = depth
    # The finest levels that do not pay (LEVEL_TOLERANCE) are dropped: their sums and every
    # other corner are the coarser level's exactly (its corners are a subset of theirs).
    depth = trimmed_depth(levels, corners, level_tolerance)  # checked by the constructors
    corners = corners_at_level(corners, built_depth, depth)
    dr.eval(corners)
    return corners, levels, blocks, depth, built_depth, radiant_total, compensated
