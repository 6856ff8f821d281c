"""Timed renders, admissible sample counts and the cached reference image.

Timing rule: the first render of a method compiles its kernels; it is the
warm-up and its extra time is reported as compile time. Every later render is
timed wall-clock until its image is evaluated (``np.array`` forces it).
Methods that are compared are timed *interleaved* (:func:`interleaved_passes`:
pass k of every method, then pass k + 1), so that a slow spell of the machine
(a shared host, a frequency change) falls on all of them alike instead of on
whichever method happened to be rendering: time ratios are only meaningful
within one run, and this makes them meaningful within one run. The order of the
methods rotates from pass to pass, so that none always runs first (after a
Python-side pause, with cold caches) or right after the same neighbour.
With the ``independent`` sampler, changing spp or seed does not recompile;
the stratified/low-discrepancy samplers recompile for each new sample count
(measured on llvm_ad_rgb, 3.9.1: about 1 s each), so each new spp gets its own
untimed warm-up (:meth:`MethodRenderer.timed_render`), and so does the first render
of a freshly loaded scene, which costs twice a later one even from cached kernels.
No compile or set-up time enters a pass time, the equal-time budget or a
convergence point. After the warm-up each method's pass is recorded with
``dr.freeze`` and later passes replay it (:mod:`mitsuba_shsampling.frozen`),
Mitsuba's integrators and this project's alike: a pass time is the kernels'
time, not Python's tracing (``compare --no-freeze`` times traced passes).
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import hashlib
import json
import os
import time

import numpy as np

import mitsuba as mi

from .. import scenes as builtin
from ..build_cache import trim_least_recently_used
from ..frozen import FrozenPass
from . import metrics, scene_setup
from .methods import DIRECT, MULTI_BOUNCE, Method

#: Seed offsets keep the renders of one run independent of each other.
SEED_WARMUP = 900_000
SEED_EQUAL_TIME = 1_000
SEED_CONVERGENCE = 2_000
SEED_REFERENCE = 5_000_000


def admissible_spp(sampler_name: str, target: int) -> int:
    """The sample count closest (in log scale) to ``target`` that ``sampler_name`` accepts.

    ``stratified`` takes squares, ``multijitter`` products of near-equal factors,
    ``ldsampler`` powers of 4; asking for another count silently rounds up.
    """
    target = max(1, int(round(target)))
    candidates = _accepted_counts(sampler_name, 4 * target + 4)
    return min(candidates, key=lambda c: (abs(np.log(c / target)), c))


@functools.lru_cache(maxsize=None)
def _accepted_counts(sampler_name: str, up_to: int) -> frozenset[int]:
    """Sample counts ``sampler_name`` turns the requests 1..up_to into."""
    previous = mi.log_level()
    mi.set_log_level(mi.LogLevel.Error)  # every rounded request logs a warning
    try:
        sampler = mi.load_dict({"type": sampler_name, "sample_count": 1})
        counts = set()
        for n in range(1, up_to + 1):
            sampler.set_sample_count(n)
            counts.add(int(sampler.sample_count()))
    finally:
        mi.set_log_level(previous)
    return frozenset(counts)


@dataclasses.dataclass
class PassSet:
    """K independent renders of one method at one sample count.

    ``images`` is (K, H, W, C) float32, ``times_s`` the wall time of each pass.
    """

    method: str
    spp: int
    images: np.ndarray
    times_s: list[float]
    seeds: list[int]

    @property
    def time_s(self) -> float:
        """Median wall time of one pass (s)."""
        return float(np.median(self.times_s))


class MethodRenderer:
    """Renders one scene with one method; owns the method's scene, sensor and integrator.

    :param scene_path: XML scene (any Mitsuba scene with a supported camera, see
        :mod:`.scene_setup`).
    :param method: the method (its ``scene_params``, e.g. MIS compensation, rebuild the envmap).
    :param settings: ``res``, ``sampler``, ``envmap`` (or None), ``max_depth``.
    """

    def __init__(self, scene_path: str, method: Method, settings: dict):
        self.method = method
        self.sampler_name = settings["sampler"]
        self.scene, self.sensor = load_for_settings(scene_path, settings, **method.scene_params)
        self.integrator = method.load_integrator(settings["max_depth"])
        self.freeze = settings.get("freeze", True)
        self.first_render_s: float | None = None
        self.compile_time_s: float | None = None
        #: The plugin's own set-up (per-scene state and plan, :meth:`plan`), timed apart
        #: from the kernels' compilation; 0 for Mitsuba's integrators, which set up at load.
        self.setup_time_s: float | None = None
        self.warm_spps: set[int] = set()
        self._frozen: dict[int, FrozenPass] = {}

    @property
    def frozen(self) -> bool | None:
        """Whether every recorded pass replays frozen (False where one fell back to
        unfrozen renders, None before any was recorded or with freezing off)."""
        if not self._frozen:
            return None
        return all(p.frozen for p in self._frozen.values())

    def render(self, spp: int, seed: int) -> tuple[np.ndarray, float]:
        """One render: (image (H, W, C) float32, wall time in s). A sample count that
        :meth:`warm_up` recorded replays its frozen pass (:mod:`mitsuba_shsampling.frozen`)."""
        frozen = self._frozen.get(spp)
        start = time.perf_counter()
        if frozen is not None:
            image = frozen(seed)
        else:
            image = mi.render(self.scene, sensor=self.sensor, integrator=self.integrator, spp=spp, seed=seed)
        image = np.array(image, dtype=np.float32)
        return image, time.perf_counter() - start

    def timed_render(self, spp: int, seed: int) -> tuple[np.ndarray, float]:
        """:meth:`render`, after an untimed :meth:`warm_up` if ``spp`` has not rendered yet."""
        if spp not in self.warm_spps:
            self.warm_up(spp)
        return self.render(spp, seed)

    def record(self, spp: int) -> None:
        """Record the frozen pass at ``spp`` (untimed; nothing with ``freeze`` off), after a
        plain render compiled it, built the integrator's state and chose its strategies.

        Record only once every scene of the run is loaded: kernels that call a
        BSDF or an emitter through a pointer record the set of such objects alive
        in the process, and a scene loaded later makes the next replay record again."""
        if self.freeze and spp not in self._frozen:
            self._frozen[spp] = FrozenPass(self.scene, self.sensor, self.integrator, spp)
            np.array(self._frozen[spp](SEED_WARMUP + 1))

    def plan(self) -> None:
        """Make the integrator's per-scene state and plan now, once, timed
        (:attr:`setup_time_s`): the project's integrators make them before their first
        pass (``integrator.plan``), Mitsuba's at load."""
        if self.setup_time_s is not None:
            return
        start = time.perf_counter()
        if hasattr(self.integrator, "plan"):
            self.integrator.plan(self.scene, self.sensor)
        self.setup_time_s = time.perf_counter() - start

    def actual_spp(self) -> int:
        """The sample count of the last render (samplers round some requests)."""
        return int(self.sensor.sampler().sample_count())

    def warm_up(self, spp: int, record: bool = True) -> float:
        """Compile the kernels with one untimed render, then (with ``record``) record the
        frozen pass (:meth:`record`); returns the first render's wall time (s).

        The compile time is that time minus the median of the next timed passes; the
        plugin's set-up is timed before it (:meth:`plan`).
        """
        self.plan()
        _, elapsed = self.render(spp, SEED_WARMUP)
        if record:
            self.record(spp)
        self.warm_spps.add(spp)
        if self.first_render_s is None:
            self.first_render_s = elapsed
        return elapsed


def interleaved_passes(jobs: dict[str, tuple[MethodRenderer, int]], count: int, seed0: int,
                       on_pass=None) -> tuple[dict[str, PassSet], dict[str, Exception]]:
    """``count`` timed passes of several methods, round robin: pass k of every method
    before pass k + 1 of any, pass k starting at the (k mod n)-th of the n methods (see the
    module's timing rule).

    :param jobs: method name -> (its renderer, the spp to render; made admissible here).
    :param seed0: pass k of every method uses seed ``seed0 + k``.
    :param on_pass: called with no argument after every render (progress bars).
    :returns: (PassSet per method that rendered, the exception of each method that failed;
        a failed method is not rendered again).
    """
    failed: dict[str, Exception] = {}
    spps: dict[str, int] = {}
    for name, (renderer, spp) in jobs.items():
        spps[name] = admissible_spp(renderer.sampler_name, spp)
        try:
            if spps[name] not in renderer.warm_spps:
                renderer.warm_up(spps[name])  # samplers other than `independent` recompile per spp
        except Exception as err:  # noqa: BLE001 (reported per method by the caller)
            failed[name] = err
    images: dict[str, list] = {name: [] for name in jobs if name not in failed}
    times: dict[str, list] = {name: [] for name in images}
    order = list(images)
    for k in range(count):
        shift = k % len(order) if order else 0
        for name in order[shift:] + order[:shift]:
            if name in failed:
                continue
            renderer = jobs[name][0]
            try:
                image, elapsed = renderer.render(spps[name], seed0 + k)
            except Exception as err:  # noqa: BLE001
                failed[name] = err
                del images[name], times[name]
                continue
            images[name].append(image)
            times[name].append(elapsed)
            if on_pass is not None:
                on_pass()
    result = {}
    for name in images:
        renderer = jobs[name][0]
        result[name] = PassSet(renderer.method.name, renderer.actual_spp(), np.stack(images[name]),
                               times[name], [seed0 + k for k in range(count)])
        if renderer.compile_time_s is None and renderer.first_render_s is not None:
            renderer.compile_time_s = max(0.0, renderer.first_render_s - result[name].time_s)
    return result, failed


def load_for_settings(scene_path: str, settings: dict, mis_compensation: bool = False
                      ) -> tuple[mi.Scene, mi.Sensor]:
    """Load ``scene_path`` as written, with the comparison's envmap, and its camera rebuilt
    at the comparison's resolution and sampler (see :mod:`.scene_setup`).

    :returns: (scene, sensor); render with ``mi.render(scene, sensor=sensor, ...)``.
    """
    scene = builtin.load_scene(scene_path)
    if settings.get("envmap") or mis_compensation:
        scene = scene_setup.with_environment(scene, settings.get("envmap"), mis_compensation)
    sensor = scene_setup.comparison_sensor(scene, settings["res"], settings["sampler"], 1)
    return scene, sensor


def reference_integrator(family: str, max_depth: int) -> dict:
    """The reference of a family: ``path`` at max_depth 2 (= direct lighting) or ``max_depth``."""
    return {"type": "path", "max_depth": 2 if family == DIRECT else max_depth}


def reference_key(scene_path: str, scene: mi.Scene, settings: dict, family: str, ref_spp: int) -> str:
    """Hash of everything the reference image depends on: the scene's files and traversed
    parameters by content (:func:`.scene_setup.content_digest`) and the render settings."""
    digest = hashlib.sha256()
    extra = [settings["envmap"]] if settings.get("envmap") else []
    digest.update(scene_setup.content_digest(scene_path, scene, extra).encode())
    digest.update(json.dumps({
        "integrator": reference_integrator(family, settings["max_depth"]),
        "res": settings["res"], "ref_spp": ref_spp, "chunks": REFERENCE_CHUNKS,
        "variant": mi.variant(), "mitsuba": mi.__version__,
    }, sort_keys=True).encode())
    return digest.hexdigest()[:16]


@dataclasses.dataclass
class Reference:
    """Converged image of a scene, from :data:`REFERENCE_CHUNKS` independent chunks.

    :param chunks: (N, H, W, C) chunk images; their mean is ``image``.
    :param image: (H, W, C) the reference.
    :param variance: (H, W, C) variance of ``image`` as an estimate (chunk spread / N).
    :param chunk_means: (N,) image-mean luminance of each chunk: the reference's own error
        in the bias test.
    """

    chunks: np.ndarray
    spp: int
    path: str
    cached: bool
    time_s: float

    @property
    def image(self) -> np.ndarray:
        return self.chunks.mean(axis=0)

    @property
    def variance(self) -> np.ndarray:
        return self.chunks.var(axis=0, ddof=1) / self.chunks.shape[0]

    @property
    def chunk_means(self) -> np.ndarray:
        return metrics.image_mean_luminance(self.chunks)

    @property
    def non_finite(self) -> int:
        """Pixel-channel values of the reference that are NaN or infinite."""
        return int(np.count_nonzero(~np.isfinite(self.image)))


#: The reference is rendered in this many independent chunks: their spread estimates its own
#: error (per pixel, and of its image mean in the bias test).
REFERENCE_CHUNKS = 8

MAX_REFERENCE_BYTES = 2 * 2**30
"""The cached references (``ref_*`` files of a cache folder) kept at most; beyond it the least
recently used go, each reference's ``.npz`` and ``.exr`` together (a 480 x 360 reference is
~19 MB: about a hundred are kept)."""


def _reference_entry(path: str) -> str:
    return os.path.splitext(path)[0]


def prune_references(cache_dir: str) -> None:
    """Bound the references of ``cache_dir`` (:data:`MAX_REFERENCE_BYTES`); a read touches its file."""
    with contextlib.suppress(OSError):
        paths = [os.path.join(cache_dir, name) for name in os.listdir(cache_dir)
                 if name.startswith("ref_") and name.endswith((".npz", ".exr"))]
        trim_least_recently_used(paths, MAX_REFERENCE_BYTES, group=_reference_entry)


def render_reference(scene_path: str, settings: dict, family: str, ref_spp: int,
                     cache_dir: str, progress=None) -> Reference:
    """Render (or reuse from ``cache_dir``) the ``path`` reference of a scene.

    The image is the mean of :data:`REFERENCE_CHUNKS` independent chunks of
    ``ref_spp / chunks`` samples (independent sampler). The chunks are cached as
    ``ref_<scene>_<key>.npz`` and their mean as ``.exr`` beside it; the key changes with
    any referenced file, traversed parameter or setting (:func:`reference_key`).
    """
    os.makedirs(cache_dir, exist_ok=True)
    ref_settings = dict(settings, sampler="independent")
    scene, sensor = load_for_settings(scene_path, ref_settings)
    key = reference_key(scene_path, scene, ref_settings, family, ref_spp)
    stem = os.path.splitext(os.path.basename(scene_path))[0]
    path = os.path.join(cache_dir, f"ref_{stem}_{key}.npz")
    if os.path.isfile(path):
        with np.load(path) as data:
            reference = Reference(data["chunks"], int(data["spp"]), path, True, 0.0)
        with contextlib.suppress(OSError):
            os.utime(path)  # used now: the last to go when the references are pruned
        return reference

    integrator = mi.load_dict(reference_integrator(family, settings["max_depth"]))
    chunk_spp = max(1, ref_spp // REFERENCE_CHUNKS)
    start = time.perf_counter()
    chunks = []
    for i in range(REFERENCE_CHUNKS):
        chunks.append(np.array(mi.render(scene, sensor=sensor, integrator=integrator, spp=chunk_spp,
                                         seed=SEED_REFERENCE + i), dtype=np.float32))
        if progress is not None:
            progress.update(1)
    elapsed = time.perf_counter() - start
    reference = Reference(np.stack(chunks), chunk_spp * REFERENCE_CHUNKS, path, False, elapsed)
    write_exr(path[:-4] + ".exr", reference.image)
    # The .npz is the cache entry: write it under a temporary name and rename it
    # (atomic on one file system), so that another process (a sweep's other
    # worker) never reads a half-written reference.
    partial = f"{path}.{os.getpid()}.partial"
    try:
        with open(partial, "wb") as f:
            np.savez(f, chunks=reference.chunks, spp=reference.spp)
        os.replace(partial, path)
    finally:
        if os.path.exists(partial):
            os.remove(partial)
    prune_references(cache_dir)
    return reference


def write_exr(path: str, image: np.ndarray) -> None:
    """Write an (H, W, C) float image as a float32 EXR."""
    mi.Bitmap(np.ascontiguousarray(image, dtype=np.float32)).write(path)


def read_exr(path: str) -> np.ndarray:
    """Read an EXR as an (H, W, C) float32 array."""
    return np.array(mi.Bitmap(path), dtype=np.float32)


__all__ = ["MULTI_BOUNCE", "PassSet", "MethodRenderer", "Reference", "admissible_spp", "interleaved_passes",
           "prune_references", "render_reference", "reference_integrator", "write_exr", "read_exr"]
