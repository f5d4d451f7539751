"""Cells of two faults_unknown_size JSON files that differ (session 19; scratch).

python cmp_cells.py A.json B.json: per cell (sim, magnitude, ramp), false runs, detection,
wrong retractions, mode accuracy, each fault's MARE (%) and coverage (%) and median delay
(ms), printed as A -> B where they differ; "same" cells are counted.
"""

import json
import sys


def cells(path):
    out = {}
    for k, v in json.load(open(path)).items():
        if not k.startswith("sim"):
            continue
        for c in v:
            key = (k, c.get("case"), c["magnitude"], c.get("ramp"))
            row = {
                "false": c["runs_with_false_declaration"],
                "det": min(c["detection_probability"].values(), default=1.0),
                "wr": sum(c.get("wrong_retractions", {}).values()),
                "acc": round(c["mode_accuracy"], 4),
            }
            for f, x in c["magnitude_mare"].items():
                row[f"mare_{f}"] = None if x is None else round(100 * x, 2)
            for f, x in c["magnitude_coverage"].items():
                row[f"cov_{f}"] = None if x is None else round(100 * x)
            for f, x in c["median_delay_s"].items():
                row[f"ms_{f}"] = None if x is None else round(1e3 * x, 1)
            out[key] = row
    return out


a, b = (cells(p) for p in sys.argv[1:3])
same = 0
for key, ra in a.items():
    rb = b[key]
    diff = {k: f"{ra[k]} -> {rb.get(k)}" for k in ra if ra[k] != rb.get(k)}
    if diff:
        print(key, diff)
    else:
        same += 1
print(f"{same} of {len(a)} cells the same")
