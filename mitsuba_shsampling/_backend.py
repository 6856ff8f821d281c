"""What the package needs from Dr.Jit and Mitsuba: a usable libLLVM, a supported variant.

Dr.Jit 1.5 JIT-compiles through a system libLLVM. With LLVM <= 15 (Debian 12's
default) the first float ``dr.minimum``/``dr.maximum`` aborts the whole
process ("LLVM ERROR: Cannot select ... fminimum"), so the check has to happen
before the first kernel, where it can still raise a Python exception: when the
plugins are registered for an LLVM variant (at import, or at ``mi.set_variant``).
The CUDA variants do not use libLLVM, so they neither need nor check it.

Variants: the SH warps are Dr.Jit kernels and the estimators carry unpolarized
radiance, so the JIT (``llvm_*``, ``cuda_*``) variants that are not polarized
are supported (RGB, mono and spectral). :func:`unsupported_variant_reason` is the one place that
decides it (the plugins' registration and the command line both ask it).
"""

from __future__ import annotations

import glob
import os
import sys

MIN_LLVM_MAJOR = 16
INSTALL_HINT = (
    "install LLVM 19 with 'sudo apt-get install libllvm19' (Debian 12 / Ubuntu 24.04), "
    "or point DRJIT_LIBLLVM_PATH at a libLLVM.so of version >= 16"
)


class BackendError(ImportError):
    """Raised when no usable libLLVM (>= 16) is available to Dr.Jit."""


class VariantError(RuntimeError):
    """Raised when the package is used under a Mitsuba variant it does not support."""


#: Suggested variant in messages.
DEFAULT_VARIANT = "llvm_ad_rgb"


def unsupported_variant_reason(variant: str | None) -> str | None:
    """None if the SH plugins run under ``variant``, else a one-line reason."""
    if variant is None:
        return f"no Mitsuba variant is set; call mi.set_variant('{DEFAULT_VARIANT}') first"
    if not variant.startswith(("llvm_", "cuda_")):
        return (f"variant '{variant}' is not supported: the SH warps are Dr.Jit kernels; "
                f"use a JIT variant such as '{DEFAULT_VARIANT}'")
    if "polarized" in variant:
        return (f"variant '{variant}' is not supported: the product's estimators carry unpolarized "
                f"radiance (a Stokes vector per lane would need Mueller-matrix BSDF lobes); use the "
                f"same variant without '_polarized', e.g. '{variant.replace('_polarized', '')}'")
    return None


def _newest_good_libllvm() -> str | None:
    """Path of the newest system libLLVM >= 16, or None."""
    found = []
    for path in glob.glob("/usr/lib/*/libLLVM*.so*") + glob.glob("/usr/lib/llvm-*/lib/libLLVM*.so*"):
        name = os.path.basename(path)
        digits = name.replace("libLLVM", "").lstrip("-.").split(".")[0].split("-")[0]
        if digits.isdigit() and int(digits) >= MIN_LLVM_MAJOR:
            found.append((int(digits), path))
    return max(found)[1] if found else None


def prefer_good_libllvm() -> None:
    """Point Dr.Jit at a libLLVM >= 16 before it loads one itself.

    Dr.Jit tries ``dlopen("libLLVM.so")`` before scanning for the newest
    version, and that unversioned name is often LLVM 15. Only acts when
    ``drjit`` is not imported yet and the user did not choose a library.
    """
    if "drjit" in sys.modules or "DRJIT_LIBLLVM_PATH" in os.environ:
        return
    path = _newest_good_libllvm()
    if path is not None:
        os.environ["DRJIT_LIBLLVM_PATH"] = path


def check_llvm_backend() -> tuple[int, int, int]:
    """Return the loaded LLVM version, or raise :class:`BackendError`."""
    import drjit as dr

    if not dr.has_backend(dr.JitBackend.LLVM):
        raise BackendError(
            "mitsuba_shsampling: Dr.Jit could not load a libLLVM, so the LLVM variants "
            f"(e.g. 'llvm_ad_rgb') are unavailable; {INSTALL_HINT}."
        )
    version = tuple(dr.detail.llvm_version())
    if version[0] < MIN_LLVM_MAJOR:
        raise BackendError(
            f"mitsuba_shsampling: Dr.Jit loaded LLVM {'.'.join(map(str, version))}, which aborts "
            f"the process on float min/max; {INSTALL_HINT}."
        )
    return version


def check_backend(variant: str | None) -> None:
    """Raise :class:`BackendError` where ``variant`` is an LLVM one and Dr.Jit has no
    usable libLLVM (:func:`check_llvm_backend`); other variants need nothing from it."""
    if variant is not None and variant.startswith("llvm_"):
        check_llvm_backend()
