"""Specification of EnvPyramid: envmap luminance integrated over equal-area cells.

Reference values come from the ``envmap`` emitter's own ``eval``, integrated by
an independent quadrature: each grid cell is cut at the texel rows/columns
(where the bilinear radiance has kinks) and every piece is integrated with
Gauss-Legendre rules in (theta, phi), d omega = sin(theta) dtheta dphi. The
directions are built here from the ARCHITECTURE.md grid-frame formula, not by
the code under test.
"""

from __future__ import annotations

import gc
import glob
import os
import warnings
import weakref

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

mi.set_variant("llvm_ad_rgb")

from mitsuba_shsampling.grid import Cell, cell_index, grid_coordinates, grid_direction  # noqa: E402
from mitsuba_shsampling.envmap import DEFAULT_MAX_DEPTH, EnvPyramid, auto_depth  # noqa: E402
from mitsuba_shsampling.envmap import pyramid as pyramid_module  # noqa: E402
from mitsuba_shsampling.envmap.pyramid import (  # noqa: E402
    DIM_TOTAL, LEVEL_TOLERANCE, SUBTEXEL_LEVELS, TRIM_FLOOR_DEPTH, _corner_radiance, coarse_leaf_excess, leaf_records)
from mitsuba_shsampling.envmap.synthetic import (  # noqa: E402
    constant_latlong, envmap_emitter, sun_sky_latlong, window_latlong)
from mitsuba_shsampling.warp.env_leaves import finish_pdf  # noqa: E402

from conftest import ENVMAPS_DIR

ENVMAP_DIR = str(ENVMAPS_DIR)
TILTED_30DEG = mi.ScalarAffineTransform4f().rotate(
    (np.array([0.3, 0.8, -0.52]) / np.linalg.norm([0.3, 0.8, -0.52])).tolist(), 30.0)


def random_latlong(height: int, width: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.uniform(0.0, 2.0, size=(height, width, 3)).astype(np.float32)


def eval_luminance(emitter: mi.Emitter, world_dirs: np.ndarray) -> np.ndarray:
    """Emitter luminance seen along world directions (N, 3), float64."""
    si = dr.zeros(mi.SurfaceInteraction3f, len(world_dirs))
    si.wi = -mi.Vector3f(world_dirs.T.astype(np.float32))
    return mi.luminance(emitter.eval(si)).numpy().astype(np.float64)


def world_from_grid_reference(grid_dirs: np.ndarray, to_world) -> np.ndarray:
    """Grid frame -> envmap local (+Y up) -> world, per ARCHITECTURE.md."""
    x, y, z = grid_dirs[:, 0], grid_dirs[:, 1], grid_dirs[:, 2]
    local = np.stack([-y, z, -x], axis=1)
    matrix = np.eye(4) if to_world is None else np.array(to_world.matrix, dtype=np.float64).reshape(4, 4)
    return local @ matrix[:3, :3].T


def reference_cell_integral(emitter, to_world, texels_hw, z0, z1, phi0, phi1,
                            theta_nodes: int = 6, phi_nodes: int = 3) -> float:
    """Integral of the emitter's luminance over grid cell [z0,z1] x [phi0,phi1]."""
    height, width = texels_hw
    theta_lo, theta_hi = np.arccos(z1), np.arccos(z0)
    theta_breaks = np.arange(height) * np.pi / max(height - 1, 1)
    theta_edges = np.unique(np.concatenate(
        [[theta_lo, theta_hi], theta_breaks[(theta_breaks > theta_lo) & (theta_breaks < theta_hi)]]))
    # Texel columns sit at u = (x + 0.5)/W, i.e. grid phi = 2 pi (1 - u).
    phi_breaks = 2 * np.pi * (1 - (np.arange(width) + 0.5) / width)
    phi_edges = np.unique(np.concatenate(
        [[phi0, phi1], phi_breaks[(phi_breaks > phi0) & (phi_breaks < phi1)]]))

    gt, wt = np.polynomial.legendre.leggauss(theta_nodes)
    gp, wp = np.polynomial.legendre.leggauss(phi_nodes)
    t_mid, t_half = 0.5 * (theta_edges[1:] + theta_edges[:-1]), 0.5 * np.diff(theta_edges)
    p_mid, p_half = 0.5 * (phi_edges[1:] + phi_edges[:-1]), 0.5 * np.diff(phi_edges)
    theta = (t_mid[:, None] + t_half[:, None] * gt[None, :]).ravel()
    w_theta = (t_half[:, None] * wt[None, :]).ravel() * np.sin(theta)
    phi = (p_mid[:, None] + p_half[:, None] * gp[None, :]).ravel()
    w_phi = (p_half[:, None] * wp[None, :]).ravel()

    th, ph = np.meshgrid(theta, phi, indexing="ij")
    grid = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1).reshape(-1, 3)
    values = eval_luminance(emitter, world_from_grid_reference(grid, to_world))
    return float(values @ np.outer(w_theta, w_phi).ravel())


def cell_bounds(level: int, iz: int, iphi: int):
    cells = 1 << level
    return (-1 + 2 * iz / cells, -1 + 2 * (iz + 1) / cells,
            2 * np.pi * iphi / cells, 2 * np.pi * (iphi + 1) / cells)


MAPS = {
    "random_32x64": dict(image=random_latlong(32, 64), scale=1.0, to_world=None),
    "sun_sky_32x64_rotated": dict(image=sun_sky_latlong(32, 64), scale=0.5, to_world=TILTED_30DEG),
    "odd_7x13_rotated": dict(image=random_latlong(7, 13, seed=3), scale=2.0, to_world=TILTED_30DEG),
}


@pytest.fixture(scope="module", params=sorted(MAPS))
def case(request):
    spec = MAPS[request.param]
    emitter = envmap_emitter(spec["image"], spec["scale"], spec["to_world"])
    return dict(spec, name=request.param, emitter=emitter, pyramid=EnvPyramid(emitter))


# ------------------------------------------------------------- integrals


def test_total_equals_sphere_integral_of_emitter_luminance(case):
    reference = reference_cell_integral(case["emitter"], case["to_world"], case["image"].shape[:2],
                                        -1.0, 1.0, 0.0, 2 * np.pi)
    # float32 radiance in eval and in the stored root: ~1e-6 relative.
    assert case["pyramid"].total == pytest.approx(reference, rel=1e-5)
    assert case["pyramid"].level_numpy(0)[0, 0] == pytest.approx(reference, rel=1e-5)


def test_total_agrees_with_brute_force_midpoint_quadrature():
    """A check that does not use the texel layout at all (looser tolerance)."""
    image = random_latlong(32, 64, seed=7)
    emitter = envmap_emitter(image, 1.0, TILTED_30DEG)
    n = 1024
    z = -1 + (np.arange(n) + 0.5) * 2 / n
    phi = (np.arange(2 * n) + 0.5) * np.pi / n
    zz, pp = np.meshgrid(z, phi, indexing="ij")
    s = np.sqrt(1 - zz ** 2)
    grid = np.stack([s * np.cos(pp), s * np.sin(pp), zz], -1).reshape(-1, 3)
    values = eval_luminance(emitter, world_from_grid_reference(grid, TILTED_30DEG))
    reference = values.sum() * (2 / n) * (np.pi / n)
    assert EnvPyramid(emitter).total == pytest.approx(reference, rel=2e-4)


def test_constant_map_integrates_to_four_pi_radiance():
    pyramid = EnvPyramid(envmap_emitter(constant_latlong(16, 32, 3.0), scale=2.0))
    assert pyramid.total == pytest.approx(4 * np.pi * 6.0, rel=1e-12)
    finest = pyramid.level_numpy(pyramid.depth)
    np.testing.assert_allclose(finest, 6.0 * 4 * np.pi / finest.size, rtol=1e-6)


def test_a_constant_map_stays_uncompensated_whatever_its_cells_rounding():
    """Compensation would leave a constant map black: its cells differ from their mean by
    rounding alone, and that residue is not taken for a target."""
    for height, width in ((16, 32), (64, 128), (256, 512)):
        pyramid = EnvPyramid(envmap_emitter(constant_latlong(height, width, 0.7)), mis_compensation=True)
        assert not pyramid.mis_compensation
        assert pyramid.total == pytest.approx(4 * np.pi * 0.7, rel=1e-7)  # 0.7 as float32


def test_cells_match_emitter_integral_over_cell_including_poles_and_seam(case):
    pyramid, emitter = case["pyramid"], case["emitter"]
    rng = np.random.default_rng(1)
    for level in sorted({1, 3, pyramid.depth}):
        last = (1 << level) - 1
        cells = [(0, 0), (last, last), (0, last), (last, 0), (last // 2, 0), (last // 2, last)]
        cells += [tuple(c) for c in rng.integers(0, last + 1, size=(6, 2))]
        values = pyramid.level_numpy(level)
        for iz, iphi in cells:
            reference = reference_cell_integral(emitter, case["to_world"], case["image"].shape[:2],
                                                *cell_bounds(level, iz, iphi))
            assert values[iz, iphi] == pytest.approx(reference, rel=2e-5, abs=1e-7 * pyramid.total), \
                (case["name"], level, iz, iphi)


def test_sun_smaller_than_a_cell_keeps_its_full_power():
    """A one-texel sun in a 256x512 map inside one coarse cell is not lost or blurred away."""
    image = sun_sky_latlong(256, 512, sun_radius_deg=0.1, sun_radiance=1e6, sky_radiance=0.0)
    emitter = envmap_emitter(image)
    pyramid = EnvPyramid(emitter, max_depth=6)
    sun = np.array([0.3, 0.8, -0.5]) / np.linalg.norm([0.3, 0.8, -0.5])
    grid_sun = np.array([-sun[2], -sun[0], sun[1]])
    z, phi = grid_sun[2], np.arctan2(grid_sun[1], grid_sun[0]) % (2 * np.pi)
    iz, iphi = int((z + 1) / 2 * 64), int(phi / (2 * np.pi) * 64)
    reference = reference_cell_integral(emitter, None, (256, 512), *cell_bounds(6, iz, iphi))
    finest = pyramid.level_numpy(6)
    assert finest[iz, iphi] == pytest.approx(reference, rel=2e-5)
    assert finest[iz, iphi] > 0.5 * pyramid.total


# ------------------------------------------------------------- layout


def test_parent_equals_sum_of_children_at_every_level(case):
    pyramid = case["pyramid"]
    for k in range(pyramid.depth):
        parent, child = pyramid.level_numpy(k), pyramid.level_numpy(k + 1)
        m = parent.shape[0]
        sums = child.astype(np.float64).reshape(m, 2, m, 2).sum(axis=(1, 3))
        np.testing.assert_allclose(parent, sums, rtol=1e-6, atol=1e-9 * pyramid.total)


def test_children_gather_returns_the_four_children_in_ab_order(case):
    pyramid = case["pyramid"]
    rng = np.random.default_rng(2)
    for level in range(pyramid.depth):
        iz, iphi = rng.integers(0, 1 << level, size=(2, 16))
        child = pyramid.level_numpy(level + 1)
        expected = np.stack([child[2 * iz + a, 2 * iphi + b] for a in (0, 1) for b in (0, 1)])
        for level_arg in (level, mi.UInt32(level)):
            got = np.array(pyramid.children(level_arg, mi.UInt32(iz), mi.UInt32(iphi)))
            np.testing.assert_array_equal(got, expected)


def test_a_cells_four_children_and_a_leaf_record_are_read_in_one_packet_gather(case):
    """Dr.Jit reads adjacent values as one packet only from memory it maps at a 64-byte
    aligned address; the pyramid's arrays once mapped numpy's, 16 bytes past a page, so
    every children gather was four scalar gathers (a tenth of the product sample's time)."""
    from mitsuba_shsampling.device_arrays import PACKET_ALIGNMENT, device_array

    pyramid = case["pyramid"]
    for level in (1, pyramid.depth - 1):  # a block of the upper levels, then a leaf record
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        try:
            dr.kernel_history()
            dr.eval(pyramid.children(level, dr.arange(mi.UInt32, 2), dr.arange(mi.UInt32, 2)))
            (kernel,) = [k for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT]
        finally:
            dr.set_flag(dr.JitFlag.KernelHistory, False)
        ir = kernel["ir"].getvalue()
        assert "gather_4xf32" in ir and "masked.gather.v" not in ir.replace("gather_4xf32", "")
    # The bits are kept: the records hold uint32 words in float32 slots.
    words = np.array([1, 0x7FC00001, 0x80000000, 0x007FFFFF], dtype=np.uint32)
    np.testing.assert_array_equal(np.array(device_array(mi.Float, words.view(np.float32))).view(np.uint32), words)
    assert PACKET_ALIGNMENT == 64


def test_cell_integral_gathers_level_values_for_python_and_traced_levels(case):
    pyramid = case["pyramid"]
    rng = np.random.default_rng(4)
    levels = rng.integers(0, pyramid.depth + 1, size=64)
    iz = np.array([rng.integers(0, 1 << k) for k in levels])
    iphi = np.array([rng.integers(0, 1 << k) for k in levels])
    expected = np.array([pyramid.level_numpy(k)[a, b] for k, a, b in zip(levels, iz, iphi)])
    got = pyramid.cell_integral(mi.UInt32(levels), mi.UInt32(iz), mi.UInt32(iphi)).numpy()
    np.testing.assert_array_equal(got, expected)
    assert pyramid.cell_integral(0, mi.UInt32(0), mi.UInt32(0)).numpy()[0] == np.float32(pyramid.total)


def test_children_works_with_traced_level_inside_symbolic_loop(case):
    """Greedy descent to the brightest leaf, in a dr.while_loop, matches numpy."""
    pyramid = case["pyramid"]

    def cond(level, iz, iphi):
        return level < pyramid.depth

    def body(level, iz, iphi):
        c = pyramid.children(level, iz, iphi)
        upper_z = dr.maximum(c.z, c.w) > dr.maximum(c.x, c.y)
        upper_phi = dr.select(upper_z, c.w > c.z, c.y > c.x)
        iz = 2 * iz + dr.select(upper_z, 1, 0)
        iphi = 2 * iphi + dr.select(upper_phi, 1, 0)
        return level + 1, mi.UInt32(iz), mi.UInt32(iphi)

    with dr.scoped_set_flag(dr.JitFlag.SymbolicLoops, True):
        _, iz, iphi = dr.while_loop((mi.UInt32(0), mi.UInt32(0), mi.UInt32(0)), cond, body)

    ref_iz = ref_iphi = 0
    for k in range(pyramid.depth):
        c = pyramid.level_numpy(k + 1)[2 * ref_iz:2 * ref_iz + 2, 2 * ref_iphi:2 * ref_iphi + 2]
        a = int(max(c[1]) > max(c[0]))
        ref_iz, ref_iphi = 2 * ref_iz + a, 2 * ref_iphi + int(c[a, 1] > c[a, 0])
    assert (iz.numpy()[0], iphi.numpy()[0]) == (ref_iz, ref_iphi)


def test_leaf_corners_are_the_emitter_luminance_at_the_corners_to_a_byte_of_the_largest():
    """The leaf records keep each leaf's corner values as bytes in units of the largest
    of the four; the bilinear placement only uses their ratios (plus a floor)."""
    image = sun_sky_latlong(32, 64)
    emitter = envmap_emitter(image, 1.0, TILTED_30DEG)
    pyramid = EnvPyramid(emitter, max_depth=6)
    rng = np.random.default_rng(7)
    n = 1 << pyramid.depth
    iz, iphi = rng.integers(0, n, size=(2, 256))
    got = np.stack([v.numpy() for v in pyramid.leaf_corners(Cell(pyramid.depth, mi.UInt32(iz), mi.UInt32(iphi)))])
    # leaf_corners adds a fortieth of the four values' sum to each: take it off again.
    stored = got - 0.025 * got.sum(axis=0) / 1.1
    corner_z = [iz, iz, iz + 1, iz + 1]
    corner_phi = [iphi, iphi + 1, iphi, iphi + 1]
    z = -1.0 + 2.0 * np.stack(corner_z) / n
    phi = 2 * np.pi * np.stack(corner_phi) / n
    s = np.sqrt(np.maximum(1.0 - z * z, 0.0))
    grid = np.stack([s * np.cos(phi), s * np.sin(phi), z], axis=-1).reshape(-1, 3)
    expected = eval_luminance(emitter, world_from_grid_reference(grid, TILTED_30DEG)).reshape(4, -1)
    np.testing.assert_allclose(stored / stored.max(axis=0), expected / expected.max(axis=0), atol=1.0 / 255 + 1e-3)


def test_leaf_records_keep_the_shape_of_denormal_and_huge_corners_and_zero_for_black_leaves():
    corners = np.zeros((5, 5), dtype=np.float32)
    corners[1, 1] = 1e-42    # denormal: the largest corner of the leaves around it
    corners[3, 3] = 3e38     # near float32's largest
    corners[3, 4] = 1.5e38
    words = leaf_records(np.zeros((4, 4), dtype=np.float32), corners)[..., 4:].view(np.uint32)
    leaf_word = {(2 * i + a, 2 * j + b): int(words[i, j, 2 * a + b]) for i in range(2) for j in range(2)
                 for a in range(2) for b in range(2)}
    # Corners (z0 phi0, z0 phi1, z1 phi0, z1 phi1) are the bytes from the lowest up.
    assert leaf_word[(0, 0)] == 255 << 24 and leaf_word[(1, 1)] == 255
    assert leaf_word[(2, 3)] == (128 << 24) | (255 << 16) and leaf_word[(3, 3)] == (128 << 8) | 255
    assert leaf_word[(3, 0)] == 0   # a black leaf: its placement is uniform


# ------------------------------------------------------------- frames


def random_directions(n: int, seed: int = 0) -> np.ndarray:
    d = np.random.default_rng(seed).normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def test_grid_from_world_and_world_from_grid_are_inverse():
    pyramid = EnvPyramid.from_latlong(random_latlong(8, 16), to_world=TILTED_30DEG)
    d = mi.Vector3f(random_directions(1000).T.astype(np.float32))
    there_and_back = pyramid.world_from_grid(pyramid.grid_from_world(d))
    np.testing.assert_allclose(np.array(there_and_back), np.array(d), atol=2e-6)
    back_and_there = pyramid.grid_from_world(pyramid.world_from_grid(d))
    np.testing.assert_allclose(np.array(back_and_there), np.array(d), atol=2e-6)


def test_grid_frame_is_right_handed_and_z_is_local_up():
    pyramid = EnvPyramid.from_latlong(random_latlong(8, 16))
    ex, ey, ez = (np.array(pyramid.world_from_grid(mi.Vector3f(*map(float, e)))).ravel() for e in np.eye(3))
    np.testing.assert_allclose(np.cross(ex, ey), ez, atol=1e-7)
    np.testing.assert_allclose(ez, [0, 1, 0], atol=1e-7)


def test_grid_phi_is_two_pi_one_minus_u_and_z_is_cos_theta_of_the_emitter():
    """Encode u and v in the texels (linear in u and theta, so bilinear lookup is
    exact away from the seam) and read them back through the emitter's eval."""
    height, width = 64, 128
    image = np.zeros((height, width, 3), np.float32)
    image[..., 0] = ((np.arange(width) + 0.5) / width)[None, :]
    image[..., 1] = (np.arange(height) / (height - 1))[:, None]
    emitter = envmap_emitter(image, 1.0, TILTED_30DEG)
    pyramid = EnvPyramid(emitter)

    world = random_directions(4000, seed=5)
    si = dr.zeros(mi.SurfaceInteraction3f, len(world))
    si.wi = -mi.Vector3f(world.T.astype(np.float32))
    rgb = np.array(emitter.eval(si))
    u, v = rgb[0], rgb[1]

    z, phi = grid_coordinates(pyramid.grid_from_world(mi.Vector3f(world.T.astype(np.float32))))
    z, phi = z.numpy(), phi.numpy()
    # Between the last and the first texel column the encoded u wraps from ~1 to ~0.
    seam_distance = np.minimum(phi, 2 * np.pi - phi) / (2 * np.pi)
    off_seam = seam_distance > 0.5 / width + 1e-4
    np.testing.assert_allclose(z, np.cos(np.pi * v), atol=2e-5)
    wrapped = (phi - 2 * np.pi * (1 - u) + np.pi) % (2 * np.pi) - np.pi
    np.testing.assert_allclose(wrapped[off_seam], 0, atol=2e-5)
    assert off_seam.mean() > 0.95


def test_grid_coords_handle_poles_and_seam():
    d = mi.Vector3f([0, 0, 1, 1, 1, 0.6], [0, 0, -1e-9, 1e-9, 0, 0], [1, -1, 0, 0, 0, 0.8])
    z, phi = grid_coordinates(d)
    phi = phi.numpy()
    assert np.all((phi >= 0) & (phi <= 2 * np.pi))
    np.testing.assert_allclose(z.numpy(), [1, -1, 0, 0, 0, 0.8])
    np.testing.assert_allclose(phi[[0, 1, 3, 4, 5]], 0, atol=1e-6)
    assert phi[2] == 0 or phi[2] > 2 * np.pi - 1e-6
    pyramid = EnvPyramid.from_latlong(random_latlong(8, 16))
    iz, iphi = cell_index(pyramid.depth, z, mi.Float(phi))
    cells = 1 << pyramid.depth
    assert np.all(iz.numpy() < cells) and np.all(iphi.numpy() < cells)
    assert iz.numpy()[0] == cells - 1 and iz.numpy()[1] == 0


def test_cell_index_inverts_cell_bounds():
    level = 4
    iz, iphi = np.meshgrid(np.arange(16), np.arange(16), indexing="ij")
    z = -1 + (iz.ravel() + 0.5) * 2 / 16
    phi = (iphi.ravel() + 0.5) * 2 * np.pi / 16
    d = grid_direction(mi.Float(z), mi.Float(phi))
    got_iz, got_iphi = cell_index(level, *grid_coordinates(d))
    np.testing.assert_array_equal(got_iz.numpy(), iz.ravel())
    np.testing.assert_array_equal(got_iphi.numpy(), iphi.ravel())


# ------------------------------------------------------------- construction & bad input


def test_from_latlong_equals_pyramid_of_the_emitter():
    image = sun_sky_latlong(16, 32)
    a = EnvPyramid(envmap_emitter(image, 0.7, TILTED_30DEG))
    b = EnvPyramid.from_latlong(image, scale=0.7, to_world=TILTED_30DEG)
    # The emitter's texels can differ from the image by an ulp (bitmap conversion).
    np.testing.assert_allclose(a.buffer.numpy(), b.buffer.numpy(), rtol=1e-6)
    assert a.depth == b.depth and a.total == pytest.approx(b.total, rel=1e-6)


def test_depth_resolves_the_texels_plus_subtexel_levels_and_is_capped():
    assert auto_depth(256, 512) == 9 + SUBTEXEL_LEVELS
    assert auto_depth(512, 1024) == min(10 + SUBTEXEL_LEVELS, DEFAULT_MAX_DEPTH)
    assert auto_depth(4096, 8192) == DEFAULT_MAX_DEPTH == 11
    assert auto_depth(1, 1) == 1 + SUBTEXEL_LEVELS
    assert auto_depth(32, 64, max_depth=4) == 4
    pyramid = EnvPyramid(envmap_emitter(random_latlong(32, 64)), max_depth=3)
    assert pyramid.depth == 3
    # Levels 0..2 in 4-float blocks; level 3 in one 8-float record per level-2 cell.
    assert pyramid.buffer.numpy().nbytes == 4 * 4 * (1 + (4 ** 2 - 1) // 3)
    assert pyramid.records.numpy().nbytes == 4 * 8 * 4 ** 2
    assert pyramid.nbytes == pyramid.buffer.numpy().nbytes + pyramid.records.numpy().nbytes
    assert pyramid.build_time_s >= 0
    with pytest.raises(ValueError):
        EnvPyramid(envmap_emitter(random_latlong(4, 8)), max_depth=0)


def test_a_finest_level_that_does_not_pay_is_dropped_and_a_subtexel_sun_keeps_it():
    """1024 x 512 maps (built to depth 11): a smooth window light loses its finer levels down
    to the trimming floor; a half-degree sun keeps the level finer than its texels."""
    smooth = EnvPyramid(envmap_emitter(window_latlong(512, 1024)))
    assert (smooth.depth, smooth.trimmed_levels) == (TRIM_FLOOR_DEPTH, DEFAULT_MAX_DEPTH - TRIM_FLOOR_DEPTH)
    assert smooth.nbytes < 3 * 2**20
    sun = EnvPyramid(envmap_emitter(sun_sky_latlong(512, 1024, sun_radius_deg=0.5)), mis_compensation=True)
    assert (sun.depth, sun.trimmed_levels) == (DEFAULT_MAX_DEPTH, 0)
    assert EnvPyramid(envmap_emitter(window_latlong(512, 1024)), level_tolerance=0).depth == DEFAULT_MAX_DEPTH
    assert "trimmed_levels=2" in repr(smooth)


def test_a_trimmed_pyramid_is_the_pyramid_built_at_its_depth():
    """Dropping levels sums the finer cells and keeps every other corner: the same cell
    integrals (to float rounding) and the same corner bytes as building at that depth."""
    emitter = envmap_emitter(window_latlong(512, 1024))
    trimmed = EnvPyramid(emitter)
    built = EnvPyramid(emitter, max_depth=trimmed.depth, level_tolerance=0)
    assert trimmed.depth == built.depth < DEFAULT_MAX_DEPTH
    assert trimmed.total == pytest.approx(built.total, rel=1e-6)
    np.testing.assert_allclose(trimmed.buffer.numpy(), built.buffer.numpy(), rtol=1e-5, atol=1e-9 * built.total)
    records = [p.records.numpy().reshape(-1, 8) for p in (trimmed, built)]
    np.testing.assert_allclose(records[0][:, :4], records[1][:, :4], rtol=1e-5, atol=1e-9 * built.total)
    assert np.array_equal(records[0][:, 4:].view(np.uint32), records[1][:, 4:].view(np.uint32))


def test_coarse_leaf_excess_is_the_second_moment_the_coarse_walk_adds_on_the_finest_cells():
    """Against the sampler itself: the probability the depth-5 walk and bilinear leaves give each
    depth-7 cell, integrated from their pdf (:func:`finish_pdf`), in sum t^2 / q - 1."""
    image = random_latlong(16, 32, seed=3)
    image[5, 11] = 400.0  # a one-texel sun, so that the leaves' slopes matter
    fine = EnvPyramid.from_latlong(image, max_depth=7, level_tolerance=0)
    coarse = EnvPyramid.from_latlong(image, max_depth=5, level_tolerance=0)
    finest = fine.level_numpy(7).astype(np.float64)
    luminance = image @ np.array([0.212671, 0.715160, 0.072169])
    corners = _corner_radiance(luminance.astype(np.float32), 128).numpy().reshape(129, 129)
    predicted = coarse_leaf_excess(finest, corners, 5)

    points = 6  # midpoint rule inside each fine cell (the pdf is bilinear there, up to the grid's z)
    n = 128 * points
    z = -1 + (np.arange(n) + 0.5) * 2 / n
    phi = (np.arange(n) + 0.5) * 2 * np.pi / n
    zz, pp = np.meshgrid(z, phi, indexing="ij")
    root = Cell(0, mi.UInt32(0), mi.UInt32(0))
    pdf = finish_pdf(coarse, root, mi.Float(1.0), mi.Float(zz.ravel()), mi.Float(pp.ravel())).numpy()
    q = pdf.reshape(128, points, 128, points).mean(axis=(1, 3)) * (4 * np.pi / 128**2)
    assert q.sum() == pytest.approx(1.0, rel=1e-3)
    t = finest / finest.sum()
    brute = float(np.sum(t * t / q)) - 1
    assert predicted > 10 * LEVEL_TOLERANCE  # the sun's slopes inside a texel: the level pays here
    assert predicted == pytest.approx(brute, rel=0.02)
    assert coarse_leaf_excess(finest, corners, 7) == 0.0  # the finest level against itself


def test_coarse_leaf_excess_is_zero_for_a_constant_map_and_black_map():
    finest = np.full((64, 64), 3.0)
    assert abs(coarse_leaf_excess(finest, np.full((65, 65), 1.0), 4)) < 1e-12
    assert coarse_leaf_excess(np.zeros((64, 64)), np.zeros((65, 65)), 4) == 0.0


def test_the_leaf_records_are_the_children_then_the_corners_packed_as_bytes_of_their_largest():
    """Against the layout written out on the host: record (I, J) holds level D's four children
    of cell (I, J), then per child a little-endian word of its four corners (z0 phi0, z0 phi1,
    z1 phi0, z1 phi1), each round(255 value / largest of the four), ties to even; a black leaf
    packs zeros."""
    rng = np.random.default_rng(8)
    n = 64
    corners = (rng.random((n + 1, n + 1)) * (rng.random((n + 1, n + 1)) > 0.2)).astype(np.float32)
    corners[10:14, 20:24] = 0.0                       # black leaves
    corners[30, 30:34] = np.float32(0.5 / 255)        # exact halves: ties round to even
    corners[31, 30:34] = np.float32(1.0)
    blocks = rng.random((n * n // 4, 4)).astype(np.float32)
    records = leaf_records(blocks, corners)
    leaf = [corners[:-1, :-1], corners[:-1, 1:], corners[1:, :-1], corners[1:, 1:]]
    largest = np.maximum(np.maximum(leaf[0], leaf[1]), np.maximum(leaf[2], leaf[3]))
    largest[largest == 0] = 1.0
    words = np.zeros((n, n), dtype=np.uint32)
    for k, value in enumerate(leaf):
        words |= np.rint(value / largest * np.float32(255)).astype(np.uint32) << np.uint32(8 * k)
    expected = words.reshape(n // 2, 2, n // 2, 2).transpose(0, 2, 1, 3).reshape(n // 2, n // 2, 4)
    assert np.array_equal(records[..., 4:].view(np.uint32), expected)
    assert np.array_equal(records[..., :4], blocks.reshape(n // 2, n // 2, 4))


def test_coarse_leaf_excess_matches_a_float64_numpy_reference_at_every_level():
    """The kernel against the formula written out on the host: leaf shares, the corner floor
    and the bilinear sub-cell masses, sum t^2 / q - 1."""
    image = random_latlong(16, 32, seed=6)
    image[9, 20] = 250.0
    luminance = (image @ np.array([0.212671, 0.715160, 0.072169])).astype(np.float32)
    finest = EnvPyramid.from_latlong(image, max_depth=7, level_tolerance=0).level_numpy(7).astype(np.float64)
    corners = _corner_radiance(luminance, 128).numpy().reshape(129, 129).astype(np.float64)
    t = finest / finest.sum()
    for level in (6, 5, 3):
        parts, m = 128 >> level, 1 << level
        c = corners[::parts, ::parts]
        v = [c[:-1, :-1], c[:-1, 1:], c[1:, :-1], c[1:, 1:]]
        v = [x + 0.025 * sum(v) for x in v]
        leaf = t.reshape(m, parts, m, parts).sum(axis=(1, 3))
        v = [x * leaf / (0.25 * sum(v)) for x in v]
        edges = np.linspace(0, 1, parts + 1)
        high = 0.5 * np.diff(edges ** 2)
        low = np.diff(edges) - high
        q = (low[None, :, None, None] * (v[0][:, None, :, None] * low + v[1][:, None, :, None] * high)
             + high[None, :, None, None] * (v[2][:, None, :, None] * low + v[3][:, None, :, None] * high))
        reference = float(np.sum(t.reshape(m, parts, m, parts) ** 2 / q)) - 1.0
        assert coarse_leaf_excess(finest, corners, level) == pytest.approx(reference, rel=1e-9)


def test_the_compensated_and_plain_pyramids_of_a_map_share_its_finest_level_and_keep_nothing():
    """The integrators build both pyramids of a map, one after the other, inside
    ``finest_level_kept``: the second takes the first's finest level. Outside it, a level is
    shared only while something holds it, and once nothing does, it is freed."""
    luminance = random_latlong(8, 16, seed=6) @ np.array([0.212671, 0.715160, 0.072169])
    luminance = luminance.astype(np.float32)
    first = pyramid_module._target_at_finest_level(luminance, 1.0, 6)
    assert pyramid_module._target_at_finest_level(luminance, 1.0, 6) is first
    assert pyramid_module._target_at_finest_level(luminance, 2.0, 6) is not first  # another scale
    alive = weakref.ref(first)
    del first
    gc.collect()
    assert alive() is None

    with pyramid_module.finest_level_kept():
        alive = weakref.ref(pyramid_module._target_at_finest_level(luminance, 1.0, 6))
        gc.collect()
        assert alive() is not None and pyramid_module._target_at_finest_level(luminance, 1.0, 6) is alive()
    gc.collect()
    assert alive() is None


def test_a_new_map_of_the_same_resolution_builds_its_pyramid_with_the_kernels_compiled_for_the_last():
    """Every figure of a map (its total, its mean for the compensation) reaches the kernels as an
    opaque value: as a literal it made the level test's and the compensation's kernels new to
    Dr.Jit's kernel cache for every map a user tries. 256 x 128 texels: depth 10, so the finest
    level is tested (``trimmed_depth``)."""
    image = random_latlong(128, 256, seed=11)
    image[40:44, 100:104] *= 400.0  # a small bright patch, so that the compensation subtracts something

    def kernels(texels):
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        try:
            dr.kernel_history()
            for compensated in (True, False):
                EnvPyramid.from_latlong(texels, mis_compensation=compensated)
            return {k["hash"] for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT}
        finally:
            dr.set_flag(dr.JitFlag.KernelHistory, False)

    first = kernels(image)
    other = kernels(np.roll(image * 0.37, 64, axis=1))
    assert len(first) > 5
    assert other <= first


@pytest.mark.parametrize("tolerance", [-1e-3, float("nan"), float("inf"), True, "0.1"])
def test_a_bad_level_tolerance_is_a_value_error_before_the_emitter_is_touched(tolerance):
    with pytest.raises(ValueError, match="level_tolerance"):
        EnvPyramid.from_latlong(random_latlong(8, 16), level_tolerance=tolerance)
    image = random_latlong(8, 16)
    image[2, 3] = np.nan
    emitter = envmap_emitter(image)
    with pytest.raises(ValueError, match="level_tolerance"):
        EnvPyramid(emitter, level_tolerance=tolerance)
    assert np.isnan(mi.traverse(emitter)["data"].numpy()).any()  # not sanitised by a failed build


def test_nan_inf_and_negative_texels_count_as_zero_with_one_warning():
    image = random_latlong(16, 32, seed=9)
    bad = image.copy()
    bad[3, 4] = np.nan
    bad[5, 0] = np.inf
    bad[0, 31] = -2.0
    bad[15, 7, 1] = -np.inf
    clean = image.copy()
    clean[3, 4] = clean[5, 0] = clean[0, 31] = clean[15, 7] = 0
    with pytest.warns(RuntimeWarning, match=r"\b4 envmap texel") as record:
        pyramid = EnvPyramid(envmap_emitter(bad))
    assert len(record) == 1
    expected = EnvPyramid(envmap_emitter(clean))
    np.testing.assert_array_equal(pyramid.buffer.numpy(), expected.buffer.numpy())
    assert np.isfinite(pyramid.total) and pyramid.total > 0


def test_all_zero_map_gives_black_pyramid():
    pyramid = EnvPyramid(envmap_emitter(np.zeros((16, 32, 3), np.float32)))
    assert pyramid.is_black and pyramid.total == 0.0
    assert not np.any(pyramid.buffer.numpy())
    assert not EnvPyramid(envmap_emitter(random_latlong(4, 8))).is_black


def test_a_map_too_dim_for_float32_cell_integrals_is_black_with_a_warning_and_a_dim_one_is_not():
    with pytest.warns(RuntimeWarning, match=r"below 1e-20"):
        too_dim = EnvPyramid(envmap_emitter(random_latlong(16, 32) * np.float32(1e-36)))
    assert too_dim.is_black and 0.0 < too_dim.total < DIM_TOTAL
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        dim = EnvPyramid(envmap_emitter(random_latlong(16, 32) * np.float32(1e-12)))
    assert not dim.is_black


def test_one_texel_map_is_constant_radiance():
    image = np.full((1, 1, 3), [1.0, 2.0, 3.0], np.float32)
    luminance = float(image[0, 0] @ [0.212671, 0.715160, 0.072169])
    from_image = EnvPyramid.from_latlong(image)
    from_emitter = EnvPyramid(envmap_emitter(image))
    for pyramid in (from_image, from_emitter):
        assert pyramid.total == pytest.approx(4 * np.pi * luminance, rel=1e-6)
        finest = pyramid.level_numpy(pyramid.depth)
        np.testing.assert_allclose(finest, finest.flat[0], rtol=1e-6)


def test_luminance_only_image_is_accepted():
    image = random_latlong(8, 16)
    luminance = image.astype(np.float64) @ [0.212671, 0.715160, 0.072169]
    a = EnvPyramid.from_latlong(image)
    b = EnvPyramid.from_latlong(luminance)
    np.testing.assert_allclose(a.buffer.numpy(), b.buffer.numpy(), rtol=1e-6)


def test_non_envmap_emitter_is_a_type_error():
    with pytest.raises(TypeError, match="envmap"):
        EnvPyramid(mi.load_dict({"type": "constant"}))
    with pytest.raises(TypeError, match="envmap"):
        EnvPyramid(mi.load_dict({"type": "diffuse"}))


def test_negative_scale_and_non_rotation_to_world_are_value_errors():
    with pytest.raises(ValueError, match="scale"):
        EnvPyramid.from_latlong(random_latlong(4, 8), scale=-1.0)
    with pytest.raises(ValueError, match="rotation"):
        EnvPyramid.from_latlong(random_latlong(4, 8), to_world=mi.ScalarAffineTransform4f().scale(2.0))


# ------------------------------------------------------------- real maps


def test_real_envmap_total_and_cells_match_emitter():
    path = sorted(glob.glob(os.path.join(ENVMAP_DIR, "*.hdr")))[0]
    emitter = mi.load_dict({"type": "envmap", "filename": path})
    pyramid = EnvPyramid(emitter, level_tolerance=0)
    height, width = mi.traverse(emitter)["data"].shape[:2]
    texels = (height, width - 2)
    assert pyramid.depth == auto_depth(*texels) and pyramid.trimmed_levels == 0
    reference = reference_cell_integral(emitter, None, texels, -1.0, 1.0, 0.0, 2 * np.pi,
                                        theta_nodes=2, phi_nodes=1)
    assert pyramid.total == pytest.approx(reference, rel=1e-4)
    rng = np.random.default_rng(6)
    finest = pyramid.level_numpy(pyramid.depth)
    for iz, iphi in rng.integers(0, 1 << pyramid.depth, size=(8, 2)):
        cell = reference_cell_integral(emitter, None, texels, *cell_bounds(pyramid.depth, iz, iphi))
        assert finest[iz, iphi] == pytest.approx(cell, rel=2e-5, abs=1e-7 * pyramid.total)
