"""Every model's magnitudes over one run of a ``ramps`` cell (session 24).

Usage (repository root, ``PYTHONPATH=src``): ``trace_models.py SIM MAG RUN [-- NAME=VALUE
...]`` with the environment of ``../session11_ramp2/ramp_false.py one`` (``SEED``, ``RAMP``,
``STEP``, ``K0``) and ``DUR`` (the run's length in s; default the ``ramps`` part's).  Runs
the cell's run ``RUN`` as ``ramp_false.py one`` does, then scans ``Diagnoser.step`` over the
same data and prints, every ``STEP`` samples from ``K0``, the mode probabilities, the
declared set, and every model's magnitudes ``(F, M)`` and their sds; saves them to ``SAVE``
(default ``trace_models.npz``).
"""

import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "session11_ramp2"))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import ramp_false as rf  # noqa: E402

from uimm_jax.engine import _est_rules as rules  # noqa: E402
from uimm_jax.engine.truth import run_keys  # noqa: E402
from uimm_jax.studies import run as srun  # noqa: E402

rf.DURATION = float(os.environ.get("DUR", rf.DURATION))


def main():
    argv = sys.argv[1:]
    sets = argv[argv.index("--") + 1 :] if "--" in argv else []
    pos = argv[: argv.index("--")] if "--" in argv else argv
    rf._settings(sets)
    sim, mag, r = int(pos[0]), float(pos[1]), int(pos[2])
    a, b = rf.FIRST[sim]
    ramp = {"ramp": rf.RAMP} if rf.RAMP else {}
    ev = [
        {"time": 0.5, "fault": a, "magnitude": mag, **ramp},
        {"time": rf.ONSET2, "fault": b, "magnitude": mag, **ramp},
    ]
    sc = rf._scenario(sim, ev)
    setup = srun.setup_scenario(sc, "uimm-est")
    key = jnp.asarray(run_keys(int(os.environ.get("SEED", "0")), 64)[0][r])
    rec = {}

    def diagnose(setup, y, u=None, **kw):
        rec["y"], rec["u"] = y, u
        return srun.filter_measurements(setup, y, u, **kw)

    orig = jax.random.PRNGKey
    jax.random.PRNGKey = lambda s: key  # the sweep's noise key of run r
    try:
        o = srun.execute_run(setup, diagnose)
    finally:
        jax.random.PRNGKey = orig
    d, p, n = setup.diagnoser, setup.params, setup.diagnoser.dyn.n
    y = jnp.asarray(rec["y"])
    u = srun.scenario_inputs(sc, y.shape[0]) if rec["u"] is None else rec["u"]
    u = jnp.asarray(u, y.dtype)

    def body(st, uy):
        st, _ = d.step(st, p, uy[0], uy[1], with_cov=False)
        var = rules.mag_var(st.imm.cov, n)
        return st, (st.imm.mean[n:], var, st.imm.log_mode_probs, st.declared)

    _, (mags, var, lmp, dec) = jax.lax.scan(jax.jit(body), setup.init_state, (u, y))
    mags, sd, mp = np.asarray(mags), np.sqrt(np.asarray(var)), np.exp(np.asarray(lmp))
    dec = np.asarray(dec)
    np.savez(os.environ.get("SAVE", "trace_models.npz"), mags=mags, sd=sd, mp=mp, dec=dec)
    step, k0 = int(os.environ.get("STEP", 5000)), int(os.environ.get("K0", 0))
    np.set_printoptions(linewidth=220, suppress=True)
    print("step, mode probabilities, declared; magnitudes (F x M); their sds")
    for k in range(k0, mags.shape[0], step):
        print(k, np.round(mp[k], 3), dec[k].astype(int))
        print("   ", np.round(mags[k], 3).tolist())
        print("   ", np.round(sd[k], 4).tolist())
    print({k: o.summary[k] for k in ("declarations", "retractions")})


if __name__ == "__main__":
    main()
