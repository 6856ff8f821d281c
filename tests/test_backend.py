"""Specification: the package needs a libLLVM >= 16 only under an LLVM variant.

A CUDA-only machine (no libLLVM) imports the package and runs its CUDA variants; an
LLVM variant without a usable libLLVM is refused with :class:`BackendError` and the
install hint, before any kernel (an LLVM 15 kernel aborts the process). Runs in a fresh
interpreter in which Dr.Jit reports no LLVM backend (``dr.has_backend`` mocked).
"""

import json
import os
import subprocess
import sys

import pytest

WITHOUT_LLVM = r"""
import json
import drjit as dr
real_has_backend = dr.has_backend
dr.has_backend = lambda backend: False if backend == dr.JitBackend.LLVM else real_has_backend(backend)
import mitsuba as mi
import mitsuba_shsampling as package
from mitsuba_shsampling._backend import check_backend

outcome = {"imported": True}
check_backend("cuda_ad_rgb")
check_backend("cuda_ad_spectral")
outcome["cuda variants"] = "no check"


def error_of(action, error_type=package.BackendError):
    try:
        action()
    except error_type as error:
        return str(error)
    return None


outcome["LLVM_VERSION"] = error_of(lambda: package.LLVM_VERSION)
outcome["set_variant"] = error_of(lambda: mi.set_variant("llvm_ad_rgb"))
# Mitsuba's parser passes the plugin's error on in its own RuntimeError.
outcome["load_dict"] = error_of(lambda: mi.load_dict({"type": "sh_direct"}), RuntimeError)
print(json.dumps(outcome))
"""


@pytest.fixture(scope="module")
def outcome():
    environment = {k: v for k, v in os.environ.items() if k != "MI_DEFAULT_VARIANT"}
    done = subprocess.run([sys.executable, "-c", WITHOUT_LLVM], capture_output=True, text=True,
                          env=environment, timeout=120, check=False)
    assert done.returncode == 0, done.stderr[-2000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_the_package_imports_without_a_libllvm_and_cuda_variants_do_not_check_for_one(outcome):
    assert outcome["imported"] is True
    assert outcome["cuda variants"] == "no check"


def test_an_llvm_variant_without_a_libllvm_is_refused_with_the_install_hint(outcome):
    for step in ("set_variant", "load_dict", "LLVM_VERSION"):
        assert outcome[step] is not None, f"{step} did not refuse"
        assert "could not load a libLLVM" in outcome[step]
        assert "libllvm19" in outcome[step]


def test_with_a_usable_libllvm_the_version_is_read_when_asked():
    import mitsuba_shsampling

    assert mitsuba_shsampling.LLVM_VERSION[0] >= 16
