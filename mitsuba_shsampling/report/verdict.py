"""The verdict of a comparison: who wins at equal samples and at equal time, by how much, how sure.

Works on the report as saved (:func:`.schema.load_report` of ``report.json``), so it
can be recomputed from a saved report. For each scene, sampler and method family:

- **equal samples**: lowest expected MSE (mean over passes of each pass's MSE);
- **equal time**: highest efficiency 1 / (MSE x time per pass) of the equal-time renders;
- **equal time, from the equal-sample passes** (``time_normalised``): the same efficiency
  from the equal-sample passes' MSE, each pass timed at the cost per sample the method had
  at equal time (:func:`at_equal_time_cost`, so that a fixed overhead per pass counts as it
  does there). For these unbiased estimators the MSE falls as 1 / spp, so it estimates
  what the equal-time renders estimate; but there the two methods render each
  pass at one seed and one spp, so noise they draw alike (the same pixel positions, the
  same BSDF-sampled paths: a sun seen in a mirror, a caustic through glass) cancels in the
  pairing, while at equal time their spp differ and it does not. Where the two equal-time
  intervals do not overlap, a caveat says so.

The factor set against the winner is *the project's plugin at its defaults over the
best of Mitsuba's own strategies* (the roles of :mod:`.methods`: every Mitsuba method of
the family that ran, ``direct``, ``direct`` with ``mis_compensation``, envmap-only and
BSDF-only for direct lighting, ``path`` for multi-bounce): what a user gets by switching
the integrator (:data:`.methods.DEFAULT_PLUGIN_METHOD`; the first project method when
that one did not run). The project's other rows follow, each against the same best
Mitsuba strategy and named by its plugin parameters (``sh_direct (strategy=product_only)``).
When no project method ran, the factor is the winner over the runner-up. Each interval is
the paired bootstrap over passes of :func:`.metrics.paired_bootstrap`: pass k of both methods
is resampled together (the passes are i.i.d. across k; methods share seeds, so pairing also
keeps their correlation).
Reference rows (the oracle) are no contenders: they appear in the caveats only.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from .methods import DEFAULT_PLUGIN_METHOD, MITSUBA, PROJECT, REFERENCE, role_of
from .metrics import BIAS_ALPHA, INTERVAL, TAIL_PERCENTILE, paired_bootstrap
from .schema import (CONTEST_TITLES, MethodResult, PassResult, Report, RunResult, VerdictCell, VerdictOther,
                     VerdictRow, load_report)

#: A baseline pass shorter than this is dominated by per-launch overhead and timer noise.
MIN_PASS_TIME_S = 0.020
#: The baseline renders the same spp at equal samples and at equal time; per-sample times of
#: the two phases further apart than this factor mean the machine's speed changed (other load,
#: a cold start), and every time ratio of the run with it.
MAX_TIME_DRIFT = 1.5
#: Equal-time renders at this many spp or fewer are too coarse to compare.
MIN_EQUAL_TIME_SPP = 2
#: The reference's own noise, relative to the winner's MSE, above which ratios shrink towards 1.
MAX_REFERENCE_NOISE = 0.1


def configuration(name: str, result: MethodResult, family: str) -> str:
    """The plugin configuration of method ``name`` as a user writes it: ``sh_direct (defaults)``
    for :data:`.methods.DEFAULT_PLUGIN_METHOD`, else the plugin and the parameters the method
    sets, ``sh_direct (emitter_samples=2, bsdf_samples=0, strategy=product_only)``."""
    integrator = dict(result.integrator or {"type": name})
    plugin = integrator.pop("type", name)
    if name == DEFAULT_PLUGIN_METHOD.get(family) or not integrator:
        return f"{plugin} (defaults)"
    params = ", ".join(f"{k}={str(v).lower() if isinstance(v, bool) else v}" for k, v in integrator.items())
    return f"{plugin} ({params})"


def _ratio(x: float, y: float) -> float:
    """x / y, NaN unless both are finite and y is positive."""
    return x / y if math.isfinite(x) and math.isfinite(y) and y > 0 else math.nan


def _paired_bootstrap(statistic, a: PassResult, b: PassResult, seed: int = 0) -> tuple[float, float]:
    """Interval of statistic(a_resampled) / statistic(b_resampled), pass indices shared
    (:func:`.metrics.paired_bootstrap`; NaN if any resampled ratio is: see :class:`VerdictCell`)."""
    k = min(len(a.error.mse_per_pass), len(b.error.mse_per_pass))
    return paired_bootstrap(lambda idx: _ratio(statistic(a, idx), statistic(b, idx)), k, seed)


def _mse(entry: PassResult, idx=None) -> float:
    # A pass whose every pixel was non-finite has no MSE: NaN.
    values = np.array(entry.error.mse_per_pass, dtype=float)
    return float(values.mean() if idx is None else values[idx].mean())


def _efficiency(entry: PassResult, idx=None) -> float:
    times = np.asarray(entry.times_s)
    time_s = float(np.median(times if idx is None else times[idx]))
    denom = _mse(entry, idx) * time_s
    return 1.0 / denom if denom > 0 else (math.inf if denom == 0 else math.nan)


def at_equal_time_cost(result: MethodResult) -> PassResult:
    """``result``'s equal-sample passes, each timed at what a sample cost it at equal time
    (the equal-time pass's time over its spp, times the equal-sample spp): the efficiency
    of these passes estimates the equal-time renders' even where a pass has a fixed
    overhead (tracing, a launch, the film), which makes a pass's time not proportional
    to its samples. The equal-sample passes unchanged where no equal-time phase ran."""
    timed = result.equal_time
    if timed is None or not timed.spp or not timed.time_s:
        return result.equal_spp
    time_s = timed.time_s * result.equal_spp.spp / timed.spp
    return dataclasses.replace(result.equal_spp, times_s=[time_s] * len(result.equal_spp.times_s), time_s=time_s)


#: Each kind of contest (the order of :data:`.schema.CONTEST_TITLES`): the phase whose
#: passes it reads, its quantity.
KINDS = {"equal_spp": ("equal_spp", "MSE"), "equal_time": ("equal_time", "efficiency"),
         "time_normalised": ("equal_spp", "efficiency")}
#: Each quantity: its statistic of a method's passes, and the sign that ranks the best first.
QUANTITIES = {"MSE": (_mse, 1.0), "efficiency": (_efficiency, -1.0)}


def _cell(results: dict[str, MethodResult], kind: str, project: list[str], mitsuba: list[str],
          lead: str | None = None) -> VerdictCell:
    """The contest of ``kind`` (:data:`KINDS`): its winner, and ``lead`` (default: the best
    project method) over the best Mitsuba strategy, or with no project method the winner over
    the runner-up."""
    phase, quantity = KINDS[kind]
    entries = {n: getattr(results[n], phase) for n in project + mitsuba}
    if kind == "time_normalised":
        entries = {n: at_equal_time_cost(results[n]) for n in entries}
    statistic, sign = QUANTITIES[quantity]

    def rank(name: str) -> tuple[bool, float]:
        """Best first; a method whose statistic is NaN last."""
        value = statistic(entries[name])
        return (math.isnan(value), 0.0 if math.isnan(value) else sign * value)

    order = sorted(entries, key=rank)
    best_of = lambda names: min(names, key=rank)  # noqa: E731
    winner, runner_up = order[0], order[1] if len(order) > 1 else None
    if project and mitsuba:
        numerator, denominator = lead or best_of(project), best_of(mitsuba)
    else:
        numerator, denominator = winner, runner_up or winner
    a, b = entries[numerator], entries[denominator]
    low, high = _paired_bootstrap(statistic, a, b)
    winner_low, winner_high = (_paired_bootstrap(statistic, entries[winner], entries[runner_up])
                               if runner_up else (math.nan, math.nan))
    return VerdictCell(quantity=quantity, winner=winner, winner_is_project=winner in project,
                       numerator=numerator, denominator=denominator,
                       ratio=_ratio(statistic(a), statistic(b)), low=low, high=high,
                       runner_up=runner_up, winner_low=winner_low, winner_high=winner_high)


#: The caveats that void the times of a row, by the start of their text: every efficiency
#: ratio (both equal-time contests), or only the equal-time renders'.
TIME_BUDGET_TOO_SMALL = "time budget too small to be meaningful"
TIME_BUDGET_UNRELIABLE = "time budget unreliable"
EQUAL_TIME_TOO_COARSE = "equal-time spp too coarse to compare"
VOIDED_CONTESTS = {TIME_BUDGET_TOO_SMALL: ("equal_time", "time_normalised"),
                   TIME_BUDGET_UNRELIABLE: ("equal_time", "time_normalised"),
                   EQUAL_TIME_TOO_COARSE: ("equal_time",)}


def voiding_caveat(kind: str, caveats: list[str]) -> str | None:
    """The first of a row's ``caveats`` that voids its contest ``kind`` (:data:`KINDS`), by
    its opening words (:data:`VOIDED_CONTESTS`); None if none does."""
    return next((start for c in caveats for start, kinds in VOIDED_CONTESTS.items()
                 if kind in kinds and c.startswith(start)), None)


def winner_text(cell: VerdictCell, kind: str, caveats: list[str]) -> str:
    """How reports name the winner of a contest: "best of all" only where the interval of the
    winner over the runner-up excludes 1 and no caveat voids the contest's times."""
    void = voiding_caveat(kind, caveats)
    if void is not None:
        return f"no winner: {void} (see the caveats)"
    if not cell.winner_decided:
        return f"no clear winner ({cell.winner} first by point estimate; {cell.runner_up or '-'} within its interval)"
    best = "lowest MSE" if cell.quantity == "MSE" else "highest efficiency"
    return (f"{cell.winner} best of all ({best}: [{cell.winner_low:.3g}, {cell.winner_high:.3g}] x "
            f"{cell.runner_up}'s)")


def _caveats(scene_path: str, run: RunResult, names: list[str], baseline: str, contenders: list[str],
             shown: list[str]) -> list[str]:
    """Notes on the run's methods ``names``; the equal-time resolution only of the ``contenders``
    (a reference row at 1 spp within the baseline's time is what it costs, not a coarse budget);
    heavy tails only of the methods the verdict ``shown`` (a baseline nobody would choose, such as
    ``bsdf_only``, is no reason to doubt the verdict)."""
    results = run.methods
    notes = []
    # The budget each row was given (stored with it: the baseline itself may have
    # failed in the equal-time phase and left the run).
    first_timed = results[names[0]].equal_time
    base_time = (first_timed.time_budget_s if first_timed else None) or 0.0
    if 0.0 < base_time < MIN_PASS_TIME_S:
        notes.append(f"{TIME_BUDGET_TOO_SMALL}: a {baseline} pass takes "
                     f"{1e3 * base_time:.1f} ms (per-launch overhead and timer noise weigh on every "
                     f"time; raise --res or --spp)")
    base = results.get(baseline)
    if base and base.equal_spp.time_s and base.equal_time.time_s:
        per_sample = [p.time_s / p.spp for p in (base.equal_spp, base.equal_time)]
        drift = max(per_sample) / min(per_sample)
        if drift > MAX_TIME_DRIFT:
            notes.append(f"{TIME_BUDGET_UNRELIABLE}: a {baseline} pass took {drift:.1f}x as long at equal "
                         f"samples ({1e3 * base.equal_spp.time_s:.1f} ms) as at equal time "
                         f"({1e3 * base.equal_time.time_s:.1f} ms), so the machine's speed changed "
                         f"during the run (other load, a cold start) and every time ratio with it; "
                         f"rerun on a quiet machine, or with more --passes")
    spps = {n: results[n].equal_time.spp for n in contenders}
    if min(spps.values()) <= MIN_EQUAL_TIME_SPP:
        listing = ", ".join(f"{n} {s}" for n, s in spps.items())
        notes.append(f"{EQUAL_TIME_TOO_COARSE} ({listing}): raise --spp")
    kinds = (("equal_spp", "equal samples"), ("equal_time", "equal time"))
    heavy = [n for n in shown if any(getattr(results[n], k).tail_worse_than_baseline for k, _ in kinds)]
    if heavy:
        passes = len(results[names[0]].equal_spp.times_s)
        notes.append(f"heavy tails: {', '.join(heavy)} {'is' if len(heavy) == 1 else 'are'} worse than "
                     f"{baseline} in the brightest pixel, the {TAIL_PERCENTILE:g} % error or the firefly "
                     f"count (the scene's table says which); rare bright samples dominate such an "
                     f"error, so it may be larger than {passes} passes show")
    for n in names:
        flagged = [(title, getattr(results[n], k).bias.p_value) for k, title in kinds
                   if getattr(results[n], k).bias.flagged]
        if flagged:
            where = ", ".join(f"{title} (p = {p:.2g})" for title, p in flagged)
            notes.append(
                f"bias flag: {n} at {where}. Its average image differs from the reference by more than "
                f"noise explains: a bias, samples so heavy-tailed that the passes missed the rare bright "
                f"ones, or chance (probability {BIAS_ALPHA:g} per test for an unbiased method). Re-check "
                f"with independent seeds and more passes: python scripts/bias_check.py {scene_path} "
                f"--method {n} --passes 64")
        bad = sum(getattr(results[n], k).error.non_finite for k, _ in kinds)
        if bad:
            notes.append(f"{n} rendered {bad} non-finite pixel values (NaN or infinite); they are left "
                         f"out of its statistics")
    return notes


def verdict(report: Report | dict) -> list[VerdictRow]:
    """One row per scene x sampler x method family of ``report`` (or of the report.json dict,
    read by :func:`.schema.load_report`); reference rows (:data:`.methods.REFERENCE`) take no
    part in the contest."""
    report = load_report(report)
    rows = []
    for scene in report.scenes:
        for run in scene.runs:
            results = run.methods
            for family in dict.fromkeys(r.family for r in results.values()):
                names = [n for n, r in results.items() if r.family == family]
                contenders = [n for n in names if role_of(n) != REFERENCE]
                project = [n for n in contenders if role_of(n) == PROJECT]
                mitsuba = [n for n in contenders if role_of(n) == MITSUBA]
                if len(contenders) < 2:
                    continue
                baseline = results[names[0]].equal_time.budget_method
                ref = (scene.references or {}).get(family)
                lead = DEFAULT_PLUGIN_METHOD.get(family) if DEFAULT_PLUGIN_METHOD.get(family) in project \
                    else (project[0] if project else None)
                contests = {kind: _cell(results, kind, project, mitsuba, lead) for kind in KINDS}
                cell_spp, cell_time, cell_normalised = contests.values()
                others = [VerdictOther(method=n, configuration=configuration(n, results[n], family),
                                       **{kind: _cell(results, kind, project, mitsuba, n) for kind in KINDS})
                          for n in project if n != lead and mitsuba]
                shown = list(dict.fromkeys([c.numerator for c in (cell_spp, cell_time)]
                                           + [c.denominator for c in (cell_spp, cell_time)]
                                           + [o.method for o in others]))
                caveats = _caveats(scene.path, run, names, baseline, contenders, shown)
                winner_mse = results[cell_spp.winner].equal_spp.error.mse
                ref_noise = ref.mean_variance if ref else math.nan  # NaN: no finite reference pixel
                if winner_mse > 0 and ref_noise > MAX_REFERENCE_NOISE * winner_mse:
                    caveats.append(f"the reference's own noise is {ref_noise / winner_mse:.0%} "
                                   f"of the winner's MSE: every MSE ratio is pulled towards 1 (raise --ref-spp)")
                for kind, cell in contests.items():
                    title = CONTEST_TITLES[kind]
                    if not math.isfinite(cell.ratio):
                        caveats.append(f"at {title} the ratio of {cell.numerator} to {cell.denominator} "
                                       f"is n/a: the {cell.quantity} of one of them is zero or not finite (a black "
                                       f"environment renders every pixel exactly; non-finite pixels are "
                                       f"counted above)")
                    elif not cell.decided:
                        caveats.append(f"at {title} the {INTERVAL:.0%} interval of {cell.numerator} "
                                       f"vs {cell.denominator} contains 1: no clear winner between them")
                if _disjoint(cell_time, cell_normalised):
                    caveats.append(
                        f"the two equal-time estimates disagree: {cell_time.ratio:.3g} [{cell_time.low:.3g}, "
                        f"{cell_time.high:.3g}] from the equal-time renders, {cell_normalised.ratio:.3g} "
                        f"[{cell_normalised.low:.3g}, {cell_normalised.high:.3g}] from the equal-sample passes "
                        f"(a bias, an MSE that does not fall as 1/spp, or rare samples in one phase only)")
                rows.append(VerdictRow(scene=scene.scene, sampler=run.sampler, family=family, **contests,
                                       caveats=caveats,
                                       configuration=(configuration(lead, results[lead], family)
                                                      if lead and mitsuba else None),
                                       others=others))
    return rows


def _disjoint(a: VerdictCell, b: VerdictCell) -> bool:
    """The two cells compare the same methods and their intervals do not overlap."""
    same = (a.numerator, a.denominator) == (b.numerator, b.denominator)
    bounds = (a.low, a.high, b.low, b.high)
    return same and all(math.isfinite(x) for x in bounds) and (a.high < b.low or b.high < a.low)


def ratio_with_interval(quantity: str, a: PassResult, b: PassResult) -> tuple[float, float, float]:
    """(ratio, low, high): ``a``'s ``quantity`` ("MSE" or "efficiency", :data:`QUANTITIES`)
    over ``b``'s (entries of one phase of one run), with the verdict's 90 % paired bootstrap
    interval over passes."""
    statistic, _ = QUANTITIES[quantity]
    low, high = _paired_bootstrap(statistic, a, b)
    return _ratio(statistic(a), statistic(b)), low, high
