"""pooled.py TAG FOLDER [SEEDS [STEM METHOD]]: acceptance parts pooled over seeds (session 30).

SEEDS: comma-separated (default 0,1,2,3,4); STEM: the methods part of the file names
(default ``uimm-est``; ``uimm-imm`` for ``--methods uimm imm``), METHOD the cells read
(default ``uimm-est``).  Reads the files of ``faults_unknown_size.py`` written by
``session26_onset/parts.sh`` with tag TAG at each seed (default 0-4) from FOLDER
(relative to this folder's parent): ``sizes``, ``ramps_1.0``, ``ramps_10.0`` (``TAG_s1``,
``TAG_s2``), ``intermittent`` and ``paper``.  Prints per part: runs with a false
declaration of all runs, per cell the mean over seeds of detection and isolation (worst
cell shown) and of MARE and of 95 % coverage (worst cell shown), wrong
retractions, and at magnitude 1 (abrupt) the mean over seeds of each seed's median delay.
"""

import json
import statistics as st
import sys
from collections import defaultdict
from pathlib import Path

HERE = Path(__file__).resolve().parents[1]


def files(part, tag, seed, where, stem):
    names = [f"{part}_{stem}_64{tag}_seed{seed}.json"]
    names += [f"{part}_{stem}_64{tag}_s{s}_seed{seed}.json" for s in (1, 2)]
    return [where / n for n in names if (where / n).is_file()]


def main(tag, folder, seeds, stem="uimm-est", method="uimm-est"):
    where = HERE / folder
    for part in ("sizes", "ramps_1.0", "ramps_10.0", "intermittent", "paper"):
        false = runs = wrong = 0
        det = iso = 1.0
        mare, cov, delay, rdel, retr, dets, isos = (defaultdict(list) for _ in range(7))
        for k in seeds:
            for path in files(part, tag, k, where, stem):
                data = json.loads(path.read_text())
                for sim, cs in data.items():
                    if not sim.startswith("sim"):
                        continue
                    for c in (c for c in cs if c["method"] == method):
                        cell = (sim, c["magnitude"], c.get("ramp"))
                        false += c["runs_with_false_declaration"]
                        runs += c["runs"]
                        wrong += sum(c.get("wrong_retractions", {}).values())
                        for f, v in c["detection_probability"].items():
                            dets[cell + (f,)].append(v)
                        if c["isolation_accuracy"] is not None:
                            isos[cell].append(c["isolation_accuracy"])
                        for f, v in c.get("magnitude_mare", {}).items():
                            if v is not None:
                                mare[cell + (f,)].append(v)
                        for f, v in c.get("magnitude_coverage", {}).items():
                            if v is not None:
                                cov[cell + (f,)].append(v)
                        if c["magnitude"] == 1.0 and not c.get("ramp"):
                            for f, v in c["median_delay_s"].items():
                                if v is not None:
                                    delay[(sim, f)].append(v * 1e3)
                        for f, v in (c.get("retraction_delay_s") or {}).items():
                            if v is not None:
                                rdel[f].append(v["median"] * 1e3)
                        for f, v in (c.get("retraction_probability") or {}).items():
                            if v is not None:
                                retr[f].append(v)
        if not runs:
            print(f"{part:12s} no files")
            continue
        det = min((st.mean(v) for v in dets.values()), default=1.0)
        iso = min((st.mean(v) for v in isos.values()), default=1.0)
        worst_mare = max(((st.mean(v), k) for k, v in mare.items()), default=(None, None))
        worst_cov = min(((st.mean(v), k) for k, v in cov.items()), default=(None, None))
        line = f"{part:12s} false runs {false}/{runs}  detection >= {100 * det:.1f} %"
        line += f"  isolation >= {100 * iso:.1f} %"
        if worst_mare[0] is not None:
            line += f"  MARE <= {100 * worst_mare[0]:.1f} % {worst_mare[1]}"
            line += f"  coverage >= {100 * worst_cov[0]:.1f} % {worst_cov[1]}"
        line += f"  wrong retractions {wrong}"
        if delay:
            means = {k: round(st.mean(v), 1) for k, v in sorted(delay.items())}
            line += f"  delay at 1 (ms) {means}"
        if retr:
            line += "  retracted >= " + str({k: min(v) for k, v in retr.items()})
            means = {k: round(st.mean(v), 1) for k, v in rdel.items()}
            line += f"  retraction delay (ms) {means}"
        print(line)


if __name__ == "__main__":
    seeds = [int(s) for s in sys.argv[3].split(",")] if len(sys.argv) > 3 else range(5)
    main(sys.argv[1], sys.argv[2], seeds, *sys.argv[4:6])
