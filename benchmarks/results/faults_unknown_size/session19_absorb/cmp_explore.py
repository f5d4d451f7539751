"""Cells of two explore JSON files (session15_reopen/explore.py) that differ (session 19).

python cmp_explore.py A.json B.json
"""

import json
import sys


def cells(path):
    d = json.load(open(path))
    part = next(k for k in d if k not in ("command", "wall_s"))
    out = {}
    for c in d[part]:
        key = (c["case"], c["magnitude"], c.get("ramp"))
        row = {
            "false": c["runs_with_false_declaration"],
            "det": min(c["detection_probability"].values(), default=1.0),
            "wr": sum(c.get("wrong_retractions", {}).values()),
            "acc": round(c["mode_accuracy"], 4),
        }
        for f, x in (c.get("retraction_probability") or {}).items():
            row[f"ret_{f}"] = x
        for f, x in (c.get("magnitude_mare") or {}).items():
            row[f"mare_{f}"] = None if x is None else round(100 * x, 2)
        for f, x in (c.get("magnitude_coverage") or {}).items():
            row[f"cov_{f}"] = None if x is None else round(100 * x)
        for f, x in (c.get("retraction_delay_s") or {}).items():
            med = None if x is None else x["median"]
            row[f"ret_ms_{f}"] = None if med is None else round(1e3 * med, 1)
        out[key] = row
    return out


a, b = (cells(p) for p in sys.argv[1:3])
for key, ra in a.items():
    rb = b.get(key, {})
    print(key)
    print("  ", {k: f"{ra[k]} -> {rb.get(k)}" if ra[k] != rb.get(k) else ra[k] for k in ra})
