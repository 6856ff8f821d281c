"""The ``compare`` command: every method of a scene at equal samples and equal time.

For each scene and sampler, each method renders K independent passes at an
equal ray budget, then K passes at the spp that takes about as long as the
baseline (``direct`` 1+1 or ``path``) at the requested spp, then a
convergence sweep (one render per spp value). Everything is measured against a
cached ``path`` reference and written to ``report.json``, ``metrics.csv``,
EXR/PNG files and ``index.html``.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import os
import platform
import sys
import time

import numpy as np
from tqdm import tqdm

import drjit as dr
import mitsuba as mi

from .. import scenes as builtin
from . import html, images, metrics
from .methods import BASELINE, DIRECT, MULTI_BOUNCE, MULTI_BOUNCE_BASELINE, Method, available_methods
from .figures import sampler_demo_figures
from .plots import convergence_figure
from .rendering import (SEED_CONVERGENCE, SEED_EQUAL_TIME, MethodRenderer, PassSet, Reference,
                        REFERENCE_CHUNKS, admissible_spp, render_reference, write_exr)


@dataclasses.dataclass
class CompareSettings:
    """Settings of one ``compare`` run (the CLI options)."""

    out: str = "report"
    res: int = 128
    spp: int = 16
    passes: int = 4
    ref_spp: int = 1024
    samplers: tuple[str, ...] = ("independent", "multijitter")
    methods: tuple[str, ...] | None = None
    envmap: str | None = None
    max_depth: int = 2
    seed: int = 0
    convergence_max_spp: int | None = None  # None: 4 x spp; 0 disables the sweep
    cache_dir: str = os.path.join(os.path.expanduser("~"), ".cache", "mitsuba-shsampling")
    progress: bool = True


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


def pass_metrics(passes: PassSet, reference: Reference) -> dict:
    """Metrics of K passes against the reference (per pass, averaged)."""
    mse = float(np.mean([metrics.mse(img, reference.image) for img in passes.images]))
    rel = float(np.mean([metrics.rel_mse(img, reference.image) for img in passes.images]))
    bias = metrics.bias_check(passes.images, reference.image, reference.variance)
    return {
        "spp": passes.spp,
        "mse": mse,
        "rel_mse": rel,
        "time_s": passes.time_s,
        "times_s": passes.times_s,
        "efficiency": metrics.efficiency(mse, passes.time_s),
        "mean_pixel_variance": float(metrics.pixel_variance(passes.images).mean()),
        "bias_ok": bias["bias_ok"],
        "bias_fail_fraction": bias["fail_fraction"],
        "bias_mean_z": bias["mean_z"],
        "bias_expected_fail_fraction": bias["expected_fail_fraction"],
        "bias_pixels_suspect": bias["pixels_suspect"],
        "seeds": passes.seeds,
    }


def save_passes(folder: str, tag: str, passes: PassSet, exposure: float, root: str) -> list[str]:
    """Write every pass as EXR and PNG under ``folder``; returns the EXR paths relative to ``root``."""
    os.makedirs(folder, exist_ok=True)
    paths = []
    for k, image in enumerate(passes.images):
        stem = os.path.join(folder, f"{tag}_pass{k}")
        write_exr(stem + ".exr", image)
        images.write_png(stem + ".png", images.tonemap(image, exposure))
        paths.append(os.path.relpath(stem + ".exr", root))
    return paths


class SceneComparison:
    """Runs one scene: references per family, then every sampler and method."""

    def __init__(self, scene_path: str, settings: CompareSettings, bar: tqdm):
        self.path = os.path.abspath(scene_path)
        self.name = os.path.splitext(os.path.basename(scene_path))[0]
        self.settings = settings
        self.bar = bar
        self.root = os.path.abspath(settings.out)
        self.folder = os.path.join(self.root, self.name)
        self.notes: list[str] = []
        self.render_settings = {"res": settings.res, "envmap": settings.envmap,
                                "max_depth": settings.max_depth}
        probe = builtin.load_scene(self.path, **({"envmap": settings.envmap} if settings.envmap else {}))
        self.envmap = builtin.scene_envmap(probe)
        self.has_envmap = self.envmap is not None
        if not self.has_envmap:
            self.notes.append("this scene has no environment map: product sampling has nothing to "
                              "sample here, so the SH methods can only match their fallback strategies")
        self.declared = builtin.scene_parameters(self.path)
        self.references: dict[str, Reference] = {}

    def rel(self, path: str) -> str:
        """``path`` relative to the report folder (how report.json and index.html name files)."""
        return os.path.relpath(path, self.root)

    def methods(self) -> list[Method]:
        names = list(self.settings.methods) if self.settings.methods else None
        chosen, notes = available_methods(names, multi_bounce=self.settings.max_depth > 2)
        self.notes += notes
        runnable = []
        for method in chosen:
            missing = [p for p in method.scene_params if p not in self.declared]
            if missing:
                self.notes.append(f"skipped '{method.name}': the scene declares no ${', $'.join(missing)}")
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
            ref_entries[family] = {"spp": ref.spp, "cache_file": ref.path, "cached": ref.cached,
                                   "render_time_s": ref.time_s, "file": self.rel(stem + ".exr"),
                                   "png": self.rel(stem + ".png"),
                                   "mean_variance": float(ref.variance.mean()),
                                   "integrator": "path, max_depth "
                                   + ("2" if family == DIRECT else str(self.settings.max_depth))}
        runs = [self.run_sampler(sampler, methods, refs, exposure) for sampler in self.settings.samplers]
        figures = self.sampler_figures() if any(m.product_sampling for m in methods) else []
        return {"scene": self.name, "path": self.path, "has_envmap": self.has_envmap,
                "notes": self.notes, "exposure": exposure, "references": ref_entries, "runs": runs,
                "sampler_figures": figures}

    def sampler_figures(self) -> list[dict]:
        """Warped sample points over their targets (SH lobe; lobe x this scene's map)."""
        if not self.has_envmap:
            return []
        out = []
        for i, (caption, png) in enumerate(sampler_demo_figures(self.envmap)):
            path = os.path.join(self.folder, f"sampler_points_{i}.png")
            with open(path, "wb") as f:
                f.write(png)
            out.append({"caption": caption, "png": self.rel(path)})
        return out

    @staticmethod
    def exposure(reference: np.ndarray) -> float:
        """Exposure that maps the 99th luminance percentile of the reference to 0.9."""
        lum = reference[..., :3].mean(axis=-1)
        p99 = float(np.quantile(lum, 0.99))
        return 0.9 / p99 if p99 > 0 else 1.0

    def run_sampler(self, sampler: str, methods: list[Method], refs: dict[str, Reference],
                    exposure: float) -> dict:
        s = self.settings
        settings = dict(self.render_settings, sampler=sampler)
        folder = os.path.join(self.folder, sampler)
        results: dict[str, dict] = {}
        renderers: dict[str, MethodRenderer] = {}

        # Equal ray budget: K passes each. A method that fails to load or render is dropped
        # with a note, so one broken plugin does not cost the whole comparison.
        equal_spp: dict[str, PassSet] = {}
        for m in list(methods):
            self.bar.set_description(f"{self.name}/{sampler}/{m.name} equal spp")
            try:
                r = renderers[m.name] = MethodRenderer(self.path, m, settings)
                r.warm_up(admissible_spp(sampler, equal_ray_spp(s.spp, m)))
                self.bar.update(1)
                passes = r.passes(equal_ray_spp(s.spp, m), s.passes, s.seed)
            except Exception as err:
                self.notes.append(f"'{m.name}' failed with the {sampler} sampler and was left out: "
                                  f"{type(err).__name__}: {str(err).strip().splitlines()[0] if str(err).strip() else ''}")
                methods = [x for x in methods if x is not m]
                continue
            self.bar.update(s.passes)
            equal_spp[m.name] = passes
            entry = {"label": m.label, "family": m.family, "rays_per_sample": m.rays_per_sample,
                     "integrator": m.integrator, "scene_params": m.scene_params,
                     "compile_time_s": r.compile_time_s}
            entry["equal_spp"] = pass_metrics(passes, refs[m.family])
            entry["equal_spp"]["files"] = save_passes(os.path.join(folder, m.name), "equal_spp",
                                                     passes, exposure, self.root)
            results[m.name] = entry

        # Equal time: each method gets the spp that costs the baseline's time per pass.
        for m in methods:
            self.bar.set_description(f"{self.name}/{sampler}/{m.name} equal time")
            base = self.baseline_name(m, results)
            budget = equal_spp[base].time_s
            per_sample = equal_spp[m.name].time_s / equal_spp[m.name].spp
            target = max(1, round(budget / per_sample)) if per_sample > 0 else equal_spp[m.name].spp
            passes = renderers[m.name].passes(target, s.passes, s.seed + SEED_EQUAL_TIME)
            self.bar.update(s.passes)
            entry = pass_metrics(passes, refs[m.family])
            entry.update(time_budget_s=budget, budget_method=base,
                         files=save_passes(os.path.join(folder, m.name), "equal_time", passes,
                                           exposure, self.root))
            results[m.name]["equal_time"] = entry

        # Convergence sweep: one render per spp value, with the first sampler only (the
        # others recompile their kernels for every new sample count).
        max_spp = 4 * s.spp if s.convergence_max_spp is None else s.convergence_max_spp
        if sampler != s.samplers[0]:
            max_spp = 0
        for m in methods:
            points = []
            if max_spp > 0:
                self.bar.set_description(f"{self.name}/{sampler}/{m.name} convergence")
                for i, spp in enumerate(convergence_spps(sampler, max_spp)):
                    image, elapsed = renderers[m.name].render(spp, s.seed + SEED_CONVERGENCE + i)
                    ref = refs[m.family].image
                    stem = os.path.join(folder, m.name, f"convergence_spp{spp}")
                    write_exr(stem + ".exr", image)
                    points.append({"spp": spp, "time_s": elapsed, "mse": metrics.mse(image, ref),
                                   "rel_mse": metrics.rel_mse(image, ref),
                                   "file": self.rel(stem + ".exr")})
                    self.bar.update(1)
            results[m.name]["convergence"] = points

        self.add_ratios(results)
        maps = self.write_maps(folder, methods, equal_spp, refs)
        run = {"sampler": sampler, "methods": results, "maps": maps, "convergence_plot": None}
        if max_spp > 0:
            plot = convergence_figure({results[n]["label"]: results[n]["convergence"] for n in results},
                                      f"{self.name}, {sampler} sampler")
            plot_path = os.path.join(folder, "convergence.png")
            with open(plot_path, "wb") as f:
                f.write(plot)
            run["convergence_plot"] = self.rel(plot_path)
        return run

    @staticmethod
    def baseline_name(method: Method, results: dict) -> str:
        """The method whose time per pass sets the equal-time budget of ``method``'s family."""
        base = BASELINE if method.family == DIRECT else MULTI_BOUNCE_BASELINE
        if base in results:
            return base
        same_family = [n for n, r in results.items() if r["family"] == method.family]
        return same_family[0]

    @staticmethod
    def add_ratios(results: dict) -> None:
        """MSE and efficiency relative to the family baseline (same run)."""
        for name, entry in results.items():
            base = results.get(BASELINE if entry["family"] == DIRECT else MULTI_BOUNCE_BASELINE)
            for kind in ("equal_spp", "equal_time"):
                if base is None:
                    continue
                b, e = base[kind], entry[kind]
                e["mse_ratio_vs_baseline"] = e["mse"] / b["mse"] if b["mse"] > 0 else None
                e["efficiency_ratio_vs_baseline"] = (e["efficiency"] / b["efficiency"]
                                                     if b["efficiency"] > 0 else None)

    def write_maps(self, folder: str, methods: list[Method], equal_spp: dict[str, PassSet],
                   refs: dict[str, Reference]) -> dict:
        """False-colour per-pixel variance and relative-error maps (shared log scales)."""
        variance = {m.name: metrics.pixel_variance(equal_spp[m.name].images) for m in methods}
        error = {m.name: metrics.rel_squared_error_map(equal_spp[m.name].images, refs[m.family].image)
                 for m in methods}
        out = {}
        for kind, maps in (("variance", variance), ("rel_error", error)):
            vmin, vmax = images.log_range(list(maps.values()))
            for name, values in maps.items():
                path = os.path.join(folder, name, f"{kind}_map.png")
                images.write_png(path, images.false_colour(values, vmin, vmax))
                write_exr(os.path.join(folder, name, f"{kind}_map.exr"), values[..., None])
                out.setdefault(name, {})[kind] = self.rel(path)
            out.setdefault("_scale", {})[kind] = [vmin, vmax]
        return out


def count_renders(settings: CompareSettings, n_methods: int) -> int:
    """Renders the progress bar counts for one scene (an estimate before methods are known)."""
    sweep = 0 if settings.convergence_max_spp == 0 else len(
        convergence_spps(settings.samplers[0], settings.convergence_max_spp or 4 * settings.spp))
    per_sampler = n_methods * (1 + 2 * settings.passes)
    return per_sampler * len(settings.samplers) + n_methods * sweep + REFERENCE_CHUNKS


def write_csv(path: str, report: dict) -> None:
    """One row per scene x sampler x method x comparison."""
    fields = ["scene", "sampler", "method", "comparison", "spp", "mse", "rel_mse", "time_s",
              "efficiency", "bias_ok", "bias_fail_fraction", "bias_mean_z", "mean_pixel_variance",
              "mse_ratio_vs_baseline", "efficiency_ratio_vs_baseline", "compile_time_s"]
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=fields)
        writer.writeheader()
        for scene in report["scenes"]:
            for run in scene["runs"]:
                for name, entry in run["methods"].items():
                    for kind in ("equal_spp", "equal_time"):
                        row = {k: entry[kind].get(k) for k in fields if k in entry[kind]}
                        row.update(scene=scene["scene"], sampler=run["sampler"], method=name,
                                   comparison=kind, compile_time_s=entry["compile_time_s"])
                        writer.writerow(row)


def run_compare(scene_paths: list[str], settings: CompareSettings) -> dict:
    """Run the comparison of every scene, write the report folder, return the report dict."""
    os.makedirs(settings.out, exist_ok=True)
    started = time.time()
    report = environment_info()
    settings_dict = dataclasses.asdict(settings)
    settings_dict["samplers"] = list(settings.samplers)
    report["settings"] = settings_dict
    report["scenes"] = []
    for path in scene_paths:
        n_methods = len(available_methods(list(settings.methods) if settings.methods else None,
                                          multi_bounce=settings.max_depth > 2)[0])
        with tqdm(total=count_renders(settings, n_methods), disable=not settings.progress,
                  desc=os.path.basename(path), unit="render", file=sys.stderr) as bar:
            report["scenes"].append(SceneComparison(path, settings, bar).run())
    report["total_time_s"] = time.time() - started
    with open(os.path.join(settings.out, "report.json"), "w") as f:
        json.dump(report, f, indent=2)
    write_csv(os.path.join(settings.out, "metrics.csv"), report)
    html.write_html(os.path.join(settings.out, "index.html"), report)
    return report
