"""The self-contained ``index.html`` of a comparison report.

Written from the report as saved (:class:`.schema.Report`). The
verdict comes first, then what each method name means, then the caveats, then one section per scene (its map,
references, metrics, renders at full resolution with zoomed crops, error maps
with their colour bars, convergence, warped sample points); settings and
machine are in a collapsed ``<details>`` at the bottom. The page fits 1400 px. Every image is embedded
as a base64 PNG (the page works when copied alone); links point to the EXR files
next to it, by paths relative to the report folder.
"""

from __future__ import annotations

import html as html_escape
import json
import math
import os

import numpy as np

from . import metrics, verdict
from .images import data_uri, false_colour, png_bytes
from .methods import DIRECT, MITSUBA, MULTI_BOUNCE, PROJECT, REFERENCE, role_of
from .schema import (CONTEST_TITLES, MaterialEntry, MethodResult, Report, RunResult, SceneResult, VerdictCell,
                     serialise)

STYLE = """
body { font-family: sans-serif; margin: 1.5em; color: #222; max-width: 1400px; }
table { border-collapse: collapse; margin: 0.5em 0 1em 0; font-size: 0.85em; }
th, td { border: 1px solid #bbb; padding: 3px 6px; text-align: right; }
.scroll { max-width: 100%; overflow-x: auto; } .scroll td { white-space: nowrap; }
th { background: #eee; } td.name { text-align: left; }
table#verdict { font-size: 1em; } table[id^=verdict] td, table[id^=verdict] th { text-align: left; }
td.win { background: #d7f5d0; font-weight: bold; } td.loss { background: #f8d3cf; font-weight: bold; }
.row { display: flex; flex-wrap: wrap; gap: 8px; }
figure { margin: 0; text-align: center; font-size: 0.75em; }
figure img { image-rendering: pixelated; min-width: 256px; }
.crop { overflow: hidden; } .crop img { max-width: none; min-width: 0; }
.bar { display: flex; align-items: center; gap: 6px; font-size: 0.8em; margin: 0.3em 0 1em 0; }
.bar img { width: 256px; height: 12px; } .envmap img { vertical-align: middle; margin-right: 0.5em; }
.note { color: #8a4b00; } .bad { color: #b00; font-weight: bold; } .na { color: #b00; }
pre { background: #f6f6f6; padding: 0.5em; font-size: 0.8em; }
dl#methods { display: grid; grid-template-columns: max-content 1fr; gap: 2px 1em; font-size: 0.9em; }
dl#methods dt { font-family: monospace; font-weight: bold; } dl#methods dd { margin: 0; }
"""


def _e(text) -> str:
    return html_escape.escape(str(text))


def _num(value, digits: int = 4) -> str:
    """A report number; a missing one (non-finite, or not measured) says so instead of 'nan'."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return '<span class="na" title="not a finite number or not measured: see the notes">n/a</span>'
    if isinstance(value, bool):
        return "yes" if value else '<span class="bad">NO</span>'
    if isinstance(value, int):
        return str(value)
    return f"{value:.{digits}g}"


class _Page:
    def __init__(self, root: str):
        self.root = root
        self.parts: list[str] = []

    def add(self, text: str) -> None:
        self.parts.append(text)

    def embed(self, rel_png: str) -> str:
        with open(os.path.join(self.root, rel_png), "rb") as f:
            return data_uri(f.read())

    def image(self, rel_png: str, caption: str, link: str | None = None) -> str:
        cap = _e(caption) + (f' (<a href="{_e(link)}">EXR</a>)' if link else "")
        return (f'<figure><img src="{self.embed(rel_png)}" alt="{_e(caption)}">'
                f'<figcaption>{cap}</figcaption></figure>')


def outcome(low: float | None, high: float | None, lower_is_better: bool) -> str:
    """What the interval [low, high] of a ratio says of its numerator: ``win`` or ``loss`` when
    it lies on one side of 1, ``tie`` when it contains 1, ``unknown`` without a finite interval.
    It is also the cell's class: ``win`` green, ``loss`` red, the others neutral."""
    if low is None or high is None or not (math.isfinite(low) and math.isfinite(high)):
        return "unknown"
    if low <= 1.0 <= high:
        return "tie"
    return "win" if (high < 1.0) == lower_is_better else "loss"


#: How a verdict cell names the numerator's outcome.
OUTCOME_WORDS = {"win": "wins", "loss": "loses", "tie": "tie", "unknown": "n/a"}


def _cell_html(cell: VerdictCell, label: str | None, kind: str, caveats: list[str]) -> str:
    """A verdict cell of contest ``kind``: the numerator (named ``label``) against the
    denominator, green when the interval says the numerator is the better of the two, red when
    the worse, neutral on a tie; the overall winner below, named only as far as the interval
    and the row's ``caveats`` allow (:func:`.verdict.winner_text`)."""
    result = outcome(cell.low, cell.high, cell.quantity == "MSE")
    return (f'<td class="name {result}"><b>{_e(label or cell.numerator)}</b> {OUTCOME_WORDS[result]}<br>'
            f'<small>{_num(cell.ratio, 3)}x the {cell.quantity} of {_e(cell.denominator)} '
            f'[{_num(cell.low, 3)}, {_num(cell.high, 3)}]; {_e(verdict.winner_text(cell, kind, caveats))}'
            f'</small></td>')


def _cells_html(row, label: str | None, caveats: list[str]) -> str:
    """A verdict row's three cells (a report from before the third shows n/a there)."""
    return "".join(_cell_html(getattr(row, kind), label, kind, caveats) if getattr(row, kind) is not None
                   else '<td class="name">n/a</td>' for kind in CONTEST_TITLES)


#: What each role makes of a method, as the definitions say it.
ROLE_WORDS = {PROJECT: "this package's plugin", MITSUBA: "Mitsuba's own strategy",
              REFERENCE: "reference row (not a contender)"}


def _method_definitions(report: Report) -> str:
    """A definitions list of every method the report ran (its name, role, plugin configuration
    as a user writes it, envmap options and label), and of "best Mitsuba", so that no name
    in the verdict or the tables is left to guess."""
    methods: dict[str, MethodResult] = {}
    for scene in report.scenes:
        for run in scene.runs:
            for name, result in run.methods.items():
                methods.setdefault(name, result)
    items = []
    for name, result in methods.items():
        config = verdict.configuration(name, result, result.family)
        if result.family == MULTI_BOUNCE:
            config += " at the comparison's max_depth"
        envmap = "".join(f", the scene's envmap rebuilt with {k}={str(v).lower() if isinstance(v, bool) else v}"
                         for k, v in (result.scene_params or {}).items())
        role = ROLE_WORDS.get(role_of(name), "a method this version does not know")
        items.append(f"<dt>{_e(name)}</dt><dd>{_e(role)}: <code>{_e(config)}</code>{_e(envmap)}; "
                     f"{_e(result.label or '')}</dd>")
    mitsuba = [n for n in methods if role_of(n) == MITSUBA]
    if mitsuba:
        items.append(f"<dt>best Mitsuba</dt><dd>in each contest (and on each material), the best of "
                     f"Mitsuba's own strategies that ran ({_e(', '.join(mitsuba))}) by point estimate of "
                     f"the contest's quantity</dd>")
    return f'<h3>Methods</h3><dl id="methods">{"".join(items)}</dl>' if items else ""


def _verdict_section(report: Report) -> str:
    rows = report.verdict
    if not rows:
        return "<p>No verdict: fewer than two methods ran in every scene.</p>"
    head = ("<tr><th>scene</th><th>sampler</th><th>lighting</th><th>equal samples (expected MSE)</th>"
            "<th>equal time (efficiency)</th><th>equal time, from the equal-sample passes (efficiency)</th>"
            "<th>caveats</th></tr>")
    body, others = [], []
    for r in rows:
        lighting = "direct" if r.family == DIRECT else "multi-bounce"
        where = f'<td>{_e(r.scene)}</td><td>{_e(r.sampler)}</td><td>{lighting}</td>'
        cells = _cells_html(r, r.configuration, r.caveats)
        body.append(f'<tr>{where}{cells}<td>{len(r.caveats)}</td></tr>')
        for other in r.others or []:
            cells = _cells_html(other, other.configuration, r.caveats)
            others.append(f"<tr>{where}{cells}</tr>")
    table = f'<table id="verdict">{head}{"".join(body)}</table>'
    legend = (f"<p>First: the project's plugin at its defaults (what switching the integrator gives) "
              f"against the best of Mitsuba's own strategies in the same run (or, with no project "
              f"method, the winner against the runner-up), green where its interval says it is "
              f"the better of the two, red where the worse, uncoloured where the interval contains 1 "
              f"(a tie): MSE ratio at equal samples (below 1: the first is better), efficiency ratio "
              f"1/(MSE x time) at equal time (above 1: the first is better), from the renders at equal "
              f"time and from the equal-sample passes (the same quantity: at one seed and spp the noise "
              f"both methods draw alike cancels there); in brackets the "
              f"{metrics.INTERVAL:.0%} paired bootstrap interval over passes.</p>"
              f'<p id="deciding-estimate"><b>Which estimate decides:</b> at equal time, the renders at '
              f"equal time. The estimate from the equal-sample passes is shown beside them; it holds "
              f"where the MSE falls as 1/spp (the independent sampler). Its passes are timed at the cost "
              f"per sample each method had at equal time, so a fixed overhead per pass counts as it does "
              f"there; a caveat says when the two disagree.</p>")
    if others:
        legend += ('<p>The project\'s other configurations, each against the same best Mitsuba strategy:</p>'
                   f'<table id="verdict-others">{head.replace("<th>caveats</th>", "")}{"".join(others)}</table>')
    legend += _method_definitions(report)
    caveats = "".join(f"<li><b>{_e(r.scene)}, {_e(r.sampler)}"
                      f"{'' if r.family == DIRECT else ', multi-bounce'}</b>: {_e(c)}</li>"
                      for r in rows for c in r.caveats)
    caveat_block = (f'<h3>Caveats</h3><ul class="note">{caveats}</ul>' if caveats
                    else "<p>No caveats: time budgets, tails, bias tests and reference noise are all fine.</p>")
    return table + legend + caveat_block


HOW_TO_READ = f"""
<h2>How to read this page</h2>
<ul>
<li><b>Equal samples</b> count shading rays (2 per pixel sample for every direct-lighting method).
<b>Expected MSE</b> is each pass's MSE averaged over many independent passes (per channel, against
the reference), so rare, very bright samples are in it; <b>pixel variance</b> is the per-pixel
variance of one pass across the passes, shown as a false-colour map. Relative MSE is the mean of
(x-ref)<sup>2</sup>/(ref<sup>2</sup>+0.01).</li>
<li><b>Equal time</b>: each method renders at the spp its measured time per sample affords within the
baseline's time per pass (median wall time of a warm pass, replayed from a <code>dr.freeze</code>
recording of the pass for every method unless <code>--no-freeze</code>, so Python's tracing is not in
it; kernel compile time is listed apart).
<b>Efficiency</b> = 1/(expected MSE x time per pass). The verdict gives it twice: from these
renders, and from the equal-sample passes. Both estimate the same efficiency (the MSE of these
unbiased estimators falls as 1/spp), but at one seed and one spp the methods draw the same pixel
positions and, where their random numbers line up, the same BSDF-sampled paths, so the noise they
share (a sun seen in a mirror, a caustic through glass) cancels in the paired ratio of the
equal-sample passes and not in the renders at equal time, whose spp differ.</li>
<li><b>Tails</b> (luminance): the brightest pixel of any pass, the {metrics.TAIL_PERCENTILE:g} %
percentile of |render - reference| over every pixel of every pass, and <b>fireflies</b>: pixels above
{metrics.FIREFLY_FACTOR:g} x their reference value + {metrics.FIREFLY_FLOOR:g} x the reference's mean.
A method is flagged when its brightest pixel exceeds {metrics.TAIL_MAX_RATIO:g} x the baseline's, its
percentile {metrics.TAIL_PERCENTILE_RATIO:g} x, or its firefly count the baseline's by
{metrics.TAIL_FIREFLY_SIGMAS:g} Poisson standard deviations.</li>
<li><b>Bias test</b>: one number per pass, its image-mean luminance; Welch's t-test of their mean
against the reference's (whose own error, from its independent chunks, is counted). False-alarm rate
{metrics.BIAS_ALPHA:g} per test (two-sided): an unbiased method is flagged about once in
{round(1 / metrics.BIAS_ALPHA)} tests. A flag means the method's average image differs from the
reference by more than noise explains; re-check it with more, independent passes
(<code>python scripts/bias_check.py SCENE --method NAME --passes 64</code>) before calling it biased.</li>
<li>MSE includes the reference's own noise (its mean variance is listed per scene).</li>
</ul>
"""


def _metrics_table(run: RunResult) -> str:
    """One row per method and comparison; a tail flagged worse than the baseline's says how many
    of its statistics are (the texts in the cell's tooltip and in report.json)."""
    cols = [("spp", lambda e: e.spp),
            ("expected MSE", lambda e: e.error.mse),
            ("pixel variance", lambda e: e.error.pixel_variance),
            ("rel. MSE", lambda e: e.error.rel_mse),
            ("time/pass (s)", lambda e: e.time_s),
            ("MSE / base", lambda e: e.mse_ratio_vs_baseline),
            ("eff. / base", lambda e: e.efficiency_ratio_vs_baseline),
            ("brightest pixel", lambda e: e.tail.max_pixel),
            (f"{metrics.TAIL_PERCENTILE:g} % |err|", lambda e: e.tail.abs_error_percentile),
            ("fireflies", lambda e: e.tail.fireflies),
            ("bias p", lambda e: e.bias.p_value)]
    head = "".join(f"<th>{c}</th>" for c, _ in cols)
    rows = [f'<tr><th>method</th><th>set-up (s)</th><th>compile (s)</th><th>comparison</th>{head}<th>tail vs baseline</th></tr>']
    for name, entry in run.methods.items():
        # Oracle rows are references (the ideal product sampler), not contenders.
        shown = f"{_e(name)} (reference row)" if entry.oracle else _e(name)
        for kind, title in (("equal_spp", "equal samples"), ("equal_time", "equal time")):
            e = getattr(entry, kind)
            cells = "".join(f"<td>{_num(get(e))}</td>" for _, get in cols[:-1])
            p = _num(e.bias.p_value)
            cells += f'<td class="bad" title="bias flag">{p} BIAS?</td>' if e.bias.flagged else f"<td>{p}</td>"
            worse = e.tail_worse_than_baseline
            tail = (f'<td class="name bad" title="{_e("; ".join(worse))}">worse: {len(worse)} of 3</td>' if worse
                    else '<td class="name">ok</td>')
            lead = (f'<td class="name" rowspan="2">{shown}</td><td rowspan="2">{_num(entry.setup_time_s, 3)}</td>'
                    f'<td rowspan="2">{_num(entry.compile_time_s, 3)}</td>' if kind == "equal_spp" else "")
            rows.append(f'<tr>{lead}<td class="name">{title}</td>{cells}{tail}</tr>')
    return '<div class="scroll"><table>' + "".join(rows) + "</table></div>"


def _colour_bar(lo: float, hi: float) -> str:
    """The log colour scale of the false-colour maps, from ``lo`` to ``hi``."""
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return ""
    ramp = false_colour(np.geomspace(max(lo, 1e-30), max(hi, 10 * max(lo, 1e-30)), 256)[None].repeat(12, 0), lo, hi)
    return (f'<div class="bar">{_num(lo, 3)}<img src="{data_uri(png_bytes(ramp))}" alt="colour scale">'
            f'{_num(hi, 3)} (log scale, inferno)</div>')


def _render_figures(page: _Page, run: RunResult, kind: str) -> str:
    """The first pass of every method at full resolution (integer zoom to at least 256 px wide),
    then the same zoomed crop of each, so that noise can be judged by eye."""
    width = run.film_size[0] if run.film_size else 128
    zoom = max(1, 256 // width)
    full, crops = [], []
    x, y, size = run.crop or (0, 0, 0)
    crop_zoom = max(1, 128 // max(size, 1))
    for name, entry in run.methods.items():
        e = getattr(entry, kind)
        src = page.embed(e.files["first_pass_png"])
        caption = f"{name}, {e.spp} spp, pass MSE {_num(e.error.mse_per_pass[0], 3)}"
        full.append(f'<figure><img src="{src}" alt="{_e(caption)}" style="width:{width * zoom}px">'
                    f'<figcaption>{_e(caption)} (<a href="{_e(e.files["first_pass"])}">EXR</a>)'
                    f'</figcaption></figure>')
        if size:
            crops.append(f'<figure><div class="crop" style="width:{size * crop_zoom}px;height:{size * crop_zoom}px">'
                         f'<img src="{src}" alt="{_e(name)}, crop" style="width:{width * crop_zoom}px;'
                         f'margin-left:-{x * crop_zoom}px;margin-top:-{y * crop_zoom}px"></div>'
                         f'<figcaption>{_e(name)}</figcaption></figure>')
    where = (f"<p>Zoomed crop, pixels [{x}, {x + size}) x [{y}, {y + size}) (where the methods' "
             f"variance as displayed is largest, highlights the display clips left out), "
             f"{crop_zoom}x:</p>" if size else "")
    return f"<div class='row'>{''.join(full)}</div>{where}<div class='row'>{''.join(crops)}</div>"


def _materials_table(rows: list[MaterialEntry]) -> str:
    """Per-material squared-error ratios against the best Mitsuba strategy there, and error shares."""
    if not rows:
        return ""
    project = list(rows[0].error_ratio)
    chose = [n for n in project if any(n in row.strategy for row in rows)]
    head = "".join(f"<th>{_e(n)}: error ratio to the best Mitsuba there, equal samples</th>"
                   f"<th>{_e(n)}: error ratio, equal time</th><th>{_e(n)}: share of its error</th>"
                   + (f"<th>{_e(n)}: strategy (predicted variance gain)</th>" if n in chose else "")
                   for n in project)
    out = [f"<table><tr><th>material</th><th>plugin</th><th>pixels</th><th>best Mitsuba strategy there "
           f"(equal samples / equal time)</th><th>its share of its error</th>{head}</tr>"]
    for row in rows:
        best = row.best_mitsuba
        cells = []
        for n in project:
            for kind in ("equal_spp", "equal_time"):
                ratio = row.error_ratio[n].get(kind)
                low, high = ((row.error_ratio_interval or {}).get(n) or {}).get(kind) or (None, None)
                result = outcome(low, high, lower_is_better=True)
                interval = (f"{metrics.INTERVAL:.0%} interval [{low:.3g}, {high:.3g}]" if result != "unknown"
                            else "no interval")
                cells.append(f'<td class="{result}" title="{OUTCOME_WORDS[result]}: {interval}">{_num(ratio, 3)}</td>')
            cells.append(f"<td>{_num(row.error_share.get(n), 2)}</td>")
            if n in chose:
                picked = row.strategy.get(n)
                cells.append(f'<td class="name">{_e(picked["strategy"])} (x{_num(picked["predicted_gain"], 2)})</td>'
                             if picked else "<td>-</td>")
        out.append(f'<tr><td class="name">{_e(row.name)}</td><td class="name">{_e(row.plugin)}</td>'
                   f'<td>{100 * row.pixel_share:.1f} %</td>'
                   f'<td class="name">{_e(best.get("equal_spp"))} / {_e(best.get("equal_time"))}</td>'
                   f'<td>{_num(row.error_share.get(best.get("equal_spp")), 2)}</td>{"".join(cells)}</tr>')
    return "".join(out) + "</table>"


def _scene_section(page: _Page, scene: SceneResult) -> None:
    page.add(f"<h2>Scene {_e(scene.scene)}</h2><p>{_e(scene.path)}</p>")
    env = scene.envmap
    if env:
        page.add(f'<p class="envmap"><img src="{page.embed(env.png)}" alt="environment map {_e(env.name)}" '
                 f'style="width:256px">Environment map: <b>{_e(env.name)}</b></p>')
    else:
        page.add('<p class="envmap">No environment map.</p>')
    for note in scene.notes:
        page.add(f'<p class="note">{_e(note)}</p>')
    refs = "".join(page.image(r.png, f"reference ({r.integrator}, {r.spp} spp in {r.chunks} "
                              f"chunks, mean variance {_num(r.mean_variance, 3)})", r.file)
                   for r in scene.references.values())
    page.add(f'<div class="row">{refs}</div>')
    for run in scene.runs:
        rendered = (f" (rendered by Mitsuba's {_e(run.sampler_plugin)}, film "
                    f"{run.film_size[0]} x {run.film_size[1]})" if run.sampler_plugin else "")
        page.add(f"<h3>{_e(scene.scene)}: {_e(run.sampler)} sampler{rendered}</h3>")
        page.add(_metrics_table(run))
        for family, rows in (run.materials or {}).items():
            page.add(f"<h4>Per material ({_e(family)} family): where each method wins and loses</h4>"
                     "<p>Each pixel counts for the material its centre sees. The error ratio is the "
                     "method's squared error on that material's pixels over the best Mitsuba "
                     "strategy's there (named), coloured by its "
                     f"{metrics.INTERVAL:.0%} paired bootstrap interval over passes (in the cell's "
                     "tooltip): green where the "
                     "interval lies below 1 (it beats every Mitsuba strategy there), red where above, "
                     "uncoloured where it contains 1. The error share is the part of the method's "
                     "squared error, summed over the image, that falls on the material.</p>")
            page.add(f'<div class="scroll">{_materials_table(rows)}</div>')
        for kind, title in (("equal_spp", "equal samples"), ("equal_time", "equal time")):
            page.add(f"<h4>Renders at {title} (first pass)</h4>{_render_figures(page, run, kind)}")
        for kind, title in (("variance", "Per-pixel variance across passes (equal samples, tails included)"),
                            ("rel_error", "Per-pixel relative squared error (equal samples)")):
            lo, hi = run.maps.scale[kind]
            figs = [page.image(maps[kind], name) for name, maps in run.maps.files.items()]
            page.add(f"<h4>{title}; shared colour scale</h4>{_colour_bar(lo, hi)}"
                     f"<div class='row'>{''.join(figs)}</div>")
        if run.convergence_plot:
            page.add("<h4>Convergence (one render per spp)</h4>")
            page.add(f'<img src="{page.embed(run.convergence_plot)}" alt="convergence">')
        else:
            page.add("<p>No convergence sweep with this sampler (it runs with the first sampler "
                     "only: the others recompile their kernels for every sample count).</p>")
    if scene.sampler_figures:
        page.add("<h3>Warped sample points (an illustration, not this scene's BSDF)</h3><p>Hierarchical "
                 "warping of an 8-band Phong lobe (s = 20) alone and times this scene's environment, on the "
                 "equal-area (phi, z) grid (square-root colour scale). From a Hammersley set the warped points "
                 "stay stratified: the warp preserves the input's low discrepancy.</p>")
        for fig in scene.sampler_figures:
            page.add(f'<img src="{page.embed(fig.png)}" alt="{_e(fig.caption)}" style="max-width:100%">')


def write_html(path: str, report: Report) -> None:
    """Write the report page for ``report`` to ``path`` (the folder of its images)."""
    page = _Page(os.path.dirname(os.path.abspath(path)))
    page.add(f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>mitsuba-shsampling comparison"
             f"</title><style>{STYLE}</style></head><body>")
    page.add("<h1>Environment-map sampling comparison</h1>")
    page.add("<h2>Verdict</h2>")
    page.add(_verdict_section(report))
    page.add(HOW_TO_READ)
    for scene in report.scenes:
        _scene_section(page, scene)
    page.add('<p>Data: <a href="report.json">report.json</a>, <a href="metrics.csv">metrics.csv</a></p>')
    page.add("<details><summary>Settings, machine and versions</summary><pre>" + _e(json.dumps({
        "machine": report.machine, "variant": report.variant, "versions": report.versions,
        "settings": serialise(report.settings), "total_time_s": round(report.total_time_s or 0.0, 1)},
        indent=1)) + "</pre></details>")
    page.add("</body></html>")
    with open(path, "w") as f:
        f.write("\n".join(page.parts))
