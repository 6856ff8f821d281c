"""Ordinary 4 kB pages for the short-lived memory of a pyramid's build.

Dr.Jit (every allocation over 2 MB) and numpy (every array of 4 MB or more) ask Linux for
transparent huge pages (``madvise(MADV_HUGEPAGE)``). Where THP is set to ``madvise``
(Debian's and Ubuntu's default) the first touch of each 2 MB page clears it whole and may
compact memory before it returns. The pyramid's level sums and level test touch ~9x the
memory of what the pyramid keeps (a depth-11 map: ~400 MB against 39 MB), each of it
once, and on the development VM those faults cost up to 1.4 s of system time in a new
scene's set-up, varying from run to run by as much (docs/MEASUREMENTS.md, "Set-up on
ordinary pages").

:func:`ordinary_pages` turns huge pages off for the process while such work runs
(``prctl(PR_SET_THP_DISABLE)``, read at each page fault) and numpy's request off too
(``_set_madvise_hugepage``, where ``prctl`` cannot be called); the previous settings are
put back when the outermost block ends. Only the pyramid's temporaries go there, and what
it keeps is copied out (:func:`kept_copy`): with the whole set-up on 4 kB pages the passes
ran 1-3 % slower, since Dr.Jit hands freed blocks to later allocations of the same size and
the passes' own arrays landed on the set-up's small pages; the cosine tables' sums (16 MB
blocks, the size of a pass's arrays) did the same (same section).
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import mmap
import sys
import threading

import numpy as np

from .device_arrays import aligned_empty

PR_SET_THP_DISABLE, PR_GET_THP_DISABLE = 41, 42
"""Linux's ``prctl`` options (``linux/prctl.h``, since 3.15)."""


def _numpy_switch():
    """numpy's ``_set_madvise_hugepage(enabled) -> previous``, or None where it has none."""
    for module in ("_core", "core"):
        multiarray = getattr(getattr(np, module, None), "multiarray", None)
        switch = getattr(multiarray, "_set_madvise_hugepage", None)
        if switch is not None:
            return switch
    return None


def _prctl():
    """libc's ``prctl`` on Linux, None elsewhere or where the C library cannot be loaded."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        prctl = ctypes.CDLL(ctypes.util.find_library("c") or None, use_errno=True).prctl
    except (OSError, AttributeError):
        return None
    prctl.restype = ctypes.c_int
    prctl.argtypes = [ctypes.c_int, ctypes.c_ulong, ctypes.c_ulong, ctypes.c_ulong, ctypes.c_ulong]
    return prctl


_NUMPY_SWITCH = _numpy_switch()
_PRCTL = _prctl()
_LOCK = threading.Lock()
_DEPTH = 0
_SAVED: tuple = (None, None)


def process_thp_disabled() -> bool | None:
    """Whether THP is off for this process (``PR_GET_THP_DISABLE``); None where it cannot be read."""
    if _PRCTL is None:
        return None
    value = _PRCTL(PR_GET_THP_DISABLE, 0, 0, 0, 0)
    return None if value < 0 else bool(value)


def numpy_asks_for_huge_pages() -> bool | None:
    """numpy's setting (None where it has no switch)."""
    if _NUMPY_SWITCH is None:
        return None
    current = _NUMPY_SWITCH(False)
    _NUMPY_SWITCH(current)
    return bool(current)


def _turn_off() -> tuple:
    """Huge pages off; returns what to put back: (THP disabled before or None, numpy's setting or None)."""
    disabled = process_thp_disabled()
    if disabled is not None and _PRCTL(PR_SET_THP_DISABLE, 1, 0, 0, 0) != 0:
        disabled = None
    return disabled, (_NUMPY_SWITCH(False) if _NUMPY_SWITCH is not None else None)


def _put_back(saved: tuple) -> None:
    disabled, numpy_setting = saved
    if disabled is not None:
        _PRCTL(PR_SET_THP_DISABLE, int(disabled), 0, 0, 0)
    if numpy_setting is not None:
        _NUMPY_SWITCH(numpy_setting)


@contextlib.contextmanager
def ordinary_pages():
    """Within: memory first touched comes in 4 kB pages; after the outermost such block
    (blocks nest, or run in two threads at once): the process's settings as they were."""
    global _DEPTH, _SAVED
    with _LOCK:
        if _DEPTH == 0:
            _SAVED = _turn_off()
        _DEPTH += 1
    try:
        yield
    finally:
        with _LOCK:
            _DEPTH -= 1
            if _DEPTH == 0:
                _put_back(_SAVED)


def kept_copy(values: np.ndarray) -> np.ndarray:
    """A read-only copy of ``values`` in memory of its own, mapped for it and first touched
    outside any :func:`ordinary_pages` block, with huge pages asked for as Dr.Jit and numpy
    ask for them (page-aligned, so :func:`~.device_arrays.device_array` maps it as it is).

    Why: Dr.Jit and the C library keep freed memory for their next allocations, so an
    array made after an :func:`ordinary_pages` block may be made in the block's 4 kB pages
    (a depth-11 pyramid's levels made by a kernel after the block: none of 86 sampled pages
    huge; copied into numpy's new arrays: 0-32 of 86). A mapping of its own is new memory.
    Where ``mmap`` has no private anonymous mappings (Windows), an aligned numpy copy."""
    if hasattr(mmap, "MAP_PRIVATE"):
        out = np.frombuffer(_new_mapping(max(values.nbytes, 1)), dtype=values.dtype, count=values.size)
        out = out.reshape(values.shape)
    else:
        out = aligned_empty(values.shape, values.dtype)
    out[...] = values
    out.flags.writeable = False
    return out


def _new_mapping(size: int) -> mmap.mmap:
    """Anonymous memory of ``size`` bytes, with huge pages asked for where Linux has them."""
    mapping = mmap.mmap(-1, size, flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS)  # (a shared one is shmem: no THP)
    if hasattr(mmap, "MADV_HUGEPAGE"):
        try:
            mapping.madvise(mmap.MADV_HUGEPAGE)
        except OSError:  # (a kernel without THP)
            pass
    return mapping
