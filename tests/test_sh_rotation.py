"""Rotation of SH coefficient vectors: g = rotate(f, R) satisfies g(d) = f(R^-1 d)."""

import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from scipy.special import sph_harm_y

mi.set_variant("llvm_ad_rgb")

from mitsuba_shsampling.sh.basis import sh_eval_sum  # noqa: E402
from mitsuba_shsampling.sh.rotation import (  # noqa: E402
    rotate, rotate_z, rotation_about_z, rotation_band_matrices, zyz_angles)
from mitsuba_shsampling.sh.zonal import (  # noqa: E402
    phong_attenuation, zonal_coefficients_z, zonal_to_sh)


def real_sh_float64(d: np.ndarray, n: int) -> np.ndarray:
    """Real SH (CS phase, z-up, index l(l+1)+m) from scipy's complex ones: (n^2, N)."""
    theta = np.arccos(np.clip(d[2], -1, 1))
    phi = np.arctan2(d[1], d[0])
    out = np.empty((n * n, d.shape[1]))
    for l in range(n):
        out[l * (l + 1)] = sph_harm_y(l, 0, theta, phi).real
        for m in range(1, l + 1):
            y = sph_harm_y(l, m, theta, phi)
            out[l * (l + 1) + m] = math.sqrt(2) * y.real
            out[l * (l + 1) - m] = math.sqrt(2) * y.imag
    return out


def random_directions(count: int, seed: int) -> np.ndarray:
    d = np.random.default_rng(seed).normal(size=(3, count))
    return d / np.linalg.norm(d, axis=0)


def to_matrix3f(r: np.ndarray) -> mi.Matrix3f:
    """(N, 3, 3) numpy rotations -> per-lane mi.Matrix3f."""
    return mi.Matrix3f(np.ascontiguousarray(np.transpose(r, (1, 2, 0))).astype(np.float32))


def lanes(coeffs) -> np.ndarray:
    """List of n^2 Dr.Jit Floats -> (n^2, lanes) numpy array (one kernel for all)."""
    dr.eval(coeffs)
    rows = [np.atleast_1d(np.asarray(c.numpy() if dr.is_array_v(c) else c)) for c in coeffs]
    width = max(row.size for row in rows)
    return np.stack([np.broadcast_to(row, (width,)) for row in rows])


N_BANDS = 20
ROTATIONS = Rotation.random(3, random_state=7).as_matrix()


@pytest.mark.parametrize("r", list(ROTATIONS))
def test_rotated_vector_at_d_equals_original_at_inverse_rotated_d_float64(r):
    f = np.random.default_rng(1).normal(size=N_BANDS**2)
    d = random_directions(2000, 2)
    g = rotate(f, r)
    original = f @ real_sh_float64(r.T @ d, N_BANDS)
    rotated = g @ real_sh_float64(d, N_BANDS)
    np.testing.assert_allclose(rotated, original, atol=1e-10 * np.max(np.abs(original)))


def test_rotated_vector_at_d_equals_original_at_inverse_rotated_d_in_a_dr_jit_kernel():
    r = ROTATIONS[0]
    f = np.random.default_rng(3).normal(size=N_BANDS**2)
    g = rotate([mi.Float(x) for x in f], r)  # shared matrix: float64 literals
    d = random_directions(4000, 4)
    rotated = sh_eval_sum(g, mi.Vector3f(d.astype(np.float32))).numpy()
    original = f @ real_sh_float64(r.T @ d, N_BANDS)
    np.testing.assert_allclose(rotated, original, atol=1e-4 * np.max(np.abs(original)))


def test_per_lane_rotations_match_the_float64_rotation_of_each_lane():
    n, count = N_BANDS, 64
    rng = np.random.default_rng(5)
    r = Rotation.random(count, random_state=9).as_matrix()
    # Gimbal configurations of the z-y-z split: beta = 0 and beta = pi.
    r[0] = np.eye(3)
    r[1] = rotation_about_z(2.0)
    r[2] = Rotation.from_euler("zyz", [0.4, math.pi, -1.1]).as_matrix()
    r[3] = np.diag([1.0, -1.0, -1.0])
    r[4] = Rotation.from_euler("zyz", [0.3, 1e-5, 0.5]).as_matrix()
    f = rng.normal(size=(n * n, count))
    g = lanes(rotate([mi.Float(row.astype(np.float32)) for row in f], to_matrix3f(r)))
    for lane in range(count):
        ref = rotate(f[:, lane], r[lane])
        np.testing.assert_allclose(g[:, lane], ref, atol=3e-5 * np.max(np.abs(ref)),
                                   err_msg=f"lane {lane}")


def test_zyz_angles_reassemble_the_rotation():
    r = Rotation.random(32, random_state=11).as_matrix()
    r[0] = np.diag([-1.0, -1.0, 1.0])
    alpha, beta, gamma = (a.numpy() for a in zyz_angles(to_matrix3f(r)))
    back = Rotation.from_euler("ZYZ", np.stack([alpha, beta, gamma], axis=1)).as_matrix()
    np.testing.assert_allclose(back, r, atol=1e-5)


def test_zonal_lobe_turned_to_r_ez_equals_the_rotated_z_aligned_lobe():
    lam = phong_attenuation(30.0, N_BANDS)
    r = ROTATIONS[1]
    turned = lanes(zonal_to_sh(lam, mi.Vector3f(*r[:, 2].tolist())))[:, 0]
    rotated = rotate(np.array(zonal_coefficients_z(lam)), r)
    np.testing.assert_allclose(turned, rotated, atol=1e-5 * np.max(np.abs(rotated)))


def test_z_rotation_agrees_with_the_general_rotation():
    f = np.random.default_rng(6).normal(size=N_BANDS**2)
    for angle in (0.3, -2.0, math.pi):
        np.testing.assert_allclose(rotate_z(f, angle), rotate(f, rotation_about_z(angle)),
                                   atol=1e-12)
    angles = np.array([0.3, -2.0, 5.0], dtype=np.float32)
    per_lane = lanes(rotate_z([mi.Float(x) for x in f], mi.Float(angles)))
    for lane, angle in enumerate(angles):
        np.testing.assert_allclose(per_lane[:, lane], rotate(f, rotation_about_z(float(angle))),
                                   atol=1e-5 * np.max(np.abs(f)))


def test_rotation_preserves_the_norm_of_every_band():
    f = np.random.default_rng(8).normal(size=N_BANDS**2)
    g = rotate(f, ROTATIONS[2])
    for l in range(N_BANDS):
        band = slice(l * l, (l + 1) ** 2)
        assert np.linalg.norm(g[band]) == pytest.approx(np.linalg.norm(f[band]), rel=1e-12)


def test_band_matrices_are_orthogonal_and_compose_like_the_rotations():
    a, b = ROTATIONS[0], ROTATIONS[1]
    for da, db, dab in zip(rotation_band_matrices(a, 10), rotation_band_matrices(b, 10),
                           rotation_band_matrices(a @ b, 10)):
        np.testing.assert_allclose(da @ da.T, np.eye(len(da)), atol=1e-12)
        np.testing.assert_allclose(da @ db, dab, atol=1e-12)


def test_rotation_keeps_numpy_batches_column_by_column():
    f = np.random.default_rng(10).normal(size=(25, 3))
    g = rotate(f, ROTATIONS[0])
    assert g.shape == (25, 3)
    np.testing.assert_allclose(g[:, 1], rotate(f[:, 1], ROTATIONS[0]), atol=1e-13)


@pytest.mark.parametrize("count", [0, 3, 10, 17])
def test_coefficient_count_that_is_not_a_square_raises(count):
    with pytest.raises(ValueError, match="n\\^2"):
        rotate(np.ones(count), np.eye(3))
    with pytest.raises(ValueError, match="n\\^2"):
        rotate_z([1.0] * count, 0.5)


@pytest.mark.parametrize("matrix", [
    np.eye(3) * 1.01,                      # scaling
    np.diag([1.0, 1.0, -1.0]),             # reflection
    np.array([[1, 0.1, 0], [0, 1, 0], [0, 0, 1.0]]),  # shear
    np.full((3, 3), np.nan),
    np.eye(2),
])
def test_matrix_that_is_not_a_rotation_raises(matrix):
    with pytest.raises(ValueError, match="rotation"):
        rotate(np.ones(9), matrix)


def test_per_lane_matrix_with_a_non_rotation_lane_raises():
    r = np.stack([np.eye(3), np.diag([1.0, 1.0, -1.0])])
    with pytest.raises(ValueError, match="1 lane"):
        rotate([mi.Float(1.0)] * 9, to_matrix3f(r))


def test_numpy_coefficients_with_per_lane_matrices_raise():
    with pytest.raises(TypeError):
        rotate(np.ones(9), to_matrix3f(np.eye(3)[None]))


def test_non_finite_z_rotation_angle_raises():
    with pytest.raises(ValueError, match="angle"):
        rotate_z(np.ones(9), float("nan"))
