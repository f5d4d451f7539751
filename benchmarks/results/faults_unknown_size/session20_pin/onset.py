# ruff: noqa  (scratch of session 20: see README.md)
import sys, jax
jax.config.update("jax_enable_x64", True)
import numpy as np, uimm_jax
from uimm_jax.scenario.write import scenario_to_dict
from uimm_jax.scenario.parse import parse_scenario
seed = int(sys.argv[1]); t0, t1 = 30.0, 30.06
for dw in (0.0, 3.0):
    d = scenario_to_dict(uimm_jax.load_scenario("scenarios/paper_sim1_tuned.toml"))
    d["filter"]["est"]["drift_walk"] = dw
    r = uimm_jax.run_scenario(parse_scenario(d), seed=seed)
    o = r.outputs
    print("drift_walk", dw, [(x['fault'], x['time']) for x in r.summary['declarations']])
    for k in range(int(t0 / 1e-4), int(t1 / 1e-4), 25):
        print(f"  t={k*1e-4:.4f} mu={np.round(o['mode_probs'][k], 3)} mag={np.round(o['magnitude'][k], 3)} sd={np.round(o['magnitude_sd'][k], 3)}")
