"""Probe: the per-step outputs of a short actuator run (paper_sim1_tuned's filter, events
moved early, one ending) saved to an npz, to compare two versions of the code bit for bit:

    PYTHONPATH=/work/main/src python per_step_outputs.py /tmp/main.npz
    PYTHONPATH=src python per_step_outputs.py /tmp/new.npz
    python per_step_outputs.py --compare /tmp/main.npz /tmp/new.npz
"""

import sys
import tomllib

import numpy as np


def run(path):
    import jax

    jax.config.update("jax_enable_x64", True)
    import uimm_jax
    from uimm_jax.scenario.parse import parse_scenario

    with open("scenarios/paper_sim1_tuned.toml", "rb") as f:
        d = tomllib.load(f)
    d["duration"] = 0.6
    d["events"] = [
        {"time": 0.1, "fault": "valve_wear", "magnitude": 1.0},
        {"time": 0.25, "fault": "leakage", "magnitude": 1.0, "end": 0.45},
    ]
    res = uimm_jax.run_scenario(parse_scenario(d), seed=1)
    out = {k: np.asarray(v) for k, v in res.outputs.items()}
    print(uimm_jax.__file__, {k: v.shape for k, v in out.items()})
    print(res.summary["declarations"], res.summary["retractions"])
    np.savez(path, **out)


def compare(a, b):
    A, B = np.load(a), np.load(b)
    assert sorted(A.files) == sorted(B.files), (A.files, B.files)
    for k in A.files:
        same = A[k].shape == B[k].shape and np.array_equal(A[k], B[k], equal_nan=True)
        print(f"{k}: {A[k].shape} {'identical' if same else 'DIFFERENT'}")
        assert same, k


if __name__ == "__main__":
    if sys.argv[1] == "--compare":
        compare(sys.argv[2], sys.argv[3])
    else:
        run(sys.argv[1])
