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

import mitsuba as mi


def readable_parameters(params: mi.SceneParameters) -> list[tuple[str, object]]:
    """(key, value) of each parameter of ``params`` that has a value, in traversal order."""
    values = []
    for key in params.keys():
        try:
            values.append((key, params[key]))
        except TypeError:  # listed but never created (see the module docstring)
            continue
    return values
