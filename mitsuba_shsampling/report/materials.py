"""Per-material breakdown: where in the image a method wins and where it loses.

A realistic image is mostly ground, walls and diffuse objects; one number for the
whole image hides that a method can win on the glossy object and lose on the
ground. Each pixel is given the material (BSDF instance) seen through its centre,
by one camera ray per pixel centre (the box-filtered AOV of the BSDF index, without
the film's reconstruction filter, so that every pixel has exactly one material).
Pixels whose centre sees no surface are the ``background``.

For each material and method the breakdown gives, from the K passes of the
comparison:

- the expected squared error (against the reference, averaged over the passes)
  summed over the material's pixels, as a ratio to the best Mitsuba strategy *on
  that material* (so a ratio below 1 means the method beats every Mitsuba strategy
  there), at equal samples and at equal time, with the paired bootstrap interval over
  passes that the verdict uses (:func:`.metrics.paired_bootstrap`; the best Mitsuba
  strategy is the one of all passes). Squared error rather than variance,
  because a strategy can be noiseless on a material by leaving it dark: envmap-only
  sampling gives a smooth glass no light at all;
- the share of the method's image error (the same squared error, summed over
  pixels) that the material carries.

The film filter spreads a pixel's samples over its neighbours, so a thin object's
edge pixels mix materials; the per-pixel-centre assignment counts them where their
centre falls.
"""

from __future__ import annotations

import numpy as np

import drjit as dr
import mitsuba as mi

from ..scene_materials import registry_id, scene_materials
from .metrics import paired_bootstrap
from .schema import MaterialEntry

BACKGROUND = "background"


def material_map(scene: mi.Scene, sensor: mi.Sensor) -> tuple[np.ndarray, list[tuple[str, str]]]:
    """Material index of every pixel (H, W), -1 for the background, and (name, plugin) per index.

    One ray through each pixel centre of ``sensor``'s film (its crop window included); shapes that
    share a BSDF instance share an index.
    """
    film = sensor.film()
    width, height = (int(v) for v in film.crop_size())
    idx = np.arange(width * height)
    # Relative to the crop window, as Mitsuba's integrators place their samples (the sensor
    # maps the window onto its part of the view).
    pos = mi.Point2f(((idx % width) + 0.5) / width, ((idx // width) + 0.5) / height)
    ray, _ = sensor.sample_ray(0.0, 0.5, pos, mi.Point2f(0.5))
    si = scene.ray_intersect(ray)
    hit_ids = np.array(dr.reinterpret_array(mi.UInt32, si.shape), dtype=np.int64)
    valid = np.array(si.is_valid())

    # Registry id of each shape -> index of its material (shared BSDFs share an index).
    materials = scene_materials(scene)
    shape_to_material = {registry_id(shape): index for index, m in enumerate(materials)
                         for shape in scene.shapes() if shape.bsdf() is m.bsdf}
    labels = [(m.name, m.plugin) for m in materials]

    lookup = np.vectorize(lambda r: shape_to_material.get(int(r), -1), otypes=[np.int64])
    ids = np.where(valid, lookup(hit_ids) if hit_ids.size else hit_ids, -1)
    return ids.reshape(height, width), labels


def breakdown(ids: np.ndarray, labels: list[tuple[str, str]], equal_spp: dict[str, np.ndarray],
              equal_time: dict[str, np.ndarray], reference: np.ndarray, project: list[str],
              mitsuba: list[str]) -> list[MaterialEntry]:
    """The per-material rows (largest pixel share first) for the methods of one run.

    :param ids: (H, W) material index per pixel (:func:`material_map`).
    :param equal_spp, equal_time: method -> its (K, H, W, C) passes; methods missing from
        ``equal_time`` get None there.
    :param reference: (H, W, C) reference image of the methods' family.
    :param project, mitsuba: names of the project's and of Mitsuba's methods among them.
    """
    def squared_error(passes: np.ndarray) -> np.ndarray:
        """(K, H, W) squared error of each pass against the reference, averaged over channels
        (a non-finite value counts for nothing)."""
        with np.errstate(invalid="ignore"):
            error = np.where(np.isfinite(passes), (passes - reference[None]) ** 2, np.nan)
        return np.nan_to_num(np.nanmean(error, axis=3))

    errors = {kind: {n: squared_error(p) for n, p in passes.items()}
              for kind, passes in (("equal_spp", equal_spp), ("equal_time", equal_time))}
    total_error = {n: float(e.sum()) for n, e in errors["equal_spp"].items()}

    entries = []
    names = [(BACKGROUND, "(environment)")] + labels
    for index, (name, plugin) in zip(range(-1, len(labels)), names):
        mask = ids == index
        if not mask.any():
            continue
        ratios: dict[str, dict[str, float | None]] = {n: {} for n in project}
        intervals: dict[str, dict[str, list[float]]] = {n: {} for n in project}
        best: dict[str, str | None] = {}
        for kind, maps in errors.items():
            per_pass = {n: e[:, mask].sum(axis=1) for n, e in maps.items()}
            candidates = [n for n in mitsuba if n in per_pass]
            best[kind] = min(candidates, key=lambda n: per_pass[n].mean()) if candidates else None
            for n in project:
                base = per_pass[best[kind]] if best[kind] else None
                if n not in per_pass or base is None or not base.mean() > 0:
                    ratios[n][kind] = None
                    continue
                ratios[n][kind] = float(per_pass[n].mean() / base.mean())
                mine = per_pass[n]
                intervals[n][kind] = list(paired_bootstrap(
                    lambda idx, a=mine, b=base: a[idx].mean() / b[idx].mean(), min(len(mine), len(base))))
        shares = {n: float(e[:, mask].sum()) / total_error[n] if total_error[n] > 0 else None
                  for n, e in errors["equal_spp"].items()}
        entries.append(MaterialEntry(name=name, plugin=plugin, pixel_share=float(mask.mean()),
                                     error_ratio=ratios, best_mitsuba=best, error_share=shares,
                                     error_ratio_interval=intervals))
    return sorted(entries, key=lambda e: -e.pixel_share)
