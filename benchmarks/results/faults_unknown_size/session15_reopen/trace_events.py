"""Every model's magnitudes and log-likelihoods, sample by sample, in one run of given events.

Usage (repository root, ``PYTHONPATH=src``):
``trace_events.py SIM DURATION SEED K0 K1 'FAULT@T0[+LEN][~RAMP][*MAG]' ... [-- NAME=VALUE]``
(events as ``session14_retract/one_events.py``).  Prints, for each sample in ``K0..K1``,
the mode probabilities, the declared code, each model's innovation log-likelihood (eq. 27)
relative to model 0's, and each model's magnitudes (rows: faults; columns: models) with
their sds.  Session 15 used it on sim 2 with air in oil first (a leakage declared as valve
wear begins): ``trace_events.py 2 2.0 2 11990 12100 'air_in_oil@0.5' 'valve_wear@1.2'``.
"""

import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "session14_retract"))
sys.path.insert(0, str(HERE.parent / "session11_ramp2"))
import one_events  # noqa: E402
import trace_models  # noqa: E402

import uimm_jax.engine.uimm_est as ue  # noqa: E402

K = {"k": 0, "k0": 0, "k1": 0}


def _record(mean, var, lmp, loglik, declared):
    k = K["k"]
    K["k"] += 1
    if K["k0"] <= k < K["k1"]:
        np.set_printoptions(linewidth=240, suppress=True)
        print(
            k,
            "mu",
            np.round(np.exp(lmp[:, 0]), 3),
            "D",
            int(np.sum(declared[:, 0] * (1 << np.arange(declared.shape[0])))),
            "ll-ll0",
            np.round(loglik[:, 0] - loglik[0, 0], 2),
            "mags",
            np.round(mean[..., 0], 3).tolist(),
            "sd",
            np.round(np.sqrt(np.maximum(var[..., 0], 0)), 3).tolist(),
            flush=True,
        )


if __name__ == "__main__":
    argv = sys.argv[1:]
    pos = argv[: argv.index("--")] if "--" in argv else argv
    K["k0"], K["k1"] = int(pos[3]), int(pos[4])
    sys.argv = [sys.argv[0], *pos[:3], *pos[5:], *argv[len(pos) :]]
    ue.UIMMEstDiagnoser.step = trace_models.traced_step(_record)
    one_events.main()
