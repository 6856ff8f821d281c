"""Fit quality and per-lane cost of the BSDF lobe proxies (``mitsuba_shsampling.lobes``).

For each BSDF and view elevation, compares the cosine-weighted lobe g (the BSDF's
own ``eval``, by a 300 x 600 midpoint rule on the hemisphere) with

- the fitted proxy (``SceneLobes``: diffuse + mirror-Phong, exponent clamped to
  what the scene's band count represents), and
- for ``roughconductor`` only, the analytic proxy: a single Phong lobe about the
  mirror direction with s = 1 / (2 alpha^2) and the exact energy.

Metrics (0 = proxy proportional to g): ``mis_div`` = chi-square divergence of g
against (proxy + g)/2 (relative variance of a balance-heuristic MIS sample from
proxy or a perfect BSDF sampler, constant lighting); ``chi2`` = plain chi-square
divergence of g against the proxy (relative variance of proxy-only sampling,
inf when the proxy misses part of g). Both are on the exact proxy function, before
the SH band limit. Also: warm throughput of ``SceneLobes.coefficients``.

    python3 scripts/bench_lobes.py [--quick] [--json out.json]
"""

from __future__ import annotations

import argparse
import math
import time

import drjit as dr
import mitsuba as mi
import numpy as np

from ..lobes import SceneLobes
from ..lobes.fit import luminance
from . import set_default_variant, write_json

BSDFS = {
    "diffuse": {"type": "diffuse"},
    "ggx 0.05": {"type": "roughconductor", "distribution": "ggx", "alpha": 0.05},
    "ggx 0.1": {"type": "roughconductor", "distribution": "ggx", "alpha": 0.1},
    "ggx 0.2": {"type": "roughconductor", "distribution": "ggx", "alpha": 0.2},
    "ggx 0.3": {"type": "roughconductor", "distribution": "ggx", "alpha": 0.3},
    "ggx 0.5": {"type": "roughconductor", "distribution": "ggx", "alpha": 0.5},
    "beckmann 0.2": {"type": "roughconductor", "distribution": "beckmann", "alpha": 0.2},
    "roughplastic ggx 0.1": {"type": "roughplastic", "distribution": "ggx", "alpha": 0.1},
    "roughplastic beck 0.3": {"type": "roughplastic", "alpha": 0.3},
    "principled r0.4 m0.5": {"type": "principled", "roughness": 0.4, "metallic": 0.5},
    "twosided ggx 0.2": {"type": "twosided", "bsdf": {"type": "roughconductor",
                                                      "distribution": "ggx", "alpha": 0.2}},
    "blend diffuse/ggx 0.15": {"type": "blendbsdf", "weight": 0.5, "bsdf_0": {"type": "diffuse"},
                               "bsdf_1": {"type": "roughconductor", "distribution": "ggx",
                                          "alpha": 0.15}},
}
VIEW_COSINES = [0.1, 0.3, 0.6, 0.9]
#: Band cap of the measured fits: above the plugins' default, so that the figures are the
#: fit's own rather than the exponent clamp of a low band count (and stay comparable with
#: earlier runs).
FIT_BANDS = 20
QUICK_VIEW_COSINES = [0.3, 0.9]


def hemisphere(n=300):
    z = (np.arange(n) + 0.5) / n
    phi = (np.arange(2 * n) + 0.5) * math.pi / n
    zz, pp = np.meshgrid(z, phi, indexing="ij")
    st = np.sqrt(1 - zz * zz)
    return np.stack([st * np.cos(pp), st * np.sin(pp), zz], -1).reshape(-1, 3), math.pi / n / n


def lobe(bsdf, c, dirs):
    si = dr.zeros(mi.SurfaceInteraction3f, len(dirs))
    si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
    si.n = mi.Normal3f(0, 0, 1)
    si.wi = mi.Vector3f(math.sqrt(1 - c * c), 0, c)
    return np.array(luminance(bsdf.eval(mi.BSDFContext(), si, mi.Vector3f(*dirs.T))), np.float64)


def divergences(g, proxy, weight):
    energy = g.sum() * weight
    mis = (g * g / (0.5 * (proxy + g) + 1e-300)).sum() * weight / energy - 1
    with np.errstate(divide="ignore", invalid="ignore"):
        chi2 = np.where(g > 0, g * g / proxy, 0).sum() * weight / energy - 1
    return float(mis), float(chi2)


def phong_proxy(dirs, axis, s):
    return (s + 1) / (2 * math.pi) * np.maximum(dirs @ axis, 0) ** s


def run(quick: bool = False) -> dict:
    """Fit figures per (BSDF, view cosine), and the per-lane cost of the lookup."""
    view_cosines = QUICK_VIEW_COSINES if quick else VIEW_COSINES
    dirs, weight = hemisphere()
    rows = []
    print(f"{'bsdf':24s} {'cos':>4s} {'E err':>7s} {'w_g/E':>6s} {'s':>6s} {'mis_div':>8s} "
          f"{'chi2':>8s} | {'analytic mis_div':>16s} {'chi2':>8s}  fit time")
    for name, desc in BSDFS.items():
        scene = mi.load_dict({"type": "scene", "plane": {"type": "rectangle", "bsdf": desc}})
        t0 = time.perf_counter()
        lobes = SceneLobes(scene, max_bands=FIT_BANDS)
        fit_time = time.perf_counter() - t0
        bsdf = scene.shapes()[0].bsdf()
        c = np.array(view_cosines)
        d = np.stack([np.sqrt(1 - c * c), 0 * c, c], -1)
        si = scene.ray_intersect(mi.Ray3f(mi.Point3f(*(2 * d.T)), mi.Vector3f(*(-d.T))))
        w_d, w_g, s, _ = (np.array(v, np.float64) for v in lobes.lookup(si))
        for k, cv in enumerate(view_cosines):
            g = lobe(bsdf, cv, dirs)
            energy = g.sum() * weight
            mirror = np.array([-math.sqrt(1 - cv * cv), 0, cv])
            proxy = w_d[k] * dirs[:, 2] / math.pi + w_g[k] * phong_proxy(dirs, mirror, s[k])
            mis, chi2 = divergences(g, proxy, weight)
            row = dict(bsdf=name, view_cos=cv, energy=energy, energy_rel_err=(w_d[k] + w_g[k]) / energy - 1,
                       glossy_fraction=w_g[k] / (w_d[k] + w_g[k]), exponent=s[k], mis_div=mis, chi2=chi2,
                       n_bands=lobes.n_bands, fit_time_s=fit_time)
            analytic = ""
            if desc["type"] == "roughconductor":
                s_a = 1 / (2 * desc["alpha"] ** 2)
                mis_a, chi2_a = divergences(g, energy * phong_proxy(dirs, mirror, s_a), weight)
                row.update(analytic_exponent=s_a, analytic_mis_div=mis_a, analytic_chi2=chi2_a)
                analytic = f"{mis_a:16.3f} {chi2_a:8.3g}"
            rows.append(row)
            print(f"{name:24s} {cv:4.1f} {row['energy_rel_err']:+7.2%} {row['glossy_fraction']:6.2f} "
                  f"{s[k]:6.1f} {mis:8.3f} {chi2:8.3g} | {analytic:>25s}  {fit_time:.2f}s")

    # Per-lane cost: 2^20 lanes, several BSDFs, warm (second run).
    scene = mi.load_dict({"type": "scene", **{
        f"s{i}": {"type": "sphere", "center": [2.5 * i, 0, 0], "bsdf": desc}
        for i, desc in enumerate(BSDFS.values())}})
    lobes = SceneLobes(scene, max_bands=FIT_BANDS)
    n = 1 << (18 if quick else 20)
    x = dr.arange(mi.Float, n) / n * 2.5 * len(BSDFS) - 1.0
    si = scene.ray_intersect(mi.Ray3f(mi.Point3f(x, 0.3, 5.0), mi.Vector3f(0, 0, -1)))
    dr.eval(si)
    times = []
    for _ in range(3):
        t0 = time.perf_counter()
        coeffs, use = lobes.coefficients(si, lambda v: mi.Vector3f(-v.z, -v.x, v.y))
        dr.eval(coeffs, use)
        dr.sync_thread()
        times.append(time.perf_counter() - t0)
    rate = n / min(times[1:]) / 1e6
    print(f"\ncoefficients(): {lobes.n_bands} bands, {n} lanes, first {times[0]:.2f}s "
          f"(compile), warm {min(times[1:]) * 1e3:.1f} ms = {rate:.1f} M lanes/s")
    return dict(rows=rows, coefficients=dict(n_bands=lobes.n_bands, lanes=n, warm_seconds=min(times[1:]),
                                             first_seconds=times[0]))


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="two view elevations, 2^18 lanes")
    parser.add_argument("--json", default="bench_lobes.json")
    args = parser.parse_args(argv)
    set_default_variant()
    write_json(args.json, run(args.quick))


if __name__ == "__main__":
    main()
