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


def aligned_empty(shape, dtype) -> np.ndarray:
    """``np.empty(shape, dtype)`` whose first element is :data:`PACKET_ALIGNMENT`-aligned (made
    read-only once written, :func:`device_array` maps it without a copy)."""
    dtype = np.dtype(dtype)
    count = int(np.prod(shape))
    storage = np.empty(count + PACKET_ALIGNMENT // dtype.itemsize, dtype=dtype)
    start = (-storage.ctypes.data % PACKET_ALIGNMENT) // dtype.itemsize
    return storage[start:start + count].reshape(shape)


def device_array(cls, values):
    """``values`` (array-like) as a flat Dr.Jit array of type ``cls`` (``mi.Float``,
    ``mi.UInt32``, ``mi.Int32``, ``mi.Bool``, ``mi.Float64``) over a
    :data:`PACKET_ALIGNMENT`-aligned copy, or over ``values`` itself where it is a read-only,
    contiguous and aligned array of that dtype. The bits are kept where ``values`` already has
    ``cls``'s dtype (e.g. uint32 words in a float32 view)."""
    dtype = _DTYPES[dr.type_v(cls)]
    flat = np.ascontiguousarray(values, dtype=dtype).ravel()
    if not flat.flags.writeable and flat.ctypes.data % PACKET_ALIGNMENT == 0:
        # Read-only and aligned (e.g. a build's arrays, views of Dr.Jit's own memory): mapped as
        # it is. A read-only array is taken as one that nothing writes to again; the copy of a
        # pyramid's 32 MB leaf records was 0.01-0.09 s of each build (docs/MEASUREMENTS.md).
        return cls(flat)
    aligned = aligned_empty(flat.size, dtype)
    aligned[...] = flat
    return cls(aligned)
