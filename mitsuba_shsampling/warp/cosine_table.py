"""Product sampling of a clamped cosine and the environment, from one table per normal.

A diffuse lobe's shape is max(n . w, 0) whatever the view: it depends on the
normal n alone. So the product max(n . w, 0) x L(w) needs no per-lane SH
expansion: :class:`CosineTable` tabulates it once per scene for the normals at
the centres of :data:`NORMAL_BINS` x :data:`NORMAL_BINS` bins on each face of a
cube in world space (486 normals, at most about 9 degrees from any normal, and
the world's axes, where walls, floors and ceilings face, exactly at a bin's
centre), down to level :data:`TABLE_DEPTH` of the environment's pyramid, and a
lane walks the table of the bin its own normal falls in. Each table holds the
same defensive mixture as :class:`~.product.ProductWeights`,

    W(c) = (1 - e) T(c) / T(root) + e E(c) / E(root),    T(c) = sum over c' in c of E(c') max(n_bin . w_c', 0),

with E the pyramid's cell integral and c' the cells one level finer than c, w_c'
their centres (a cell astride the horizon keeps its lit half), summed up the
levels, so the walk's weights are absolute (:func:`~.hierarchy.walk_sample_absolute`)
and the pdf walk reads one weight. Below the table both parts of the mixture
follow the environment, and the pyramid finishes the walk exactly as in
:class:`~.product.ProductWarp` (the same descent and leaf placement).

A lane's own normal differs from its bin's by up to half a bin: the table is then
the product for a slightly tilted cosine. That changes how well the samples follow
the integrand, not the estimate: the pdf is the exact density of the walk, and
the defensive share e keeps it positive wherever the map is lit (directions
above the lane's horizon but below the bin's included).

Cost per sample: the normal's bin, :data:`TABLE_DEPTH` gathers of four
contiguous weights, then the pyramid's descent; the pdf is one gather besides
the pyramid's two. No SH coefficients, no proxy levels.
"""

from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np

from ..build_cache import cached_build, content_key
from ..device_arrays import device_array
from ..envmap.pyramid import block_offset, sum_pyramid_blocks
from ..grid import Cell, grid_coordinates
from .env_leaves import finish_pdf, finish_sample
from .hierarchy import Split, walk_pdf_absolute, walk_sample_absolute

TABLE_DEPTH = 6
"""Levels the tables cover (4096 cells of about 3.2 degrees at the finest): the
depth where the product warp's proxy levels end (:data:`~.product.DEFAULT_PROXY_DEPTH`)."""

NORMAL_BINS = 9
"""Bins per side of each cube face: 6 x 9 x 9 = 486 normals, 10.6 MB of tables. Odd,
so that each world axis is a bin's centre; an equal-area (z, phi) grid of normals
would put the world's up at 20 degrees from its nearest bin centre (the pole's
cells are slivers) and the horizontal normals on bin boundaries."""


BLOCKS_PER_TABLE = block_offset(TABLE_DEPTH)
"""4-float blocks of one table (the layout of :func:`~mitsuba_shsampling.envmap.pyramid.sum_pyramid_blocks`)."""


def _cell_centres(level: int) -> np.ndarray:
    """(2^level, 2^level, 3) grid-frame directions of the cells' centres, float64."""
    n = 1 << level
    z = -1.0 + (np.arange(n) + 0.5) * (2.0 / n)
    phi = (np.arange(n) + 0.5) * (2.0 * math.pi / n)
    s = np.sqrt(np.maximum(1.0 - z * z, 0.0))
    return np.stack(np.broadcast_arrays(s[:, None] * np.cos(phi)[None, :],
                                        s[:, None] * np.sin(phi)[None, :], z[:, None]), axis=-1)


def bin_normals() -> np.ndarray:
    """(bins, 3) world-space unit normals at the bins' centres, in the order of
    :func:`normal_bin`: face (+x, -x, +y, -y, +z, -z), then the two other axes'
    coordinates (in axis order) over the major one, each in :data:`NORMAL_BINS` steps."""
    steps = -1.0 + (np.arange(NORMAL_BINS) + 0.5) * (2.0 / NORMAL_BINS)
    u, v = np.meshgrid(steps, steps, indexing="ij")
    faces = []
    for axis in range(3):
        others = [k for k in range(3) if k != axis]
        for sign in (1.0, -1.0):
            d = np.zeros((NORMAL_BINS, NORMAL_BINS, 3))
            d[..., axis], d[..., others[0]], d[..., others[1]] = sign, u, v
            faces.append(d.reshape(-1, 3))
    normals = np.concatenate(faces)
    return normals / np.linalg.norm(normals, axis=1, keepdims=True)


def normal_bin(n: mi.Vector3f) -> mi.UInt32:
    """Bin of world-space normals ``n`` (:func:`bin_normals`' order): the cube face of
    the largest coordinate, then the other two over it."""
    a = dr.abs(n)
    x_major = (a.x >= a.y) & (a.x >= a.z)
    y_major = ~x_major & (a.y >= a.z)
    major = dr.select(x_major, a.x, dr.select(y_major, a.y, a.z))
    first = dr.select(x_major, n.y, n.x)
    second = dr.select(x_major | y_major, n.z, n.y)
    negative = dr.select(x_major, n.x, dr.select(y_major, n.y, n.z)) < 0
    face = dr.select(x_major, 0, dr.select(y_major, 2, 4)) + dr.select(negative, 1, 0)
    scale = 0.5 * NORMAL_BINS / dr.maximum(major, 1e-30)

    def step(c):
        return mi.UInt32(dr.clip(dr.fma(c, scale, 0.5 * NORMAL_BINS), 0.0, NORMAL_BINS - 1))

    return (mi.UInt32(face) * NORMAL_BINS + step(first)) * NORMAL_BINS + step(second)


def mixture_tables(env_cells: np.ndarray, normals: np.ndarray, defensive_share: float, on_device: bool = False):
    """W per normal at level :data:`TABLE_DEPTH`: (normals, 2^D, 2^D), float64, each summing to 1
    (``on_device``: the same values flat, one table after the other, as a device array).

    ``env_cells``: a level of the pyramid at least as fine as D (non-negative cell
    integrals, (2^k, 2^k), k >= D); ``normals`` (count, 3) grid-frame unit normals.
    The product part of a level-D cell is the sum over its level-k cells of their
    integral times max(n . centre, 0): with k = D + 1, a cell astride the horizon keeps
    the weight of its lit half (at its own centre the cosine can be 0). A normal whose
    hemisphere holds no light gets the environment alone (e = 1), as a product lane
    whose lobe has no mass does.

    One float64 kernel, a lane per (normal, level-D cell): on two cores 0.02-0.03 s for
    the 486 tables of a map, where the same sums in numpy took 0.10-0.14 s of every new
    map's set-up (docs/MEASUREMENTS.md)."""
    env = np.asarray(env_cells, dtype=np.float64)
    fine, n = env.shape[0], 1 << TABLE_DEPTH
    k = fine // n
    count = len(normals)
    # The level-k cells regrouped so that the k x k of one level-D cell are adjacent.
    centres = _cell_centres(int(round(math.log2(fine)))).reshape(n, k, n, k, 3)
    centres = centres.transpose(0, 2, 1, 3, 4).reshape(n * n, k * k, 3)
    env = env.reshape(n, k, n, k).transpose(0, 2, 1, 3).reshape(n * n, k * k)
    coarse = env.sum(axis=1)
    lane = dr.arange(mi.UInt32, count * n * n)
    table, cell = lane // (n * n), lane % (n * n)
    normal = [dr.gather(mi.Float64, device_array(mi.Float64, normals[:, a]), table) for a in range(3)]
    product = dr.zeros(mi.Float64, count * n * n)
    for part in range(k * k):
        centre = [dr.gather(mi.Float64, device_array(mi.Float64, centres[:, part, a]), cell) for a in range(3)]
        cosine = dr.maximum(normal[0] * centre[0] + normal[1] * centre[1] + normal[2] * centre[2], 0.0)
        product += cosine * dr.gather(mi.Float64, device_array(mi.Float64, env[:, part]), cell)
    product_total = dr.gather(mi.Float64, dr.block_sum(product, n * n), table)
    env_part = dr.gather(mi.Float64, device_array(mi.Float64, coarse / coarse.sum()), cell)
    lit = product_total > 0
    mixed = dr.select(lit, (1.0 - defensive_share) * product / dr.select(lit, product_total, 1.0)
                      + defensive_share * env_part, env_part)
    return mixed if on_device else np.asarray(mixed.numpy(), dtype=np.float64).reshape(count, n, n)


class CosineTableWeights:
    """Weight provider of the absolute walks (:mod:`.hierarchy`): the four children's
    mixture weights W of one lane's table, one gather a level."""

    def __init__(self, table: "CosineTable", first_block: mi.UInt32):
        self.table, self.first_block = table, first_block

    def root(self):
        return None

    def children(self, state, cell: Cell) -> Split:
        block = self.first_block + block_offset(cell.level) + ((mi.UInt32(cell.iz) << cell.level) | mi.UInt32(cell.iphi))
        return Split(tuple(dr.gather(mi.Vector4f, self.table.buffer, block)), None)

    def advance(self, state, pending, cell: Cell, a, b):
        return None


class CosineTable:
    """Sampler of max(n . w, 0) x environment (defensively mixed) for per-lane normals.

    Parameter ``pyramid`` (:class:`~mitsuba_shsampling.envmap.pyramid.EnvPyramid`, at
    least :data:`TABLE_DEPTH` levels deep): the environment; the tables follow its
    cells (compensated where it is).

    Parameter ``defensive_share`` (float in (0, 1]): e, the environment's own share.

    ``sample(normal, u)`` returns (world direction, solid-angle pdf) for grid-frame unit
    normals; ``pdf(normal, d)`` the density of world directions ``d``. Both read the
    table of the normal's bin (:func:`normal_bin`).
    """

    def __init__(self, pyramid, defensive_share: float):
        if pyramid.depth < TABLE_DEPTH:
            raise ValueError(f"CosineTable needs a pyramid at least {TABLE_DEPTH} levels deep, got {pyramid.depth}")
        self.pyramid = pyramid
        self.defensive_share = defensive_share
        world = bin_normals()
        grid = pyramid.grid_from_world(mi.Vector3f(*(device_array(mi.Float, c) for c in world.T)))
        normals = np.stack([np.asarray(c.numpy(), dtype=np.float64) for c in (grid.x, grid.y, grid.z)], axis=1)
        cells_per_table = 1 << (2 * TABLE_DEPTH)
        if pyramid.is_black:
            blocks = sum_pyramid_blocks(dr.full(mi.Float64, 4.0**-TABLE_DEPTH, len(world) * cells_per_table),
                                           TABLE_DEPTH, len(world)).numpy()
        else:
            cells = pyramid.level_numpy(min(TABLE_DEPTH + 1, pyramid.depth))
            # The same map level, frame and share give the same tables (build_cache): in this
            # process only. Built in kernels they cost 25-40 ms; their file, 21 MB, cost more to
            # write than that, on a core the set-up needed.
            blocks = cached_build("cosine_tables", content_key(cells, normals, float(defensive_share)), lambda: {
                "blocks": sum_pyramid_blocks(mixture_tables(cells, normals, defensive_share, on_device=True),
                                                TABLE_DEPTH, len(world)).numpy()}, on_disk=False)["blocks"]
        self.buffer = device_array(mi.Float, blocks)
        self.nbytes = 4 * dr.width(self.buffer)
        dr.eval(self.buffer)

    def weights(self, normal: mi.Vector3f) -> CosineTableWeights:
        """The walk's weight provider for the tables of these grid-frame normals' bins."""
        return CosineTableWeights(self, normal_bin(self.pyramid.world_from_grid(normal)) * BLOCKS_PER_TABLE)

    def sample(self, normal: mi.Vector3f, u: mi.Point2f):
        """Warp ``u`` in [0,1)^2 to a world direction; returns (direction, pdf)."""
        cell, t, prob, valid, _ = walk_sample_absolute(self.weights(normal), TABLE_DEPTH, u)
        return finish_sample(self.pyramid, cell, t, prob, valid)

    def pdf(self, normal: mi.Vector3f, d: mi.Vector3f) -> mi.Float:
        """Density (per steradian) with which :meth:`sample` produces world direction ``d``."""
        z, phi = grid_coordinates(self.pyramid.grid_from_world(d))
        cell, prob, _ = walk_pdf_absolute(self.weights(normal), TABLE_DEPTH, z, phi)
        return finish_pdf(self.pyramid, cell, prob, z, phi)
