# ruff: noqa  (scratch of session 20: see README.md)
"""endmu.py TOML SEEDS [NAME=VALUE...]: final-second mode probs and z of each declared estimate"""
import sys, warnings
import jax
jax.config.update("jax_enable_x64", True)
import numpy as np
import uimm_jax
from uimm_jax.scenario.write import scenario_to_dict
from uimm_jax.scenario.parse import parse_scenario
from uimm_jax.studies.truth import true_magnitudes
d = scenario_to_dict(uimm_jax.load_scenario(sys.argv[1]))
for a in sys.argv[3:]:
    k, v = a.split("=")
    d["filter"]["est"][k] = {"true": True, "false": False}.get(v, None) if v in ("true", "false") else (float(v) if ("." in v or "e" in v) else int(v))
sc = parse_scenario(d)
seeds = range(int(sys.argv[2]))
for s in seeds:
    r = uimm_jax.run_scenario(sc, seed=s)
    o = r.outputs
    N = len(o["declared"])
    tm = true_magnitudes(sc, list(r.setup.table.names), N)
    mu = np.asarray(o["mode_probs"])
    last = slice(N - 5000, N)
    z = (o["magnitude"][-1] - tm[-1]) / o["magnitude_sd"][-1]
    print(s, "mu last 0.5s", np.round(mu[last].mean(0), 3), "mu@-1s", np.round(mu[N-10000], 3), "z", np.round(z, 2), "decl", [(x['fault'], round(x['time'], 3)) for x in r.summary['declarations']], "retr", [(x['fault'], round(x['time'], 3)) for x in r.summary['retractions']], flush=True)
