"""Mitsuba integrator plugins using SH product sampling of the environment.

Mitsuba registrations are per variant. Importing :mod:`mitsuba_shsampling`
calls :func:`register` for the active variant and installs a Mitsuba variant
callback that calls it again after every ``mi.set_variant``, so ``sh_direct``,
``sh_path``, ``sh_prb`` and the references ``oracle_direct`` and ``oracle_path`` are always
known to ``mi.load_dict`` and the XML parser.

Under a variant the plugins cannot run on (scalar, polarized), all
names are registered to a stub that raises
:class:`~mitsuba_shsampling.VariantError` with the reason when a scene or
dict instantiates it, instead of Mitsuba's generic "plugin not found".
"""

from __future__ import annotations

import importlib

import mitsuba as mi

from .._backend import BackendError, VariantError, check_backend, unsupported_variant_reason

#: Every plugin this package registers.
PLUGIN_NAMES = ("sh_direct", "sh_path", "sh_prb", "oracle_direct", "oracle_path")

_class_variant: str | None = None


def _plugin_classes() -> dict[str, type]:
    """Plugin name -> class, bound to the current variant.

    A Python subclass of ``mi.SamplingIntegrator`` is tied to the variant that
    was active when its ``class`` statement ran, so the modules are re-executed
    after a variant switch (as Mitsuba does for its own Python integrators;
    ``sh_prb``'s base class, Mitsuba's ``RBIntegrator``, is rebound by Mitsuba).
    """
    global _class_variant
    from . import oracle_direct, oracle_path, sh_direct, sh_path, sh_prb

    if _class_variant is not None and _class_variant != mi.variant():
        sh_direct = importlib.reload(sh_direct)
        sh_path = importlib.reload(sh_path)
        sh_prb = importlib.reload(sh_prb)
        oracle_direct = importlib.reload(oracle_direct)
        oracle_path = importlib.reload(oracle_path)
    _class_variant = mi.variant()
    return {"sh_direct": sh_direct.SHDirectIntegrator, "sh_path": sh_path.SHPathIntegrator,
            "sh_prb": sh_prb.SHPRBIntegrator, "oracle_direct": oracle_direct.OracleDirectIntegrator,
            "oracle_path": oracle_path.OraclePathIntegrator}


def _refusal(reason: str, error: type = VariantError):
    message = reason if reason.startswith("mitsuba_shsampling:") else f"mitsuba_shsampling: {reason}"

    def refuse(props: mi.Properties):
        raise error(message)
    return refuse


def register() -> None:
    """Register the plugins (:data:`PLUGIN_NAMES`) for the current variant (as stubs
    that raise :class:`~mitsuba_shsampling.VariantError` under unsupported ones).

    :raises VariantError: no variant is set.
    :raises BackendError: an LLVM variant is set and Dr.Jit has no usable libLLVM.
    """
    reason = unsupported_variant_reason(mi.variant())
    if mi.variant() is None:
        raise VariantError(f"mitsuba_shsampling: {reason}")
    if reason is not None:
        for name in PLUGIN_NAMES:
            mi.register_integrator(name, _refusal(reason))
        return
    try:
        check_backend(mi.variant())
    except BackendError as error:
        # Loading a plugin later says so too, rather than Mitsuba's "plugin not found".
        for name in PLUGIN_NAMES:
            mi.register_integrator(name, _refusal(str(error), BackendError))
        raise
    for name, cls in _plugin_classes().items():
        mi.register_integrator(name, lambda props, cls=cls: cls(props))


def _register_for_new_variant(old: str | None, new: str | None) -> None:
    """Mitsuba variant callback (see :func:`mitsuba.detail.add_variant_callback`)."""
    if new is not None:
        register()
