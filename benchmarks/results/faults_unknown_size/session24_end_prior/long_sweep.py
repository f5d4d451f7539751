"""A ``ramps`` cell with longer runs (session 24, before ``--settle`` existed).

Usage (repository root, ``PYTHONPATH=src``): ``DUR=32.5 RAMP=10 long_sweep.py SIM SEED MAG
[MAG ...] [-- NAME=VALUE ...]``: ``ramp_false.run_cells`` with runs of ``DUR`` s (the
``ramps`` part's case otherwise: the same as ``faults_unknown_size.py ramps --settle DUR -
(2.5 + 2 RAMP)``), 64 runs (``RUNS``); prints and writes ``long_<SIM>_<SEED><TAG>.json``
here: false runs, wrong retractions, coverage, MARE, detection and isolation per cell.
"""

import json
import os
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "session11_ramp2"))

import ramp_false as rf  # noqa: E402

KEEP = ("magnitude", "runs_with_false_declaration", "wrong_retractions", "magnitude_coverage")
KEEP += ("magnitude_mare", "detection_probability", "isolation_accuracy")


def main():
    rf.DURATION = float(os.environ.get("DUR", rf.DURATION))
    argv = sys.argv[1:]
    sets = argv[argv.index("--") + 1 :] if "--" in argv else []
    pos = argv[: argv.index("--")] if "--" in argv else argv
    rf._settings(sets)
    sim, seed, mags = int(pos[0]), int(pos[1]), [float(m) for m in pos[2:]]
    t0 = time.time()
    res = rf.run_cells(sim, mags, runs=int(os.environ.get("RUNS", 64)), seed=seed)
    out = [{k: s[k] for k in KEEP} for s in res.summaries]
    for cell in out:
        print(json.dumps(cell), flush=True)
    doc = {"cells": out, "argv": sys.argv, "dur": rf.DURATION, "ramp": rf.RAMP}
    tag = os.environ.get("TAG", "")
    (HERE / f"long_{sim}_{seed}{tag}.json").write_text(json.dumps(doc, indent=1))
    print("wall", time.time() - t0)


if __name__ == "__main__":
    main()
