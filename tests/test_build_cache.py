"""Specification: the disk cache of builds is bounded. Folders of other package versions beyond
the most recently used few are deleted (only folders named like a version), and this version's
least recently used files go once it holds more than its bound; a build read back counts as used;
a build that costs less than its file is kept in the process only. The report's reference renders beside them are bounded the same way."""

import os
import threading
import time

import numpy as np

from mitsuba_shsampling import build_cache


def touch(path, size=10, age=0.0):
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "wb") as f:
        f.write(b"x" * size)
    stamp = time.time() - age
    os.utime(path, (stamp, stamp))
    os.utime(os.path.dirname(path), (stamp, stamp))


def test_other_versions_beyond_the_most_recently_used_are_deleted_and_foreign_folders_kept(tmp_path):
    own = tmp_path / "0123456789abcdef"
    touch(str(own / "pyramid" / "a.npz"))
    versions = [f"{k:016x}" for k in range(1, 5)]
    for age, name in enumerate(versions):  # versions[0] the most recently used
        touch(str(tmp_path / name / "pyramid" / "b.npz"), age=100.0 * (age + 1))
        os.utime(tmp_path / name, (time.time() - 100.0 * (age + 1),) * 2)
    touch(str(tmp_path / "my_renders" / "keep.exr"), age=1e6)
    build_cache.prune(str(own))
    left = sorted(p.name for p in tmp_path.iterdir())
    assert left == sorted(["0123456789abcdef", "my_renders"] + versions[:build_cache.KEPT_VERSIONS])


def test_this_versions_least_recently_used_files_go_beyond_its_bound(tmp_path, monkeypatch):
    monkeypatch.setattr(build_cache, "MAX_FOLDER_BYTES", 1000)
    own = tmp_path / "0123456789abcdef"
    for k in range(6):  # 6 x 300 bytes, file 0 the oldest
        touch(str(own / "pyramid" / f"{k}.npz"), size=300, age=100.0 * (6 - k))
    build_cache.prune(str(own))
    left = sorted(p.name for p in (own / "pyramid").iterdir())
    assert left == ["4.npz", "5.npz"]  # 600 bytes <= 0.8 x 1000; the newest kept
    assert sum(p.stat().st_size for p in (own / "pyramid").iterdir()) <= build_cache.PRUNED_SHARE * 1000


def test_a_build_read_back_counts_as_used(tmp_path, monkeypatch):
    monkeypatch.setenv(build_cache.ENVIRONMENT_VARIABLE, str(tmp_path))
    build_cache.clear_in_process()
    build_cache.cached_build("test", "key", lambda: {"values": np.arange(3.0)})
    build_cache.flush()
    path = os.path.join(build_cache.cache_folder(), "test", "key.npz")
    os.utime(path, (1.0, 1.0))
    build_cache.clear_in_process()
    record = build_cache.cached_build("test", "key", lambda: {"values": np.zeros(3)})
    assert np.array_equal(record["values"], np.arange(3.0))  # read, not built
    assert os.path.getmtime(path) > time.time() - 60


def test_a_build_kept_in_the_process_only_writes_no_file_and_is_found_in_the_process(tmp_path, monkeypatch):
    monkeypatch.setenv(build_cache.ENVIRONMENT_VARIABLE, str(tmp_path))
    build_cache.clear_in_process()
    build_cache.cached_build("test", "cheap", lambda: {"values": np.arange(3.0)}, on_disk=False)
    build_cache.flush()
    assert not os.path.exists(os.path.join(build_cache.cache_folder(), "test", "cheap.npz"))
    record = build_cache.cached_build("test", "cheap", lambda: {"values": np.zeros(3)}, on_disk=False)
    assert np.array_equal(record["values"], np.arange(3.0))  # this process's build, not a new one


def test_the_reports_references_are_bounded_too_each_npz_with_its_exr(tmp_path, monkeypatch):
    """A reference (``ref_<scene>_<key>.npz`` and its ``.exr``) goes whole, least recently
    used first; nothing else in the folder is touched."""
    from mitsuba_shsampling.report import rendering
    monkeypatch.setattr(rendering, "MAX_REFERENCE_BYTES", 1000)
    for k in range(4):  # 4 references of 300 + 100 bytes, reference 0 the oldest
        touch(str(tmp_path / f"ref_scene_{k}.npz"), size=300, age=100.0 * (4 - k))
        touch(str(tmp_path / f"ref_scene_{k}.exr"), size=100, age=100.0 * (4 - k))
    os.utime(tmp_path / "ref_scene_1.npz")  # read just now
    touch(str(tmp_path / "notes.npz"), size=5000, age=1e6)
    rendering.prune_references(str(tmp_path))
    left = sorted(p.name for p in tmp_path.iterdir() if p.is_file())
    assert left == ["notes.npz", "ref_scene_1.exr", "ref_scene_1.npz", "ref_scene_3.exr", "ref_scene_3.npz"]


class Tracked(np.ndarray):
    """An array that notes the thread that frees it (views of it note nothing)."""
    freed_in: list = []

    def __del__(self):
        if getattr(self, "tracked", False):
            Tracked.freed_in.append(threading.current_thread().name)


def test_a_record_written_to_disk_is_let_go_on_the_callers_thread_not_the_writers(tmp_path, monkeypatch):
    """A build's arrays may be views of Dr.Jit memory: their last reference must not go in the
    writer thread (Dr.Jit work from a second thread deadlocks under Dr.Jit's Info log level)."""
    monkeypatch.setenv(build_cache.ENVIRONMENT_VARIABLE, str(tmp_path))
    build_cache.clear_in_process()
    release = threading.Event()
    write = build_cache._write
    monkeypatch.setattr(build_cache, "_write", lambda path, record: (release.wait(10), write(path, record)))
    values = np.arange(4.0).view(Tracked)
    values.tracked = True
    Tracked.freed_in.clear()
    build_cache.cached_build("test", "tracked", lambda: {"values": values})
    build_cache.clear_in_process()
    del values  # the writer's copy of the record, and the callers', are all that hold it now
    release.set()
    written = os.path.join(build_cache.cache_folder(), "test", "tracked.npz")
    deadline = time.time() + 10
    while not os.path.exists(written) and time.time() < deadline:
        time.sleep(0.01)
    time.sleep(0.2)  # the write has returned, and the writer's thread let go of its work item
    assert Tracked.freed_in == []  # still held on the callers' side
    build_cache.flush()
    assert Tracked.freed_in == ["MainThread"]
    assert os.path.exists(written)
