"""Per-cell summary of a ramp_demo sweep (runs.csv): false declarations, valve wear's end.

python demo_summary.py DIR [DIR ...]; valve wear's truth is 2 x the cell's magnitude.
"""

import csv
import statistics
import sys
from itertools import groupby

for d in sys.argv[1:]:
    rows = list(csv.DictReader(open(f"{d}/runs.csv")))
    for mag, cell in groupby(rows, key=lambda r: float(r["magnitude"])):
        cell = list(cell)
        true = 2.0 * mag
        vw = [float(r["valve_wear:magnitude"]) for r in cell]
        sd = [float(r["valve_wear:magnitude_sd"]) for r in cell]
        ai = [float(r["air_in_oil:magnitude"]) for r in cell]
        false = [
            int(r["run"])
            for r in cell
            if "false" in (r[f"{f}:declaration"] for f in ("valve_wear", "leakage", "air_in_oil"))
        ]
        wrong = [
            int(r["run"])
            for r in cell
            if r["valve_wear:retracted_s"] or r["air_in_oil:retracted_s"]
        ]
        cover = sum(abs(v - true) <= 1.96 * s for v, s in zip(vw, sd, strict=True))
        low = [f"{int(r['run'])}:{v:.2f}" for r, v in zip(cell, vw, strict=True) if v < 0.95 * true]
        acc = statistics.mean(float(r["mode_accuracy"]) for r in cell)
        print(
            f"{d} x{mag:g}: false {len(false)} {false}; retracted {wrong}; valve wear median "
            f"{statistics.median(vw):.3f} min {min(vw):.3f}, covered {cover}/{len(cell)}, "
            f"under 95 %: {low}; air median {statistics.median(ai):.3f}; mode acc {acc:.4f}"
        )
