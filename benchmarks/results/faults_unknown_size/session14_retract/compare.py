"""Compare result files of ``faults_unknown_size.py`` cell by cell (session 14).

Usage: ``python compare.py BASE.json NEW.json [MORE.json ...]``: per cell of ``BASE`` (sim,
case, magnitude, ramp) ``same`` or ``**DIFF`` against the first of the other files that has
it, with false runs / false declarations, detection and isolation (%), median delays (ms),
MARE (%), coverage (%), wrong retractions (a fault retracted while present), retraction
share and delay median / p95 / max (ms; intermittent cells) and mode accuracy.  Session 13's
``compare.py`` without the retraction columns.
"""

import json
import sys


def load(path):
    out = {}
    for key, cells in json.load(open(path)).items():
        if not isinstance(cells, list):
            continue
        for s in cells:
            if isinstance(s, dict) and "method" in s:
                out[(key, s.get("case"), s.get("magnitude"), s.get("ramp"))] = s
    return out


def line(s):
    det = ",".join(f"{100 * x:.0f}" for x in (s.get("detection_probability") or {}).values())
    delay = s.get("median_delay_s", {}).values()
    dl = ",".join("-" if x is None else f"{1e3 * x:.1f}" for x in delay)
    mare = ",".join(f"{100 * x:.1f}" for x in s.get("magnitude_mare", {}).values())
    cov = ",".join(f"{100 * x:.0f}" for x in s.get("magnitude_coverage", {}).values())
    iso = s.get("isolation_accuracy")
    iso = "-" if iso is None else f"{100 * iso:.0f}"
    false = f"F{s['false_declarations']}/{s.get('false_declarations_all')}"
    wrong = ",".join(str(v) for v in (s.get("wrong_retractions") or {}).values())
    ret = ""
    if s.get("retraction_probability"):
        p = ",".join(f"{100 * x:.0f}" for x in s["retraction_probability"].values())
        d = ";".join(
            "/".join(f"{1e3 * v[k]:.1f}" for k in ("median", "p95", "max"))
            for v in s["retraction_delay_s"].values()
        )
        ret = f" ret {p} % {d} ms"
    return (
        f"{false} det {det} iso {iso} dl {dl} mare {mare} cov {cov} wrong {wrong}{ret} "
        f"ma {s['mode_accuracy']:.5f}"
    )


def main():
    base = load(sys.argv[1])
    others = [load(p) for p in sys.argv[2:]]
    for key, s in base.items():
        new = next((o[key] for o in others if key in o), None)
        if new is None:
            print(key, "missing")
            continue
        a, b = line(s), line(new)
        print(("  same " if a == b else "**DIFF ") + str(key))
        print("   base", a)
        if a != b:
            print("   new ", b)


if __name__ == "__main__":
    main()
