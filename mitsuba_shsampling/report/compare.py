"""The ``compare`` command: every method of a scene at equal samples and equal time.

For each scene and sampler, each method renders K independent passes (K >= 32 by
default, so that rare, huge samples show up in the expected error) at an equal
ray budget, then K passes at the spp that takes about as long as the baseline
(``direct`` 1+1 or ``path``) at the requested spp, then a convergence sweep (one
render per spp value). Everything is measured against a cached ``path``
reference (:mod:`.metrics`: expected error, tails, bias test), judged in a
verdict (:mod:`.verdict`), and written to ``report.json``, ``metrics.csv``,
EXR/PNG files and ``index.html``. Results are the typed report of :mod:`.schema`.
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
from .schema import (CompareSettings, ConvergencePoint, EnvmapEntry, ErrorMaps, MethodResult, PassResult,
                     ReferenceEntry, Report, RunResult, SamplerFigure, SceneResult, load_report, serialise,
                     write_report)


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


def measure(passes: PassSet, reference: Reference, files: dict[str, str]) -> PassResult:
    """Every statistic of K passes against the reference."""
    error = metrics.error_stats(passes.images, reference.image)
    return PassResult(
        spp=passes.spp, time_s=passes.time_s, times_s=passes.times_s,
        efficiency=metrics.efficiency(error.mse, passes.time_s), error=error,
        tail=metrics.tail_stats(passes.images, reference.image),
        bias=metrics.bias_test(metrics.image_mean_luminance(passes.images), reference.chunk_means),
        seeds=passes.seeds, files=files)


def save_passes(folder: str, tag: str, passes: PassSet, exposure: float, root: str) -> dict[str, str]:
    """Write the first pass (EXR, PNG) and the mean of all passes (EXR) under ``folder``."""
    os.makedirs(folder, exist_ok=True)
    stem = os.path.join(folder, tag)
    write_exr(stem + "_pass0.exr", passes.images[0])
    images.write_png(stem + "_pass0.png", images.tonemap(passes.images[0], exposure))
    write_exr(stem + "_mean.exr", passes.images.mean(axis=0))
    return {"first_pass": os.path.relpath(stem + "_pass0.exr", root),
            "first_pass_png": os.path.relpath(stem + "_pass0.png", root),
            "mean": os.path.relpath(stem + "_mean.exr", root)}


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


class SceneComparison:
    """Runs one scene: references per family, then every sampler and method.

    :param name: the scene's name in the report (:func:`scene_labels`; default: the file's stem),
        also its folder under the report folder.
    """

    def __init__(self, scene_path: str, settings: CompareSettings, bar: tqdm, name: str | None = None):
        self.path = os.path.abspath(scene_path)
        self.name = name or os.path.splitext(os.path.basename(scene_path))[0]
        self.settings = settings
        self.bar = bar
        self.root = os.path.abspath(settings.out)
        self.folder = os.path.join(self.root, self.name)
        self.notes: list[str] = []
        self.render_settings = {"res": settings.res, "envmap": settings.envmap,
                                "max_depth": settings.max_depth}
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
            texels = np.array(mi.traverse(self.envmap)["data"])[:, 1:-1]
            bad = int(np.count_nonzero(~np.isfinite(texels)))
            if bad:
                self.notes.append(
                    f"the environment map has {bad} non-finite texel values (NaN or infinite). Pixels "
                    f"that come out non-finite (in the reference or in any pass) are counted and left "
                    f"out of every statistic. An integrator that zeroes such texels (the SH integrators "
                    f"warn when they do) renders another map than the reference and Mitsuba's methods: "
                    f"on this scene its comparison with them is not like for like")
        self.references: dict[str, Reference] = {}

    def rel(self, path: str) -> str:
        """``path`` relative to the report folder (how report.json and index.html name files)."""
        return os.path.relpath(path, self.root)

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

    def run(self) -> dict:
        methods = self.methods()
        families = sorted({m.family for m in methods})
        refs = {f: self.reference(f) for f in families}
        os.makedirs(self.folder, exist_ok=True)
        exposure = self.exposure(next(iter(refs.values())).image) if refs else 1.0
        ref_entries = {}
        for family, ref in refs.items():
            stem = os.path.join(self.folder, f"reference_{family}")
            write_exr(stem + ".exr", ref.image)
            images.write_png(stem + ".png", images.tonemap(ref.image, exposure))
            if ref.non_finite:
                self.notes.append(f"the {family} reference has {ref.non_finite} non-finite pixel values: "
                                  f"those pixels are left out of every method's statistics")
            ref_entries[family] = ReferenceEntry(
                spp=ref.spp, chunks=int(ref.chunks.shape[0]), cache_file=ref.path, cached=ref.cached,
                render_time_s=ref.time_s, file=self.rel(stem + ".exr"), png=self.rel(stem + ".png"),
                mean_variance=float(np.nanmean(np.where(np.isfinite(ref.variance), ref.variance, np.nan))),
                integrator="path, max_depth " + ("2" if family == DIRECT else str(self.settings.max_depth)))
        runs = [self.run_sampler(sampler, methods, refs, exposure) for sampler in self.settings.samplers]
        figures = self.sampler_figures() if any(m.product_sampling for m in methods) else []
        return SceneResult(scene=self.name, path=self.path, has_envmap=self.has_envmap,
                           envmap=self.envmap_entry(), notes=self.notes, exposure=exposure,
                           references=ref_entries, runs=runs, sampler_figures=figures)

    def envmap_entry(self) -> EnvmapEntry | None:
        """The environment map's file name (``--envmap``, else the scene's) and a thumbnail."""
        if not self.has_envmap:
            return None
        named = re.search(r'filename = "([^"]*)"', str(self.envmap))
        name = os.path.basename(self.settings.envmap) if self.settings.envmap else (
            named.group(1) if named else "(built from a bitmap)")
        path = os.path.join(self.folder, "envmap.png")
        os.makedirs(self.folder, exist_ok=True)
        images.write_png(path, images.thumbnail(np.array(mi.traverse(self.envmap)["data"])[:, 1:-1]))
        return EnvmapEntry(name=name, png=self.rel(path))

    def sampler_figures(self) -> list[SamplerFigure]:
        """Warped sample points over their targets (SH lobe; lobe x this scene's map)."""
        if not self.has_envmap:
            return []
        out = []
        for i, (caption, png) in enumerate(sampler_demo_figures(self.envmap)):
            path = os.path.join(self.folder, f"sampler_points_{i}.png")
            with open(path, "wb") as f:
                f.write(png)
            out.append(SamplerFigure(caption=caption, png=self.rel(path)))
        return out

    @staticmethod
    def exposure(reference: np.ndarray) -> float:
        """Exposure that maps the 99th luminance percentile of the (finite) reference to 0.9."""
        lum = metrics.luminance(reference)
        lum = lum[np.isfinite(lum)]
        p99 = float(np.quantile(lum, 0.99)) if lum.size else 0.0
        return 0.9 / p99 if p99 > 0 else 1.0

    def drop(self, method: Method, sampler: str, err: Exception) -> None:
        """Note that ``method`` failed and is left out of this sampler's comparison."""
        first_line = str(err).strip().splitlines()[0] if str(err).strip() else ""
        self.notes.append(f"'{method.name}' failed with the {sampler} sampler and was left out: "
                          f"{type(err).__name__}: {first_line}")

    def run_sampler(self, sampler: str, methods: list[Method], refs: dict[str, Reference],
                    exposure: float) -> RunResult:
        s = self.settings
        settings = dict(self.render_settings, sampler=sampler)
        folder = os.path.join(self.folder, sampler)
        results: dict[str, MethodResult] = {}
        renderers: dict[str, MethodRenderer] = {}

        # Equal ray budget: K passes each, timed interleaved across the methods. A method
        # that fails to load or render is dropped with a note, so one broken plugin does
        # not cost the whole comparison.
        for m in list(methods):
            self.bar.set_description(f"{self.name}/{sampler}/{m.name} compile")
            try:
                r = renderers[m.name] = MethodRenderer(self.path, m, settings)
                r.warm_up(admissible_spp(sampler, equal_ray_spp(s.spp, m)))
            except Exception as err:
                self.drop(m, sampler, err)
                methods = [x for x in methods if x is not m]
            self.bar.update(1)
        self.bar.set_description(f"{self.name}/{sampler} equal spp (methods interleaved)")
        equal_spp, failed = interleaved_passes(
            {m.name: (renderers[m.name], equal_ray_spp(s.spp, m)) for m in methods},
            s.passes, s.seed, on_pass=lambda: self.bar.update(1))
        for m in [m for m in methods if m.name in failed]:
            self.drop(m, sampler, failed[m.name])
        methods = [m for m in methods if m.name in equal_spp]
        for m in methods:
            passes = equal_spp[m.name]
            files = save_passes(os.path.join(folder, m.name), "equal_spp", passes, exposure, self.root)
            results[m.name] = MethodResult(
                label=m.label, family=m.family, rays_per_sample=m.rays_per_sample,
                integrator=m.integrator, scene_params=m.scene_params,
                compile_time_s=renderers[m.name].compile_time_s,
                equal_spp=measure(passes, refs[m.family], files), oracle=m.oracle)

        # Equal time: each method gets the spp that costs the baseline's time per pass.
        budgets, targets = {}, {}
        for m in methods:
            base = self.baseline_name(m, results)
            budgets[m.name] = (base, equal_spp[base].time_s)
            per_sample = equal_spp[m.name].time_s / equal_spp[m.name].spp
            targets[m.name] = (max(1, round(budgets[m.name][1] / per_sample)) if per_sample > 0
                               else equal_spp[m.name].spp)
        self.bar.set_description(f"{self.name}/{sampler} equal time (methods interleaved)")
        equal_time, failed = interleaved_passes(
            {m.name: (renderers[m.name], targets[m.name]) for m in methods},
            s.passes, s.seed + SEED_EQUAL_TIME, on_pass=lambda: self.bar.update(1))
        for m in [m for m in methods if m.name in failed]:
            self.drop(m, sampler, failed[m.name])
            del results[m.name]
        methods = [m for m in methods if m.name in equal_time]
        for m in methods:
            passes = equal_time[m.name]
            files = save_passes(os.path.join(folder, m.name), "equal_time", passes, exposure, self.root)
            result = results[m.name]
            result.equal_time = measure(passes, refs[m.family], files)
            base, budget = budgets[m.name]
            result.equal_time.time_budget_s = budget
            result.equal_spp.budget_method = result.equal_time.budget_method = base

        # Convergence sweep: one render per spp value, with the first sampler only (the
        # others recompile their kernels for every new sample count).
        max_spp = 4 * s.spp if s.convergence_max_spp is None else s.convergence_max_spp
        if sampler != s.samplers[0]:
            max_spp = 0
        for m in methods:
            if max_spp > 0:
                self.bar.set_description(f"{self.name}/{sampler}/{m.name} convergence")
                for i, spp in enumerate(convergence_spps(sampler, max_spp)):
                    image, elapsed = renderers[m.name].timed_render(spp, s.seed + SEED_CONVERGENCE + i)
                    ref = refs[m.family].image
                    stem = os.path.join(folder, m.name, f"convergence_spp{spp}")
                    write_exr(stem + ".exr", image)
                    results[m.name].convergence.append(ConvergencePoint(
                        spp=spp, time_s=elapsed, mse=metrics.mse(image, ref), rel_mse=metrics.rel_mse(image, ref),
                        file=self.rel(stem + ".exr")))
                    self.bar.update(1)

        self.compare_with_baselines(results)
        maps = self.write_maps(folder, methods, equal_spp, refs)
        # What actually rendered, read back from the sensor the passes used.
        sensor = next(iter(renderers.values())).sensor if renderers else None
        breakdown = self.material_breakdown(renderers, methods, equal_spp, equal_time, refs)
        run = RunResult(sampler=sampler, methods=results, maps=maps, crop=self.crop(methods, equal_spp),
                        convergence_plot=None, materials=breakdown,
                        sampler_plugin=sensor.sampler().class_name() if sensor else None,
                        film_size=[int(v) for v in sensor.film().size()] if sensor else None)
        if max_spp > 0:
            plot = convergence_figure({r.label: r.convergence for r in results.values()},
                                      f"{self.name}, {sampler} sampler")
            plot_path = os.path.join(folder, "convergence.png")
            with open(plot_path, "wb") as f:
                f.write(plot)
            run.convergence_plot = self.rel(plot_path)
        return run

    @staticmethod
    def material_breakdown(renderers: dict[str, MethodRenderer], methods: list[Method],
                           equal_spp: dict[str, PassSet], equal_time: dict[str, PassSet],
                           refs: dict[str, Reference]) -> dict[str, list[materials.MaterialEntry]]:
        """Per family, the per-material variance ratios and error shares (:mod:`.materials`)."""
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
        return out

    @staticmethod
    def baseline_name(method: Method, results: dict[str, MethodResult]) -> str:
        """The method whose time per pass sets the equal-time budget of ``method``'s family."""
        base = BASELINE if method.family == DIRECT else MULTI_BOUNCE_BASELINE
        if base in results:
            return base
        same_family = [n for n, r in results.items() if r.family == method.family]
        # Never a reference row: an oracle pass costs 10-200x a renderer's.
        return ([n for n in same_family if not results[n].oracle] or same_family)[0]

    @staticmethod
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

    @staticmethod
    def crop(methods: list[Method], equal_spp: dict[str, PassSet]) -> list[int] | None:
        """[x, y, size] of the zoomed crop shown for every method: the window of a sixth of the
        image (at least 8 px) where the methods' summed per-pixel variance is largest."""
        if not methods:
            return None
        variance = sum(metrics.pixel_variance(equal_spp[m.name].images) for m in methods)
        size = max(8, min(variance.shape) // 6)
        return [*images.noisiest_window(variance, size), min(size, *variance.shape)]

    def write_maps(self, folder: str, methods: list[Method], equal_spp: dict[str, PassSet],
                   refs: dict[str, Reference]) -> ErrorMaps:
        """False-colour per-pixel variance and relative-error maps (shared log scales)."""
        variance = {m.name: metrics.pixel_variance(equal_spp[m.name].images) for m in methods}
        error = {m.name: metrics.rel_squared_error_map(equal_spp[m.name].images, refs[m.family].image)
                 for m in methods}
        out = ErrorMaps(files={}, scale={})
        for kind, maps in (("variance", variance), ("rel_error", error)):
            vmin, vmax = images.log_range(list(maps.values()))
            for name, values in maps.items():
                path = os.path.join(folder, name, f"{kind}_map.png")
                images.write_png(path, images.false_colour(values, vmin, vmax))
                write_exr(os.path.join(folder, name, f"{kind}_map.exr"), values[..., None])
                out.files.setdefault(name, {})[kind] = self.rel(path)
            out.scale[kind] = [vmin, vmax]
        return out


def count_renders(settings: CompareSettings, n_methods: int) -> int:
    """Renders the progress bar counts for one scene (an estimate before methods are known)."""
    sweep = 0 if settings.convergence_max_spp == 0 else len(
        convergence_spps(settings.samplers[0], settings.convergence_max_spp or 4 * settings.spp))
    per_sampler = n_methods * (1 + 2 * settings.passes)
    return per_sampler * len(settings.samplers) + n_methods * sweep + REFERENCE_CHUNKS


CSV_FIELDS = ["scene", "sampler", "method", "comparison", "spp", "mse", "rel_mse", "pixel_variance",
              "time_s", "efficiency", "max_pixel", "abs_error_percentile", "fireflies", "bias_t",
              "bias_p_value", "bias_flagged", "mse_ratio_vs_baseline", "efficiency_ratio_vs_baseline",
              "compile_time_s"]


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
                            "compile_time_s": entry.compile_time_s}))


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
