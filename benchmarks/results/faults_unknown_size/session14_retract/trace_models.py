"""Trace every model's magnitude estimates of one ramp run (session 14, retractions).

Usage (repository root, ``PYTHONPATH=src``): ``trace_models.py SIM MAG RUN [-- NAME=VALUE ...]``
with ``RAMP`` (env, default 10) as ``session11_ramp2/ramp_false.py``.  Re-simulates run ``RUN``
of the ramps part's 64-run case (its noise key) and prints, every ``STEP`` samples (env,
default 5000) and every sample in ``K0``..``K1`` (env), the mode probabilities, the declared
set and, per model, each fault's magnitude estimate and sd (after the step's hand-over).
"""

import os
import sys
from pathlib import Path

import jax
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "session11_ramp2"))
import ramp_false as rf  # noqa: E402

import uimm_jax.engine.uimm_est as ue  # noqa: E402
from uimm_jax.engine import _est_rules as rules  # noqa: E402

STEP = int(os.environ.get("STEP", 5000))
K0, K1 = int(os.environ.get("K0", -1)), int(os.environ.get("K1", -1))
_count = [0]


def _record(mean, var, lmp, loglik, declared):
    k = _count[0]
    _count[0] += 1
    if k % STEP == 0 or K0 <= k < K1:
        np.set_printoptions(linewidth=220, suppress=True)
        print(
            k,
            np.round(np.exp(lmp), 3),
            declared.astype(int),
            "mags",
            np.round(mean, 4).tolist(),
            "sd",
            np.round(np.sqrt(np.maximum(var, 0)), 4).tolist(),
            flush=True,
        )


_orig = ue.UIMMEstDiagnoser.step


def traced_step(record):
    """``UIMMEstDiagnoser.step`` that also calls ``record(mean, var, log_mode_probs,
    model_loglik, declared)`` on the host after each step (the magnitudes of every model and
    their variances; session 15's ``trace_events.py`` uses it too)."""

    def step(self, state, params, u, y, *, with_cov=True):
        new, out = _orig(self, state, params, u, y, with_cov=with_cov)
        n = self.dyn.n
        jax.debug.callback(
            record,
            new.imm.mean[n:],
            rules.mag_var(new.imm.cov, n),
            new.imm.log_mode_probs,
            out.step.model_loglik,
            new.declared,
            ordered=True,
        )
        return new, out

    return step


_step = traced_step(_record)
ue.UIMMEstDiagnoser.step = _step

if __name__ == "__main__":
    argv = sys.argv[1:]
    sets = argv[argv.index("--") + 1 :] if "--" in argv else []
    pos = argv[: argv.index("--")] if "--" in argv else argv
    rf._settings(sets)
    os.environ.setdefault("STEP", "1000000000")
    rf.one(int(pos[0]), float(pos[1]), int(pos[2]))
