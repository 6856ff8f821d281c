"""The sweep grid: a TOML file naming scenes, maps, samplers, methods and compare settings.

One grid cell is one ``compare`` job: a scene x map x sampler with all the grid's methods.
Example (``sweeps/readme_table.toml`` is a full one)::

    scenes = ["sphere_ggx010", "../my_scenes/teapot.xml"]   # built-in names or XML files
    maps = ["sunsky", "../tests/data/envmaps/*.hdr"]         # built-in names, files, globs, "scene"
    samplers = ["independent"]
    methods = ["direct", "direct_misc", "env_only", "bsdf_only", "sh_direct"]
    res = 96
    spp = 16
    passes = 4
    ref_spp = 1024
    convergence_max_spp = 0

Conventions:

- Relative paths and globs are relative to the folder of the grid file; matches of a glob
  are taken in sorted order. A cell's files must be visible under the same absolute path
  on every worker (a shared filesystem); built-in scenes and maps are looked up on the
  worker itself (:func:`mitsuba_shsampling.scenes.builtin_scenes`).
- The map ``"scene"`` keeps each scene's own environment (no ``--envmap``).
- Compare settings the grid leaves out (``res``, ``spp``, ...) take ``compare``'s defaults.
- Scene and map names (built-in name or file stem) label the cells, so they must be unique.
"""

from __future__ import annotations

import dataclasses
import glob
import os

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

from .. import scenes as builtin
from .._backend import unsupported_variant_reason
from ..command_line import DEFAULT_VARIANT, SAMPLERS, max_depth_problem

#: Keyword of ``maps``: keep the scene's own environment.
SCENE_MAP = "scene"


def _at_least(minimum: int):
    """The check of an integer setting bounded below: what is wrong with a value, or None."""
    def problem(value) -> str | None:
        if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
            return f"must be an integer >= {minimum}, got {value!r}"
        return None
    return problem


#: Integer compare settings a grid may set, each with its check; ``max_depth`` is checked as
#: ``compare --max-depth`` is (-1 or at least 2).
INT_SETTINGS = {"res": _at_least(1), "spp": _at_least(1), "passes": _at_least(2), "ref_spp": _at_least(1),
                "max_depth": max_depth_problem, "seed": _at_least(0), "convergence_max_spp": _at_least(0)}
LIST_KEYS = ("scenes", "maps", "samplers", "methods")


class GridError(ValueError):
    """The grid file is unreadable, names something that does not exist, or has a bad value."""


@dataclasses.dataclass(frozen=True)
class Source:
    """A scene or map of the grid: a built-in (looked up where it is used) or a file.

    :param name: label of the cells (built-in name, file stem, or ``"scene"`` for a map).
    :param file: absolute path for a file, None for a built-in or the scene's own map.
    """

    name: str
    file: str | None = None

    def path(self, table: dict[str, str]) -> str | None:
        """The file to load: ``file``, or the built-in ``name`` in ``table`` (None for ``"scene"``)."""
        if self.file is not None:
            return self.file
        return table.get(self.name)


@dataclasses.dataclass(frozen=True)
class Cell:
    """One ``compare`` job: scene x map x sampler, with the grid's methods and settings.

    ``settings`` holds only what the grid sets (``res``, ``spp``, ``passes``, ``ref_spp``,
    ``max_depth``, ``seed``, ``convergence_max_spp``); ``methods`` is None for compare's default.
    """

    scene: Source
    map: Source
    sampler: str
    methods: tuple[str, ...] | None
    settings: tuple[tuple[str, int], ...]
    variant: str = DEFAULT_VARIANT

    @property
    def label(self) -> str:
        """``scene/map/sampler``: how tables and progress bars name the cell."""
        return f"{self.scene.name}/{self.map.name}/{self.sampler}"

    def scene_path(self) -> str:
        """The scene file on this machine (built-ins resolved here, not where the grid was read)."""
        return self.scene.path(builtin.builtin_scenes())

    def map_path(self) -> str | None:
        """The map file on this machine, or None to keep the scene's own environment."""
        return self.map.path(builtin.builtin_envmaps())


@dataclasses.dataclass(frozen=True)
class Grid:
    """A parsed grid file; :meth:`cells` enumerates it scene-major, then map, then sampler."""

    path: str
    scenes: tuple[Source, ...]
    maps: tuple[Source, ...]
    samplers: tuple[str, ...]
    methods: tuple[str, ...] | None
    settings: tuple[tuple[str, int], ...]
    variant: str

    def cells(self) -> list[Cell]:
        return [Cell(scene, env, sampler, self.methods, self.settings, self.variant)
                for scene in self.scenes for env in self.maps for sampler in self.samplers]

    def describe(self) -> dict:
        """JSON-ready summary of the grid (for the aggregate report)."""
        return {"path": self.path,
                "scenes": [dataclasses.asdict(s) for s in self.scenes],
                "maps": [dataclasses.asdict(m) for m in self.maps],
                "samplers": list(self.samplers),
                "methods": list(self.methods) if self.methods else None,
                "settings": dict(self.settings), "variant": self.variant}


def _string_list(data: dict, key: str, required: bool) -> list[str] | None:
    value = data.get(key)
    if value is None:
        if required:
            raise GridError(f"the grid needs a '{key}' list")
        return None
    if isinstance(value, str):
        value = [value]
    if not isinstance(value, list) or not value or not all(isinstance(v, str) and v for v in value):
        raise GridError(f"'{key}' must be a non-empty list of strings")
    return value


def _expand(entry: str, folder: str, what: str) -> list[str]:
    """Absolute files named by ``entry`` (a path or a glob, relative to ``folder``)."""
    pattern = os.path.normpath(os.path.join(folder, os.path.expanduser(entry)))
    if glob.has_magic(entry):
        files = sorted(f for f in glob.glob(pattern) if os.path.isfile(f))
        if not files:
            raise GridError(f"{what} pattern '{entry}' matches no file (looked in {os.path.dirname(pattern)})")
        return files
    if not os.path.isfile(pattern):
        raise GridError(f"{what} file not found: {entry} (resolved to {pattern})")
    return [pattern]


def _sources(entries: list[str], table: dict[str, str], folder: str, what: str,
             keywords: tuple[str, ...] = ()) -> tuple[Source, ...]:
    out: list[Source] = []
    for entry in entries:
        if entry in keywords:
            out.append(Source(entry))
        elif entry in table:
            out.append(Source(entry))
        elif glob.has_magic(entry) or os.sep in entry or "." in entry:
            out += [Source(os.path.splitext(os.path.basename(f))[0], f) for f in _expand(entry, folder, what)]
        else:
            raise GridError(f"unknown built-in {what} '{entry}' (built-ins: {', '.join(table)}; "
                            f"or give a file path)")
    names = [s.name for s in out]
    duplicates = sorted({n for n in names if names.count(n) > 1})
    if duplicates:
        raise GridError(f"{what} names must be unique, and {', '.join(duplicates)} appear more than once "
                        f"(rename a file: cells are labelled by file stem)")
    return tuple(out)


def load_grid(path: str) -> Grid:
    """Read and check a grid file; every file it names must exist here.

    :raises GridError: unreadable TOML, unknown key, missing file or built-in, bad value.
    """
    try:
        with open(path, "rb") as f:
            data = tomllib.load(f)
    except FileNotFoundError:
        raise GridError(f"grid file not found: {path}") from None
    except tomllib.TOMLDecodeError as err:
        raise GridError(f"cannot parse grid file {path}: {err}") from None
    known = set(LIST_KEYS) | set(INT_SETTINGS) | {"variant"}
    unknown = sorted(set(data) - known)
    if unknown:
        raise GridError(f"unknown key(s) {', '.join(unknown)} in {path} (known: {', '.join(sorted(known))})")
    folder = os.path.dirname(os.path.abspath(path))

    scenes = _sources(_string_list(data, "scenes", True), builtin.builtin_scenes(), folder, "scene")
    maps = _sources(_string_list(data, "maps", False) or [SCENE_MAP], builtin.builtin_envmaps(),
                    folder, "map", keywords=(SCENE_MAP,))
    samplers = _string_list(data, "samplers", False) or ["independent"]
    bad = [s for s in samplers if s not in SAMPLERS]
    if bad:
        raise GridError(f"unknown sampler(s) {', '.join(bad)}; choose among {', '.join(SAMPLERS)}")
    methods = _string_list(data, "methods", False)
    if methods:
        from ..report.methods import METHODS
        known_methods = [m.name for m in METHODS]
        bad = [m for m in methods if m not in known_methods]
        if bad:
            raise GridError(f"unknown method(s) {', '.join(bad)} (known: {', '.join(known_methods)})")

    settings = []
    for key, problem in INT_SETTINGS.items():
        if key in data:
            why = problem(data[key])
            if why:
                raise GridError(f"'{key}' {why}")
            settings.append((key, data[key]))
    variant = data.get("variant", DEFAULT_VARIANT)
    if not isinstance(variant, str):
        raise GridError(f"'variant' must be a string naming a JIT variant (e.g. {DEFAULT_VARIANT}), got {variant!r}")
    reason = unsupported_variant_reason(variant)
    if reason is not None:
        raise GridError(f"'variant': {reason}")
    return Grid(os.path.abspath(path), scenes, maps, tuple(samplers),
                tuple(methods) if methods else None, tuple(settings), variant)
