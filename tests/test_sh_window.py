"""Windows against ringing: documented properties and the automatic non-negative window."""

import math

import mitsuba as mi
import numpy as np
import pytest
from scipy.special import eval_legendre

mi.set_variant("llvm_ad_rgb")

from mitsuba_shsampling.sh.basis import sh_eval_sum  # noqa: E402
from mitsuba_shsampling.sh.window import (  # noqa: E402
    apply_window, hann_window, lanczos_window, nonnegative_window,
    nonnegative_window_strength, poussin_window, tempered_poussin_window, window_quality)
from mitsuba_shsampling.sh.zonal import phong_attenuation, zonal_to_sh  # noqa: E402


def profile_scipy(attenuation, t):
    """Independent float64 zonal profile sum_l (2l+1)/(4 pi) lambda_l P_l(t)."""
    return sum((2 * l + 1) / (4 * math.pi) * lam * eval_legendre(l, t)
               for l, lam in enumerate(attenuation))


WINDOWS = {
    "hann": hann_window,
    "lanczos": lanczos_window,
    "poussin": poussin_window,
    "tempered": lambda n: tempered_poussin_window(n, 0.4),
    "auto": lambda n: nonnegative_window(phong_attenuation(100.0, n)),
}


@pytest.mark.parametrize("name", WINDOWS)
@pytest.mark.parametrize("n", [1, 2, 10, 20])
def test_window_keeps_band_zero_and_decreases_monotonically_within_zero_one(name, n):
    w = WINDOWS[name](n)
    assert w.shape == (n,)
    assert w[0] == 1.0
    assert np.all(np.diff(w) <= 1e-15)
    assert np.all((w >= 0) & (w <= 1))


def test_hann_and_lanczos_follow_their_definitions():
    n = 12
    l = np.arange(n)
    np.testing.assert_allclose(hann_window(n), (1 + np.cos(np.pi * l / n)) / 2, atol=1e-15)
    x = np.pi * l[1:] / n
    np.testing.assert_allclose(lanczos_window(n)[1:], np.sin(x) / x, atol=1e-15)


@pytest.mark.parametrize("n", [2, 5, 20])
def test_poussin_window_is_the_legendre_expansion_of_a_non_negative_kernel(n):
    t = np.linspace(-1, 1, 2001)
    kernel = ((1 + t) / 2) ** (n - 1)
    coeffs = np.polynomial.legendre.poly2leg(
        np.polynomial.polynomial.polypow([0.5, 0.5], n - 1))
    np.testing.assert_allclose(poussin_window(n), coeffs / coeffs[0] / (2 * np.arange(n) + 1),
                               rtol=1e-10)
    assert np.all(profile_scipy(poussin_window(n), t) >= -1e-12)


@pytest.mark.parametrize("s", [20.0, 100.0, 200.0])
@pytest.mark.parametrize("n", [10, 20])
def test_automatic_window_makes_the_phong_lobe_non_negative_on_a_denser_grid(s, n):
    lam = phong_attenuation(s, n)
    windowed = np.array(lam) * nonnegative_window(lam)
    theta = np.linspace(0, np.pi, 50001)  # 6x denser than the grid used to choose it
    profile = profile_scipy(windowed, np.cos(theta))
    assert profile.min() >= -1e-9 * profile.max()


def test_automatic_window_meets_a_relative_tolerance_and_is_milder_for_a_larger_one():
    lam = phong_attenuation(100.0, 20)
    strict = nonnegative_window_strength(lam, tolerance=1e-4)
    loose = nonnegative_window_strength(lam, tolerance=1e-3)
    assert 0 < loose < strict < 1
    profile = profile_scipy(np.array(lam) * tempered_poussin_window(20, loose),
                            np.cos(np.linspace(0, np.pi, 50001)))
    assert profile.min() >= -1.01e-3 * profile.max()


def test_automatic_window_is_the_identity_for_an_already_non_negative_lobe():
    # (1 + t) / (4 pi): lambda = (1, 1/3).
    assert nonnegative_window_strength([1.0, 1.0 / 3.0]) == 0.0
    np.testing.assert_array_equal(nonnegative_window([1.0, 1.0 / 3.0]), [1.0, 1.0])


def test_windowed_lobe_turned_to_any_axis_stays_non_negative_in_float32():
    lam = phong_attenuation(100.0, 12)
    w = nonnegative_window(lam)
    axis = mi.Vector3f(0.48, -0.6, 0.64)
    coeffs = apply_window(zonal_to_sh(lam, axis), w)
    rng = np.random.default_rng(0)
    d = rng.normal(size=(3, 200000))
    d /= np.linalg.norm(d, axis=0)
    values = sh_eval_sum(coeffs, mi.Vector3f(d.astype(np.float32))).numpy()
    assert values.min() >= -1e-5 * values.max()


def test_window_quality_reproduces_the_truncation_figures_of_math_md():
    # Energy missed by truncation (docs/MATH.md section 8) = l2_loss^2 without a window.
    for s, n, energy in [(20.0, 10, 7e-3), (100.0, 10, 0.37), (100.0, 20, 0.019), (200.0, 20, 0.136)]:
        q = window_quality(phong_attenuation(s, 600), np.ones(n))
        assert q["l2_loss"] ** 2 == pytest.approx(energy, rel=0.05)
    q = window_quality(phong_attenuation(100.0, 600), np.ones(20))
    assert q["min_rel"] == pytest.approx(-0.02, abs=0.002)  # "rings to -2 % of the peak"


def test_apply_window_scales_each_band_for_lists_and_numpy_alike():
    f = np.arange(1.0, 10.0)
    w = np.array([1.0, 0.5, 0.25])
    expected = f * np.array([1, .5, .5, .5, .25, .25, .25, .25, .25])
    np.testing.assert_allclose(apply_window(f, w), expected)
    np.testing.assert_allclose([float(x) for x in apply_window(list(f), w)], expected)
    batch = apply_window(np.stack([f, 2 * f], axis=1), w)
    np.testing.assert_allclose(batch[:, 1], 2 * expected)


def test_window_of_the_wrong_length_raises():
    with pytest.raises(ValueError, match="factors"):
        apply_window(np.ones(9), np.ones(4))
    with pytest.raises(ValueError, match="n\\^2"):
        apply_window(np.ones(8), np.ones(3))


def test_invalid_window_arguments_raise():
    with pytest.raises(ValueError, match="strength"):
        tempered_poussin_window(5, 1.5)
    with pytest.raises(ValueError, match="tolerance"):
        nonnegative_window_strength([1.0, 0.5], tolerance=-1.0)
    with pytest.raises(ValueError, match="non-finite"):
        nonnegative_window([1.0, float("nan")])
    with pytest.raises(ValueError, match="bands"):
        hann_window(0)
