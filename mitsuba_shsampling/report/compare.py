"""The ``compare`` command: every method of a scene at equal samples and equal time.

For each scene and sampler, each method renders K independent passes (K >= 32 by
default, so that rare, huge samples show up in the expected error) at an equal
ray budget, then K passes at the spp that takes about as long as the baseline
(``direct`` 1+1 or ``path``) at the requested spp, then a convergence sweep (one
render per spp value). Everything is measured against a cached ``path``
reference (:mod:`.metrics`: expected error, tails, bias test), judged in a
verdict (:mod:`.verdict`), and written to ``report.json``, ``metrics.csv``,
EXR/PNG files and ``index.html``. Results are the typed report of :mod:`.schema`.

The module is cut the way a run goes: the phases of one sampler (:func:`equal_samples`,
:func:`equal_time`, :func:`convergence`) only render and time; scoring (:func:`measure`,
:func:`compare_with_baselines`, the maps, the per-material breakdown) only computes;
:class:`ReportFiles` writes every file; :class:`SceneComparison` runs them in order for one
scene and notes what failed.
"""

from __future__ import annotations

import csv
import os
import platform
import re
import sys
import time

import numpy as np
from tqdm import tqdm

import drjit as dr
import mitsuba as mi

from ..scenes import SceneError, scene_envmap
from . import html, images, materials, metrics, verdict
from .methods import (BASELINE, DIRECT, MITSUBA_METHODS, MULTI_BOUNCE_BASELINE, PROJECT_METHODS, Method,
                      available_methods, is_multi_bounce)
from .figures import sampler_demo_figures
from .plots import convergence_figure
from .rendering import (SEED_CONVERGENCE, SEED_EQUAL_TIME, MethodRenderer, PassSet, Reference,
                        REFERENCE_CHUNKS, admissible_spp, interleaved_passes, load_for_settings,
                        render_reference, write_exr)
from .schema import (CompareSettings, ConvergencePoint, EnvmapEntry, ErrorMaps, MaterialEntry, MethodResult,
                     PassResult, ReferenceEntry, Report, RunResult, SamplerFigure, SceneResult, load_report,
                     serialise, write_report)


def environment_info() -> dict:
    """Machine, variant and library versions the run used."""
    return {
        "machine": {
            "platform": platform.platform(),
            "processor": platform.processor() or platform.machine(),
            "cpu_count": os.cpu_count(),
            "python": sys.version.split()[0],
        },
        "variant": mi.variant(),
        "versions": {
            "mitsuba": mi.__version__,
            "drjit": dr.__version__,
            "llvm": ".".join(map(str, dr.detail.llvm_version())) if dr.has_backend(dr.JitBackend.LLVM) else None,
            "numpy": np.__version__,
        },
    }


def equal_ray_spp(spp: int, method: Method) -> int:
    """Samples per pixel that give ``method`` the ray budget of 2 rays x ``spp``."""
    return max(1, round(spp * 2 / method.rays_per_sample))


def convergence_spps(sampler: str, max_spp: int) -> list[int]:
    """Admissible sample counts roughly doubling from 1 to ``max_spp``."""
    values = sorted({admissible_spp(sampler, 2 ** i) for i in range(int(np.log2(max(1, max_spp))) + 1)})
    return [v for v in values if v <= max(max_spp, values[0])]


def scene_labels(paths: list[str]) -> list[str]:
    """A name per scene for the tables and the report's folders: the file's stem, with as many
    parent folders as tell apart files of the same stem (``a/scene``, ``b/scene``); the same
    file given again gets ``_2``, ``_3``, ..."""
    full = [os.path.splitext(os.path.abspath(p))[0].split(os.sep) for p in paths]
    depth = [1] * len(paths)
    while True:
        labels = ["/".join(parts[-d:]) for parts, d in zip(full, depth)]
        clashes = [i for i, label in enumerate(labels)
                   if any(labels[j] == label and full[j] != full[i] for j in range(len(paths)))]
        if not clashes:
            break
        for i in clashes:
            depth[i] += 1
    counts: dict[str, int] = {}
    unique = []
    for label in labels:
        counts[label] = counts.get(label, 0) + 1
        unique.append(label if counts[label] == 1 else f"{label}_{counts[label]}")
    return unique


def exposure(reference: np.ndarray) -> float:
    """Exposure that maps the 99th luminance percentile of the (finite) reference to 0.9."""
    lum = metrics.luminance(reference)
    lum = lum[np.isfinite(lum)]
    p99 = float(np.quantile(lum, 0.99)) if lum.size else 0.0
    return 0.9 / p99 if p99 > 0 else 1.0


# Scoring: statistics of the renders, no files -----------------------------------------------

def measure(passes: PassSet, reference: Reference) -> PassResult:
    """Every statistic of K passes against the reference (their files are recorded when written)."""
    error = metrics.error_stats(passes.images, reference.image)
    return PassResult(
        spp=passes.spp, time_s=passes.time_s, times_s=passes.times_s,
        efficiency=metrics.efficiency(error.mse, passes.time_s), error=error,
        tail=metrics.tail_stats(passes.images, reference.image),
        bias=metrics.bias_test(metrics.image_mean_luminance(passes.images), reference.chunk_means),
        seeds=passes.seeds)


def baseline_name(method: Method, results: dict[str, MethodResult]) -> str:
    """The method whose time per pass sets the equal-time budget of ``method``'s family."""
    base = BASELINE if method.family == DIRECT else MULTI_BOUNCE_BASELINE
    if base in results:
        return base
    same_family = [n for n, r in results.items() if r.family == method.family]
    # Never a reference row: an oracle pass costs 10-200x a renderer's.
    return ([n for n in same_family if not results[n].oracle] or same_family)[0]


def compare_with_baselines(results: dict[str, MethodResult]) -> None:
    """MSE, efficiency and tails relative to the family baseline (same run, same kind)."""
    for entry in results.values():
        base_name = BASELINE if entry.family == DIRECT else MULTI_BOUNCE_BASELINE
        base = results.get(base_name)
        if base is None:
            continue
        for b, e in ((base.equal_spp, entry.equal_spp), (base.equal_time, entry.equal_time)):
            e.mse_ratio_vs_baseline = e.error.mse / b.error.mse if b.error.mse > 0 else None
            e.efficiency_ratio_vs_baseline = e.efficiency / b.efficiency if b.efficiency > 0 else None
            if entry is not base:
                e.tail_worse_than_baseline = metrics.tail_worse(e.tail, b.tail, base_name)


def crop(methods: list[Method], equal_spp: dict[str, PassSet], refs: dict[str, Reference],
         exposure_value: float) -> list[int] | None:
    """[x, y, size] of the zoomed crop shown for every method: the window of a sixth of the
    image (at least 8 px) where the methods' summed per-pixel variance *as displayed* is largest.

    The variance is that of the tone-mapped passes (:func:`.images.display`, what the page's
    PNGs show), and pixels the tone mapping clips in the method's reference count for nothing:
    the linear variance grows with the radiance squared, so it picked a highlight that is
    solid white in every method's crop."""
    if not methods:
        return None
    variance = 0.0
    for m in methods:
        shown = images.display(equal_spp[m.name].images, exposure_value).var(axis=0).mean(axis=-1)
        variance = variance + np.where(images.clipped_pixels(refs[m.family].image, exposure_value), 0.0, shown)
    size = max(8, min(variance.shape) // 6)
    return [*images.noisiest_window(variance, size), min(size, *variance.shape)]


def error_maps(methods: list[Method], equal_spp: dict[str, PassSet],
               refs: dict[str, Reference]) -> dict[str, dict[str, np.ndarray]]:
    """Per kind (``variance``, ``rel_error``), per method, the (H, W) per-pixel map of the
    equal-sample passes: variance across passes, relative squared error against the reference."""
    return {"variance": {m.name: metrics.pixel_variance(equal_spp[m.name].images) for m in methods},
            "rel_error": {m.name: metrics.rel_squared_error_map(equal_spp[m.name].images, refs[m.family].image)
                          for m in methods}}


def strategy_choice(renderer: MethodRenderer) -> dict | None:
    """What the renderer's integrator chose per material (``strategy`` ``auto``), as a dict."""
    choice = getattr(renderer.integrator, "choice", None)
    made = choice(renderer.scene) if callable(choice) else None
    return made.as_dict() if made is not None else None


def material_breakdown(renderers: dict[str, MethodRenderer], methods: list[Method],
                       equal_spp: dict[str, PassSet], equal_time: dict[str, PassSet],
                       refs: dict[str, Reference]) -> dict[str, list[MaterialEntry]]:
    """Per family, the per-material error ratios and error shares (:mod:`.materials`)."""
    if not methods:
        return {}
    renderer = renderers[methods[0].name]
    ids, labels = materials.material_map(renderer.scene, renderer.sensor)
    out = {}
    for family in sorted({m.family for m in methods}):
        names = [m.name for m in methods if m.family == family and not m.oracle]
        out[family] = materials.breakdown(
            ids, labels, {n: equal_spp[n].images for n in names},
            {n: equal_time[n].images for n in names if n in equal_time}, refs[family].image,
            [n for n in names if n in PROJECT_METHODS], [n for n in names if n in MITSUBA_METHODS])
        for n in names:
            choice = strategy_choice(renderers[n])
            chosen = {m["name"]: m for m in choice["materials"]} if choice else {}
            for row in out[family]:
                if row.name in chosen:
                    row.strategy[n] = {"strategy": chosen[row.name]["strategy"],
                                       "predicted_gain": chosen[row.name]["predicted_gain"]}
    return out


# The phases of one sampler: renders, timed, no files ----------------------------------------

def equal_samples(renderers: dict[str, MethodRenderer], methods: list[Method], settings: CompareSettings,
                  on_pass=None) -> tuple[dict[str, PassSet], dict[str, Exception]]:
    """K passes of every method at the ray budget of ``settings.spp`` samples of 2 rays, timed
    interleaved (:func:`.rendering.interleaved_passes`): the passes, and the methods that failed."""
    return interleaved_passes({m.name: (renderers[m.name], equal_ray_spp(settings.spp, m)) for m in methods},
                              settings.passes, settings.seed, on_pass=on_pass)


def equal_time_budgets(methods: list[Method], equal_spp: dict[str, PassSet],
                       results: dict[str, MethodResult]) -> dict[str, tuple[str, float, int]]:
    """Per method: the method whose time per pass is its budget (:func:`baseline_name`), that
    time (s), and the spp the method's own time per sample at equal samples affords in it."""
    budgets = {}
    for m in methods:
        base = baseline_name(m, results)
        budget_s = equal_spp[base].time_s
        per_sample = equal_spp[m.name].time_s / equal_spp[m.name].spp
        spp = max(1, round(budget_s / per_sample)) if per_sample > 0 else equal_spp[m.name].spp
        budgets[m.name] = (base, budget_s, spp)
    return budgets


def equal_time(renderers: dict[str, MethodRenderer], methods: list[Method],
               budgets: dict[str, tuple[str, float, int]], settings: CompareSettings,
               on_pass=None) -> tuple[dict[str, PassSet], dict[str, Exception]]:
    """K passes of every method at the spp of its budget (:func:`equal_time_budgets`), timed
    interleaved, with seeds of their own: the passes, and the methods that failed."""
    return interleaved_passes({m.name: (renderers[m.name], budgets[m.name][2]) for m in methods},
                              settings.passes, settings.seed + SEED_EQUAL_TIME, on_pass=on_pass)


def convergence(renderer: MethodRenderer, spps: list[int], seed: int, reference: Reference,
                on_render=None) -> list[tuple[ConvergencePoint, np.ndarray]]:
    """One render per spp of ``spps`` (each new spp warmed up untimed), scored against the
    reference: the points, each with its image."""
    out = []
    for i, spp in enumerate(spps):
        image, elapsed = renderer.timed_render(spp, seed + i)
        out.append((ConvergencePoint(spp=spp, time_s=elapsed, mse=metrics.mse(image, reference.image),
                                     rel_mse=metrics.rel_mse(image, reference.image)), image))
        if on_render is not None:
            on_render()
    return out


# Files: every file of the report, written in one place --------------------------------------

class ReportFiles:
    """Writes one scene's files (EXR, PNG, false-colour maps, plots) under its folder of the
    report and records their report-relative paths (how report.json and index.html name them).

    Layout: ``<scene>/reference_<family>.{exr,png}``, ``<scene>/envmap.png``,
    ``<scene>/sampler_points_<i>.png``, ``<scene>/<sampler>/convergence.png`` and per method
    ``<scene>/<sampler>/<method>/``: ``{equal_spp,equal_time}_{pass0.exr,pass0.png,mean.exr}``,
    ``{variance,rel_error}_map.{png,exr}``, ``convergence_spp<n>.exr``.
    """

    def __init__(self, root: str, scene: str):
        self.root = root
        self.folder = os.path.join(root, scene)

    def path(self, *parts: str) -> str:
        """The absolute path of ``parts`` under the scene's folder (its folder created)."""
        path = os.path.join(self.folder, *parts)
        os.makedirs(os.path.dirname(path), exist_ok=True)
        return path

    def rel(self, path: str) -> str:
        """``path`` relative to the report folder."""
        return os.path.relpath(path, self.root)

    def reference(self, family: str, reference: Reference, exposure_value: float) -> tuple[str, str]:
        """The reference image of ``family``: (EXR, PNG)."""
        stem = self.path(f"reference_{family}")
        write_exr(stem + ".exr", reference.image)
        images.write_png(stem + ".png", images.tonemap(reference.image, exposure_value))
        return self.rel(stem + ".exr"), self.rel(stem + ".png")

    def envmap_thumbnail(self, texels: np.ndarray) -> str:
        path = self.path("envmap.png")
        images.write_png(path, images.thumbnail(texels))
        return self.rel(path)

    def sampler_figures(self, figures: list[tuple[str, bytes]]) -> list[SamplerFigure]:
        out = []
        for i, (caption, png) in enumerate(figures):
            path = self.path(f"sampler_points_{i}.png")
            with open(path, "wb") as f:
                f.write(png)
            out.append(SamplerFigure(caption=caption, png=self.rel(path)))
        return out

    def passes(self, sampler: str, method: str, tag: str, passes: PassSet, exposure_value: float) -> dict[str, str]:
        """The first pass (EXR, PNG) and the mean of all passes (EXR), as :attr:`.schema.PassResult.files`."""
        stem = self.path(sampler, method, tag)
        write_exr(stem + "_pass0.exr", passes.images[0])
        images.write_png(stem + "_pass0.png", images.tonemap(passes.images[0], exposure_value))
        write_exr(stem + "_mean.exr", passes.images.mean(axis=0))
        return {"first_pass": self.rel(stem + "_pass0.exr"), "first_pass_png": self.rel(stem + "_pass0.png"),
                "mean": self.rel(stem + "_mean.exr")}

    def error_maps(self, sampler: str, maps: dict[str, dict[str, np.ndarray]]) -> ErrorMaps:
        """False-colour PNGs (one log scale per kind, shared by the methods) and EXRs of ``maps``
        (:func:`error_maps`)."""
        out = ErrorMaps(files={}, scale={})
        for kind, per_method in maps.items():
            vmin, vmax = images.log_range(list(per_method.values()))
            for name, values in per_method.items():
                path = self.path(sampler, name, f"{kind}_map.png")
                images.write_png(path, images.false_colour(values, vmin, vmax))
                write_exr(self.path(sampler, name, f"{kind}_map.exr"), values[..., None])
                out.files.setdefault(name, {})[kind] = self.rel(path)
            out.scale[kind] = [vmin, vmax]
        return out

    def convergence(self, sampler: str, method: str, point: ConvergencePoint, image: np.ndarray) -> str:
        path = self.path(sampler, method, f"convergence_spp{point.spp}.exr")
        write_exr(path, image)
        return self.rel(path)

    def convergence_plot(self, sampler: str, png: bytes) -> str:
        path = self.path(sampler, "convergence.png")
        with open(path, "wb") as f:
            f.write(png)
        return self.rel(path)

    def run(self, run: RunResult, equal_spp: dict[str, PassSet], equal_time: dict[str, PassSet],
            sweep: dict[str, list[tuple[ConvergencePoint, np.ndarray]]] | None,
            maps: dict[str, dict[str, np.ndarray]], exposure_value: float, title: str) -> None:
        """Every file of one sampler's run, recorded in ``run`` (its passes' ``files``, its
        convergence points' ``file``, ``maps``, ``convergence_plot``); ``sweep`` is None when the
        run had no convergence sweep."""
        for name, result in run.methods.items():
            result.equal_spp.files = self.passes(run.sampler, name, "equal_spp", equal_spp[name], exposure_value)
            result.equal_time.files = self.passes(run.sampler, name, "equal_time", equal_time[name], exposure_value)
            for point, image in (sweep or {}).get(name, []):
                point.file = self.convergence(run.sampler, name, point, image)
        run.maps = self.error_maps(run.sampler, maps)
        if sweep is not None:
            curves = {r.label: r.convergence for r in run.methods.values()}
            run.convergence_plot = self.convergence_plot(run.sampler, convergence_figure(curves, title))


# One scene ----------------------------------------------------------------------------------

class SceneComparison:
    """Runs one scene: references per family, then per sampler the phases (equal samples, equal
    time, convergence), scores them, and has :class:`ReportFiles` write the files.

    :param name: the scene's name in the report (:func:`scene_labels`; default: the file's stem),
        also its folder under the report folder.
    """

    def __init__(self, scene_path: str, settings: CompareSettings, bar: tqdm, name: str | None = None):
        self.path = os.path.abspath(scene_path)
        self.name = name or os.path.splitext(os.path.basename(scene_path))[0]
        self.settings = settings
        self.bar = bar
        self.files = ReportFiles(os.path.abspath(settings.out), self.name)
        self.notes: list[str] = []
        self.render_settings = {"res": settings.res, "envmap": settings.envmap,
                                "max_depth": settings.max_depth, "freeze": settings.freeze}
        try:
            probe, _ = load_for_settings(self.path, dict(self.render_settings, sampler="independent"))
        except SceneError as err:
            raise SceneError(f"{scene_path}: {err}") from None
        self.envmap = scene_envmap(probe)
        self.has_envmap = self.envmap is not None
        if not self.has_envmap:
            self.notes.append("this scene has no environment map: product sampling has nothing to "
                              "sample here, so the SH methods can only match their fallback strategies")
        else:
            bad = int(np.count_nonzero(~np.isfinite(self.envmap_texels())))
            if bad:
                self.notes.append(
                    f"the environment map has {bad} non-finite texel values (NaN or infinite). Pixels "
                    f"that come out non-finite (in the reference or in any pass) are counted and left "
                    f"out of every statistic. An integrator that zeroes such texels (the SH integrators "
                    f"warn when they do) renders another map than the reference and Mitsuba's methods: "
                    f"on this scene its comparison with them is not like for like")
        self.references: dict[str, Reference] = {}

    def envmap_texels(self) -> np.ndarray:
        """The environment map's texels (H, W, C), without the wrap-around column of its bitmap."""
        return np.array(mi.traverse(self.envmap)["data"])[:, 1:-1]

    def methods(self) -> list[Method]:
        names = list(self.settings.methods) if self.settings.methods else None
        chosen, notes = available_methods(names, multi_bounce=is_multi_bounce(self.settings.max_depth))
        self.notes += notes
        runnable = []
        for method in chosen:
            if method.scene_params and not self.has_envmap:
                self.notes.append(f"skipped '{method.name}': it rebuilds the envmap "
                                  f"({', '.join(method.scene_params)}) and the scene has none")
                continue
            runnable.append(method)
        return runnable

    def reference(self, family: str) -> Reference:
        if family not in self.references:
            ref = render_reference(self.path, dict(self.render_settings, sampler="independent"),
                                   family, self.settings.ref_spp, self.settings.cache_dir,
                                   progress=self.bar)
            self.references[family] = ref
        return self.references[family]

    def run(self) -> SceneResult:
        methods = self.methods()
        families = sorted({m.family for m in methods})
        refs = {f: self.reference(f) for f in families}
        exposure_value = exposure(next(iter(refs.values())).image) if refs else 1.0
        ref_entries = {}
        for family, ref in refs.items():
            exr, png = self.files.reference(family, ref, exposure_value)
            if ref.non_finite:
                self.notes.append(f"the {family} reference has {ref.non_finite} non-finite pixel values: "
                                  f"those pixels are left out of every method's statistics")
            ref_entries[family] = ReferenceEntry(
                spp=ref.spp, chunks=int(ref.chunks.shape[0]), cache_file=ref.path, cached=ref.cached,
                render_time_s=ref.time_s, file=exr, png=png,
                mean_variance=float(np.nanmean(np.where(np.isfinite(ref.variance), ref.variance, np.nan))),
                integrator="path, max_depth " + ("2" if family == DIRECT else str(self.settings.max_depth)))
        runs = [self.run_sampler(sampler, methods, refs, exposure_value) for sampler in self.settings.samplers]
        # Warped sample points over their targets (SH lobe; lobe x this scene's map).
        figures = (self.files.sampler_figures(sampler_demo_figures(self.envmap))
                   if self.has_envmap and any(m.product_sampling for m in methods) else [])
        return SceneResult(scene=self.name, path=self.path, has_envmap=self.has_envmap,
                           envmap=self.envmap_entry(), notes=self.notes, exposure=exposure_value,
                           references=ref_entries, runs=runs, sampler_figures=figures)

    def envmap_entry(self) -> EnvmapEntry | None:
        """The environment map's file name (``--envmap``, else the scene's) and a thumbnail."""
        if not self.has_envmap:
            return None
        named = re.search(r'filename = "([^"]*)"', str(self.envmap))
        name = os.path.basename(self.settings.envmap) if self.settings.envmap else (
            named.group(1) if named else "(built from a bitmap)")
        return EnvmapEntry(name=name, png=self.files.envmap_thumbnail(self.envmap_texels()))

    def drop(self, method: Method, sampler: str, err: Exception) -> None:
        """Note that ``method`` failed and is left out of this sampler's comparison."""
        first_line = str(err).strip().splitlines()[0] if str(err).strip() else ""
        self.notes.append(f"'{method.name}' failed with the {sampler} sampler and was left out: "
                          f"{type(err).__name__}: {first_line}")

    def compile(self, sampler: str, methods: list[Method]) -> tuple[dict[str, MethodRenderer], list[Method]]:
        """A warmed-up renderer per method, and the methods that loaded and rendered. A method
        that fails is dropped with a note, so one broken plugin does not cost the whole comparison."""
        settings = dict(self.render_settings, sampler=sampler)
        renderers: dict[str, MethodRenderer] = {}
        loaded = []
        spps = {m.name: admissible_spp(sampler, equal_ray_spp(self.settings.spp, m)) for m in methods}
        for m in methods:
            self.bar.set_description(f"{self.name}/{sampler}/{m.name} compile")
            try:
                renderers[m.name] = MethodRenderer(self.path, m, settings)
                renderers[m.name].warm_up(spps[m.name], record=False)
                loaded.append(m)
            except Exception as err:
                self.drop(m, sampler, err)
            self.bar.update(1)
        # The frozen passes are recorded once every method's scene is loaded (MethodRenderer.record).
        for m in list(loaded):
            try:
                renderers[m.name].record(spps[m.name])
            except Exception as err:
                self.drop(m, sampler, err)
                loaded.remove(m)
                del renderers[m.name]
        return renderers, loaded

    def run_sampler(self, sampler: str, methods: list[Method], refs: dict[str, Reference],
                    exposure_value: float) -> RunResult:
        s = self.settings
        tick = lambda: self.bar.update(1)  # noqa: E731
        renderers, methods = self.compile(sampler, methods)

        # Equal ray budget: K passes each, timed interleaved across the methods.
        self.bar.set_description(f"{self.name}/{sampler} equal spp (methods interleaved)")
        equal_spp, failed = equal_samples(renderers, methods, s, on_pass=tick)
        for m in [m for m in methods if m.name in failed]:
            self.drop(m, sampler, failed[m.name])
        methods = [m for m in methods if m.name in equal_spp]
        results = {m.name: MethodResult(
            label=m.label, family=m.family, rays_per_sample=m.rays_per_sample, integrator=m.integrator,
            scene_params=m.scene_params, compile_time_s=renderers[m.name].compile_time_s,
            setup_time_s=renderers[m.name].setup_time_s,
            equal_spp=measure(equal_spp[m.name], refs[m.family]), oracle=m.oracle) for m in methods}

        # Equal time: each method gets the spp that costs the baseline's time per pass.
        budgets = equal_time_budgets(methods, equal_spp, results)
        self.bar.set_description(f"{self.name}/{sampler} equal time (methods interleaved)")
        timed, failed = equal_time(renderers, methods, budgets, s, on_pass=tick)
        for m in [m for m in methods if m.name in failed]:
            self.drop(m, sampler, failed[m.name])
            del results[m.name]
        methods = [m for m in methods if m.name in timed]
        for m in methods:
            result = results[m.name]
            base, budget_s, _ = budgets[m.name]
            result.equal_time = measure(timed[m.name], refs[m.family])
            result.equal_time.time_budget_s = budget_s
            result.equal_spp.budget_method = result.equal_time.budget_method = base

        # Convergence sweep: one render per spp value, with the first sampler only (the
        # others recompile their kernels for every new sample count).
        max_spp = 4 * s.spp if s.convergence_max_spp is None else s.convergence_max_spp
        sweep = None
        if max_spp > 0 and sampler == s.samplers[0]:
            sweep = {}
            for m in methods:
                self.bar.set_description(f"{self.name}/{sampler}/{m.name} convergence")
                sweep[m.name] = convergence(renderers[m.name], convergence_spps(sampler, max_spp),
                                            s.seed + SEED_CONVERGENCE, refs[m.family], on_render=tick)
                results[m.name].convergence = [point for point, _ in sweep[m.name]]

        compare_with_baselines(results)
        for m in methods:
            results[m.name].strategy_choice = strategy_choice(renderers[m.name])
            results[m.name].frozen = renderers[m.name].frozen
        # What actually rendered, read back from the sensor the passes used.
        sensor = next(iter(renderers.values())).sensor if renderers else None
        run = RunResult(sampler=sampler, methods=results, maps=ErrorMaps(files={}, scale={}),
                        crop=crop(methods, equal_spp, refs, exposure_value), convergence_plot=None,
                        materials=material_breakdown(renderers, methods, equal_spp, timed, refs),
                        sampler_plugin=sensor.sampler().class_name() if sensor else None,
                        film_size=[int(v) for v in sensor.film().size()] if sensor else None)
        self.files.run(run, equal_spp, timed, sweep, error_maps(methods, equal_spp, refs), exposure_value,
                       f"{self.name}, {sampler} sampler")
        return run


def count_renders(settings: CompareSettings, n_methods: int) -> int:
    """Renders the progress bar counts for one scene (an estimate before methods are known)."""
    sweep = 0 if settings.convergence_max_spp == 0 else len(
        convergence_spps(settings.samplers[0], settings.convergence_max_spp or 4 * settings.spp))
    per_sampler = n_methods * (1 + 2 * settings.passes)
    return per_sampler * len(settings.samplers) + n_methods * sweep + REFERENCE_CHUNKS


CSV_FIELDS = ["scene", "sampler", "method", "comparison", "spp", "mse", "rel_mse", "pixel_variance",
              "time_s", "efficiency", "max_pixel", "abs_error_percentile", "fireflies", "bias_t",
              "bias_p_value", "bias_flagged", "mse_ratio_vs_baseline", "efficiency_ratio_vs_baseline",
              "setup_time_s", "compile_time_s"]


def write_csv(path: str, report: Report) -> None:
    """One row per scene x sampler x method x comparison (non-finite numbers left empty)."""
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=CSV_FIELDS)
        writer.writeheader()
        for scene in report.scenes:
            for run in scene.runs:
                for name, entry in run.methods.items():
                    for kind in ("equal_spp", "equal_time"):
                        e = getattr(entry, kind)
                        writer.writerow(serialise({
                            "scene": scene.scene, "sampler": run.sampler, "method": name,
                            "comparison": kind, "spp": e.spp, "mse": e.error.mse, "rel_mse": e.error.rel_mse,
                            "pixel_variance": e.error.pixel_variance, "time_s": e.time_s,
                            "efficiency": e.efficiency, "max_pixel": e.tail.max_pixel,
                            "abs_error_percentile": e.tail.abs_error_percentile, "fireflies": e.tail.fireflies,
                            "bias_t": e.bias.t, "bias_p_value": e.bias.p_value, "bias_flagged": e.bias.flagged,
                            "mse_ratio_vs_baseline": e.mse_ratio_vs_baseline,
                            "efficiency_ratio_vs_baseline": e.efficiency_ratio_vs_baseline,
                            "setup_time_s": entry.setup_time_s, "compile_time_s": entry.compile_time_s}))


def run_compare(scene_paths: list[str], settings: CompareSettings) -> Report:
    """Run the comparison of every scene, write the report folder, return the report as saved.

    The verdict, the CSV and the page are made from the report as ``report.json`` holds it
    (:func:`.schema.load_report` of its JSON form), so that they are what a saved report gives.
    """
    os.makedirs(settings.out, exist_ok=True)
    started = time.time()
    scenes = []
    for path, name in zip(scene_paths, scene_labels(scene_paths)):
        n_methods = len(available_methods(list(settings.methods) if settings.methods else None,
                                          multi_bounce=is_multi_bounce(settings.max_depth))[0])
        with tqdm(total=count_renders(settings, n_methods), disable=not settings.progress,
                  desc=os.path.basename(path), unit="render", file=sys.stderr) as bar:
            scenes.append(SceneComparison(path, settings, bar, name).run())
    measured = Report(**environment_info(), settings=settings, scenes=scenes, total_time_s=time.time() - started)
    report = load_report(serialise(measured))
    report.verdict = verdict.verdict(report)
    write_report(os.path.join(settings.out, "report.json"), report)
    write_csv(os.path.join(settings.out, "metrics.csv"), report)
    html.write_html(os.path.join(settings.out, "index.html"), report)
    return report
