"""Quadrature projection onto the SH basis."""

import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

mi.set_variant("llvm_ad_rgb")

from mitsuba_shsampling.sh.basis import sh_eval_sum  # noqa: E402
from mitsuba_shsampling.sh.projection import project, quadrature_rule  # noqa: E402


def values(coeffs) -> np.ndarray:
    return np.array([c.numpy()[0] for c in coeffs])


@pytest.mark.parametrize("n_bands", [1, 2, 7, 20])
def test_band_limited_random_function_is_reproduced_exactly(n_bands):
    f = np.random.default_rng(n_bands).normal(size=n_bands**2)
    shared = [float(x) for x in f]
    got = values(project(lambda d: sh_eval_sum(shared, d), n_bands))
    np.testing.assert_allclose(got, f, atol=2e-5 * np.max(np.abs(f)))


def test_projection_onto_more_bands_than_the_function_has_yields_zeros_above():
    f = np.random.default_rng(0).normal(size=16)
    got = values(project(lambda d: sh_eval_sum([float(x) for x in f], d), 8))
    np.testing.assert_allclose(got[:16], f, atol=2e-5)
    np.testing.assert_allclose(got[16:], 0, atol=2e-5)


def test_quadrature_weights_sum_to_the_sphere_area_and_directions_are_unit():
    d, w = quadrature_rule(9, 17)
    assert dr.width(w) == 9 * 17
    assert float(dr.sum(w)[0]) == pytest.approx(4 * math.pi, rel=1e-6)
    np.testing.assert_allclose(dr.norm(d).numpy(), 1, atol=1e-6)


def test_numpy_valued_function_is_accepted():
    got = values(project(lambda d: np.full(dr.width(d), 2.0), 3))
    expected = np.zeros(9)
    expected[0] = 2 * math.sqrt(4 * math.pi)
    np.testing.assert_allclose(got, expected, atol=1e-5)


def test_linear_function_projects_onto_band_one():
    # z = sqrt(4 pi / 3) y_1^0.
    got = values(project(lambda d: d.z, 3))
    expected = np.zeros(9)
    expected[2] = math.sqrt(4 * math.pi / 3)
    np.testing.assert_allclose(got, expected, atol=1e-5)


def test_non_finite_function_values_raise():
    with pytest.raises(ValueError, match="non-finite"):
        project(lambda d: d.z / 0.0, 3)


def test_wrong_number_of_function_values_raises():
    with pytest.raises(ValueError, match="one value per direction"):
        project(lambda d: np.ones(5), 3)


@pytest.mark.parametrize("bad", [0, -1, 2.0, None])
def test_invalid_band_count_raises(bad):
    with pytest.raises(ValueError, match="n_bands"):
        project(lambda d: d.z, bad)


def test_invalid_quadrature_size_raises():
    with pytest.raises(ValueError, match="n_z"):
        quadrature_rule(0, 4)
