"""Host-side builds kept by the content of their inputs: in the process and on disk.

The per-scene state is built on the host from the scene's data: the environment
pyramid from the map's texels, a lobe fit from a BSDF's parameters, the cosine
tables from the pyramid. The same inputs always give the same arrays, so a build
is looked up by a key made of its inputs' content (:func:`content_key`) before it
runs, as Dr.Jit looks up a compiled kernel by its source:

- in this process (a second integrator object, a re-load of the same scene, a
  parameter change that leaves this input as it was): a small table of recent
  builds;
- on disk, in the user's cache folder (``platformdirs``), one ``.npz`` file per
  build, in a folder named after the package's code (a digest of its source files,
  so an edited build function never reads an older one's arrays): a fresh process on
  a scene rendered before skips the builds, as it skips the compilation of the
  kernels. Files are written in a thread of their own, off the set-up's path
  (:func:`flush` waits for them; so does the interpreter at exit). The folder is bounded
  (:func:`prune`): :data:`MAX_FOLDER_BYTES` for this version, least recently used first, and
  :data:`KEPT_VERSIONS` folders of other versions.

``SHSAMPLING_CACHE_DIR`` names another folder; ``SHSAMPLING_CACHE_DIR=off`` keeps
builds in the process only, and so does :func:`kept_in_process` for the builds made
inside it (a state rebuilt after its scene's parameters changed). A file that cannot be read is built again and
rewritten (a cache never decides a result); one that cannot be written is left
out with no more than a warning.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import re
import shutil
import tempfile
import threading
import warnings
from collections import OrderedDict
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Callable

import numpy as np

ENVIRONMENT_VARIABLE = "SHSAMPLING_CACHE_DIR"
"""Names the cache folder; ``off`` (or ``0``, ``none``) keeps builds in the process only."""

IN_PROCESS_ENTRIES = 64
"""Builds kept in the process (the least recently used goes first)."""

MAX_FOLDER_BYTES = 2 * 2**30
"""This package version's builds kept on disk at most; beyond it the least recently used
files go (down to :data:`PRUNED_SHARE` of it). A 1k map's two pyramids are ~80 MB, a scene's
cosine tables ~20 MB a map."""

PRUNED_SHARE = 0.8
"""What a pruning of this version's folder leaves of :data:`MAX_FOLDER_BYTES`."""

KEPT_VERSIONS = 2
"""Folders of other package versions (other code digests) kept beside this one's, the most
recently used; older ones are deleted. (Every edit of the code is a version: a developer's
cache folder held 70 of them, 9.4 GB, before this bound.)"""

_DIGEST_NAME = re.compile(r"^[0-9a-f]{16}$")
"""A version folder's name (:func:`code_digest`): only such folders are ever deleted."""

#: A build's result: names -> numpy arrays or JSON values (numbers, strings, lists).
Record = dict

_memory: "OrderedDict[str, Record]" = OrderedDict()
#: A user may build from threads of their own (the writer below is one more): the table is shared.
_memory_lock = threading.Lock()
#: Open :func:`kept_in_process` blocks (any thread's).
_in_process_only = 0
#: Writes to the disk cache run in one thread of their own, off the set-up's path (a pyramid's
#: ``.npz`` is 10-40 MB, 20-50 ms to write); the interpreter waits for them at exit.
_writer: ThreadPoolExecutor | None = None
#: Writes handed to the writer, each with the record it writes. The record is held here, on the
#: callers' side, until a caller sees its write done: its arrays may be views of Dr.Jit memory,
#: and the writer must not drop their last reference (Dr.Jit work from a second thread deadlocks
#: under Dr.Jit's ``Info`` log level; docs/MEASUREMENTS.md, "The per-scene state built on one thread").
_pending: list[tuple[Future, Record | None]] = []
#: The cache folder was pruned in this process (:func:`prune`, once, before the first write).
_pruned = False


@contextlib.contextmanager
def kept_in_process():
    """Builds made inside the block (their threads' included) are kept in this process and
    not written to the disk cache; the disk is still read. For a state rebuilt because its
    scene's parameters changed: an optimisation changes them at every step, its builds are
    never met again, and each write cost ~50 ms of a 0.26 s rebuild (a 64 x 32 map's cosine
    tables, ``scripts/bench_inverse.py``'s envmap task)."""
    global _in_process_only
    with _memory_lock:
        _in_process_only += 1
    try:
        yield
    finally:
        with _memory_lock:
            _in_process_only -= 1


def cache_folder() -> str | None:
    """The folder of this package version's builds, or None where the disk cache is off."""
    chosen = os.environ.get(ENVIRONMENT_VARIABLE)
    if chosen is not None and chosen.strip().lower() in ("off", "0", "none", ""):
        return None
    if chosen is None:
        import platformdirs

        chosen = platformdirs.user_cache_dir("mitsuba-shsampling")
    return os.path.join(chosen, code_digest())


_code_digest: str | None = None


def code_digest() -> str:
    """A digest of the package's Python sources (computed once per process)."""
    global _code_digest
    if _code_digest is None:
        root = os.path.dirname(os.path.abspath(__file__))
        digest = hashlib.blake2b(digest_size=8)
        for folder, folders, files in sorted(os.walk(root)):
            folders.sort()
            for name in sorted(f for f in files if f.endswith(".py")):
                with open(os.path.join(folder, name), "rb") as f:
                    digest.update(name.encode() + b"\x00" + f.read())
        _code_digest = digest.hexdigest()
    return _code_digest


def content_key(*parts) -> str:
    """A hex digest of ``parts``: numpy arrays by dtype, shape and bytes, anything else
    by its ``repr`` (numbers, strings, tuples of them)."""
    digest = hashlib.blake2b(digest_size=20)
    for part in parts:
        if isinstance(part, np.ndarray):
            array = np.ascontiguousarray(part)
            digest.update(f"{array.dtype.str}{array.shape}".encode())
            digest.update(array.view(np.uint8).ravel())
        else:
            digest.update(repr(part).encode())
        digest.update(b"\x00")
    return digest.hexdigest()


def cached_build(kind: str, key: str, build: Callable[[], Record], on_disk: bool = True) -> Record:
    """``build()``'s record for ``key``, built only if neither this process nor the disk
    cache has it. ``kind`` names the sort of build (its files' folder). ``on_disk`` False:
    kept in this process only, for a build that costs less than its file (writing it
    competes with the set-up for the machine's cores)."""
    name = f"{kind}/{key}"
    with _memory_lock:
        record = _memory.get(name)
        if record is not None:
            _memory.move_to_end(name)
            return record
    folder = cache_folder()
    path = os.path.join(folder, kind, key + ".npz") if folder and on_disk else None
    record = _read(path) if path else None
    if record is None:
        record = build()
        if path and not _in_process_only:
            _write_later(path, record)
    with _memory_lock:
        _memory[name] = record
        while len(_memory) > IN_PROCESS_ENTRIES:
            _memory.popitem(last=False)
    return record


def _write_later(path: str, record: Record) -> None:
    """:func:`_write` in the writer thread (the record's arrays are never written to after a build)."""
    global _writer
    global _pruned
    with _memory_lock:
        if _writer is None:
            _writer = ThreadPoolExecutor(max_workers=1, thread_name_prefix="shsampling-build-cache")
        _pending[:] = [(f, r) for f, r in _pending if not f.done()]
        if not _pruned:
            _pruned = True
            _pending.append((_writer.submit(prune, cache_folder()), None))
        handed = _Handed(record)
        _pending.append((_writer.submit(_write_handed, path, handed), record))


class _Handed:
    """A record as the writer gets it: the writer lets go of it before its write counts as
    done (:func:`_write_handed`), so that the callers' reference in ``_pending`` is the last."""

    __slots__ = ("record",)

    def __init__(self, record: Record):
        self.record = record


def _write_handed(path: str, handed: _Handed) -> None:
    try:
        _write(path, handed.record)
    finally:
        handed.record = None


def flush() -> None:
    """Wait until every build handed to the disk cache so far is written."""
    with _memory_lock:
        pending = [future for future, _ in _pending]
    for future in pending:
        future.result()
    with _memory_lock:
        _pending[:] = [(f, r) for f, r in _pending if not f.done()]


def clear_in_process() -> None:
    """Forget the builds kept in this process (tests; the disk cache is left alone)."""
    _memory.clear()


def _read(path: str) -> Record | None:
    if not os.path.exists(path):
        return None
    try:
        with np.load(path, allow_pickle=False) as stored:
            values = json.loads(str(stored["__values__"]))
            record = {**{k: stored[k] for k in stored.files if k != "__values__"}, **values}
    except Exception:  # a truncated or foreign file: build again (and overwrite it)
        return None
    with contextlib.suppress(OSError):
        os.utime(path)  # used now: the last to go when the folder is pruned
    return record


def prune(folder: str | None) -> None:
    """Bound the disk cache: delete the folders of other package versions beyond the
    :data:`KEPT_VERSIONS` most recently used (only folders named like a code digest), and
    this version's least recently used files beyond :data:`MAX_FOLDER_BYTES`. Errors (a
    folder another process is pruning) are ignored: a missing file is built again."""
    if folder is None or not os.path.isdir(os.path.dirname(folder)):
        return
    root, own = os.path.split(folder)

    def last_used(path: str) -> float:
        times = [os.path.getmtime(path)]
        with contextlib.suppress(OSError), os.scandir(path) as entries:
            times += [e.stat().st_mtime for e in entries]
        return max(times)

    with contextlib.suppress(OSError):
        others = [os.path.join(root, name) for name in os.listdir(root)
                  if name != own and _DIGEST_NAME.match(name) and os.path.isdir(os.path.join(root, name))]
        for old in sorted(others, key=last_used, reverse=True)[KEPT_VERSIONS:]:
            shutil.rmtree(old, ignore_errors=True)
    trim_least_recently_used([os.path.join(here, name) for here, _, names in os.walk(folder) for name in names],
                             MAX_FOLDER_BYTES)


def trim_least_recently_used(paths: list, max_bytes: int, group=lambda path: path) -> None:
    """Where ``paths`` hold more than ``max_bytes``, delete the least recently used (by
    modification time: a read should touch its file) down to :data:`PRUNED_SHARE` of it.
    ``group(path)`` names the entry a file belongs to: an entry's files go together, when
    its newest is the oldest left. Files that vanish meanwhile (another process pruning)
    are skipped."""
    entries: dict = {}
    for path in paths:
        with contextlib.suppress(OSError):
            info = os.stat(path)
            entry = entries.setdefault(group(path), [0.0, 0, []])
            entry[0], entry[1] = max(entry[0], info.st_mtime), entry[1] + info.st_size
            entry[2].append(path)
    total = sum(size for _, size, _ in entries.values())
    if total <= max_bytes:
        return
    for _, size, files in sorted(entries.values(), key=lambda entry: entry[0]):
        if total <= PRUNED_SHARE * max_bytes:
            break
        for path in files:
            with contextlib.suppress(OSError):
                os.remove(path)
        total -= size


def _write(path: str, record: Record) -> None:
    arrays = {k: v for k, v in record.items() if isinstance(v, np.ndarray)}
    values = {k: v for k, v in record.items() if not isinstance(v, np.ndarray)}
    try:
        os.makedirs(os.path.dirname(path), exist_ok=True)
        # Written under a temporary name and renamed: a process reading the cache at the
        # same time sees the whole file or none.
        handle, temporary = tempfile.mkstemp(dir=os.path.dirname(path), suffix=".tmp")
        with os.fdopen(handle, "wb") as f:
            np.savez(f, __values__=np.array(json.dumps(values)), **arrays)
        os.replace(temporary, path)
    except OSError as err:
        warnings.warn(f"mitsuba_shsampling: cannot write the build cache {path} ({err}); "
                      f"set {ENVIRONMENT_VARIABLE} to a writable folder, or to 'off'", RuntimeWarning)
