"""Summarise `compare` reports as the README's results table (Markdown).

    python scripts/results_table.py report_a/report.json report_b/report.json ...
    python scripts/results_table.py sweep_out/aggregate.json     # every finished cell of a sweep

For every scene x sampler, the SH method is set against the *best* of
Mitsuba's own direct-lighting strategies in the same run (the set of
``mitsuba_shsampling.report.methods.mitsuba_strategies``, as in the verdict; lowest expected MSE at equal samples,
highest efficiency = 1/(MSE x time) from the equal-sample passes, and from the
renders at equal time), and against ``direct`` 1+1. "bias ok" is
the report's bias test (p >= 1e-3), "tail ok" its tail comparison with ``direct``.
"""

from __future__ import annotations

import argparse
import json
import os

from mitsuba_shsampling.report.methods import mitsuba_strategies
from mitsuba_shsampling.sweep.aggregate import KIND as SWEEP_AGGREGATE

SH_METHOD = "sh_direct"


def reports(path: str):
    """The compare reports a file holds: a report.json itself, or each finished cell of a sweep."""
    with open(path) as f:
        data = json.load(f)
    if data.get("kind") != SWEEP_AGGREGATE:
        yield data
        return
    for cell in data["cells"]:
        if cell.get("status") == "ok" and cell.get("report"):
            with open(os.path.join(os.path.dirname(os.path.abspath(path)), cell["report"])) as f:
                yield json.load(f)


def envmap_name(report: dict) -> str:
    envmap = report["settings"].get("envmap")
    return os.path.splitext(os.path.basename(envmap))[0] if envmap else "built-in sunsky"


def rows(report: dict):
    for scene in report["scenes"]:
        for run in scene["runs"]:
            methods = run["methods"]
            if SH_METHOD not in methods:
                continue
            ours = methods[SH_METHOD]["equal_spp"]
            mitsuba = mitsuba_strategies(methods)
            theirs = {n: methods[n]["equal_spp"] for n in mitsuba}
            best_mse = min(theirs, key=lambda n: theirs[n]["error"]["mse"])
            best_eff = max(theirs, key=lambda n: theirs[n]["efficiency"])
            direct = theirs.get("direct")
            timed = {n: methods[n]["equal_time"]["efficiency"] for n in (*mitsuba, SH_METHOD)
                     if methods[n].get("equal_time")}
            best_timed = max((n for n in timed if n != SH_METHOD), key=timed.get, default=None)
            yield {
                "map": envmap_name(report), "scene": scene["scene"], "sampler": run["sampler"],
                "mse_vs_direct": ours["error"]["mse"] / direct["error"]["mse"] if direct else None,
                "mse_vs_best": ours["error"]["mse"] / theirs[best_mse]["error"]["mse"], "best_mse": best_mse,
                "eff_vs_direct": ours["efficiency"] / direct["efficiency"] if direct else None,
                "eff_vs_best": ours["efficiency"] / theirs[best_eff]["efficiency"], "best_eff": best_eff,
                "time_vs_direct": ours["time_s"] / direct["time_s"] if direct else None,
                "timed_eff_vs_best": (timed[SH_METHOD] / timed[best_timed]
                                      if best_timed and SH_METHOD in timed else None),
                "bias_ok": not ours["bias"]["flagged"],
                "tail_ok": not ours["tail_worse_than_baseline"],
            }


def fmt(x, digits=2):
    return "n/a" if x is None else f"{x:.{digits}f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("reports", nargs="+")
    parser.add_argument("--json", help="also write the rows as JSON")
    args = parser.parse_args()
    table = [r for path in args.reports for report in reports(path) for r in rows(report)]
    print("| map | scene | MSE / direct | MSE / best Mitsuba (which) | efficiency / direct "
          "| efficiency / best Mitsuba (which) | equal-time efficiency / best Mitsuba | time / direct "
          "| bias ok | tail ok |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in table:
        print(f"| {r['map']} | {r['scene']} | {fmt(r['mse_vs_direct'])} | {fmt(r['mse_vs_best'])} "
              f"({r['best_mse']}) | {fmt(r['eff_vs_direct'])} | {fmt(r['eff_vs_best'])} ({r['best_eff']}) "
              f"| {fmt(r['timed_eff_vs_best'])} | {fmt(r['time_vs_direct'])} | {'yes' if r['bias_ok'] else 'NO'} "
              f"| {'yes' if r['tail_ok'] else 'NO'} |")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(table, f, indent=1)


if __name__ == "__main__":
    main()
