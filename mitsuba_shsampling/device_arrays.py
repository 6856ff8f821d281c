"""numpy arrays as Dr.Jit arrays, in memory that every kernel reads the same way.

On the LLVM backend ``mi.Float(array)`` maps the numpy array's memory without a copy,
and drjit-core (1.5) flags the mapping unaligned unless its address is a multiple of
:data:`PACKET_ALIGNMENT`. An unaligned array (1) is read one gather per value where its
layout was made for packet gathers of 2-8 adjacent values, and (2) makes every kernel
that reads it different code (``align 1`` loads). numpy's addresses are 16-byte aligned
and differ from process to process, so the second made the same scene's kernels new to
Dr.Jit's kernel cache in about half of fresh processes: about a second of a plan's set-up
compiled again (docs/MEASUREMENTS.md, "Set-up before the first pass"). Every array this
package builds from numpy for a kernel goes through :func:`device_array`.
"""

from __future__ import annotations

import drjit as dr
import numpy as np

PACKET_ALIGNMENT = 64
"""Bytes to which memory that Dr.Jit maps from numpy must be aligned for it to read 2-8
adjacent values in one packet gather (``dr.gather(mi.Vector4f, ...)``) and to compile
aligned loads (checked in drjit-core 1.5). numpy's large arrays start 16 bytes past a page
(glibc's allocation header), so they never were; small ones were by chance."""

_DTYPES = {dr.VarType.Float32: np.float32, dr.VarType.Float64: np.float64, dr.VarType.UInt32: np.uint32,
           dr.VarType.Int32: np.int32, dr.VarType.Bool: np.bool_}


def device_array(cls, values):
    """``values`` (array-like) as a flat Dr.Jit array of type ``cls`` (``mi.Float``,
    ``mi.UInt32``, ``mi.Int32``, ``mi.Bool``, ``mi.Float64``) over a
    :data:`PACKET_ALIGNMENT`-aligned copy. The bits are kept where ``values`` already has
    ``cls``'s dtype (e.g. uint32 words in a float32 view)."""
    dtype = _DTYPES[dr.type_v(cls)]
    flat = np.ascontiguousarray(values, dtype=dtype).ravel()
    itemsize = flat.itemsize
    storage = np.empty(flat.size + PACKET_ALIGNMENT // itemsize, dtype=dtype)
    start = (-storage.ctypes.data % PACKET_ALIGNMENT) // itemsize
    aligned = storage[start:start + flat.size]
    aligned[...] = flat
    return cls(aligned)
