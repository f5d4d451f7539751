# ruff: noqa  (scratch of sessions 18-19: see README.md)
"""Per-cell comparison of faults_unknown_size JSON files: python cmp.py A.json B.json ..."""
import json, sys
def rows(path):
    d = json.load(open(path))
    out = {}
    for k, v in d.items():
        if not k.startswith("sim"): continue
        for c in v:
            key = (k, c.get("case"), c["magnitude"], c.get("ramp"))
            mare = max([x for x in c["magnitude_mare"].values() if x is not None], default=None)
            cov = min([x for x in c["magnitude_coverage"].values() if x is not None], default=None)
            out[key] = dict(false=c["runs_with_false_declaration"], runs=c["runs"],
                det=min(c["detection_probability"].values(), default=1.0),
                wr=sum(c.get("wrong_retractions", {}).values()),
                mare=None if mare is None else round(100*mare, 2), cov=None if cov is None else round(100*cov),
                delay={f: None if x is None else round(1e3*x, 1) for f, x in c["median_delay_s"].items()})
    return out
files = sys.argv[1:]
R = [rows(f) for f in files]
for key in R[0]:
    print(key)
    for f, r in zip(files, R):
        c = r.get(key)
        print(f"   {f.split('/')[-1][:50]:50s} {c}")
