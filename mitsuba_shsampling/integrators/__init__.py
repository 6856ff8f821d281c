"""Mitsuba integrator plugins using SH product sampling of the environment.

``register()`` registers ``sh_direct`` and ``sh_path`` for the active Mitsuba
variant (registration is per variant). Importing :mod:`mitsuba_shsampling`
calls it when a variant is already set; call it again after switching
variants.
"""

from __future__ import annotations

import mitsuba as mi

PLUGINS = ("sh_direct", "sh_path")


def register() -> None:
    """Register the integrators for the current variant."""
    from .environment import check_variant
    from .sh_direct import SHDirectIntegrator
    from .sh_path import SHPathIntegrator

    check_variant()
    mi.register_integrator("sh_direct", lambda props: SHDirectIntegrator(props))
    mi.register_integrator("sh_path", lambda props: SHPathIntegrator(props))
