"""Content keys of grid cells, and the per-cell job: one ``compare`` run.

A cell's key hashes everything its result depends on, so that a sweep run again
recomputes exactly the cells whose inputs changed:

- the bytes of the scene file, of every file it includes and of every file a
  ``<string>`` value of it names (after ``$name`` substitution with the cell's map and
  the scene's defaults), found by a plain XML scan (:func:`scene_files`);
- the bytes of the map file;
- the cell's sampler, methods, compare settings and variant;
- the code version (:func:`code_version`): this package's version and a hash of its
  ``.py`` files, and the Mitsuba and Dr.Jit versions.

:func:`run_cell` is the only place that calls ``compare``; it runs wherever the cell is
scheduled and returns the report folder as a zip archive, so workers need no access to
the sweep's output folder.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import importlib.metadata
import io
import json
import os
import re
import socket
import tempfile
import time
import traceback
import xml.etree.ElementTree as ET
import zipfile

import mitsuba_shsampling

from .grid import SCENE_MAP, Cell

PACKAGE_DIR = os.path.dirname(os.path.abspath(mitsuba_shsampling.__file__))
#: Innermost traceback frames a failed cell's ``error`` keeps (``traceback`` has them all).
ERROR_FRAMES = 3


@functools.lru_cache(maxsize=1)
def code_version() -> str:
    """``<package version>+<hash of the package's .py files>`` and the Mitsuba / Dr.Jit versions."""
    digest = hashlib.sha256()
    for folder, dirs, files in os.walk(PACKAGE_DIR):
        dirs[:] = sorted(d for d in dirs if d != "__pycache__")
        for name in sorted(f for f in files if f.endswith(".py")):
            path = os.path.join(folder, name)
            digest.update(os.path.relpath(path, PACKAGE_DIR).encode() + b"\0")
            with open(path, "rb") as f:
                digest.update(f.read())
    versions = ", ".join(f"{lib} {importlib.metadata.version(lib)}" for lib in ("mitsuba", "drjit"))
    return f"{mitsuba_shsampling.__version__}+{digest.hexdigest()[:12]} ({versions})"


@functools.lru_cache(maxsize=None)
def _file_digest(path: str, mtime_ns: int, size: int) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def file_digest(path: str) -> str:
    """SHA-256 of a file's bytes (memoised per path, modification time and size)."""
    stat = os.stat(path)
    return _file_digest(os.path.abspath(path), stat.st_mtime_ns, stat.st_size)


_PARAMETER = re.compile(r"\$(\w+)")


def scene_files(scene_path: str, params: dict[str, str] | None = None) -> list[str]:
    """The scene file, then every file it references, as far as a plain XML scan finds them.

    Follows ``<include filename=...>`` recursively and takes every ``<string value=...>`` that
    names an existing file (bitmaps, meshes, the envmap, ...), after substituting ``$name``
    with ``params`` or else the ``<default>`` values seen so far. Relative names are looked up
    next to the referring file, then next to the scene file. A file that does not parse as
    XML is still listed (its bytes count), its references are not.

    :returns: absolute paths, the scene first, each once.
    """
    top = os.path.dirname(os.path.abspath(scene_path))
    values = dict(params or {})
    found: list[str] = []

    def resolve(name: str, folder: str) -> str | None:
        name = _PARAMETER.sub(lambda m: values.get(m.group(1), m.group(0)), name)
        for base in (folder, top):
            candidate = os.path.normpath(os.path.join(base, name))
            if os.path.isfile(candidate):
                return candidate
        return None

    def visit(path: str) -> None:
        if path in found:
            return
        found.append(path)
        if not path.endswith(".xml"):
            return
        try:
            root = ET.parse(path).getroot()
        except (ET.ParseError, OSError):
            return
        for default in root.iter("default"):
            values.setdefault(default.get("name"), default.get("value", ""))
        for element in root.iter():
            name = element.get("filename") if element.tag == "include" else (
                element.get("value") if element.tag == "string" else None)
            if name:
                resolved = resolve(name, os.path.dirname(path))
                if resolved is not None:
                    visit(resolved)

    visit(os.path.abspath(scene_path))
    return found


def cell_inputs(cell: Cell) -> dict:
    """Everything the result of ``cell`` depends on, with files by content (JSON-ready)."""
    scene = cell.scene_path()
    envmap = cell.map_path()
    files = scene_files(scene, {"envmap": envmap} if envmap else None)
    if envmap and os.path.abspath(envmap) not in files:
        files.append(os.path.abspath(envmap))
    top = os.path.dirname(os.path.abspath(scene))

    def shown(path: str) -> str:
        rel = os.path.relpath(path, top)
        return path if rel.startswith("..") else rel

    return {
        "scene": cell.scene.name, "map": cell.map.name, "sampler": cell.sampler,
        "methods": list(cell.methods) if cell.methods else None,
        "settings": dict(cell.settings), "variant": cell.variant, "code": code_version(),
        "files": [[shown(f), file_digest(f)] for f in files],
        "map_file": [shown(envmap), file_digest(envmap)] if envmap else None,
    }


def cell_key(inputs: dict) -> str:
    """16 hex digits of the SHA-256 of :func:`cell_inputs`."""
    return hashlib.sha256(json.dumps(inputs, sort_keys=True).encode()).hexdigest()[:16]


@dataclasses.dataclass
class CellResult:
    """What one cell's job returns.

    :param status: ``"ok"`` or ``"failed"``.
    :param archive: zip of the compare report folder (``report.json``, ``index.html``, images);
        None if the cell failed.
    :param error: if the cell failed, :func:`describe_failure` of its exception.
    :param traceback: the full traceback if the cell failed.
    :param wall_time_s: wall time of the job on the worker.
    :param host: where it ran (host name and process id).
    :param drjit_threads: Dr.Jit's thread count during the job.
    :param code_version: :func:`code_version` where it ran.
    """

    status: str
    archive: bytes | None = None
    error: str | None = None
    traceback: str | None = None
    wall_time_s: float = 0.0
    host: str = ""
    drjit_threads: int = 0
    code_version: str = ""


def describe_failure(err: BaseException) -> str:
    """``Type: message`` (every line of the message: Mitsuba's and a plugin's errors say what
    went wrong after the first line), then the innermost :data:`ERROR_FRAMES` frames."""
    frames = traceback.format_tb(err.__traceback__)[-ERROR_FRAMES:]
    return ("".join(traceback.format_exception_only(type(err), err)).strip()
            + ("\n" + "".join(frames).rstrip() if frames else ""))


def use_variant(variant: str) -> None:
    """Make ``variant`` the active Mitsuba variant of this process (no-op if it already is)."""
    import mitsuba as mi

    if mi.variant() != variant:
        mi.set_variant(variant)


def _zip_folder(folder: str) -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as archive:
        for root, _, files in os.walk(folder):
            for name in sorted(files):
                path = os.path.join(root, name)
                archive.write(path, os.path.relpath(path, folder))
    return buffer.getvalue()


def run_cell(cell: Cell, cache_dir: str | None = None) -> CellResult:
    """Run ``compare`` on one cell here; never raises (a failure is a ``"failed"`` result).

    :param cell: the cell; built-in scenes and maps are resolved on this machine, files must
        exist here under the grid's paths.
    :param cache_dir: reference cache folder (None: compare's default on this machine).
    """
    import drjit as dr

    started = time.perf_counter()
    where = f"{socket.gethostname()}:{os.getpid()}"
    try:
        use_variant(cell.variant)
        from ..report.compare import CompareSettings, run_compare

        scene = cell.scene_path()
        if not os.path.isfile(scene):
            raise FileNotFoundError(f"scene file {scene} is not visible on {socket.gethostname()} "
                                    f"(grid files must be on a path shared by every worker)")
        envmap = cell.map_path()
        if cell.map.name != SCENE_MAP and not (envmap and os.path.isfile(envmap)):
            raise FileNotFoundError(f"map file {envmap} is not visible on {socket.gethostname()}")
        with tempfile.TemporaryDirectory(prefix="shsampling-cell-") as out:
            settings = CompareSettings(out=out, samplers=(cell.sampler,), methods=cell.methods,
                                       envmap=envmap, progress=False, **dict(cell.settings),
                                       **({"cache_dir": cache_dir} if cache_dir else {}))
            run_compare([scene], settings)
            archive = _zip_folder(out)
    except Exception as err:
        return CellResult("failed", error=describe_failure(err),
                          traceback=traceback.format_exc(), wall_time_s=time.perf_counter() - started,
                          host=where, drjit_threads=dr.thread_count(), code_version=code_version())
    return CellResult("ok", archive=archive, wall_time_s=time.perf_counter() - started, host=where,
                      drjit_threads=dr.thread_count(), code_version=code_version())
