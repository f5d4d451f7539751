# ruff: noqa  (scratch of session 26: see README.md)
"""trace.py SIM MAG RUN: one run of a sizes (RAMP=0) or ramps cell, every model's own magnitude.

Re-simulates run RUN of the sweep cell (sim SIM, magnitude MAG, ramp RAMP s from the
environment, default 10; SEED the sweep's seed) as ``session11_ramp2/ramp_false.py one``
does, and prints every STEP samples from K0 to K1: the mode probabilities, the declared
set's code, each fault's own hypothesis' magnitude with its sd (the model of slot j + 1),
model 0's magnitudes and the ``since`` counters.  SETS="a=1 b=2" changes the defaults as
``--set`` does.  Run from the repository root with ``PYTHONPATH=src``.
"""
import os, sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'session11_ramp2'))
import ramp_false as rf
import jax, jax.numpy as jnp, numpy as np
from uimm_jax.engine.truth import run_keys
from uimm_jax.studies import run as srun


def trace(sc, seed, r, k0, k1, st):
    """Run ``r`` of a 64-run sweep at ``seed`` of scenario ``sc`` (its noise key) as one
    run, printing every ``st`` samples from ``k0`` to ``k1`` (also used by
    ``session29_restart/paper_false.py``)."""
    setup = srun.setup_scenario(sc, "uimm-est")
    key = jnp.asarray(run_keys(seed, 64)[0][r])
    rec = {}
    def diagnose(setup, y, u=None, **kw):
        d = setup.diagnoser; n = d.dyn.n
        us = jnp.asarray(srun.scenario_inputs(setup.scenario, y.shape[0]) if u is None else u)
        def body(st, uy):
            st2, info = d.step(st, setup.params, uy[0], uy[1], with_cov=False)
            var = jnp.diagonal(st2.imm.cov[n:, n:], axis1=0, axis2=1)
            return st2, (st2.imm.log_mode_probs, st2.imm.mean[n:], var, st2.since, info.declared, st2.calm)
        f = jax.jit(lambda s0, xs: jax.lax.scan(body, s0, xs))
        _, o = f(setup.init_state, (us, jnp.asarray(y)))
        rec.update(zip(("lmp", "mag", "var", "since", "dec", "calm"), map(np.asarray, o)))
        return srun.filter_measurements(setup, y, u, **kw)
    orig = jax.random.PRNGKey
    jax.random.PRNGKey = lambda s: key
    try:
        o = srun.execute_run(setup, diagnose)
    finally:
        jax.random.PRNGKey = orig
    np.set_printoptions(linewidth=250, precision=3, suppress=True)
    F = rec['mag'].shape[1]
    for k in range(k0, k1, st):
        mp = np.exp(rec['lmp'][k])
        own = [f"{rec['mag'][k, j, j+1].item():.3f}±{np.sqrt(rec['var'][k, j+1, j].item()):.3f}" for j in range(F)]
        print(k, np.round(mp.ravel(), 4), rec['dec'][k], 'own:', own, 'm0:', np.round(rec['mag'][k, :, 0].ravel(), 3), 'since', rec['since'][k].ravel(), 'calm', rec['calm'][k])
    print({k: o.summary[k] for k in ("declarations", "retractions")})


def window(k0, k1, st):
    """K0, K1, STEP from the environment, with these defaults."""
    return (int(os.environ.get(k, str(v))) for k, v in (("K0", k0), ("K1", k1), ("STEP", st)))


if __name__ == "__main__":
    rf._settings(os.environ.get('SETS', '').split())
    sim, mag, r = int(sys.argv[1]), float(sys.argv[2]), int(sys.argv[3])
    a, b = rf.FIRST[sim]
    ramp = {"ramp": rf.RAMP} if rf.RAMP else {}
    ev = [{"time": 0.5, "fault": a, "magnitude": mag, **ramp}, {"time": rf.ONSET2, "fault": b, "magnitude": mag, **ramp}]
    trace(rf._scenario(sim, ev), int(os.environ.get("SEED", "0")), r, *window(11000, 13100, 100))
