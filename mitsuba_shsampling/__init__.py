"""Importance sampling of spherical harmonics for Mitsuba 3.

Implements hierarchical sample warping of SH functions and SH-lobe x
environment-map product sampling (Jarosz, Carr, Jensen, "Importance Sampling
Spherical Harmonics", Eurographics 2009) as Dr.Jit kernels.
"""

from ._backend import BackendError, check_llvm_backend, prefer_good_libllvm

prefer_good_libllvm()
LLVM_VERSION = check_llvm_backend()

from .sh.basis import sh_eval  # noqa: E402
from .integrators import register, register_if_variant_set  # noqa: E402

# Make <integrator type="sh_direct"/> work right after `import mitsuba_shsampling`
# when the user already chose a supported variant.
register_if_variant_set()

__version__ = "0.1.0"
__all__ = ["BackendError", "LLVM_VERSION", "register", "sh_eval"]
