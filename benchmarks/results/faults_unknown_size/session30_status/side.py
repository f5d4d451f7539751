"""side.py FILE...: a markdown table of fixed-size UIMM / IMM cells (session 30).

One row per cell of each ``faults_unknown_size.py`` JSON file (``--methods uimm imm``):
sim, method, magnitude, ramp, detection per fault, runs with a false declaration, isolation.
"""

import json
import sys

print("| sim | method | magnitude | ramp (s) | runs | detected | runs with a false declaration "
      "| isolated |")
print("|---|---|---|---|---|---|---|---|")
for name in sys.argv[1:]:
    data = json.load(open(name))
    for sim, cells in data.items():
        if not sim.startswith("sim"):
            continue
        for c in cells:
            det = ", ".join(f"{f} {100 * v:.0f} %" for f, v in c["detection_probability"].items())
            iso = c["isolation_accuracy"]
            iso = "-" if iso is None else f"{100 * iso:.0f} %"
            print(f"| {sim[3:]} | {c['method']} | {c['magnitude']} | {c.get('ramp') or 0} "
                  f"| {c['runs']} | {det} | {c['runs_with_false_declaration']} | {iso} |")
