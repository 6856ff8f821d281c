"""Summarise `compare` reports as the README's results table (Markdown).

    python scripts/results_table.py report_a/report.json report_b/report.json ...
    python scripts/results_table.py sweep_out/aggregate.json     # every finished cell of a sweep

    python scripts/results_table.py sweep_out/aggregate.json --family path   # sh_path against path
    python scripts/results_table.py sweep_out/aggregate.json --choices       # the chooser's predictions

    # Results as data: keep a sweep's rows (with the command, commit and machine) in results/,
    # and regenerate the README's tables from them (a test runs --check).
    python scripts/results_table.py sweep_out/aggregate.json --save results/realistic_direct.json \
        --command "python -m mitsuba_shsampling sweep sweeps/realistic_direct.toml --out sweep_out"
    python scripts/results_table.py --readme README.md --check     # or --write

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
import datetime
import json
import os
import platform
import re
import statistics
import subprocess
import sys

from mitsuba_shsampling.report.methods import DEFAULT_PLUGIN_METHOD, DIRECT, MULTI_BOUNCE, mitsuba_strategies
from mitsuba_shsampling.report.schema import Report, load_report
from mitsuba_shsampling.report.verdict import ratio_with_interval
from mitsuba_shsampling.sweep.aggregate import KIND as SWEEP_AGGREGATE

#: Mitsuba's plain strategy of each family, the "/ direct" (or "/ path") columns.
BASELINE = {DIRECT: "direct", MULTI_BOUNCE: "path"}

#: Mitsuba's best single configuration of each family for a one-shot render (the issue's
#: "direct + mis_compensation"), the "one 256-spp render" column.
ONE_SHOT_BASELINE = {DIRECT: "direct_misc", MULTI_BOUNCE: "path"}

ONE_SHOT_SPP = 256
"""Samples per pixel of the one-shot render the README prices, set-up and compilation included."""

RESULTS_KIND = "mitsuba_shsampling.results"
"""The ``kind`` of a committed results file (``--save``): rows, command, commit, machine."""

README_TABLE = re.compile(r"(<!-- table: (?P<path>[^ ]+) -->\n)(?P<body>.*?)(<!-- end table -->)", re.S)
"""A README table regenerated from a results file: the marker names the file (README-relative)."""


def reports(path: str):
    """The compare reports a file holds: a report.json itself, or each finished cell of a sweep."""
    with open(path) as f:
        data = json.load(f)
    if data.get("kind") == RESULTS_KIND:
        raise ValueError(f"{path} holds table rows, not reports: pass it to --readme or read its 'rows'")
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
            one_shot_base = methods.get(ONE_SHOT_BASELINE[family])
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
                "setup_s": methods[sh_method].setup_time_s,
                "one_shot_vs_baseline": one_shot_ratio(methods[sh_method], one_shot_base),
                "one_shot_baseline": ONE_SHOT_BASELINE[family],
            }


def one_shot_seconds(entry) -> float | None:
    """Wall time of one :data:`ONE_SHOT_SPP` render by ``entry`` in a fresh process: its set-up,
    its first pass's compilation, and the warm passes' time per sample x the samples."""
    if entry is None or entry.equal_spp.time_s is None:
        return None
    per_sample = entry.equal_spp.time_s / entry.equal_spp.spp
    return (entry.setup_time_s or 0.0) + (entry.compile_time_s or 0.0) + ONE_SHOT_SPP * per_sample


def one_shot_ratio(ours, theirs) -> float | None:
    """Efficiency of one :data:`ONE_SHOT_SPP` render, ours over theirs, set-up and compilation
    included. Derived, not rendered: the expected MSE at that spp is the equal-sample passes'
    scaled as 1/spp (both estimators are unbiased), so the MSE ratio is the equal-sample one
    and the times are :func:`one_shot_seconds`."""
    if theirs is None:
        return None
    t_ours, t_theirs = one_shot_seconds(ours), one_shot_seconds(theirs)
    mse_ours, mse_theirs = ours.equal_spp.error.mse, theirs.equal_spp.error.mse
    if not (t_ours and t_theirs and mse_ours and mse_theirs):
        return None
    return (mse_theirs * t_theirs) / (mse_ours * t_ours)


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


def git_commit() -> str:
    try:
        out = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                             cwd=os.path.dirname(os.path.abspath(__file__)), check=True)
        return out.stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def save_results(path: str, table: list[dict], family: str, command: str, sources: list[str]) -> None:
    """Write ``table`` as a committed results file, with what made it."""
    record = {"kind": RESULTS_KIND, "family": family, "command": command, "commit": git_commit(),
              "date": datetime.date.today().isoformat(), "sources": sources,
              "machine": {"cpu": platform.processor() or platform.machine(), "cores": os.cpu_count(),
                          "system": platform.platform(), "python": sys.version.split()[0]},
              "rows": table}
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with open(path, "w") as f:
        json.dump(record, f, indent=1)
        f.write("\n")


def readme_table(results: dict) -> str:
    """The README's compact table of a results file: the equal-time renders decide."""
    family = results["family"]
    base = ONE_SHOT_BASELINE[family]
    lines = [f"| scene | map | equal time: efficiency / best Mitsuba [90 %] (which) "
             f"| paired equal-sample estimate [90 %] | one {ONE_SHOT_SPP}-spp render / `{base}`, set-up included "
             f"| set-up (s) | bias, tails ok |",
             "|---|---|---|---|---|---|---|"]
    for r in results["rows"]:
        ok = "yes" if r["bias_ok"] and r["tail_ok"] else ("bias NO" if not r["bias_ok"] else "tails NO")
        lines.append(f"| {r['scene']} | {r['map']} | **{fmt(r['timed_eff_vs_best'])}** "
                     f"[{fmt(r['timed_low'])}, {fmt(r['timed_high'])}] (`{r['best_timed']}`) "
                     f"| {fmt(r['eff_vs_best'])} [{fmt(r['eff_low'])}, {fmt(r['eff_high'])}] "
                     f"| {fmt(r.get('one_shot_vs_baseline'))} | {fmt(r.get('setup_s'), 1)} | {ok} |")
    timed = sorted(r["timed_eff_vs_best"] for r in results["rows"] if r["timed_eff_vs_best"] is not None)
    if timed:
        lines.append("")
        lines.append(f"Equal time: {fmt(timed[0])}-{fmt(timed[-1])}x, median {fmt(statistics.median(timed))} "
                     f"({len(timed)} cells). `{results['command']}` at `{results['commit']}`, "
                     f"{results['date']}, {results['machine']['cores']} cores.")
    return "\n".join(lines) + "\n"


def sync_readme(readme: str, write: bool) -> list[str]:
    """Regenerate every marked table of ``readme`` from its results file; the paths of the
    tables that differ (written back where ``write``)."""
    with open(readme) as f:
        text = f.read()
    stale = []

    def regenerate(match):
        path = os.path.join(os.path.dirname(os.path.abspath(readme)), match["path"])
        with open(path) as f:
            results = json.load(f)
        table = readme_table(results)
        if table != match["body"]:
            stale.append(match["path"])
        return match.group(1) + table + match.group(4)

    updated = README_TABLE.sub(regenerate, text)
    if write and updated != text:
        with open(readme, "w") as f:
            f.write(updated)
    return stale


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("reports", nargs="*")
    parser.add_argument("--family", choices=(DIRECT, MULTI_BOUNCE), default=DIRECT,
                        help="direct: sh_direct against Mitsuba's direct strategies; path: sh_path against path")
    parser.add_argument("--json", help="also write the rows as JSON")
    parser.add_argument("--choices", action="store_true",
                        help="the chooser's predictions against the measured ratios, per cell and material")
    parser.add_argument("--save", help="write the rows as a committed results file (with --command)")
    parser.add_argument("--command", default="", help="the command that made the reports (for --save)")
    parser.add_argument("--readme", help="a Markdown file whose marked tables come from results files")
    action = parser.add_mutually_exclusive_group()
    action.add_argument("--check", action="store_true", help="with --readme: exit 1 where a table is stale")
    action.add_argument("--write", action="store_true", help="with --readme: rewrite the stale tables")
    args = parser.parse_args()
    if args.readme:
        stale = sync_readme(args.readme, write=args.write)
        for path in stale:
            print(f"{args.readme}: the table of {path} {'rewritten' if args.write else 'is stale'}")
        return 1 if stale and args.check else 0
    if not args.reports:
        parser.error("name report.json or aggregate.json files, or --readme")
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
    if args.save:
        save_results(args.save, table, args.family, args.command, args.reports)
    return 0


if __name__ == "__main__":
    sys.exit(main())
