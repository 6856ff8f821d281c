"""What the commands share: the default variant, the sampler names, the bad-input error and
the checked variant switch.

It sits below :mod:`.cli` and :mod:`.sweep`, which both read it, so the command line and the
sweep grid agree on every default without importing each other.
"""

from __future__ import annotations

from ._backend import DEFAULT_VARIANT, unsupported_variant_reason

#: Mitsuba samplers a comparison may use (``--sampler``, a grid's ``samplers``).
SAMPLERS = ("independent", "stratified", "multijitter", "ldsampler")

__all__ = ["DEFAULT_VARIANT", "SAMPLERS", "UsageError", "set_variant"]


class UsageError(Exception):
    """Bad input from the command line: reported in one line, exit code 2."""


def set_variant(variant: str) -> None:
    """``mi.set_variant(variant)``, or :class:`UsageError` saying why this variant cannot be used
    (unsupported by the plugins, missing from this Mitsuba build, or failing here)."""
    import mitsuba_shsampling  # noqa: F401  (checks the LLVM backend before Mitsuba traces anything)
    import mitsuba as mi

    reason = unsupported_variant_reason(variant)
    if reason is not None:
        raise UsageError(reason)
    if variant not in mi.variants():
        raise UsageError(f"variant '{variant}' is not available in this Mitsuba build (available: "
                         f"{', '.join(v for v in mi.variants() if unsupported_variant_reason(v) is None)})")
    try:
        mi.set_variant(variant)
    except Exception as err:  # e.g. a cuda_ variant on a machine without a GPU
        raise UsageError(f"variant '{variant}' cannot be used here: {str(err).splitlines()[0]}") from None
