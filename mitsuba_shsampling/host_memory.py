"""numpy's large arrays on ordinary pages while the plugins set up a scene.

numpy asks the kernel for transparent huge pages (``madvise(MADV_HUGEPAGE)``) on every
array of 4 MB or more. The set-up makes many such arrays for a moment (the pyramid's
levels, the cosine tables, the quadrature's points), each freshly mapped, so each of
their 2 MB pages is faulted in and cleared whole; where the kernel's ``defrag`` setting
is ``madvise`` (Debian's and Ubuntu's default) such a fault may also compact memory
before it returns. On the development VM a new scene's set-up (the material studio, the
kernels cached) took 1.32-1.99 s (system time 0.42-1.46 s) with them and 1.21-1.26 s
(0.17-0.25 s) without, four fresh processes each, interleaved (docs/MEASUREMENTS.md,
"Set-up on ordinary pages"). Nothing else changes: the same arrays, the same values,
the same plan.

The switch is numpy's own (``numpy._core.multiarray._set_madvise_hugepage``, the
function behind its ``NUMPY_MADVISE_HUGEPAGE`` variable); the user's setting is put back
when the set-up ends. Where a numpy lacks it, the set-up runs as it is.
"""

from __future__ import annotations

import contextlib

import numpy as np


def _madvise_switch():
    """numpy's ``_set_madvise_hugepage(enabled) -> previous``, or None where it has none."""
    for module in ("_core", "core"):
        multiarray = getattr(getattr(np, module, None), "multiarray", None)
        switch = getattr(multiarray, "_set_madvise_hugepage", None)
        if switch is not None:
            return switch
    return None


_SWITCH = _madvise_switch()


@contextlib.contextmanager
def ordinary_pages():
    """Within: numpy maps its new arrays without asking for huge pages; after: as before."""
    if _SWITCH is None:
        yield
        return
    previous = _SWITCH(False)
    try:
        yield
    finally:
        _SWITCH(previous)
