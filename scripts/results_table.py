"""Summarise `compare` reports as the README's results table (Markdown).

    python scripts/results_table.py report_a/report.json report_b/report.json ...
    python scripts/results_table.py sweep_out/aggregate.json     # every finished cell of a sweep

    python scripts/results_table.py sweep_out/aggregate.json --family path   # sh_path against path
    python scripts/results_table.py sweep_out/aggregate.json --choices       # the chooser's predictions

For every scene x sampler, the project's plugin at its defaults (``sh_direct``, or ``sh_path``
with ``--family path``) is set against the *best* of Mitsuba's own strategies of that family in
the same run (the set of ``mitsuba_shsampling.report.methods.mitsuba_strategies``, as in the
verdict; lowest expected MSE at equal samples, highest efficiency = 1/(MSE x time) from the
equal-sample passes, and from the renders at equal time, both with the verdict's 90 % paired
bootstrap interval: the verdict's module says why the two equal-time estimates differ), and
against ``direct`` 1+1 (or ``path``). "bias ok" is the report's bias
test (p >= 1e-3), "tail ok" its tail comparison with ``direct`` (or ``path``).

``--choices`` prints, per cell, what ``strategy`` ``auto`` chose and predicted against what was
measured (a diffuse material drawn from the cosine tables is marked "(tables)"): the predicted equal-time gain over the lean kernel (every material on its best
environment strategy, i.e. one of Mitsuba's own) against the measured equal-time efficiency
over the best Mitsuba strategy; and per material the chosen strategy, its predicted variance
gain and the measured equal-sample error ratio there.
"""

from __future__ import annotations

import argparse
import json
import os

from mitsuba_shsampling.report.methods import DEFAULT_PLUGIN_METHOD, DIRECT, MULTI_BOUNCE, mitsuba_strategies
from mitsuba_shsampling.report.schema import Report, load_report
from mitsuba_shsampling.report.verdict import ratio_with_interval
from mitsuba_shsampling.sweep.aggregate import KIND as SWEEP_AGGREGATE

#: Mitsuba's plain strategy of each family, the "/ direct" (or "/ path") columns.
BASELINE = {DIRECT: "direct", MULTI_BOUNCE: "path"}


def reports(path: str):
    """The compare reports a file holds: a report.json itself, or each finished cell of a sweep."""
    with open(path) as f:
        data = json.load(f)
    if data.get("kind") != SWEEP_AGGREGATE:
        yield load_report(data)
        return
    for cell in data["cells"]:
        if cell.get("status") == "ok" and cell.get("report"):
            yield load_report(os.path.join(os.path.dirname(os.path.abspath(path)), cell["report"]))


def envmap_name(report: Report) -> str:
    envmap = report.settings.envmap if report.settings else None
    return os.path.splitext(os.path.basename(envmap))[0] if envmap else "built-in sunsky"


def rows(report: Report | dict, family: str):
    """One row per scene x sampler that ran the family's SH method (``report`` typed, or the
    report.json dict)."""
    report = load_report(report)
    sh_method, baseline = DEFAULT_PLUGIN_METHOD[family], BASELINE[family]
    for scene in report.scenes:
        for run in scene.runs:
            methods = run.methods
            if sh_method not in methods:
                continue
            ours = methods[sh_method].equal_spp
            mitsuba = mitsuba_strategies(methods, family)
            theirs = {n: methods[n].equal_spp for n in mitsuba}
            best_mse = min(theirs, key=lambda n: theirs[n].error.mse)
            best_eff = max(theirs, key=lambda n: theirs[n].efficiency)
            base = theirs.get(baseline)
            timed = {n: methods[n].equal_time for n in (*mitsuba, sh_method) if methods[n].equal_time}
            best_timed = max((n for n in timed if n != sh_method), key=lambda n: timed[n].efficiency,
                             default=None)
            timed_ratio = (ratio_with_interval("efficiency", timed[sh_method], timed[best_timed])
                           if best_timed and sh_method in timed else (None, None, None))
            _, eff_low, eff_high = ratio_with_interval("efficiency", ours, theirs[best_eff])
            yield {
                "map": envmap_name(report), "scene": scene.scene, "sampler": run.sampler,
                "family": family, "method": sh_method,
                "mse_vs_direct": ours.error.mse / base.error.mse if base else None,
                "mse_vs_best": ours.error.mse / theirs[best_mse].error.mse, "best_mse": best_mse,
                "eff_vs_direct": ours.efficiency / base.efficiency if base else None,
                "eff_vs_best": ours.efficiency / theirs[best_eff].efficiency, "best_eff": best_eff,
                "eff_low": eff_low, "eff_high": eff_high,
                "time_vs_direct": ours.time_s / base.time_s if base else None,
                "timed_eff_vs_best": timed_ratio[0], "timed_low": timed_ratio[1], "timed_high": timed_ratio[2],
                "best_timed": best_timed,
                "brightest_vs_direct": (ours.tail.max_pixel / base.tail.max_pixel
                                        if base and base.tail.max_pixel else None),
                "bias_ok": not ours.bias.flagged,
                "tail_ok": not ours.tail_worse_than_baseline,
            }


def choice_rows(report: Report | dict, family: str):
    """Per scene x sampler: the chooser's prediction against the measured ratios."""
    report = load_report(report)
    sh_method = DEFAULT_PLUGIN_METHOD[family]
    for scene in report.scenes:
        for run in scene.runs:
            entry = run.methods.get(sh_method)
            if entry is None or not entry.strategy_choice:
                continue
            measured = next(r for r in rows(report, family)
                            if r["scene"] == scene.scene and r["sampler"] == run.sampler)
            per_material = []
            for row in run.materials.get(family, []):
                picked = row.strategy.get(sh_method)
                if picked:
                    per_material.append({"material": row.name, "pixels": row.pixel_share, **picked,
                                         "measured_error_ratio": row.error_ratio[sh_method].get("equal_spp")})
            yield {"map": envmap_name(report), "scene": scene.scene,
                   "lean": entry.strategy_choice["lean"],
                   "predicted_gain": entry.strategy_choice["predicted_gain"],
                   "measured_timed_eff_vs_best": measured["timed_eff_vs_best"],
                   "measured_low": measured["timed_low"], "measured_high": measured["timed_high"],
                   "chooser_s": entry.strategy_choice["seconds"], "materials": per_material,
                   "cosine_tables": entry.strategy_choice.get("cosine_tables", [])}


def print_choices(table: list[dict]) -> None:
    print("| map | scene | kernel | predicted gain over the lean kernel | measured equal-time efficiency / best "
          "Mitsuba [90 %] | products chosen (predicted variance gain / measured error ratio at equal samples) |")
    print("|---|---|---|---|---|---|")
    for r in table:
        # "(tables)": a diffuse material whose product is drawn from the cosine tables.
        chosen = ", ".join(f"{m['material']} {m['strategy']}"
                           f"{' (tables)' if m['material'] in r.get('cosine_tables', []) else ''} "
                           f"({fmt(m['predicted_gain'])} / {fmt(m['measured_error_ratio'])})" for m in r["materials"]
                           if m["strategy"].startswith("product")) or "none"
        print(f"| {r['map']} | {r['scene']} | {'lean' if r['lean'] else 'with product'} | "
              f"{fmt(r['predicted_gain'])} | {fmt(r['measured_timed_eff_vs_best'])} [{fmt(r['measured_low'])}, "
              f"{fmt(r['measured_high'])}] | {chosen} |")


def fmt(x, digits=2):
    return "n/a" if x is None else f"{x:.{digits}f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("reports", nargs="+")
    parser.add_argument("--family", choices=(DIRECT, MULTI_BOUNCE), default=DIRECT,
                        help="direct: sh_direct against Mitsuba's direct strategies; path: sh_path against path")
    parser.add_argument("--json", help="also write the rows as JSON")
    parser.add_argument("--choices", action="store_true",
                        help="the chooser's predictions against the measured ratios, per cell and material")
    args = parser.parse_args()
    if args.choices:
        table = [r for path in args.reports for report in reports(path) for r in choice_rows(report, args.family)]
        print_choices(table)
        if args.json:
            with open(args.json, "w") as f:
                json.dump(table, f, indent=1)
        return
    table = [r for path in args.reports for report in reports(path) for r in rows(report, args.family)]
    base = BASELINE[args.family]
    print(f"| map | scene | MSE / {base} | MSE / best Mitsuba (which) | efficiency / {base} "
          f"| efficiency / best Mitsuba [90 % interval] (which) "
          f"| equal-time efficiency / best Mitsuba [90 % interval] (which) "
          f"| time / {base} | brightest pixel / {base} | bias ok | tail ok |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in table:
        print(f"| {r['map']} | {r['scene']} | {fmt(r['mse_vs_direct'])} | {fmt(r['mse_vs_best'])} "
              f"({r['best_mse']}) | {fmt(r['eff_vs_direct'])} | {fmt(r['eff_vs_best'])} "
              f"[{fmt(r['eff_low'])}, {fmt(r['eff_high'])}] ({r['best_eff']}) "
              f"| {fmt(r['timed_eff_vs_best'])} [{fmt(r['timed_low'])}, {fmt(r['timed_high'])}] ({r['best_timed']}) "
              f"| {fmt(r['time_vs_direct'])} | {fmt(r['brightest_vs_direct'])} | {'yes' if r['bias_ok'] else 'NO'} "
              f"| {'yes' if r['tail_ok'] else 'NO'} |")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(table, f, indent=1)


if __name__ == "__main__":
    main()
