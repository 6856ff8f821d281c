"""Importance sampling of spherical harmonics for Mitsuba 3.

Implements hierarchical sample warping of SH functions and SH-lobe x
environment-map product sampling (Jarosz, Carr, Jensen, "Importance Sampling
Spherical Harmonics", Eurographics 2009) as Dr.Jit kernels.

Importing the package registers the ``sh_direct``, ``sh_path``, ``sh_prb`` and ``oracle_direct``
integrator plugins for the active Mitsuba variant and for every variant set later. Under an
LLVM variant that registration checks the libLLVM that Dr.Jit loaded (>= 16) and raises
:class:`BackendError` without one; the CUDA variants do not need it.
"""

from ._backend import BackendError, VariantError, check_llvm_backend, prefer_good_libllvm

prefer_good_libllvm()

import mitsuba as mi  # noqa: E402

from .sh.basis import sh_eval  # noqa: E402
from .frozen import freeze  # noqa: E402
from .integrators import register  # noqa: E402
from .integrators import _register_for_new_variant  # noqa: E402
from . import calibration  # noqa: E402,F401  (a plan on a backend without shipped costs calibrates through it)

if mi.variant() is not None:
    register()
mi.detail.add_variant_callback(_register_for_new_variant)

__version__ = "0.1.0"


def __getattr__(name: str):
    # LLVM_VERSION: the libLLVM version Dr.Jit loaded, checked when first read (a CUDA-only
    # machine imports the package without one).
    if name == "LLVM_VERSION":
        return check_llvm_backend()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
__all__ = ["BackendError", "LLVM_VERSION", "VariantError", "freeze", "register", "sh_eval"]
