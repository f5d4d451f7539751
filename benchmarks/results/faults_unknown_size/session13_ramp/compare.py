"""Compare two result files of ``faults_unknown_size.py`` cell by cell (session 13).

Usage: ``python compare.py BASE.json NEW.json``: per cell (sim, case, magnitude, ramp)
``same`` or ``**DIFF``, with false runs / false declarations, detection and isolation
(%), median delays (ms), MARE (%), coverage (%) and mode accuracy.
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
    return f"{false} det {det} iso {iso} dl {dl} mare {mare} cov {cov} ma {s['mode_accuracy']:.5f}"


def main():
    base, new = load(sys.argv[1]), load(sys.argv[2])
    for key, s in base.items():
        if key not in new:
            print(key, "missing")
            continue
        a, b = line(s), line(new[key])
        print(("  same " if a == b else "**DIFF ") + str(key))
        print("   base", a)
        if a != b:
            print("   new ", b)


if __name__ == "__main__":
    main()
