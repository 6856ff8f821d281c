"""The report's error statistics: expected error, heavy tails, and the bias test's stated false-alarm rate."""

import math

import numpy as np
import pytest
from scipy import stats

from mitsuba_shsampling.report import metrics


def binomial_interval(n: int, p: float, z: float = 4.0) -> tuple[float, float]:
    """Counts an honest Binomial(n, p) lands in except with probability ~6e-5 (|z| > 4)."""
    sd = math.sqrt(n * p * (1 - p))
    return n * p - z * sd, n * p + z * sd


def test_expected_mse_is_the_mean_of_the_per_pass_mses(rng):
    ref = np.full((8, 8, 3), 0.5)
    passes = ref[None] + rng.normal(0.0, 0.1, size=(32, 8, 8, 3))
    stats_ = metrics.error_stats(passes, ref)
    assert stats_.mse == pytest.approx(np.mean([np.mean((p - ref) ** 2) for p in passes]))
    assert len(stats_.mse_per_pass) == 32


def test_pixel_variance_across_passes_recovers_the_noise_variance(rng):
    ref = np.zeros((16, 16, 3))
    passes = rng.normal(0.0, 0.2, size=(64, 16, 16, 3))
    assert metrics.error_stats(passes, ref).pixel_variance == pytest.approx(0.04, rel=0.05)


def test_a_rare_huge_sample_moves_the_expected_mse_and_the_tail_but_not_the_median_pass(rng):
    ref = np.full((16, 16, 3), 0.5)
    passes = ref[None] + rng.normal(0.0, 0.05, size=(32, 16, 16, 3))
    quiet = metrics.error_stats(passes, ref)
    passes[17, 3, 4] = 500.0  # one sample that found the sun through a tiny pdf
    loud = metrics.error_stats(passes, ref)
    assert loud.mse > 100 * quiet.mse
    assert np.median(loud.mse_per_pass) == pytest.approx(np.median(quiet.mse_per_pass), rel=0.1)
    tail = metrics.tail_stats(passes, ref)
    assert tail.max_pixel == pytest.approx(500.0)
    assert tail.fireflies == 1
    assert tail.pixels == 32 * 16 * 16


def test_ordinary_noise_makes_no_fireflies(rng):
    ref = np.full((32, 32, 3), 0.5)
    passes = ref[None] * rng.gamma(4.0, 0.25, size=(32, 32, 32, 1))  # relative std 0.5
    assert metrics.tail_stats(passes, ref).fireflies == 0


def test_error_percentile_is_the_99_99th_percentile_of_the_luminance_error():
    ref = np.zeros((100, 100, 3))
    passes = np.zeros((1, 100, 100, 3))
    passes[0].reshape(-1, 3)[:, :] = np.arange(10_000)[:, None]  # grey: luminance = value
    expected = np.percentile(np.arange(10_000), metrics.TAIL_PERCENTILE)
    assert metrics.tail_stats(passes, ref).abs_error_percentile == pytest.approx(expected)


def test_tail_is_flagged_worse_than_direct_only_when_it_is(rng):
    ref = np.full((16, 16, 3), 0.5)
    direct = metrics.tail_stats(ref[None] + rng.normal(0, 0.05, size=(32, 16, 16, 3)), ref)
    same = metrics.tail_stats(ref[None] + rng.normal(0, 0.05, size=(32, 16, 16, 3)), ref)
    assert metrics.tail_worse(same, direct) == []
    heavy = ref[None] + rng.normal(0, 0.05, size=(32, 16, 16, 3))
    heavy[:, 0, :8] = 50.0  # 256 fireflies, a bright maximum and a large error percentile
    worse = metrics.tail_worse(metrics.tail_stats(heavy, ref), direct)
    assert len(worse) == 3 and any("fireflies" in w for w in worse)


def test_non_finite_values_are_counted_and_left_out_of_every_statistic(rng):
    ref = np.full((8, 8, 3), 0.5)
    passes = ref[None] + rng.normal(0, 0.05, size=(4, 8, 8, 3))
    passes[2, 1, 1] = np.nan
    passes[3, 2, 2, 0] = np.inf
    err = metrics.error_stats(passes, ref)
    assert err.non_finite == 4
    assert np.isfinite(err.mse) and np.isfinite(err.pixel_variance) and np.isfinite(err.rel_mse)
    tail = metrics.tail_stats(passes, ref)
    assert np.isfinite(tail.max_pixel) and np.isfinite(tail.abs_error_percentile)
    assert np.all(np.isfinite(metrics.image_mean_luminance(passes)))


def test_student_t_tail_matches_scipy_for_fractional_degrees_of_freedom():
    for dof in (1.0, 2.5, 7.3, 40.0, 300.0):
        for t in (0.5, 2.0, 4.0, 8.0):
            assert metrics.student_t_tail(t, dof) == pytest.approx(2 * stats.t.sf(t, dof), rel=1e-5, abs=1e-12)


def unbiased_trial(rng, k, c, sd_pass, sd_chunk):
    return metrics.bias_test(1.0 + rng.normal(0, sd_pass, k), 1.0 + rng.normal(0, sd_chunk, c))


@pytest.mark.parametrize("alpha", [1e-2, metrics.BIAS_ALPHA])
def test_bias_test_false_alarm_rate_on_unbiased_normal_pass_means_is_alpha(rng, alpha):
    # 32 passes against an 8-chunk reference whose own error is as large as the passes' mean's:
    # a test that ignored the reference error, or used normal instead of Welch's t, alarms too often.
    n = 40_000
    fails = sum(metrics.bias_test(1.0 + rng.normal(0, 0.1, 32), 1.0 + rng.normal(0, 0.05, 8),
                                  alpha=alpha).flagged for _ in range(n))
    lo, hi = binomial_interval(n, alpha)
    assert lo <= fails <= hi, (fails, n * alpha)


def test_bias_test_false_alarm_rate_holds_for_heavy_tailed_samples(rng):
    # Each pass mean averages 256 lognormal samples (sigma 1.5: skewed, heavy-tailed).
    n, k, c = 4000, 32, 8
    sigma = 1.5
    fails = 0
    for _ in range(n):
        passes = rng.lognormal(0.0, sigma, size=(k, 256)).mean(axis=1)
        chunks = rng.lognormal(0.0, sigma, size=(c, 2048)).mean(axis=1)
        fails += metrics.bias_test(passes, chunks, alpha=0.01).flagged
    lo, hi = binomial_interval(n, 0.01)
    assert fails <= hi, fails


def test_bias_test_detects_an_offset_of_five_standard_errors(rng):
    sd = 0.1
    offset = 5 * sd / math.sqrt(32)
    flagged = [metrics.bias_test(1.0 + offset + rng.normal(0, sd, 32), 1.0 + rng.normal(0, 1e-4, 8)).flagged
               for _ in range(500)]
    assert np.mean(flagged) > 0.8


def test_bias_test_uses_one_luminance_mean_per_pass_so_channel_correlation_does_not_matter(rng):
    # Grey passes have three perfectly correlated channels: testing them as three independent
    # channels would shrink the standard error by sqrt(3). One mean per pass does not.
    grey = rng.normal(1.0, 0.1, size=(32, 4, 4, 1)).repeat(3, axis=-1)
    ref_chunks = rng.normal(1.0, 0.01, size=(8, 4, 4, 1)).repeat(3, axis=-1)
    test = metrics.bias_test(metrics.image_mean_luminance(grey), metrics.image_mean_luminance(ref_chunks))
    one_channel = metrics.bias_test(grey[..., 0].mean(axis=(1, 2)), ref_chunks[..., 0].mean(axis=(1, 2)))
    assert test.standard_error == pytest.approx(one_channel.standard_error, rel=1e-5)
    assert test.t == pytest.approx(one_channel.t, rel=1e-5)


def test_relative_mse_is_the_regularised_squared_error():
    ref = np.full((2, 2, 3), 0.1)
    image = ref + 0.1
    assert metrics.rel_mse(image, ref) == pytest.approx(0.01 / (0.01 + 0.01))
    assert metrics.mse(image, ref) == pytest.approx(0.01)
    assert metrics.efficiency(0.01, 2.0) == pytest.approx(50.0)
