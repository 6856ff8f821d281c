"""Zonal lobes: Phong and clamped-cosine attenuation, lobes turned to an axis."""

import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
from scipy.special import gammaln

mi.set_variant("llvm_ad_rgb")

from mitsuba_shsampling.sh.integrals import contract_z, legendre_antiderivatives  # noqa: E402
from mitsuba_shsampling.sh.projection import project  # noqa: E402
from mitsuba_shsampling.sh.zonal import (  # noqa: E402
    RotatedZonalLobes, clamped_cosine_attenuation, phong_attenuation, rotate_zonal_lobes,
    zonal_coefficients_z, zonal_profile, zonal_to_sh)


def phong_attenuation_closed_form(s: float, l: int) -> float:
    """(s+1) J(s,l) of docs/MATH.md section 8 (float64, 1/Gamma = 0 at its poles)."""
    a, b = 1 + (s - l) / 2, (s + l + 3) / 2
    if a <= 0 and a == int(a):
        return 0.0
    sign = 1.0 if a > 0 or int(math.floor(a)) % 2 == 0 else -1.0
    log_abs = (0.5 * math.log(math.pi) - (s + 1) * math.log(2) + gammaln(s + 1)
               - gammaln(a) - gammaln(b) + math.log(s + 1))
    # Gamma(a) for a < 0 has sign (-1)^ceil(-a); gammaln returns log|Gamma|.
    if a < 0:
        sign = -1.0 if math.ceil(-a) % 2 else 1.0
    return sign * math.exp(log_abs)


@pytest.mark.parametrize("s", [5.0, 20.0, 100.0, 7.3, 0.5])
def test_phong_attenuation_matches_closed_form(s):
    lam = phong_attenuation(s, 20)
    ref = [phong_attenuation_closed_form(s, l) for l in range(20)]
    assert len(lam) == 20
    np.testing.assert_allclose(lam, ref, rtol=1e-12, atol=1e-15)


def test_phong_attenuation_decays_like_a_gaussian_in_l():
    lam = np.array(phong_attenuation(200.0, 30))
    l = np.arange(30)
    np.testing.assert_allclose(lam, np.exp(-l**2 / 400), rtol=0.1)


def test_per_lane_phong_attenuation_matches_the_scalar_one():
    s = [0.0, 1.0, 5.0, 20.0, 100.0, 1234.5]
    lanes = phong_attenuation(mi.Float(s), 20)
    for i, si in enumerate(s):
        got = [float(x.numpy()[i]) for x in lanes]
        np.testing.assert_allclose(got, phong_attenuation(si, 20), rtol=2e-5, atol=1e-6)


@pytest.mark.parametrize("s", [5.0, 20.0, 100.0])
def test_projection_of_a_phong_lobe_reproduces_the_closed_form_coefficients(s):
    axis = np.array([0.3, -0.5, 0.8])
    axis /= np.linalg.norm(axis)

    def lobe(d):  # float64 numpy evaluation of (s+1)/(2 pi) max(cos, 0)^s
        cos = np.maximum(axis @ d.numpy().astype(np.float64), 0.0)
        return (s + 1) / (2 * math.pi) * cos**s

    projected = np.array([c.numpy()[0] for c in project(lobe, 20, n_z=256, n_phi=512)])
    closed = np.array([c.numpy()[0] for c in zonal_to_sh(phong_attenuation(s, 20),
                                                          mi.Vector3f(*axis.tolist()))])
    scale = np.max(np.abs(closed))
    np.testing.assert_allclose(projected, closed, atol=2e-5 * scale)


def test_clamped_cosine_factors_match_the_zonal_coefficients_of_math_md():
    lam = clamped_cosine_attenuation(5)
    z = [math.sqrt((2 * l + 1) / (4 * math.pi)) * lam[l] for l in range(5)]
    expected = [math.sqrt(math.pi) / 2, math.sqrt(math.pi / 3), math.sqrt(5 * math.pi) / 8,
                0.0, -0.1107]
    np.testing.assert_allclose(z[:4], expected[:4], rtol=1e-14, atol=1e-15)
    assert z[4] == pytest.approx(expected[4], abs=1e-4)


def test_clamped_cosine_factors_follow_the_even_band_closed_form_and_vanish_for_odd_bands():
    lam = clamped_cosine_attenuation(40)
    assert lam[0] == pytest.approx(math.pi) and lam[1] == pytest.approx(2 * math.pi / 3)
    for l in range(2, 40):
        if l % 2:
            assert lam[l] == 0.0
        else:
            closed = (2 * math.pi * (-1) ** (l // 2 + 1) / ((l - 1) * (l + 2))
                      * math.factorial(l) / (2**l * math.factorial(l // 2) ** 2))
            assert lam[l] == pytest.approx(closed, rel=1e-12)


def test_clamped_cosine_profile_converges_to_the_clamped_cosine():
    t = np.linspace(-1, 1, 101)
    profile = zonal_profile(clamped_cosine_attenuation(200), t)
    np.testing.assert_allclose(profile, np.maximum(t, 0), atol=5e-3)


def test_z_aligned_zonal_coefficients_equal_the_lobe_turned_to_plus_z():
    lam = phong_attenuation(20.0, 8)
    turned = [c.numpy()[0] for c in zonal_to_sh(lam, mi.Vector3f(0, 0, 1))]
    np.testing.assert_allclose(turned, zonal_coefficients_z(lam), atol=1e-6)


def test_per_lane_lobes_have_per_lane_exponents_and_axes():
    s = mi.Float([10.0, 50.0])
    axes = mi.Vector3f([0.0, 1.0], [0.0, 0.0], [1.0, 0.0])
    coeffs = zonal_to_sh(phong_attenuation(s, 6), axes)
    assert len(coeffs) == 36 and dr.width(coeffs[0]) == 2
    for lane, (si, axis) in enumerate([(10.0, (0, 0, 1)), (50.0, (1, 0, 0))]):
        ref = zonal_to_sh(phong_attenuation(si, 6), mi.Vector3f(*axis))
        np.testing.assert_allclose([c.numpy()[lane] for c in coeffs],
                                   [c.numpy()[0] for c in ref], rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize("bad", [-1.0, float("nan"), float("inf"), -1e-9])
def test_invalid_scalar_phong_exponent_raises(bad):
    with pytest.raises(ValueError, match="Phong exponent"):
        phong_attenuation(bad, 10)


def test_invalid_per_lane_exponents_fall_back_to_documented_lobes():
    lam = phong_attenuation(mi.Float([-3.0, float("nan"), float("inf")]), 6)
    values = np.array([x.numpy() for x in lam])  # (band, lane)
    assert np.all(np.isfinite(values))
    hemisphere = phong_attenuation(0.0, 6)
    np.testing.assert_allclose(values[:, 0], hemisphere, atol=1e-7)
    np.testing.assert_allclose(values[:, 1], hemisphere, atol=1e-7)
    np.testing.assert_allclose(values[:, 2], np.ones(6))  # Dirac lobe


@pytest.mark.parametrize("bad", [0, -2, 2.5, True])
def test_invalid_band_count_raises(bad):
    with pytest.raises((ValueError, TypeError), match="bands"):
        phong_attenuation(10.0, bad)


def test_zonal_to_sh_rejects_more_bands_than_the_basis_supports():
    with pytest.raises(ValueError):
        zonal_to_sh([1.0] * 33, mi.Vector3f(0, 0, 1))


# ------------------------------------------------ rotated zonal lobes, factored

def two_rotated_lobes(count: int, seed: int):
    """A Phong lobe (8 bands, per-lane exponent) and a 3-band clamped cosine, each about
    its own random per-lane axis (one lane's axis zero, one's NaN), as the integrators
    build them; returns (attenuation, axis) pairs."""
    rng = np.random.default_rng(seed)
    mirror, normal = (rng.normal(size=(3, count)).astype(np.float32) for _ in range(2))
    mirror[:, 0], normal[:, 1] = 0.0, np.nan
    s = mi.Float(rng.uniform(1.0, 60.0, count).astype(np.float32))
    weight = mi.Float(rng.uniform(0.0, 1.0, count).astype(np.float32))
    return [(phong_attenuation(s, 8), mi.Vector3f(mirror)),
            ([weight * lam for lam in clamped_cosine_attenuation(3)], mi.Vector3f(normal))]


def summed_coefficients(lobes) -> np.ndarray:
    total = None
    for attenuation, axis in lobes:
        coeffs = np.array([c.numpy() for c in zonal_to_sh(attenuation, axis)])
        total = coeffs if total is None else total + np.pad(coeffs, ((0, len(total) - len(coeffs)), (0, 0)))
    return total


def test_factored_lobes_expand_to_the_sum_of_the_turned_lobes():
    lobes = two_rotated_lobes(64, seed=1)
    factored = rotate_zonal_lobes(lobes)
    assert factored.n_bands == 8
    got = np.array([c.numpy() for c in factored.coefficients()])
    np.testing.assert_allclose(got, summed_coefficients(lobes), rtol=1e-5, atol=1e-6)
    # A lobe about a zero or NaN axis is 0, as zonal_to_sh's: lane 0 holds the cosine alone.
    assert np.all(np.isfinite(got))
    np.testing.assert_allclose(got[:9, 0], summed_coefficients(lobes[1:])[:, 0], rtol=1e-5, atol=1e-7)
    assert np.all(got[9:, 0] == 0)
    np.testing.assert_array_equal(np.array([c.numpy() for c in factored.coefficients(2)]), got[:4])


def test_factored_contraction_over_l_equals_the_contraction_of_the_coefficients():
    """What the SH cell integrals need per level: A[m] = sum_l f_l^m I_l^|m| over a z range."""
    lobes = two_rotated_lobes(64, seed=2)
    factored = rotate_zonal_lobes(lobes)
    rng = np.random.default_rng(3)
    z0, z1 = np.sort(rng.uniform(-1.0, 1.0, (2, 64)).astype(np.float32), axis=0)
    lo, hi = legendre_antiderivatives(mi.Float(z0), 7), legendre_antiderivatives(mi.Float(z1), 7)
    zint = {k: hi[k] - lo[k] for k in hi}
    expected = contract_z(factored.coefficients(), zint, 7)
    for a, b in zip(factored.contract_z(zint, 7), expected):
        np.testing.assert_allclose(a.numpy(), b.numpy(), rtol=1e-5, atol=1e-6)


def test_zero_factored_lobes_have_the_structure_of_built_ones():
    zeros = RotatedZonalLobes.zeros([8, 3])
    built = rotate_zonal_lobes(two_rotated_lobes(4, seed=4))
    for field in ("legendre", "azimuth_cos", "azimuth_sin"):
        assert [len(v) for v in getattr(zeros, field)] == [len(v) for v in getattr(built, field)]
    assert all(np.all(c.numpy() == 0) for c in zeros.coefficients())
