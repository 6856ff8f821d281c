"""Specification: under a variant the plugins cannot run on, loading them raises the
package's VariantError with the reason, not Mitsuba's "plugin not found"; the plugins
follow ``mi.set_variant`` without a manual ``register()``.

Runs in a fresh interpreter: the user's order (set the variant, then import the
package) cannot be replayed in the test process, which imported it long ago.
"""

import json
import os
import subprocess
import sys

import pytest

from mitsuba_shsampling._backend import unsupported_variant_reason

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

SCRIPT = r"""
import json, sys
import mitsuba as mi
mi.set_variant(sys.argv[1])
import mitsuba_shsampling
results = {}
for variant in sys.argv[1:]:
    mi.set_variant(variant)
    for plugin in ("sh_direct", "sh_path"):
        try:
            mi.load_dict({"type": plugin})
            results[f"{variant} {plugin}"] = "loaded"
        except Exception as err:
            results[f"{variant} {plugin}"] = str(err).strip().splitlines()[-1]
print(json.dumps(results))
"""

UNSUPPORTED = ["scalar_rgb", "scalar_spectral", "llvm_ad_mono_polarized", "llvm_ad_spectral_polarized"]


@pytest.fixture(scope="module")
def outcomes():
    env = dict(os.environ, PYTHONPATH=REPO + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.run([sys.executable, "-c", SCRIPT, *UNSUPPORTED, "llvm_ad_rgb"], env=env,
                          capture_output=True, text=True, timeout=300, cwd=REPO)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("variant", UNSUPPORTED)
@pytest.mark.parametrize("plugin", ["sh_direct", "sh_path"])
def test_loading_a_plugin_under_an_unsupported_variant_raises_the_reason(outcomes, variant, plugin):
    message = outcomes[f"{variant} {plugin}"]
    assert message.startswith("VariantError: mitsuba_shsampling: ")
    assert message.endswith(unsupported_variant_reason(variant))
    assert "not found" not in message


def test_switching_back_to_a_supported_variant_registers_the_real_plugins(outcomes):
    assert outcomes["llvm_ad_rgb sh_direct"] == outcomes["llvm_ad_rgb sh_path"] == "loaded"


@pytest.mark.parametrize("variant", ["llvm_ad_rgb", "llvm_ad_mono", "llvm_ad_spectral", "cuda_ad_rgb",
                                     "cuda_ad_spectral"])
def test_jit_rgb_mono_and_spectral_variants_are_supported(variant):
    assert unsupported_variant_reason(variant) is None


@pytest.mark.parametrize("variant", UNSUPPORTED + ["cuda_ad_rgb_polarized", "scalar_mono"])
def test_scalar_and_polarized_variants_are_not(variant):
    assert "not supported" in unsupported_variant_reason(variant)
