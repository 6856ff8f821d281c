"""Ringing and fidelity of windowed Phong lobes: the table behind sh/window.py's defaults.

    python scripts/window_figures.py [--json OUT.json]

For Phong exponents s and band counts n: the minimum of the truncated (and
windowed) zonal lobe relative to its peak (negative = ringing) and the L2
fidelity loss against the exact lobe, for no window, Hann, Lanczos, the
Poussin kernel (non-negative by construction) and the automatic window at
two negativity tolerances.
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from mitsuba_shsampling.sh.window import (hann_window, lanczos_window, nonnegative_window,
                                          nonnegative_window_strength, poussin_window, window_quality)
from mitsuba_shsampling.sh.zonal import phong_attenuation

EXPONENTS = (20.0, 100.0, 200.0)
BANDS = (10, 20)
TOLERANCES = (1e-4, 1e-3)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--json", help="write the records here")
    args = parser.parse_args()
    records = []
    print(f"{'s':>5} {'n':>3} {'window':>14} {'min/peak':>10} {'L2 loss':>8} {'t':>5}")
    for s in EXPONENTS:
        exact = phong_attenuation(s, 600)
        for n in BANDS:
            truncated = exact[:n]
            windows = {"none": (np.ones(n), None), "hann": (hann_window(n), None),
                       "lanczos": (lanczos_window(n), None), "poussin": (poussin_window(n), None)}
            for tol in TOLERANCES:
                windows[f"auto {tol:g}"] = (nonnegative_window(truncated, tol),
                                            nonnegative_window_strength(truncated, tol))
            for name, (window, strength) in windows.items():
                q = window_quality(exact, window)
                records.append({"s": s, "bands": n, "window": name, "min_rel": q["min_rel"],
                                "l2_loss": q["l2_loss"], "strength": strength})
                t = "" if strength is None else f"{strength:.2f}"
                print(f"{s:5.0f} {n:3d} {name:>14} {q['min_rel']:10.2e} {q['l2_loss']:8.3f} {t:>5}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(records, f, indent=1)


if __name__ == "__main__":
    main()
