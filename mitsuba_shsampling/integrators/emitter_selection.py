"""``sh_direct``'s ``emitter_selection`` ``auto``: each emitter sample as two samples or one, priced.

In a scene with emitters besides the environment, an emitter sample can be

- ``each``: one sample of the environment (the material's strategy) and one of Mitsuba's
  emitter sampling among the others: two BSDF evaluations and two shadow rays;
- ``one``: one emitter drawn as Mitsuba's ``direct`` draws it (selection probability p of
  the environment), then one sample of it: one evaluation, one shadow ray.

With E and O the environment's and the others' one-sample estimates (means I, I_o,
variances V, V_o), ``one`` has the variance

    (V + I^2) / p + (V_o + I_o^2) / (1 - p) - (I + I_o)^2
        = V + V_o + V (1 - p) / p + V_o p / (1 - p) + [I^2 / p + I_o^2 / (1 - p) - (I + I_o)^2],

never less than ``each``'s V + V_o (the bracket is >= 0, and 0 only where p = I / (I + I_o)),
at a pass cheaper by one emitter sample. Which wins depends on the scene: ``one`` where the
environment's share of the light and of the selection are both small (many lights, a dim
sky), ``each`` otherwise (every measured scene: docs/MEASUREMENTS.md). The plan
(:func:`price_emitter_selection`) renders its chosen assignment with both, reads each one's
variance from the images (:data:`~.pilots.PILOT_IMAGES` passes at the pilots' seeds), and
prices each pass with the cost model (``plan`` ``measure``: times them); ``one`` runs where
its variance x time is lower by :data:`SELECTION_REQUIRED_GAIN`.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

from ..timing import kernel_time
from .pilots import PILOT_IMAGES, PILOT_REPEATS, PILOT_SEED, film_mean_pixel_variance

SELECTION_REQUIRED_GAIN = 1.15
"""``one`` must be predicted to beat ``each`` by this factor at equal time: its variance has
the heavier tail (a light drawn with probability p weighs 1 / p), which a few pilot images
see least."""

DESIGNS = ("each", "one")
"""The two designs, in the order a frozen pass's input marks them (:func:`~.sharing.design_marker`)."""


@dataclasses.dataclass(frozen=True)
class SelectionPrice:
    """What the plan weighed: per design, the film's variance of one pilot pass (the
    report's per-pixel measure, averaged over the film) and the pass time (lean passes)."""

    design: str
    variance: dict
    pass_time: dict

    def as_dict(self) -> dict:
        return {"design": self.design, "variance": dict(self.variance), "pass_time": dict(self.pass_time)}


def selection_summary(priced: dict) -> str:
    """What :meth:`SelectionPrice.as_dict` says, in a few words ("" where nothing was priced)."""
    if not priced:
        return ""
    chosen = priced["design"]
    other = "one" if chosen == "each" else "each"
    variance, time = priced["variance"], priced["pass_time"]
    ratio = variance[other] / variance[chosen] if variance[chosen] > 0 else float("inf")
    return (f"other emitters: {chosen} ('{other}': x{ratio:.2f} the variance at "
            f"x{time[other] / time[chosen]:.2f} the pass time)")


def price_emitter_selection(env, render_pass: Callable[[int, int], object], spp: int, pass_time: float,
                            sample_time: float, smooth_share: float, required_gain: float,
                            rounded: Callable[[float], float], lean_seconds: float | None = None) -> SelectionPrice:
    """Render ``env`` as planned with each design, price them and set
    ``env.emitter_selection`` to the better one.

    ``render_pass(spp, seed)`` renders one pass and returns its image; ``pass_time``: the
    planned pass in lean passes, with ``each``; ``sample_time``: the cost model's other-emitter
    sample per unit film share (``one`` saves it on the ``smooth_share`` of the film);
    ``rounded``: applied to the measured variances (a plan must not follow the film's
    atomic splats). With ``lean_seconds`` (the lean pass's time, ``plan`` ``measure``) the
    passes are timed instead (interleaved; the fastest counts), in lean passes."""
    timed = lean_seconds is not None
    images = {design: [] for design in DESIGNS}
    times = {design: [] for design in DESIGNS}
    saved = env.emitter_selection
    try:
        for round_ in range(PILOT_REPEATS + 1 if timed else PILOT_IMAGES):
            for design in DESIGNS:
                env.emitter_selection = design
                if timed:
                    image, seconds = kernel_time(lambda: render_pass(spp, PILOT_SEED + round_))
                    if round_ > 0:  # round 0 compiles
                        times[design].append(seconds)
                else:
                    image = render_pass(spp, PILOT_SEED + round_)
                images[design].append(image)
    finally:
        env.emitter_selection = saved
    variance = {design: rounded(film_mean_pixel_variance(images[design])) for design in DESIGNS}
    if timed:
        pass_times = {design: min(times[design]) / lean_seconds for design in DESIGNS}
    else:
        pass_times = {"each": pass_time, "one": max(pass_time - sample_time * smooth_share, 0.05 * pass_time)}
    error = {design: variance[design] * pass_times[design] for design in DESIGNS}
    design = "one" if error["one"] * required_gain < error["each"] else "each"
    env.emitter_selection = design
    return SelectionPrice(design, variance, pass_times)
