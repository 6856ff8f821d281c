"""Ordinary 4 kB pages for the set-up's short-lived memory; huge pages for what the passes read.

Dr.Jit (every allocation over 2 MB) and numpy (every array of 4 MB or more) ask Linux for
transparent huge pages (``madvise(MADV_HUGEPAGE)``). Where THP is set to ``madvise``
(Debian's and Ubuntu's default) the first touch of each 2 MB page clears it whole, and on a
virtual machine whose host takes free memory back (the development VM: Firecracker, free
page reporting) a free 2 MB block is exactly what the host took, so each such page is
faulted in again from the host as well. A new scene's set-up touches several times the
memory it keeps, each of it once (the studio under a depth-11 map: ~450 MB; the pyramid
keeps 39 MB): there those faults cost 0.7-1.3 s of system time, varying from run to run
by as much (docs/MEASUREMENTS.md, "Set-up on ordinary pages").

- :func:`setup_memory` marks a new scene's host set-up (its state's build, its plan): inside, huge pages
  are off for the process (:func:`ordinary_pages`: ``prctl(PR_SET_THP_DISABLE)``, read at
  each page fault, and numpy's request), so the temporaries come in 4 kB pages from memory
  the system had at hand. When the outermost block ends after such work, the memory the
  work freed is handed back (:func:`release_freed_memory`): Dr.Jit and the C library give a
  freed block to the next allocation of its size, and the passes' own arrays would otherwise
  land on the set-up's small pages (with the whole set-up on 4 kB pages and nothing handed
  back, the passes ran 1-3 % slower).
- :func:`kept_copy` copies what the passes read for the whole render (a pyramid's levels
  and leaf records, the cosine tables: random gathers, where the page size shows) into a
  mapping of its own, with huge pages allowed for that copy even inside a block.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import mmap
import sys
import threading

import drjit as dr
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


def _malloc_trim():
    """glibc's ``malloc_trim``, None elsewhere."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        trim = ctypes.CDLL(ctypes.util.find_library("c") or None).malloc_trim
    except (OSError, AttributeError):  # (musl has none)
        return None
    trim.restype, trim.argtypes = ctypes.c_int, [ctypes.c_size_t]
    return trim


_NUMPY_SWITCH = _numpy_switch()
_PRCTL = _prctl()
_MALLOC_TRIM = _malloc_trim()
_LOCK = threading.Lock()
_DEPTH = 0
_SAVED: tuple = (None, None)
_OPEN = 0
_WORK_DONE = False


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


@contextlib.contextmanager
def setup_memory(work: bool = True):
    """A new scene's host set-up work (``work``: its state's build, its plan), or a scope that
    may contain some (``work=False``: an integrator's host step before a pass, which builds
    or plans only where the scene is new). Work runs within :func:`ordinary_pages`; a scope
    alone changes no page setting. When the outermost such block ends and some block inside
    it did work, the memory that work freed is handed back (:func:`release_freed_memory`),
    once; a scope without work hands nothing back (a pass's arrays stay with Dr.Jit for the
    next pass). A rebuild after a parameter change (an optimisation step) is no such work:
    it keeps huge pages, and hands nothing back, as every pass."""
    global _OPEN, _WORK_DONE
    with _LOCK:
        _OPEN += 1
    release = False
    try:
        with ordinary_pages() if work else contextlib.nullcontext():
            yield
    finally:
        with _LOCK:
            _OPEN -= 1
            _WORK_DONE = _WORK_DONE or work
            release = _OPEN == 0 and _WORK_DONE
            if release:
                _WORK_DONE = False
        if release:
            release_freed_memory()


def release_freed_memory() -> None:
    """Hand the memory freed so far back to the system: Dr.Jit's cache of freed blocks
    (``flush_malloc_cache``), then the C library's (``malloc_trim``, where it is glibc's), so
    that the next allocations get new memory (with huge pages, outside :func:`ordinary_pages`)."""
    dr.flush_malloc_cache()
    if _MALLOC_TRIM is not None:
        _MALLOC_TRIM(0)


def kept_copy(values: np.ndarray) -> np.ndarray:
    """A read-only copy of ``values`` in memory of its own, mapped for it and first touched
    with the process's own huge-page settings (inside an :func:`ordinary_pages` block too),
    with huge pages asked for as Dr.Jit and numpy
    ask for them (page-aligned, so :func:`~.device_arrays.device_array` maps it as it is).

    Why: Dr.Jit and the C library keep freed memory for their next allocations, so an
    array made after an :func:`ordinary_pages` block may be made in the block's 4 kB pages
    (a depth-11 pyramid's levels made by a kernel after the block: none of 86 sampled pages
    huge; copied into numpy's new arrays: 0-32 of 86). A mapping of its own is new memory,
    and inside a block huge pages are allowed while the copy first touches it.
    Where ``mmap`` has no private anonymous mappings (Windows), an aligned numpy copy."""
    if hasattr(mmap, "MAP_PRIVATE"):
        out = np.frombuffer(_new_mapping(max(values.nbytes, 1)), dtype=values.dtype, count=values.size)
        out = out.reshape(values.shape)
    else:
        out = aligned_empty(values.shape, values.dtype)
    with _LOCK:
        inside = _DEPTH > 0
        if inside:
            _put_back(_SAVED)  # the user's settings, for this copy's first touch
        try:
            _fill(out, values)
        finally:
            if inside:
                _turn_off()  # (what it returns is the user's settings again: _SAVED keeps them)
    out.flags.writeable = False
    return out


def _fill(out: np.ndarray, values: np.ndarray) -> None:
    """The copy that first touches a kept copy's memory."""
    out[...] = values


def _new_mapping(size: int) -> mmap.mmap:
    """Anonymous memory of ``size`` bytes, with huge pages asked for where Linux has them."""
    mapping = mmap.mmap(-1, size, flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS)  # (a shared one is shmem: no THP)
    if hasattr(mmap, "MADV_HUGEPAGE"):
        try:
            mapping.madvise(mmap.MADV_HUGEPAGE)
        except OSError:  # (a kernel without THP)
            pass
    return mapping
