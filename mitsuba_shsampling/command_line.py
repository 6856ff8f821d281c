"""What the commands share: the default variant, the sampler names, the bad-input error, the
checked variant switch, the check of a comparison's ``max_depth`` and of an output folder.

It sits below :mod:`.cli` and :mod:`.sweep`, which both read it, so the command line and the
sweep grid agree on every default without importing each other.
"""

from __future__ import annotations

import os

from ._backend import DEFAULT_VARIANT, unsupported_variant_reason

#: Mitsuba samplers a comparison may use (``--sampler``, a grid's ``samplers``).
SAMPLERS = ("independent", "stratified", "multijitter", "ldsampler")

__all__ = ["DEFAULT_VARIANT", "SAMPLERS", "UsageError", "check_output_folder", "max_depth_problem", "set_variant"]


class UsageError(Exception):
    """Bad input from the command line: reported in one line, exit code 2."""


def max_depth_problem(max_depth: int) -> str | None:
    """Why ``max_depth`` cannot be a comparison's depth (``compare --max-depth``, a sweep grid's
    ``max_depth``), or None if it can: -1 (infinite, as Mitsuba's) or at least 2 (direct lighting).
    Below 2 no light is reflected, so there is nothing to compare."""
    if isinstance(max_depth, bool) or not isinstance(max_depth, int):  # a grid file's value
        return f"must be an integer, got {max_depth!r}"
    if max_depth < 2 and max_depth != -1:
        return (f"must be -1 (infinite, as Mitsuba's) or at least 2 (direct lighting), got {max_depth}: "
                f"below 2 no light is reflected to compare")
    return None


def check_output_folder(path: str, option: str = "--out") -> None:
    """:class:`UsageError` unless ``path`` can be an output folder: an existing folder, or a new
    one whose nearest existing ancestor is a folder (``os.makedirs`` would otherwise fail
    after the run's work, with a traceback)."""
    existing = os.path.abspath(path)
    while not os.path.exists(existing):
        existing = os.path.dirname(existing)
    if not os.path.isdir(existing):
        where = "is" if existing == os.path.abspath(path) else f"is inside {existing}, which is"
        raise UsageError(f"{option} {path} {where} a file, not a folder")


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
