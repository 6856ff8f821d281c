"""Copies of a scene's ``envmap`` emitter, with or without MIS compensation.

Mitsuba's ``envmap`` samples directions in proportion to its texels' luminance
(optionally minus the mean: ``mis_compensation``); the option is fixed when the
emitter is built. :func:`envmap_description` describes an emitter that holds the
same texels, ``to_world`` and ``scale`` as a given one, so that a scene can be
rebuilt with the option (``report.scene_setup``) and an integrator can sample
the scene's map with the option without touching the scene
(:func:`compensated_copy`).
"""

from __future__ import annotations

import os

import drjit as dr
import mitsuba as mi
import numpy as np


def envmap_description(emitter: mi.Emitter, filename: str | None = None,
                       mis_compensation: bool = False) -> dict:
    """``load_dict`` description of an ``envmap`` like ``emitter``: same ``to_world``
    and ``scale``, texels from ``filename`` (None: the emitter's own), and
    ``mis_compensation``."""
    params = mi.traverse(emitter)
    matrix = np.array(params["to_world"].matrix, dtype=np.float64)
    to_world = mi.ScalarTransform4f(matrix[..., 0] if matrix.ndim == 3 else matrix)
    desc = {"type": "envmap", "to_world": to_world, "scale": float(dr.ravel(params["scale"])[0]),
            "mis_compensation": mis_compensation}
    if filename is not None:
        desc["filename"] = os.path.abspath(filename)
    else:
        # `data` carries one wrap-around halo column on each side. Spectral data is no RGB
        # image: a black one of its size stands in (envmap_like copies the data itself).
        texels = np.array(params["data"])[:, 1:-1]
        if mi.is_spectral:
            texels = np.zeros(texels.shape[:2] + (3,))
        desc["bitmap"] = mi.Bitmap(np.ascontiguousarray(texels, dtype=np.float32))
    return desc


def compensated_copy(emitter: mi.Emitter) -> mi.Emitter:
    """An ``envmap`` with ``emitter``'s texels, ``to_world`` and ``scale``, sampling
    with MIS compensation. Its radiance is ``emitter``'s."""
    return envmap_like(emitter, mis_compensation=True)


def envmap_like(emitter: mi.Emitter, filename: str | None = None, mis_compensation: bool = False) -> mi.Emitter:
    """The ``envmap`` of :func:`envmap_description`. In spectral variants the emitter's
    data holds the spectral model's coefficients, not RGB: a copy of its own texels is
    loaded at their size and then given the data as it is (which rebuilds its sampling)."""
    copy = mi.load_dict(envmap_description(emitter, filename, mis_compensation))
    if filename is None and mi.is_spectral:
        params = mi.traverse(copy)
        data = mi.traverse(emitter)["data"]
        params["data"] = type(data)(data)
        params.update()
    return copy


class EmitterDirections:
    """The environment alone, sampled by Mitsuba's own ``envmap`` code.

    ``sample(u)`` returns (world direction, solid-angle pdf) and ``pdf(d)`` the
    same density: those of ``emitter.sample_direction`` / ``pdf_direction`` (an
    ``envmap``'s depend on the direction only). Traced inline, it costs what
    Mitsuba's emitter sampling costs in ``direct``.
    """

    def __init__(self, emitter: mi.Emitter):
        self.emitter = emitter

    def sample(self, u: mi.Point2f):
        ds, _ = self.emitter.sample_direction(dr.zeros(mi.Interaction3f), u)
        return ds.d, ds.pdf

    def pdf(self, d: mi.Vector3f) -> mi.Float:
        ds = dr.zeros(mi.DirectionSample3f)
        ds.d = d
        return self.emitter.pdf_direction(dr.zeros(mi.Interaction3f), ds)
