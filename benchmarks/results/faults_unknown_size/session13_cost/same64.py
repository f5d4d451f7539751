"""Session 13, second helper: the 64-run outputs of two prototype variants, compared.

Usage (repository root, the branch's sources on PYTHONPATH)::

    python benchmarks/results/faults_unknown_size/session13_cost/same64.py B VARIANT_A VARIANT_B

The data of ``cost13.py``'s batch (seeds 0..B-1, faults at 0.1 and 0.25 s, 4 000 steps);
prints the largest differences of every output (mode probabilities, mean, declared,
magnitudes and sds), the runs that declare the same sets in the same order, how far their
declaration steps move, and their end magnitudes' differences, as JSON.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parents[3] / "benchmarks"))

from compact import CompactDiagnoser  # noqa: E402
from cost13 import batch_data, batch_state, variant  # noqa: E402

from faults_unknown_size import _scenario  # noqa: E402
from uimm_jax.engine.scan import ESTIMATE_OUTPUTS, FILTER_OUTPUTS, filter_chunk  # noqa: E402
from uimm_jax.studies.run import setup_scenario  # noqa: E402


def main():
    B, va, vb = int(sys.argv[1]), sys.argv[2], sys.argv[3]
    sc = _scenario(1, 1.0)
    est = setup_scenario(sc, "uimm-est")
    N = 4000
    ub, yb = batch_data(sc, B, N)
    outs = {}
    for v in (va, vb):
        p = CompactDiagnoser(est.diagnoser, **variant(v))
        st = batch_state(p.init(est.init_state), B)
        _, o = filter_chunk(p, est.params, st, 0, (ub, yb), FILTER_OUTPUTS + ESTIMATE_OUTPUTS)
        outs[v] = [np.asarray(x) for x in o]
    names = list(FILTER_OUTPUTS + ESTIMATE_OUTPUTS)
    res = {"command": " ".join(["python", *sys.argv])}
    for i, name in enumerate(names):
        a, b = outs[va][i], outs[vb][i]
        res[f"max_abs_diff_{name}"] = float(np.max(np.abs(a.astype(float) - b.astype(float))))
    i_dec, i_mag = names.index("declared"), names.index("magnitude")
    same, shifts, end = 0, [], []
    for r in range(B):
        seqs = []
        for v in (va, vb):
            d = outs[v][i_dec][:, r]
            ch = np.flatnonzero(np.diff(d, prepend=0))
            seqs.append([(int(k), int(d[k])) for k in ch])
        if [c for _, c in seqs[0]] == [c for _, c in seqs[1]]:
            same += 1
            shifts += [abs(a[0] - b[0]) for a, b in zip(*seqs, strict=True)]
            end.append(float(np.max(np.abs(outs[va][i_mag][-1, :, r] - outs[vb][i_mag][-1, :, r]))))
    res["runs_same_declared_sets_in_order"] = f"{same} of {B}"
    res["those_runs_max_declaration_step_shift"] = int(max(shifts, default=0))
    res["those_runs_declaration_steps_shifted"] = int(np.sum(np.asarray(shifts) > 0))
    res["those_runs_end_magnitude_abs_diff_median_max"] = [
        float(np.median(end)) if end else 0.0,
        float(max(end, default=0.0)),
    ]
    print(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
