# ruff: noqa  (scratch of session 29: see README.md)
"""paper_false.py SIM SEED [RUN]: the ``paper`` part's cell (valve wear at 1 s, the second
fault at 2.5 s, 4 s runs, magnitude 1) of sim SIM at seed SEED: without RUN, the runs with a
false declaration (declaration, onset and retraction steps); with RUN, that run traced as
``session26_onset/trace.py`` does (K0, K1, STEP from the environment; SETS="a=1" as
``--set``).  Repository root,
PYTHONPATH=src."""
import os, sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'session11_ramp2'))
import ramp_false as rf
import jax, jax.numpy as jnp, numpy as np
from uimm_jax.engine.truth import run_keys
from uimm_jax.studies import run as srun
from uimm_jax.studies.sweep import run_sweep
from uimm_jax.scenario.parse import load_scenario, parse_scenario
from uimm_jax.scenario.write import scenario_to_dict

rf._settings(os.environ.get('SETS', '').split())

sim, seed = int(sys.argv[1]), int(sys.argv[2])
a, b = rf.FIRST[sim]
d = scenario_to_dict(load_scenario(rf.REPO / "scenarios" / f"paper_sim{sim}_tuned.toml"))
d["duration"] = 4.0
d["events"] = [{"fault": a, "time": 1.0, "magnitude": 1.0}, {"fault": b, "time": 2.5, "magnitude": 1.0}]
sc = parse_scenario(d, source="paper cell")
if len(sys.argv) < 4:
    case = {"name": f"sim{sim}", "events": [{"fault": a, "time": 1.0}, {"fault": b, "time": 2.5}]}
    res = run_sweep(sc, runs=64, methods=["uimm-est"], cases=[case], seed=seed, batch=128,
                    magnitudes=[1.0], fault_free=False)
    for cell in res.cells:
        c = cell.index
        fd = res.false_declared()[c]
        for r in np.nonzero(fd.any(-1))[0]:
            print('run', r, 'false', [res.faults[f] for f in np.nonzero(fd[r])[0]], 'decl', res.decl_step[c, r].tolist(), 'onset', res.onset_step[c, r].tolist(), 'retract', np.asarray(res.estimates['retract_step'][c, r]).tolist())
    sys.exit()
r = int(sys.argv[3])
setup = srun.setup_scenario(sc, "uimm-est")
key = jnp.asarray(run_keys(seed, 64)[0][r])
rec = {}
def diagnose(setup, y, u=None, **kw):
    dg = setup.diagnoser; n = dg.dyn.n
    us = jnp.asarray(srun.scenario_inputs(setup.scenario, y.shape[0]) if u is None else u)
    def body(st, uy):
        st2, info = dg.step(st, setup.params, uy[0], uy[1], with_cov=False)
        var = jnp.diagonal(st2.imm.cov[n:, n:], axis1=0, axis2=1)
        return st2, (st2.imm.log_mode_probs, st2.imm.mean[n:], var, st2.since, info.declared)
    f = jax.jit(lambda s0, xs: jax.lax.scan(body, s0, xs))
    _, o = f(setup.init_state, (us, jnp.asarray(y)))
    rec.update(zip(("lmp", "mag", "var", "since", "dec"), map(np.asarray, o)))
    return srun.filter_measurements(setup, y, u, **kw)
orig = jax.random.PRNGKey
jax.random.PRNGKey = lambda s: key
try:
    o = srun.execute_run(setup, diagnose)
finally:
    jax.random.PRNGKey = orig
k0, k1, st = (int(os.environ.get(k, v)) for k, v in (("K0", 10000), ("K1", 11000), ("STEP", 20)))
np.set_printoptions(linewidth=250, precision=3, suppress=True)
F = rec['mag'].shape[1]
for k in range(k0, k1, st):
    mp = np.exp(rec['lmp'][k])
    own = [f"{rec['mag'][k, j, j+1].item():.3f}±{np.sqrt(rec['var'][k, j+1, j].item()):.3f}" for j in range(F)]
    print(k, np.round(mp.ravel(), 4), rec['dec'][k], 'own:', own, 'm0:', np.round(rec['mag'][k, :, 0].ravel(), 3), 'since', rec['since'][k].ravel())
print({k: o.summary[k] for k in ("declarations", "retractions")})
