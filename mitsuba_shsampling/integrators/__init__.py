"""Mitsuba integrator plugins using SH product sampling of the environment.

``register()`` registers ``sh_direct`` and ``sh_path`` for the active Mitsuba
variant (Mitsuba registrations are per variant). Importing
:mod:`mitsuba_shsampling` calls it when a variant is already set; call it
again after switching variants.
"""

from __future__ import annotations

import importlib

import mitsuba as mi

PLUGINS = ("sh_direct", "sh_path")
_registered_variants: set[str] = set()
_class_variant: str | None = None


def _plugin_classes():
    """The plugin classes bound to the current variant.

    A Python subclass of ``mi.SamplingIntegrator`` is tied to the variant that
    was active when its ``class`` statement ran, so the modules are re-executed
    after a variant switch.
    """
    global _class_variant
    from . import sh_direct, sh_path

    if _class_variant is not None and _class_variant != mi.variant():
        sh_direct = importlib.reload(sh_direct)
        sh_path = importlib.reload(sh_path)
    _class_variant = mi.variant()
    return sh_direct.SHDirectIntegrator, sh_path.SHPathIntegrator


def register() -> None:
    """Register ``sh_direct`` and ``sh_path`` for the current variant."""
    from .environment import check_variant

    check_variant()
    direct_cls, path_cls = _plugin_classes()
    mi.register_integrator("sh_direct", lambda props: direct_cls(props))
    mi.register_integrator("sh_path", lambda props: path_cls(props))
    _registered_variants.add(mi.variant())


def register_if_variant_set() -> bool:
    """Register for the active variant if there is one it supports; returns success."""
    variant = mi.variant()
    if variant is None:
        return False
    try:
        register()
    except RuntimeError:
        return False
    return True
