# ruff: noqa  (scratch of session 19: see README.md)
# find the false runs of a sizes cell with --set-like overrides: find_false.py SIM MAG [NAME=VALUE...]
import sys, warnings
import jax
jax.config.update("jax_enable_x64", True)
import numpy as np
sys.path.insert(0, "benchmarks")
import uimm_jax.engine.uimm_est as ue
from uimm_jax.engine.uimm_est_types import est_settings, est_value_from_text
sim, mag = int(sys.argv[1]), float(sys.argv[2])
vals = {k: est_value_from_text(k, v) for k, v in (a.split("=") for a in sys.argv[3:])}
ue.EstSettings.__new__.__defaults__ = tuple(est_settings(vals, name="--set"))
import faults_unknown_size as fus
from uimm_jax.studies.sweep import run_sweep
a, b = fus.FIRST[sim]
sc = fus._scenario(sim, 2.0)
case = {"name": f"sim{sim}", "events": [{"fault": a, "time": 0.5}, {"fault": b, "time": 1.2}]}
res = run_sweep(sc, runs=64, methods=["uimm-est"], cases=[case], magnitudes=[mag], ramps=[0.0], fault_free=False, seed=0, batch=128)
fd = res.false_declared()[0]
for r in np.nonzero(fd.any(axis=1))[0]:
    print(r, "false", [res.faults[j] for j in np.nonzero(fd[r])[0]], "decl_step", res.decl_step[0][r], "onset", res.onset_step[0][r], "ret", res.estimates["retract_step"][0][r])
