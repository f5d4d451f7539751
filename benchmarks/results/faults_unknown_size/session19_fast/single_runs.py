# ruff: noqa  (scratch of session 19: see README.md)
"""Single runs of a ramps cell of faults_unknown_size.py, from the repository root:

    python benchmarks/results/faults_unknown_size/session19_fast/single_runs.py \
        SIM MAG RAMP SEEDS [linear|exponential] [NAME=VALUE ...] [trace=T0:T1]

prints each run's declarations (fault, time, correct, final size) and retractions; NAME=VALUE
pairs set [filter.est] keys; trace prints mode probabilities, estimates, sds and the truth.
"""
import sys, warnings
import jax
jax.config.update("jax_enable_x64", True)
import numpy as np
import uimm_jax
from uimm_jax.scenario.write import scenario_to_dict
from uimm_jax.scenario.parse import parse_scenario
sim, mag, tau = int(sys.argv[1]), float(sys.argv[2]), float(sys.argv[3])
seeds = [int(s) for s in sys.argv[4].split(",")]
growth = sys.argv[5] if len(sys.argv) > 5 else "exponential"
sets = dict(a.split("=") for a in sys.argv[6:])
trace = sets.pop("trace", None)
FIRST = {1: ("valve_wear", "leakage"), 2: ("valve_wear", "air_in_oil")}
a, b = FIRST[sim]
span = 3 * tau if growth == "exponential" else tau
d = scenario_to_dict(uimm_jax.load_scenario(f"scenarios/paper_sim{sim}_tuned.toml"))
d["duration"] = 2.5 + 2 * span
d["events"] = [{"fault": a, "time": 0.5, "magnitude": mag, "ramp": tau, "growth": growth},
               {"fault": b, "time": 1.5 + span, "magnitude": mag, "ramp": tau, "growth": growth}]
for k, v in sets.items():
    d["filter"]["est"][k] = float(v) if "." in v or "e" in v else int(v)
sc = parse_scenario(d)
for s in seeds:
    r = uimm_jax.run_scenario(sc, seed=s)
    print(s, [(x['fault'], round(x['time'], 4), x['correct'], round(x.get('magnitude', 0), 3)) for x in r.summary['declarations']],
          [(x['fault'], round(x['time'], 4)) for x in r.summary['retractions']])
    if trace:
        from uimm_jax.studies.truth import true_magnitudes
        o = r.outputs
        tm = true_magnitudes(sc, list(r.setup.table.names), len(o['declared']))
        t0, t1 = (float(x) for x in trace.split(":"))
        k0, k1 = int(t0 / sc.dt), int(t1 / sc.dt)
        for k in range(k0, k1, max(1, (k1 - k0) // 40)):
            print(f"t={k*sc.dt:7.4f} mu={np.round(o['mode_probs'][k], 3)} decl={o['declared'][k]} mag={np.round(o['magnitude'][k], 3)} sd={np.round(o['magnitude_sd'][k], 3)} true={np.round(tm[k], 3)}")
