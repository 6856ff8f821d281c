"""Plans kept in files: ``plan_file``, and plans kept in the cache folder like FFTW's wisdom.

A plan file is JSON: the strategy of each material (by name), whether the kernel
is lean, which cosine lobes read their tables, which materials' ``product_only`` gives
the BSDF its share, the options it was made with (every
option but the plan's own, :attr:`~.options.ProductOptions.plan_key`) and the whole
plan as the reports show it. It is loaded only for a scene with the same materials
and the same options; otherwise a new plan is made and the file rewritten (with a
warning that says why). A loaded plan runs exactly what it says: the same
strategies, the same kernel.

Without a ``plan_file``, every plan is kept in the cache folder
(:mod:`~mitsuba_shsampling.build_cache`) under a key of the scene's content (every
traversed parameter, the film's size) and the options (and, for an estimated plan, the
cost model's figures), so a scene planned once is planned the same way, without pilots
or quadrature, in every later process (the plan's ``mode`` then reads ``kept``).
"""

from __future__ import annotations

import json
import os
import warnings

import mitsuba as mi

from ..build_cache import cache_folder, content_key
from ..traversal import content_parts
from .strategy import strategy_named

FORMAT = 1
"""Version of the file layout."""


def wisdom_path(scene: mi.Scene, sensor: mi.Sensor, options_key: str) -> str:
    """Where a plan of this scene (content and film size) and this ``options_key`` is kept
    ("" where the cache folder is off)."""
    folder = cache_folder()
    if not folder:
        return ""
    key = content_key(*content_parts(scene), tuple(sensor.film().crop_size()), options_key, mi.variant())
    return os.path.join(folder, "plans", key + ".json")


def save(path: str, choice, options_key: str) -> None:
    """Write ``choice`` (:class:`~.chooser.StrategyChoice`) to ``path``."""
    record = {"format": FORMAT, "options": options_key, "strategies": choice.assignment(), "lean": choice.lean,
              "cosine_tables": list(choice.cosine_tables), "bsdf_shares": list(choice.bsdf_shares),
              "plan": choice.as_dict()}
    try:
        folder = os.path.dirname(os.path.abspath(path))
        os.makedirs(folder, exist_ok=True)
        with open(path, "w") as f:
            json.dump(record, f, indent=1)
    except OSError as err:
        warnings.warn(f"mitsuba_shsampling: cannot write the plan file {path} ({err})", RuntimeWarning)


def load(path: str, env, options_key: str) -> dict | None:
    """The plan stored in ``path`` if it fits ``env``'s scene and ``options_key``: material
    registry id -> :class:`~.strategy.Strategy` (``strategies``), ``lean``, the names of the
    materials whose cosine lobes read their tables (``cosine_tables``) and the plan as shown
    (``plan``). None where there is no file, and with a warning where it cannot be read or
    does not fit (the chooser then makes a plan and rewrites the file)."""
    if not os.path.exists(path):
        return None
    try:
        with open(path) as f:
            record = json.load(f)
        stored = {name: strategy_named(label) for name, label in record["strategies"].items()}
        fits = record.get("format") == FORMAT and record["options"] == options_key
        lean, cosine_tables = bool(record["lean"]), list(record.get("cosine_tables", []))
        bsdf_shares = list(record.get("bsdf_shares", []))
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as err:
        warnings.warn(f"{env.plugin}: the plan file {path} cannot be read ({err}); making a new plan", RuntimeWarning)
        return None
    by_name = {env.material_name(key): key for key in env.strategies.ids}
    why = ("it was made with other options" if not fits
           else "its materials are not this scene's" if set(stored) != set(by_name)
           else next((f"material '{n}' cannot run '{s.label}' here" for n, s in stored.items()
                      if s not in env.allowed(by_name[n])), None))
    if why:
        warnings.warn(f"{env.plugin}: the plan file {path} does not fit ({why}); making a new plan", RuntimeWarning)
        return None
    return {"strategies": {by_name[name]: strategy for name, strategy in stored.items()}, "lean": lean,
            "cosine_tables": cosine_tables, "bsdf_shares": bsdf_shares, "plan": record.get("plan", {})}
