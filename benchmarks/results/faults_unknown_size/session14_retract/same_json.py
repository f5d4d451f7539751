"""``same_json.py A.json B.json``: equal but for run times and the command? (session 14)."""

import json
import sys

DROP = {"runtime_s", "wall_s", "command"}


def strip(x):
    if isinstance(x, dict):
        return {k: strip(v) for k, v in x.items() if k not in DROP}
    if isinstance(x, list):
        return [strip(v) for v in x]
    return x


a, b = (strip(json.load(open(p))) for p in sys.argv[1:3])
print("equal" if a == b else "DIFFERENT", *sys.argv[1:3])
