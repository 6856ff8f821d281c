"""The aggregate report of a sweep: one summary row per cell, heat maps, JSON/CSV/HTML.

Per cell (read from its compare ``report.json`` by :func:`~..report.schema.load_report`, which
reads older and newer formats, a missing field as unknown, so every stored cell still summarises):

- the **winner**: the method of highest equal-time efficiency (1 / (MSE x time)), reference
  rows (the exact tabulated product, :data:`~..report.methods.REFERENCE`) left out;
- the **best Mitsuba strategy**: of Mitsuba's own direct-lighting strategies present (the
  role of :mod:`..report.methods`, :func:`~..report.methods.mitsuba_strategies`: the verdict's
  set), the one of highest equal-time efficiency (for efficiency ratios) and the one of lowest
  equal-spp MSE (for MSE ratios), as ``scripts/results_table.py`` chooses them;
- per method, the equal-time efficiency ratio and the equal-spp MSE ratio against those
  bests, with an uncertainty (one standard error) when the report lists per-pass MSEs
  (``error.mse_per_pass``): delta method over the paired passes, wall-time noise not included;
- the bias status (``bias.flagged``) and the tail status (``tail_worse_than_baseline``) of the
  equal-spp and equal-time renders;
- the report's own verdict where it has one: the project's plugin at its defaults against the best of
  Mitsuba's strategies, ratio and 90 % paired-bootstrap interval.

Heat maps (scene x map, one per sampler) show the equal-time efficiency ratio of
:data:`HEATMAP_METHOD` against the best Mitsuba strategy on a log colour scale.
"""

from __future__ import annotations

import csv
import html
import io
import json
import math
import os

import numpy as np

from ..report.methods import DIRECT, METHODS, MITSUBA, REFERENCE, mitsuba_strategies, role_of
from ..report.schema import CONTEST_TITLES, PassResult, Report, load_report, serialise
from .store import CellStore

#: The method whose efficiency ratio the heat maps show.
HEATMAP_METHOD = "sh_direct"
#: Marks the JSON as a sweep aggregate (``scripts/results_table.py`` reads both kinds).
KIND = "mitsuba-shsampling sweep aggregate"


def _finite(value: float | None) -> float | None:
    """``value`` if it is a finite number, else None (unknown: missing, or not finite)."""
    return value if value is not None and math.isfinite(value) else None


def mse_per_pass(entry: PassResult | None) -> np.ndarray | None:
    """The entry's per-pass MSEs (K >= 2 finite values), or None if the report has none."""
    values = entry.error.mse_per_pass if entry is not None and entry.error is not None else None
    if values is None or len(values) < 2:
        return None
    values = np.asarray(values, dtype=np.float64)
    return values if np.all(np.isfinite(values)) and values.mean() > 0 else None


def ratio_stderr(ratio: float, a: np.ndarray | None, b: np.ndarray | None) -> float | None:
    """One standard error of ``ratio`` = mean(a) / mean(b) (or its inverse) from per-pass values.

    Delta method. Passes k of two methods of one run share a seed, so for equally many passes the
    covariance of the pairs is subtracted; otherwise the two are taken as independent.
    """
    if a is None or b is None:
        return None
    var_a, var_b = a.var(ddof=1) / len(a), b.var(ddof=1) / len(b)
    cov = float(np.cov(a, b)[0, 1]) / len(a) if len(a) == len(b) else 0.0
    rel_var = var_a / a.mean() ** 2 + var_b / b.mean() ** 2 - 2 * cov / (a.mean() * b.mean())
    return ratio * math.sqrt(max(rel_var, 0.0))


def _bias_ok(entry: PassResult | None) -> bool | None:
    """The bias test passed; None if the entry has none."""
    if entry is None or entry.bias is None or entry.bias.flagged is None:
        return None
    return not entry.bias.flagged


def _tail_ok(entry: PassResult | None) -> bool | None:
    """No tail statistic worse than the baseline's; None if the entry does not say."""
    if entry is None or entry.tail_worse_than_baseline is None:
        return None
    return not entry.tail_worse_than_baseline


def _all(values: list[bool | None]) -> bool | None:
    """False if any is False, True if all are True, else None (unknown)."""
    return False if False in values else (True if all(v is True for v in values) else None)


def _verdict(report: Report, scene: str, sampler: str) -> dict | None:
    """The report's own verdict row of the direct-lighting family (its bootstrap intervals)."""
    for row in report.verdict or []:
        if row is not None and (row.scene, row.sampler, row.family) == (scene, sampler, DIRECT):
            keep = ("winner", "numerator", "denominator", "ratio", "low", "high")
            return {kind: {k: serialise(getattr(cell, k)) for k in keep}
                    for kind in CONTEST_TITLES if (cell := getattr(row, kind)) is not None}
    return None


def summarise_report(report: Report | dict) -> dict:
    """Summary of a one-scene, one-sampler compare report (see the module docstring), typed or
    as the report.json dict (read by :func:`~..report.schema.load_report`).

    :returns: ``winner``, ``best_mitsuba_efficiency``, ``best_mitsuba_mse``, ``bias`` (``"ok"``,
        ``"flagged: ..."`` or ``"unknown"``), ``verdict`` (the report's own, or None), ``notes`` and
        per method ``methods[name]`` with ``equal_spp_mse``, ``equal_time_efficiency``,
        ``mse_ratio_vs_best_mitsuba`` (+ ``_err``), ``efficiency_ratio_vs_best_mitsuba`` (+ ``_err``),
        ``time_ratio_vs_direct``, ``bias_ok``, ``tail_ok``. Missing values are None; a report without
        any run gives ``{"error": ...}``.
    """
    report = load_report(report)
    scene = report.scenes[0] if report.scenes else None
    run = scene.runs[0] if scene is not None and scene.runs else None
    methods = {n: m for n, m in (run.methods or {}).items() if m is not None} if run is not None else {}
    if not methods:
        return {"error": "the cell's report has no rendered method"}

    spp = {n: m.equal_spp for n, m in methods.items()}
    eqt = {n: m.equal_time for n, m in methods.items()}
    eff = {n: _finite(eqt[n].efficiency) if eqt[n] is not None else None for n in methods}
    mse = {n: _finite(spp[n].error.mse) if spp[n] is not None and spp[n].error is not None else None
           for n in methods}
    mitsuba = mitsuba_strategies(methods)
    best_eff = max((n for n in mitsuba if eff[n] is not None), key=lambda n: eff[n], default=None)
    best_mse = min((n for n in mitsuba if mse[n] is not None), key=lambda n: mse[n], default=None)
    contenders = [n for n in methods if role_of(n) != REFERENCE]
    winner = max((n for n in contenders if eff[n] is not None), key=lambda n: eff[n], default=None)
    time = {n: _finite(spp[n].time_s) if spp[n] is not None else None for n in methods}
    direct_time = time.get("direct")

    summary = {}
    for name in methods:
        eff_ratio = eff[name] / eff[best_eff] if eff[name] is not None and best_eff and eff[best_eff] else None
        mse_ratio = mse[name] / mse[best_mse] if mse[name] is not None and best_mse and mse[best_mse] else None
        # Efficiency is inverse in the MSE: its ratio has the MSE ratio's relative error
        # (wall-time noise left out).
        eff_err = mse_err = None
        if eff_ratio is not None:
            eff_err = 0.0 if name == best_eff else ratio_stderr(
                eff_ratio, mse_per_pass(eqt[name]), mse_per_pass(eqt[best_eff]))
        if mse_ratio is not None:
            mse_err = 0.0 if name == best_mse else ratio_stderr(
                mse_ratio, mse_per_pass(spp[name]), mse_per_pass(spp[best_mse]))
        summary[name] = {
            "equal_spp_mse": mse[name], "equal_time_efficiency": eff[name],
            "mse_ratio_vs_best_mitsuba": mse_ratio, "mse_ratio_vs_best_mitsuba_err": mse_err,
            "efficiency_ratio_vs_best_mitsuba": eff_ratio, "efficiency_ratio_vs_best_mitsuba_err": eff_err,
            "time_ratio_vs_direct": time[name] / direct_time if time[name] is not None and direct_time else None,
            "bias_ok": _all([_bias_ok(e) for e in (spp[name], eqt[name])]),
            "tail_ok": _all([_tail_ok(e) for e in (spp[name], eqt[name])]),
        }
    flagged = [n for n, s in summary.items() if s["bias_ok"] is False]
    bias = ("flagged: " + ", ".join(flagged) if flagged
            else "ok" if all(s["bias_ok"] for s in summary.values()) else "unknown")
    return {"winner": winner, "best_mitsuba_efficiency": best_eff, "best_mitsuba_mse": best_mse,
            "bias": bias, "verdict": _verdict(report, scene.scene, run.sampler),
            "notes": [str(n) for n in scene.notes or []], "methods": summary}


def cell_row(cell, key: str, record: dict | None, report: dict | None, out: str) -> dict:
    """The aggregate entry of one grid cell (status ``ok``, ``failed`` or ``missing``)."""
    folder = os.path.relpath(CellStore(out).folder(cell, key), out)
    row = {"scene": cell.scene.name, "map": cell.map.name, "sampler": cell.sampler, "key": key,
           "folder": folder, "status": record.get("status", "missing") if record else "missing",
           "error": record.get("error") if record else None,
           "wall_time_s": record.get("wall_time_s") if record else None,
           "host": record.get("host") if record else None,
           "drjit_threads": record.get("drjit_threads") if record else None}
    if row["status"] == "ok":
        summary = summarise_report(report) if report is not None else {"error": "report.json is missing"}
        if "error" in summary:
            row.update(status="failed", error=summary["error"])
        else:
            row.update(summary, report=os.path.join(folder, "report.json"),
                       index_html=os.path.join(folder, "index.html"))
    return row


CSV_FIELDS = ["scene", "map", "sampler", "status", "method", "winner", "best_mitsuba_efficiency",
              "best_mitsuba_mse", "equal_spp_mse", "mse_ratio_vs_best_mitsuba",
              "mse_ratio_vs_best_mitsuba_err", "equal_time_efficiency",
              "efficiency_ratio_vs_best_mitsuba", "efficiency_ratio_vs_best_mitsuba_err",
              "time_ratio_vs_direct", "bias_ok", "tail_ok", "error", "folder"]


def write_csv(path: str, rows: list[dict]) -> None:
    """One line per cell and method (one line with the error for a failed or missing cell)."""
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=CSV_FIELDS, extrasaction="ignore")
        writer.writeheader()
        for row in rows:
            if row["status"] != "ok":
                writer.writerow(row)
                continue
            for name, values in row["methods"].items():
                writer.writerow({**row, **values, "method": name})


def heatmap_png(rows: list[dict], scenes: list[str], maps: list[str], sampler: str,
                method: str = HEATMAP_METHOD) -> bytes | None:
    """Scene x map heat map of ``method``'s equal-time efficiency ratio vs the best Mitsuba strategy.

    Log2 colour scale centred on 1 (blue: ``method`` more efficient, red: less); cells without
    a value (failed, missing, method absent) are grey. None if no cell has a value.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    values = np.full((len(scenes), len(maps)), np.nan)
    errors = np.full_like(values, np.nan)
    status = {}
    for row in rows:
        if row["sampler"] != sampler:
            continue
        i, j = scenes.index(row["scene"]), maps.index(row["map"])
        status[i, j] = row["status"]
        entry = row.get("methods", {}).get(method, {})
        if entry.get("efficiency_ratio_vs_best_mitsuba") is not None:
            values[i, j] = entry["efficiency_ratio_vs_best_mitsuba"]
            if entry.get("efficiency_ratio_vs_best_mitsuba_err") is not None:
                errors[i, j] = entry["efficiency_ratio_vs_best_mitsuba_err"]
    if np.all(np.isnan(values)):
        return None
    log = np.log2(values)
    span = max(1.0, float(np.nanmax(np.abs(log))))
    cmap = plt.get_cmap("RdBu").with_extremes(bad="#cccccc")
    fig, ax = plt.subplots(figsize=(1.3 * len(maps) + 3, 0.45 * len(scenes) + 1.8))
    image = ax.imshow(np.ma.masked_invalid(log), cmap=cmap, vmin=-span, vmax=span, aspect="auto")
    for (i, j), _ in np.ndenumerate(values):
        if np.isnan(values[i, j]):
            text = status.get((i, j), "missing") if status.get((i, j)) != "ok" else "n/a"
        else:
            text = f"{values[i, j]:.2f}" + (f"\n±{errors[i, j]:.2f}" if not np.isnan(errors[i, j]) else "")
        ax.text(j, i, text, ha="center", va="center", fontsize=7,
                color="white" if abs(np.nan_to_num(log[i, j])) > 0.6 * span else "black")
    ax.set_xticks(range(len(maps)), maps, rotation=30, ha="right", fontsize=8)
    ax.set_yticks(range(len(scenes)), scenes, fontsize=8)
    bar = fig.colorbar(image, ax=ax)
    ticks = np.arange(-math.floor(span), math.floor(span) + 1)
    bar.set_ticks(ticks, labels=[f"{2.0 ** t:g}x" for t in ticks])
    ax.set_title(f"{method} / best Mitsuba strategy, equal-time efficiency ({sampler})", fontsize=9)
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=110)
    plt.close(fig)
    return buffer.getvalue()


def _fmt(value, err=None, digits: int = 2) -> str:
    if value is None:
        return "–"
    text = f"{value:.{digits}f}"
    return text + (f" ± {err:.{digits}f}" if err is not None and err > 0 else "")


def _verdict_text(verdict: dict | None) -> str:
    cell = (verdict or {}).get("equal_time") or {}
    if cell.get("ratio") is None:
        return "–"
    interval = f" [{cell['low']:.2f}, {cell['high']:.2f}]" if cell.get("low") is not None else ""
    return html.escape(f"{cell['numerator']} / {cell['denominator']}: {cell['ratio']:.2f}{interval}")


def write_html(path: str, aggregate: dict) -> None:
    """``index.html``: heat maps, the summary table, failed cells with their errors."""
    e = html.escape
    rows = aggregate["cells"]
    shown = [m for m in (aggregate["grid"]["methods"] or []) if role_of(m) != MITSUBA] or [HEATMAP_METHOD]
    counts = {s: sum(r["status"] == s for r in rows) for s in ("ok", "failed", "missing")}
    parts = ["<!DOCTYPE html><html><head><meta charset='utf-8'><title>sweep</title><style>",
             "body{font-family:sans-serif;margin:1.5em;color:#222}table{border-collapse:collapse;"
             "font-size:.85em}th,td{border:1px solid #bbb;padding:3px 7px;text-align:right}"
             "th{background:#eee}td.name{text-align:left}.bad{color:#b00;font-weight:bold}"
             "pre{background:#f6f6f6;padding:.5em;font-size:.8em;white-space:pre-wrap}</style></head><body>",
             f"<h1>Sweep of {e(os.path.basename(aggregate['grid']['path']))}</h1>",
             f"<p>{len(rows)} cells: {counts['ok']} ok, {counts['failed']} failed, {counts['missing']} "
             f"missing. Code {e(aggregate['code_version'])}. Settings: "
             f"<code>{e(json.dumps(aggregate['grid']['settings']))}</code>, methods "
             f"<code>{e(', '.join(aggregate['grid']['methods'] or ['compare default']))}</code>.</p>",
             "<p>Ratios are against the best of Mitsuba's strategies in the same cell (of "
             f"{', '.join(aggregate['mitsuba_methods'])} present): equal-time efficiency ratio (&gt; 1: better) and "
             "equal-spp MSE ratio (&lt; 1: better); ± one standard error from the per-pass MSEs "
             "(paired passes, wall-time noise not included).</p>"]
    for sampler, png in aggregate["heatmaps"].items():
        parts.append(f"<h2>{e(HEATMAP_METHOD)}, {e(sampler)} sampler</h2><img src='{e(png)}'>")
    head = "".join(f"<th>{e(m)} eff. / best</th><th>{e(m)} MSE / best</th>" for m in shown)
    parts.append("<h2>Cells</h2><table><tr><th>scene</th><th>map</th><th>sampler</th><th>winner</th>"
                 f"<th>best Mitsuba (eff. / MSE)</th>{head}<th>report's verdict, equal time "
                 "(90 % interval)</th><th>bias</th><th>report</th></tr>")
    for r in rows:
        cells = [f"<td class=name>{e(r['scene'])}</td><td class=name>{e(r['map'])}</td>"
                 f"<td class=name>{e(r['sampler'])}</td>"]
        if r["status"] != "ok":
            cells.append(f"<td class='name bad' colspan={4 + 2 * len(shown)}>{e(r['status'])}: "
                         f"{e(r['error'] or '')}</td><td></td>")
        else:
            cells.append(f"<td class=name>{e(r['winner'] or '–')}</td><td class=name>"
                         f"{e(r['best_mitsuba_efficiency'] or '–')} / {e(r['best_mitsuba_mse'] or '–')}</td>")
            for m in shown:
                v = r["methods"].get(m, {})
                cells.append(f"<td>{_fmt(v.get('efficiency_ratio_vs_best_mitsuba'), v.get('efficiency_ratio_vs_best_mitsuba_err'))}</td>"
                             f"<td>{_fmt(v.get('mse_ratio_vs_best_mitsuba'), v.get('mse_ratio_vs_best_mitsuba_err'))}</td>")
            cells.append(f"<td class=name>{_verdict_text(r.get('verdict'))}</td>")
            cls = "name" if r["bias"] == "ok" else "name bad"
            cells.append(f"<td class='{cls}'>{e(r['bias'])}</td>"
                         f"<td class=name><a href='{e(r['index_html'])}'>report</a></td>")
        parts.append("<tr>" + "".join(cells) + "</tr>")
    parts.append("</table>")
    failed = [r for r in rows if r["status"] == "failed"]
    if failed:
        parts.append("<h2>Failed cells</h2>")
        for r in failed:
            parts.append(f"<p><b>{e(r['scene'])}/{e(r['map'])}/{e(r['sampler'])}</b> "
                         f"(<code>{e(r['folder'])}/cell.json</code> has the traceback)</p>"
                         f"<pre>{e(r['error'] or '')}</pre>")
    parts.append("</body></html>")
    with open(path, "w") as f:
        f.write("\n".join(parts))


def write_aggregate(out: str, grid, entries: list[tuple], code_version: str) -> dict[str, str]:
    """Write ``aggregate.json``, ``aggregate.csv``, the heat maps and ``index.html`` into ``out``.

    :param entries: per grid cell ``(cell, key, cell.json record or None, report or None)``.
    :returns: the paths written, by kind (``json``, ``csv``, ``html``).
    """
    os.makedirs(out, exist_ok=True)
    rows = [cell_row(cell, key, record, report, out) for cell, key, record, report in entries]
    scenes = [s.name for s in grid.scenes]
    maps = [m.name for m in grid.maps]
    heatmaps = {}
    for sampler in grid.samplers:
        png = heatmap_png(rows, scenes, maps, sampler)
        if png is not None:
            name = f"heatmap_{sampler}.png"
            with open(os.path.join(out, name), "wb") as f:
                f.write(png)
            heatmaps[sampler] = name
    aggregate = {"kind": KIND, "grid": grid.describe(), "code_version": code_version,
                 "heatmap_method": HEATMAP_METHOD, "mitsuba_methods": mitsuba_strategies([m.name for m in METHODS]),
                 "heatmaps": heatmaps, "cells": rows}
    paths = {"json": os.path.join(out, "aggregate.json"), "csv": os.path.join(out, "aggregate.csv"),
             "html": os.path.join(out, "index.html")}
    with open(paths["json"], "w") as f:
        json.dump(aggregate, f, indent=1)
    write_csv(paths["csv"], rows)
    write_html(paths["html"], aggregate)
    return paths
