"""Reading every traversed parameter of a Mitsuba object, including those without a value.

``mi.traverse`` lists every parameter a plugin exposes, and some plugins list one
they never created: a ``hair`` BSDF given melanin concentrations lists ``sigma_a``
with the value ``None``, and reading it raises ``TypeError`` (``SceneParameters``
hashes the value's Dr.Jit indices as it is read). What reads *every* parameter
(the integrators' scene cache, the reference cache's key) reads through
:func:`readable_parameters`; a missing value depends on the other parameters
(the melanin concentrations), which are read.
"""

from __future__ import annotations

import re

import drjit as dr
import mitsuba as mi
import numpy as np


def readable_parameters(params: mi.SceneParameters) -> list[tuple[str, object]]:
    """(key, value) of each parameter of ``params`` that has a value, in traversal order."""
    values = []
    for key in params.keys():
        try:
            values.append((key, params[key]))
        except TypeError:  # listed but never created (see the module docstring)
            continue
    return values


def content_parts(obj: mi.Object) -> list:
    """What determines ``obj``'s behaviour, for a content key
    (:func:`~mitsuba_shsampling.build_cache.content_key`): its class, its description
    (``str``: the settings no parameter exposes, such as a microfacet distribution;
    addresses, invented object names and a sampler's last wavefront removed) and every traversed parameter's value
    (arrays as numpy, others as they are)."""
    described = re.sub(r"0x[0-9a-fA-F]+|object_\d+", "", str(obj))
    # A sampler describes its last render's wavefront too: state, not content.
    described = re.sub(r"\n *(samples_per_wavefront|wavefront_size) = [^\n]*", "", described)
    parameters = [(re.sub(r"object_\d+", "object", key), value) for key, value in readable_parameters(mi.traverse(obj))]
    if isinstance(obj, mi.Scene):
        # Mitsuba's parallel loading lists a scene's objects in another order in each process:
        # the same scene must give the same key (its plan is kept by it). Each parameter's
        # name says which object it belongs to, so sorting loses nothing that matters.
        described = "\n".join(sorted(described.splitlines()))
        parameters.sort(key=lambda item: item[0])
    parts = [obj.class_name(), described]
    for key, value in parameters:
        parts += [key, _host_value(value)]
    return parts


def _host_value(value):
    if dr.is_array_v(value):
        # Read through a detached copy: evaluating a literal (a scale, say) gives the
        # evaluated array a new variable, which would look like a parameter change to
        # SceneCache; and a plain copy of a differentiable parameter would be an AD edge.
        copy = dr.detach(value) if dr.is_diff_v(value) else type(value)(value)
        return np.asarray(copy.numpy())
    return value
