"""Timed renders, admissible sample counts and the cached reference image.

Timing rule: the first render of a method compiles its kernels; it is the
warm-up and its extra time is reported as compile time. Every later render is
timed wall-clock until its image is evaluated (``np.array`` forces it).
With the ``independent`` sampler, changing spp or seed does not recompile;
the stratified/low-discrepancy samplers recompile for each new sample count
(measured on llvm_ad_rgb, 3.9.1), so each new spp gets its own untimed warm-up.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import os
import time

import numpy as np

import mitsuba as mi

from .. import scenes as builtin
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
    """Renders one scene with one method; owns the method's scene and integrator.

    :param scene_path: XML scene.
    :param method: the method (its ``scene_params`` are applied when loading).
    :param settings: ``res``, ``sampler``, ``envmap`` (or None), ``max_depth``.
    """

    def __init__(self, scene_path: str, method: Method, settings: dict):
        self.method = method
        self.sampler_name = settings["sampler"]
        self.scene = load_for_settings(scene_path, settings, **method.scene_params)
        self.integrator = method.load_integrator(settings["max_depth"])
        self.first_render_s: float | None = None
        self.compile_time_s: float | None = None
        self.warm_spps: set[int] = set()

    def render(self, spp: int, seed: int) -> tuple[np.ndarray, float]:
        """One render: (image (H, W, C) float32, wall time in s)."""
        start = time.perf_counter()
        image = np.array(mi.render(self.scene, integrator=self.integrator, spp=spp, seed=seed),
                         dtype=np.float32)
        return image, time.perf_counter() - start

    def actual_spp(self) -> int:
        """The sample count of the last render (samplers round some requests)."""
        return int(self.scene.sensors()[0].sampler().sample_count())

    def warm_up(self, spp: int) -> float:
        """Compile the kernels with one untimed render; returns its wall time (s).

        The compile time is that time minus the median of the next timed passes.
        """
        _, elapsed = self.render(spp, SEED_WARMUP)
        self.warm_spps.add(spp)
        if self.first_render_s is None:
            self.first_render_s = elapsed
        return elapsed

    def passes(self, spp: int, count: int, seed0: int) -> PassSet:
        """``count`` independent timed passes with seeds ``seed0 + k``."""
        spp = admissible_spp(self.sampler_name, spp)
        if spp not in self.warm_spps:
            # Samplers other than `independent` recompile for a new sample count.
            self.warm_up(spp)
        else:
            # Other methods rendered since this one last ran: one untimed pass
            # first, so that no leftover compilation or cache refill is timed.
            self.render(spp, SEED_WARMUP)
        images, times = [], []
        for k in range(count):
            image, elapsed = self.render(spp, seed0 + k)
            images.append(image)
            times.append(elapsed)
        passes = PassSet(self.method.name, self.actual_spp(), np.stack(images), times,
                         [seed0 + k for k in range(count)])
        if self.compile_time_s is None:
            self.compile_time_s = max(0.0, self.first_render_s - passes.time_s)
        return passes


def load_for_settings(scene_path: str, settings: dict, **scene_params) -> mi.Scene:
    """Load ``scene_path`` at the comparison's resolution, sampler and envmap."""
    declared = builtin.scene_parameters(scene_path)
    kwargs = {"res": settings["res"]}
    if "sampler" in declared:
        kwargs["sampler"] = settings["sampler"]
    if settings.get("envmap"):
        kwargs["envmap"] = settings["envmap"]
    return builtin.load_scene(scene_path, **kwargs, **scene_params)


def reference_integrator(family: str, max_depth: int) -> dict:
    """The reference of a family: ``path`` at max_depth 2 (= direct lighting) or ``max_depth``."""
    return {"type": "path", "max_depth": 2 if family == DIRECT else max_depth}


def reference_key(scene_path: str, settings: dict, family: str, ref_spp: int) -> str:
    """Hash of everything the reference image depends on (files by content)."""
    digest = hashlib.sha256()
    # Included stage files live in an ``include`` folder next to the built-in scenes.
    include_dir = os.path.join(os.path.dirname(os.path.abspath(scene_path)), "include")
    files = [scene_path]
    if os.path.isdir(include_dir):
        files += [os.path.join(include_dir, f) for f in sorted(os.listdir(include_dir))
                  if f.endswith(".xml")]
    envmap = settings.get("envmap") or _default_envmap(scene_path)
    if envmap and os.path.isfile(envmap):
        files.append(envmap)
    for path in files:
        with open(path, "rb") as f:
            digest.update(f.read())
    digest.update(json.dumps({
        "integrator": reference_integrator(family, settings["max_depth"]),
        "res": settings["res"], "ref_spp": ref_spp, "variant": mi.variant(),
        "mitsuba": mi.__version__,
    }, sort_keys=True).encode())
    return digest.hexdigest()[:16]


def _default_envmap(scene_path: str) -> str | None:
    value = builtin.scene_parameters(scene_path).get("envmap")
    if value is None:
        return None
    return value if os.path.isabs(value) else os.path.join(os.path.dirname(os.path.abspath(scene_path)), value)


@dataclasses.dataclass
class Reference:
    """Converged image (H, W, C) and the variance of that estimate (H, W, C)."""

    image: np.ndarray
    variance: np.ndarray
    spp: int
    path: str
    cached: bool
    time_s: float


#: The reference is rendered in this many chunks: their spread estimates its own variance.
REFERENCE_CHUNKS = 4


def render_reference(scene_path: str, settings: dict, family: str, ref_spp: int,
                     cache_dir: str, progress=None) -> Reference:
    """Render (or reuse from ``cache_dir``) the ``path`` reference of a scene.

    The image is the mean of :data:`REFERENCE_CHUNKS` independent chunks of
    ``ref_spp / chunks`` samples (independent sampler); the variance of that mean is
    estimated from the chunks and stored next to it, as ``<key>.exr`` and ``<key>_var.exr``.
    """
    os.makedirs(cache_dir, exist_ok=True)
    key = reference_key(scene_path, settings, family, ref_spp)
    stem = os.path.splitext(os.path.basename(scene_path))[0]
    path = os.path.join(cache_dir, f"ref_{stem}_{key}.exr")
    var_path = os.path.join(cache_dir, f"ref_{stem}_{key}_var.exr")
    if os.path.isfile(path) and os.path.isfile(var_path):
        return Reference(read_exr(path), read_exr(var_path), ref_spp, path, True, 0.0)

    ref_settings = dict(settings, sampler="independent")
    scene = load_for_settings(scene_path, ref_settings)
    integrator = mi.load_dict(reference_integrator(family, settings["max_depth"]))
    chunk_spp = max(1, ref_spp // REFERENCE_CHUNKS)
    start = time.perf_counter()
    chunks = []
    for i in range(REFERENCE_CHUNKS):
        chunks.append(np.array(mi.render(scene, integrator=integrator, spp=chunk_spp,
                                         seed=SEED_REFERENCE + i), dtype=np.float32))
        if progress is not None:
            progress.update(1)
    elapsed = time.perf_counter() - start
    chunks = np.stack(chunks)
    image = chunks.mean(axis=0)
    variance = chunks.var(axis=0, ddof=1) / REFERENCE_CHUNKS
    write_exr(path, image)
    write_exr(var_path, variance)
    return Reference(image, variance, chunk_spp * REFERENCE_CHUNKS, path, False, elapsed)


def write_exr(path: str, image: np.ndarray) -> None:
    """Write an (H, W, C) float image as a float32 EXR."""
    mi.Bitmap(np.ascontiguousarray(image, dtype=np.float32)).write(path)


def read_exr(path: str) -> np.ndarray:
    """Read an EXR as an (H, W, C) float32 array."""
    return np.array(mi.Bitmap(path), dtype=np.float32)


__all__ = ["MULTI_BOUNCE", "PassSet", "MethodRenderer", "Reference", "admissible_spp",
           "render_reference", "reference_integrator", "write_exr", "read_exr"]
