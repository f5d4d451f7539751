# ruff: noqa  (scratch of session 22: see README.md)
"""Air in oil's 95 % coverage on sim 2's 10 s ramps at 2 and 3, per seed and pooled.

Usage (repository root): ``python benchmarks/results/faults_unknown_size/session22_lead/pooled_cov.py``
reads the 64-run files of seeds 0-6 (seed 0: the acceptance files ``_s21RA4k_s2``,
``_s21DWL_s2``, ``_s22DLU_s2``; seeds 1-6: ``_s22def_seedK``, ``_s22DWL_seedK``,
``_s22DLU_seedK``) and prints runs covered of 64 per seed and the pooled fraction.
"""
import json
from pathlib import Path

HERE = Path(__file__).resolve().parent
TOP = HERE.parent
SEED0 = {"def": "_s21RA4k_s2", "DWL": "_s21DWL_s2", "DLU": "_s22DLU_s2"}


def load(tag, seed):
    if seed == 0:
        name = f"ramps_10.0_uimm-est_64{SEED0[tag]}.json"
    else:
        name = f"ramps_10.0_uimm-est_64_s22{tag}_seed{seed}.json"
    for where in (HERE, TOP):
        if (where / name).is_file():
            return json.loads((where / name).read_text())
    return None


for mag in (2.0, 3.0):
    for tag in ("def", "DWL", "DLU"):
        per = []
        for seed in range(7):
            d = load(tag, seed)
            if d is None:
                continue
            c = next(c for c in d["sim2"] if c["magnitude"] == mag)
            per.append(round(64 * c["magnitude_coverage"]["air_in_oil"]))
        if per:
            print(f"mag {mag} {tag:4s} covered per seed {per}  pooled {sum(per)}/{64 * len(per)} "
                  f"= {100 * sum(per) / (64 * len(per)):.1f} %")
