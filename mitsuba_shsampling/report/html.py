"""The self-contained ``index.html`` of a comparison report.

Every image is embedded as a base64 PNG (the page works when copied alone);
links point to the EXR files next to it, by paths relative to the report folder.
"""

from __future__ import annotations

import html as html_escape
import json
import os

from .images import data_uri

STYLE = """
body { font-family: sans-serif; margin: 1.5em; color: #222; }
table { border-collapse: collapse; margin: 0.5em 0 1em 0; font-size: 0.85em; }
th, td { border: 1px solid #bbb; padding: 3px 7px; text-align: right; }
th { background: #eee; } td.name { text-align: left; }
.row { display: flex; flex-wrap: wrap; gap: 8px; }
figure { margin: 0; text-align: center; font-size: 0.75em; }
figure img { image-rendering: pixelated; width: 192px; }
.note { color: #8a4b00; } .bad { color: #b00; font-weight: bold; }
pre { background: #f6f6f6; padding: 0.5em; font-size: 0.8em; }
"""


def _e(text) -> str:
    return html_escape.escape(str(text))


def _num(value, digits: int = 4) -> str:
    if value is None:
        return "-"
    if isinstance(value, bool):
        return "yes" if value else '<span class="bad">NO</span>'
    if isinstance(value, (int,)):
        return str(value)
    return f"{value:.{digits}g}"


class _Page:
    def __init__(self, root: str):
        self.root = root
        self.parts: list[str] = []

    def add(self, text: str) -> None:
        self.parts.append(text)

    def image(self, rel_png: str, caption: str, link: str | None = None) -> str:
        with open(os.path.join(self.root, rel_png), "rb") as f:
            uri = data_uri(f.read())
        cap = _e(caption) + (f' (<a href="{_e(link)}">EXR</a>)' if link else "")
        return f'<figure><img src="{uri}" alt="{_e(caption)}"><figcaption>{cap}</figcaption></figure>'


def _metrics_table(run: dict) -> str:
    cols = [("spp", "spp"), ("mse", "MSE"), ("rel_mse", "rel. MSE"), ("time_s", "time/pass (s)"),
            ("efficiency", "efficiency"), ("mse_ratio_vs_baseline", "MSE / base"),
            ("efficiency_ratio_vs_baseline", "eff. / base"), ("bias_ok", "unbiased"),
            ("bias_fail_fraction", "pixels |z|>4"), ("bias_expected_fail_fraction", "expected"),
            ("bias_mean_z", "mean z")]
    head = "".join(f"<th>{c}</th>" for _, c in cols)
    rows = [f'<tr><th>method</th><th>rays/sample</th><th>compile (s)</th><th>comparison</th>{head}</tr>']
    for name, entry in run["methods"].items():
        for kind, title in (("equal_spp", "equal samples"), ("equal_time", "equal time")):
            cells = "".join(
                f"<td{' class=bad' if k == 'bias_fail_fraction' and entry[kind].get('bias_pixels_suspect') else ''}>"
                f"{_num(entry[kind].get(k))}</td>" for k, _ in cols)
            rows.append(f'<tr><td class="name">{_e(name)}</td><td>{entry["rays_per_sample"]}</td>'
                        f'<td>{_num(entry["compile_time_s"], 3)}</td><td class="name">{title}</td>{cells}</tr>')
    return "<table>" + "".join(rows) + "</table>"


def write_html(path: str, report: dict) -> None:
    """Write the report page for ``report`` (the dict saved as report.json) to ``path``."""
    page = _Page(os.path.dirname(os.path.abspath(path)))
    settings = report["settings"]
    page.add(f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>mitsuba-shsampling comparison"
             f"</title><style>{STYLE}</style></head><body>")
    page.add("<h1>Environment-map sampling comparison</h1>")
    page.add("<p>Equal samples count shading rays (2 per pixel sample for every direct-lighting "
             "method). MSE and relative MSE (mean of (x-ref)<sup>2</sup>/(ref<sup>2</sup>+0.01)) are "
             "per pass, averaged over passes; time is the median wall time of a warm pass (kernel "
             "compile time separate); efficiency = 1/(MSE x time). The bias check compares the mean of "
             "the passes with the reference: 'unbiased' means the image-mean z-score is within 4; the "
             "fraction of pixel-channels with |z| &gt; 4 is shown next to its expectation for normal "
             "pass values (red when clearly above: local bias or heavy-tailed samples). Equal time: each method renders at the spp its measured time per sample affords "
             "within the baseline's time per pass. MSE includes the reference's own noise "
             "(its mean variance is listed per scene).</p>")
    page.add("<h2>Run</h2><pre>" + _e(json.dumps({
        "machine": report["machine"], "variant": report["variant"], "versions": report["versions"],
        "settings": settings, "total_time_s": round(report.get("total_time_s", 0.0), 1)}, indent=1))
        + "</pre>")
    for scene in report["scenes"]:
        page.add(f"<h2>Scene {_e(scene['scene'])}</h2><p>{_e(scene['path'])}</p>")
        for note in scene["notes"]:
            page.add(f'<p class="note">{_e(note)}</p>')
        refs = "".join(page.image(r["png"], f"reference ({r['integrator']}, {r['spp']} spp, "
                                  f"mean variance {r['mean_variance']:.3g})", r["file"])
                       for r in scene["references"].values())
        page.add(f'<div class="row">{refs}</div>')
        if scene.get("sampler_figures"):
            page.add("<h3>Warped sample points</h3><p>Hierarchical warping of an 8-band Phong lobe "
                     "(s = 20) alone and times this scene's environment, on the equal-area (phi, z) "
                     "grid (square-root colour scale). From a Hammersley set the warped points stay "
                     "stratified: the warp preserves the input's low discrepancy.</p>")
            for fig in scene["sampler_figures"]:
                with open(os.path.join(page.root, fig["png"]), "rb") as f:
                    page.add(f'<img src="{data_uri(f.read())}" alt="{_e(fig["caption"])}">')
        for run in scene["runs"]:
            page.add(f"<h3>{_e(scene['scene'])}: {_e(run['sampler'])} sampler</h3>")
            page.add(_metrics_table(run))
            for kind, title in (("equal_spp", "equal samples"), ("equal_time", "equal time")):
                figs = []
                for name, entry in run["methods"].items():
                    exr = entry[kind]["files"][0]
                    figs.append(page.image(exr[:-4] + ".png",
                                           f"{name}, {entry[kind]['spp']} spp, MSE {entry[kind]['mse']:.3g}",
                                           exr))
                page.add(f"<h4>Renders at {title} (first pass)</h4><div class='row'>{''.join(figs)}</div>")
            for kind, title in (("variance", "Per-pixel variance across passes (equal samples)"),
                                ("rel_error", "Per-pixel relative squared error (equal samples)")):
                lo, hi = run["maps"]["_scale"][kind]
                figs = [page.image(maps[kind], name) for name, maps in run["maps"].items()
                        if name != "_scale"]
                page.add(f"<h4>{title}; shared log colour scale {lo:.3g} .. {hi:.3g} (inferno)</h4>"
                         f"<div class='row'>{''.join(figs)}</div>")
            if run["convergence_plot"]:
                page.add("<h4>Convergence (one render per spp)</h4>")
                with open(os.path.join(page.root, run["convergence_plot"]), "rb") as f:
                    page.add(f'<img src="{data_uri(f.read())}" alt="convergence">')
            else:
                page.add("<p>No convergence sweep with this sampler (it runs with the first sampler "
                         "only: the others recompile their kernels for every sample count).</p>")
    page.add('<p>Data: <a href="report.json">report.json</a>, <a href="metrics.csv">metrics.csv</a></p>')
    page.add("</body></html>")
    with open(path, "w") as f:
        f.write("\n".join(page.parts))
