"""Specification: the plugins run in spectral variants (``llvm_ad_spectral``, and
``cuda_ad_spectral`` by the same code). The pyramid of a spectral ``envmap`` weighs each
texel as Mitsuba's own envmap sampling does there; the estimators evaluate the emitter and
the BSDFs at each lane's sampled wavelengths.

The figures come from ``tests/spectral_checks.py``, run once in a fresh interpreter under
that variant (see its docstring for what each one measures and why a wrong implementation
moves it).
"""

import json
import os
import subprocess
import sys

import pytest

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(HERE)

#: chi2 significance level (mitsuba.chi2's default).
ALPHA = 0.01
#: Largest z-score of an image or 4 x 4 block mean against Mitsuba's integrator.
Z_LIMIT = 5.0
#: |t| above which two gradient means disagree (two parameters).
T_LIMIT = 4.5


@pytest.fixture(scope="module")
def figures(tmp_path_factory):
    out = tmp_path_factory.mktemp("spectral") / "figures.json"
    env = dict(os.environ, PYTHONPATH=REPO + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.run([sys.executable, os.path.join(HERE, "spectral_checks.py"), str(out)], env=env,
                          capture_output=True, text=True, timeout=900, cwd=str(out.parent))
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(out.read_text())


@pytest.mark.parametrize("strategy", ["environment", "environment_compensated", "product"])
def test_every_environment_strategy_of_a_spectral_map_samples_its_own_pdf(figures, strategy):
    assert figures["chi2"][strategy] > ALPHA


def test_the_compensated_copy_of_a_spectral_map_has_the_maps_radiance_at_every_wavelength(figures):
    assert figures["copy_radiance_error"] < 1e-3


@pytest.mark.parametrize("integrator", ["sh_direct", "sh_path"])
@pytest.mark.parametrize("scene", ["glossy", "diffuse"])
def test_spectral_renders_are_unbiased_against_mitsubas_integrators(figures, integrator, scene):
    assert figures[f"{integrator}_{scene}_z"] < Z_LIMIT
    if integrator == "sh_direct":
        assert figures[f"sh_direct_{scene}_finite"]


def test_the_bsdf_only_strategy_is_unbiased_in_the_spectral_variant(figures):
    assert figures["sh_direct_bsdf_only_glossy_z"] < Z_LIMIT


def test_sh_direct_has_lower_variance_than_direct_on_a_glossy_sphere_at_equal_samples(figures):
    assert figures["sh_direct_glossy_variance_ratio"] < 0.9


def test_sh_prbs_spectral_gradients_agree_with_prbs_and_are_not_zero(figures):
    assert all(abs(t) < T_LIMIT for t in figures["gradient_welch_t"])
    assert all(abs(t) > 3.0 for t in figures["gradient_own_t"])
