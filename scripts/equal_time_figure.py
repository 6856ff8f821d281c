"""The README's picture: equal-time crops of the plugin and of Mitsuba's best, beside the reference.

    python scripts/equal_time_figure.py REPORT_DIR [REPORT_DIR ...] -o docs/equal_time_crops.png

Each ``REPORT_DIR`` is a ``compare`` report (a sweep's cell folder will do); each gives one row:
the reference, the best of Mitsuba's strategies at equal time (the verdict's contender, the
highest equal-time efficiency) and the project's plugin at its defaults, each the first pass of
the renders at equal time, cropped to the window the report zooms on (where the methods'
variance is largest, chosen on the tone-mapped image) and enlarged without filtering. The
titles give each method's samples per pixel, its expected MSE over the passes and the
equal-time efficiency ratio with its 90 % interval, as the report states them.
"""

from __future__ import annotations

import argparse
import os

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from mitsuba_shsampling.report.methods import DEFAULT_PLUGIN_METHOD, DIRECT, mitsuba_strategies  # noqa: E402
from mitsuba_shsampling.report.schema import load_report  # noqa: E402
from mitsuba_shsampling.report.verdict import ratio_with_interval  # noqa: E402


def panels(folder: str, family: str = DIRECT):
    """(title of the row, [(panel title, RGB crop)]) of one report folder's first run."""
    report = load_report(os.path.join(folder, "report.json"))
    scene = report.scenes[0]
    run = scene.runs[0]
    ours_name = DEFAULT_PLUGIN_METHOD[family]
    methods = run.methods
    timed = {n: methods[n].equal_time for n in mitsuba_strategies(methods, family) if methods[n].equal_time}
    best = max(timed, key=lambda n: timed[n].efficiency)
    ours = methods[ours_name].equal_time
    ratio, low, high = ratio_with_interval("efficiency", ours, timed[best])
    x, y, size = run.crop
    # Twice the report's window, about its centre (kept inside the film): more of the scene
    # around the noisiest spot.
    height, width = run.film_size[1], run.film_size[0]
    size2 = min(2 * size, width, height)
    x = int(min(max(x + size // 2 - size2 // 2, 0), width - size2))
    y = int(min(max(y + size // 2 - size2 // 2, 0), height - size2))
    size = size2

    def cut(png: str) -> np.ndarray:
        return plt.imread(os.path.join(folder, png))[y:y + size, x:x + size, :3]

    reference = scene.references[family]
    envmap = scene.envmap.name if scene.envmap else "its own map"
    row = (f"{scene.scene} under {envmap}: {ours_name} / {best} at equal time "
           f"{ratio:.2f}x [{low:.2f}, {high:.2f}]")
    return row, [(f"reference ({reference.spp} spp)", cut(reference.png)),
                 (f"{best}: {timed[best].spp} spp, MSE {timed[best].error.mse:.2e}", cut(timed[best].files["first_pass_png"])),
                 (f"{ours_name}: {ours.spp} spp, MSE {ours.error.mse:.2e}", cut(ours.files["first_pass_png"]))]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("reports", nargs="+", metavar="REPORT_DIR")
    parser.add_argument("-o", "--out", default="docs/equal_time_crops.png")
    args = parser.parse_args()
    rows = [panels(folder) for folder in args.reports]
    fig = plt.figure(figsize=(10.5, 3.9 * len(rows)), layout="constrained")
    for (title, row), sub in zip(rows, np.atleast_1d(fig.subfigures(len(rows), 1))):
        sub.suptitle(title, fontsize=10.5, weight="bold")
        for (caption, image), ax in zip(row, sub.subplots(1, 3)):
            ax.imshow(image, interpolation="nearest")
            ax.set_title(caption, fontsize=9)
            ax.set_xticks([])
            ax.set_yticks([])
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    fig.savefig(args.out, dpi=110)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
